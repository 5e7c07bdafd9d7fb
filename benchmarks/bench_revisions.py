"""Whole-command timings of this tree against another revision of softgrasp, in the same run.

Times what a user waits for: the whole ``softgrasp plan`` process (imports, meshing, the plan, the
files and figures) on the built-in default object, and ``softgrasp plan --solver dynamic`` (the
paper's explicit RK4 through the closing increments). Each command runs for this tree and for the
reference revision (checked out into a temporary git worktree, run with the same Python and
packages), alternating between the two so that a drift of the machine's speed falls on both alike.
One untimed run of each first fills Numba's disk caches ("warm cache"). Prints the median and best
wall time of each, their ratio (this tree / reference; below 1 is faster), and whether the two plans'
set-points agree to 1e-6 relative.

Run: ``.venv/bin/python benchmarks/bench_revisions.py [--against REV] [--repeats N]``
(``REV`` defaults to ``HEAD~1``; any commit, tag or branch).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]

#: The commands timed: a label and the arguments after ``softgrasp``.
COMMANDS = {
    "plan": ["plan"],
    "plan --solver dynamic": ["plan", "--solver", "dynamic"],
}


def _run(src: pathlib.Path, args: list[str], out: pathlib.Path) -> float:
    """Wall time [s] of one whole ``softgrasp`` process run from the package tree ``src``."""
    env = dict(os.environ, PYTHONPATH=str(src))
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "softgrasp.cli", *args, "--out", str(out)],
        env=env,
        capture_output=True,
        text=True,
    )
    elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"softgrasp {' '.join(args)} failed in {src}:\n{proc.stderr[-2000:]}")
    return elapsed


def _setpoints(out: pathlib.Path) -> list[float]:
    """The fingers' set-points and their held state's contact-force norms and normal forces [N]
    of a plan.json."""
    doc = json.loads((out / "plan.json").read_text())
    values: list[float] = []
    for finger in doc["fingers"]:
        values += [float(finger[k]) for k in ("setpoint_N", "force_norm_N", "normal_force_N") if k in finger]
    if not values:
        raise SystemExit(f"no set-points found in {out / 'plan.json'}")
    return values


def _agree(a: list[float], b: list[float], rtol: float = 1e-6) -> bool:
    return len(a) == len(b) and all(
        abs(x - y) <= rtol * max(abs(x), abs(y), 1e-12) for x, y in zip(a, b, strict=True)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", default="HEAD~1", help="reference revision (default HEAD~1)")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of each command and tree")
    args = parser.parse_args()
    rev = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", args.against],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="softgrasp-bench-") as tmp:
        tmp_path = pathlib.Path(tmp)
        ref_tree = tmp_path / "reference"
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", "--quiet", str(ref_tree), rev],
            check=True,
        )
        try:
            trees = {"this tree": ROOT / "src", f"reference {rev}": ref_tree / "src"}
            print(f"softgrasp whole-command timings, {os.cpu_count()} CPUs, {args.repeats} runs each")
            print(f"{'command':<24}{'tree':<22}{'median s':>10}{'best s':>10}{'ratio':>8}")
            for label, cmd in COMMANDS.items():
                times: dict[str, list[float]] = {name: [] for name in trees}
                points: dict[str, list[float]] = {}
                for name, src in trees.items():  # warm Numba's caches; keep the set-points
                    out = tmp_path / f"warm-{len(points)}"
                    _run(src, cmd, out)
                    points[name] = _setpoints(out)
                for i in range(args.repeats):
                    order = list(trees.items()) if i % 2 == 0 else list(reversed(trees.items()))
                    for name, src in order:
                        times[name].append(_run(src, cmd, tmp_path / f"run-{i}"))
                names = list(trees)
                ref_median = statistics.median(times[names[1]])
                for name in names:
                    median = statistics.median(times[name])
                    print(
                        f"{label:<24}{name:<22}{median:>10.2f}{min(times[name]):>10.2f}"
                        f"{median / ref_median:>8.2f}"
                    )
                same = _agree(points[names[0]], points[names[1]])
                print(f"{'':<24}set-points equal to 1e-6: {'yes' if same else 'NO'}")
        finally:
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(ref_tree)], check=False
            )


if __name__ == "__main__":
    main()
