"""Benchmark: the wait a user sees for ``softgrasp plan``, beside MuJoCo, in the same run.

Measured in rounds, alternating, each case in a fresh process as a user starts it. The plans
run as ``softgrasp plan`` runs for a user: in a child of softgrasp's warm server
(:mod:`softgrasp.cli.launch`, started by ``softgrasp server start`` before the rounds); the ones
marked *own process* with ``--no-server``, as a plan runs where no server is up:

* **yardstick** — MuJoCo 4 flex pressing the 452-node rubber sphere for 2 s with one fingertip
  (``bench_indent.mujoco_flex``: the same scene as ``bench_indent.py``; the 2 s of simulation,
  timed as that script times it);
* **plan ~2 000 nodes** — ``softgrasp plan --mesh-size 0.008`` (2 196 nodes), the whole process,
  warm (kernels, the mesh and the object's rest on the table in the cache folders: the same
  object planned again); and the same in its own process;
* **plan ~2 000 nodes, settling** — the same, its rest not kept (a cache folder holding the mesh
  and the hand only: an object planned for the first time, as meshed);
* **default plan** — ``softgrasp plan``: the whole process, and the time until its set-points are
  printed (the table's header on stdout); and that time in its own process;
* **first run** — ``softgrasp plan`` with empty cache folders (Numba's, ``NUMBA_CACHE_DIR``, and
  softgrasp's, under ``XDG_CACHE_HOME``): what a first run after installing costs, and what it says
  while it waits. No server is up for those caches (a server is keyed by its environment), so it
  runs in its own process; the server it starts as it ends is stopped before the next case.

Before the rounds, one default plan runs under ``python -X importtime``: its imports by package
(self times summed; ``-X importtime`` itself adds to them), and whether any package the command
does not need (Matplotlib, MuJoCo, Dask, PyArrow, gmsh, yourdfpy) was imported by the command's
own process (the figures are drawn in a child process; the mesh and the hand come from the cache).

Every plan's set-points are compared with the first default plan's (they must not change with
the caches). Prints medians over the rounds and the ratios the speed targets use.

Run: ``.venv/bin/python benchmarks/bench_cli.py [--rounds N] [--no-first-run]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

#: The yardstick's sphere: the mesh size giving 452 nodes.
YARDSTICK_NODES = 452
#: The ~2 000-node plan's mesh size [m] (2 196 nodes).
FINE_MESH_SIZE = 0.008


def _softgrasp(args: list[str], env: dict[str, str]) -> dict:
    """Run ``softgrasp ARGS`` in a new process; its wall time, the time its set-points were
    printed, its stderr and its plan's set-points."""
    out = Path(tempfile.mkdtemp(prefix="bench_cli_"))
    cmd = [sys.executable, "-m", "softgrasp", "plan", "--out", str(out / "run"), *args]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    t_setpoints = None
    assert p.stdout is not None
    for line in p.stdout:
        if t_setpoints is None and "set-point N" in line:
            t_setpoints = time.perf_counter() - t0
    err = p.stderr.read() if p.stderr is not None else ""
    code = p.wait()
    wall = time.perf_counter() - t0
    if code != 0:
        raise SystemExit(f"softgrasp plan {' '.join(args)} failed ({code}):\n{err}")
    setpoints = json.loads((out / "run" / "plan.json").read_text())["setpoints_N"]
    shutil.rmtree(out, ignore_errors=True)
    return {"wall": wall, "setpoints_at": t_setpoints, "stderr": err, "setpoints": setpoints}


#: Packages the default ``softgrasp plan`` must not import in its own process.
UNNEEDED = ("matplotlib", "mujoco", "dask", "distributed", "pyarrow", "gmsh", "yourdfpy")


def _without_rests(folder: str) -> dict[str, str]:
    """An environment whose softgrasp cache folder (under ``folder``) holds the kept meshes and
    hands of this one's, and no kept rest."""
    from softgrasp import usercache
    from softgrasp.grasp.kept_rest import KIND

    target = Path(folder) / "softgrasp"
    for kind in ("meshes", "hands"):
        if (usercache.cache_dir() / kind).is_dir():
            shutil.copytree(usercache.cache_dir() / kind, target / kind)
    assert not (target / KIND).exists()
    return {**os.environ, "XDG_CACHE_HOME": folder}


def _imports(env: dict[str, str]) -> tuple[dict[str, float], float]:
    """The default plan's imports under ``python -X importtime``: seconds by top-level package
    (each module's own time), and the total."""
    out = Path(tempfile.mkdtemp(prefix="bench_cli_"))
    cmd = [sys.executable, "-X", "importtime", "-m", "softgrasp", "plan", "--out", str(out / "run")]
    run = subprocess.run(cmd, capture_output=True, text=True, env=env)
    shutil.rmtree(out, ignore_errors=True)
    if run.returncode != 0:
        raise SystemExit(f"softgrasp plan failed ({run.returncode}):\n{run.stderr}")
    by: dict[str, float] = {}
    for line in run.stderr.splitlines():
        if not line.startswith("import time:") or "|" not in line:
            continue
        own, _, name = line[len("import time:") :].split("|")
        if not own.strip().isdigit():  # the header line
            continue
        package = name.strip().split(".")[0]
        by[package] = by.get(package, 0.0) + int(own) * 1e-6
    return by, sum(by.values())


def _yardstick_mesh_size() -> float:
    """The sphere's mesh size [m] that gives :data:`YARDSTICK_NODES` nodes."""
    from softgrasp.model.objects import make_object

    for h in np.arange(0.0150, 0.0130, -0.0001):
        if make_object("sphere", float(h))[0].n_nodes == YARDSTICK_NODES:
            return float(h)
    raise SystemExit(f"no mesh size gives the {YARDSTICK_NODES}-node sphere with this gmsh")


def _yardstick(h: float) -> float:
    """MuJoCo's 2 s squeeze of the sphere meshed at ``h``, in a fresh process [s]."""
    here = str(Path(__file__).resolve().parent)
    code = (
        f"import sys; sys.path.insert(0, {here!r}); import bench_indent as b; "
        "from softgrasp.model.objects import make_object; "
        f"m, mat, mass = make_object('sphere', {h!r}); r = b.mujoco_flex(m, mat, mass); print(r.wall_s)"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(run.stdout.strip().splitlines()[-1])


def _server(action: str, env: dict[str, str]) -> str:
    """``softgrasp server ACTION`` in environment ``env``; what it printed."""
    cmd = [sys.executable, "-m", "softgrasp", "server", action]
    run = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if run.returncode != 0:
        raise SystemExit(f"softgrasp server {action} failed ({run.returncode}):\n{run.stderr}")
    return run.stdout.strip()


def _stop_started_server(env: dict[str, str], within_s: float = 10.0) -> None:
    """Stop the server a plan in environment ``env`` started as it ended, once it has begun (so
    that it does not load its kernels during the next case), and wait until it is gone."""
    from softgrasp.cli import launch, serverlock

    folder = launch.socket_folder()
    if folder is None:
        return
    path = folder / f"{launch.server_key(env)}.sock"
    end = time.monotonic() + within_s
    while time.monotonic() < end:
        mine = [s for s in serverlock.running(folder) if s.socket == path]
        if mine:
            serverlock.stop(mine[0])
            while time.monotonic() < end and any(s.socket == path for s in serverlock.running(folder)):
                time.sleep(0.05)
            return
        time.sleep(0.05)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3, help="rounds of the alternating cases (default 3)")
    ap.add_argument("--no-first-run", action="store_true", help="skip the empty-cache first run")
    args = ap.parse_args()

    warm_env = dict(os.environ)
    h452 = _yardstick_mesh_size()
    # Warm the caches (kernels, meshes, hand) before the rounds.
    _server("stop", warm_env)
    reference = _softgrasp(["--no-server"], warm_env)["setpoints"]
    _softgrasp(["--mesh-size", str(FINE_MESH_SIZE), "--no-server"], warm_env)
    print(_server("start", warm_env))
    by, total = _imports(warm_env)
    top = sorted(by.items(), key=lambda kv: -kv[1])[:6]
    print(
        f"default plan's imports in its own process (python -X importtime): {total:.2f} s; "
        + ", ".join(f"{name} {t:.3f} s" for name, t in top)
    )
    loaded = [name for name in UNNEEDED if name in by]
    print(
        "  not imported by the command's process: "
        + ", ".join(n for n in UNNEEDED if n not in loaded)
        + ("; IMPORTED: " + ", ".join(loaded) if loaded else "")
    )

    times: dict[str, list[float]] = {
        "yardstick": [],
        "fine": [],
        "fine_own": [],
        "fine_settling": [],
        "default": [],
        "default_setpoints": [],
        "default_own_setpoints": [],
        "first": [],
    }
    first_status = ""
    changed: list[str] = []
    for k in range(args.rounds):
        times["yardstick"].append(_yardstick(h452))
        fine = _softgrasp(["--mesh-size", str(FINE_MESH_SIZE)], warm_env)
        times["fine"].append(fine["wall"])
        own = _softgrasp(["--mesh-size", str(FINE_MESH_SIZE), "--no-server"], warm_env)
        times["fine_own"].append(own["wall"])
        if own["setpoints"] != fine["setpoints"]:
            changed.append(f"plan ~2 000 nodes in its own process, round {k + 1}")
        with tempfile.TemporaryDirectory(prefix="bench_cli_rests_") as folder:
            settling = _softgrasp(["--mesh-size", str(FINE_MESH_SIZE)], _without_rests(folder))
        times["fine_settling"].append(settling["wall"])
        if settling["setpoints"] != fine["setpoints"]:
            changed.append(f"plan ~2 000 nodes settling against its kept rest, round {k + 1}")
        default = _softgrasp([], warm_env)
        times["default"].append(default["wall"])
        times["default_setpoints"].append(default["setpoints_at"])
        if default["setpoints"] != reference:
            changed.append(f"default plan, round {k + 1}")
        own = _softgrasp(["--no-server"], warm_env)
        times["default_own_setpoints"].append(own["setpoints_at"])
        if own["setpoints"] != reference:
            changed.append(f"default plan in its own process, round {k + 1}")
        if not args.no_first_run:
            with tempfile.TemporaryDirectory(prefix="bench_cli_cache_") as cache:
                env = {**warm_env, "NUMBA_CACHE_DIR": f"{cache}/numba", "XDG_CACHE_HOME": f"{cache}/xdg"}
                first = _softgrasp([], env)
                _stop_started_server(env)
            times["first"].append(first["wall"])
            first_status = next((ln for ln in first["stderr"].splitlines() if "compiling" in ln), "(none)")
            if not np.allclose(list(first["setpoints"].values()), list(reference.values()), rtol=1e-9):
                changed.append(f"first run, round {k + 1}")
        print(f"round {k + 1}: " + ", ".join(f"{n} {v[-1]:.2f} s" for n, v in times.items() if v), flush=True)

    med = {n: statistics.median(v) for n, v in times.items() if v}
    print(f"\n`softgrasp plan`, whole process, medians of {args.rounds} alternating rounds:")
    print(f"  MuJoCo, {YARDSTICK_NODES}-node sphere squeezed for 2 s (yardstick): {med['yardstick']:.2f} s")
    print(
        f"  plan --mesh-size {FINE_MESH_SIZE} (2 196 nodes), warm: {med['fine']:.2f} s = "
        f"{med['fine'] / med['yardstick']:.2f} x the yardstick (target <= 0.5)"
    )
    print(
        f"  the same in its own process (--no-server): {med['fine_own']:.2f} s = "
        f"{med['fine_own'] / med['yardstick']:.2f} x the yardstick"
    )
    print(
        f"  the same, settling on the table (its rest not kept): {med['fine_settling']:.2f} s = "
        f"{med['fine_settling'] / med['yardstick']:.2f} x the yardstick"
    )
    print(
        f"  default plan, warm: set-points printed at {med['default_setpoints']:.2f} s (target <= 1 s), "
        f"process {med['default']:.2f} s; in its own process (--no-server) at "
        f"{med['default_own_setpoints']:.2f} s"
    )
    if "first" in med:
        said = first_status.strip()
        print(f"  first run, empty caches: {med['first']:.1f} s (target <= 15 s); it said: {said}")
    print(
        "  set-points: " + ("unchanged in every run" if not changed else "CHANGED in " + ", ".join(changed))
    )


if __name__ == "__main__":
    main()
