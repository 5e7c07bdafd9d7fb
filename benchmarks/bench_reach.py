"""Benchmark of the hand's placement: the compiled floating-palm WDLS against the NumPy oracle.

The default ``softgrasp plan`` asks ``place_hand`` to place the Shadow-like hand on a few
initial-grasp candidates (the hand refuses the first ones: it reaches them only with joints inside
the object). This script runs that command once, recording those calls (their fingertip targets and
the settled object) and the command's wall time, then does the same for the planner alone at
larger mesh sizes; it replays every call with the compiled solve
(:mod:`softgrasp.hand.descent`, what ``place_hand`` runs) and with the NumPy oracle of the
tests (``tests/oracles/hand.py``), alternating, and prints per call the best and median times, the
ratio, and whether both gave the same outcome (the same refusal, or the same placement to 1e-9).

Run: ``make bench`` or ``.venv/bin/python benchmarks/bench_reach.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import softgrasp.grasp.planner as planner
import softgrasp.grasp.setup as setup
from softgrasp.errors import InfeasibleGrasp
from softgrasp.hand import placement
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from oracles import hand as oracle  # noqa: E402 - the tests' directory first

#: Sphere mesh sizes [m] of the planner alone: 549 and 2 196 nodes.
SIZES = (0.014, 0.008)

SOLVES = {"compiled": placement._solve, "NumPy": oracle.solve}


def _recording(run) -> tuple[list[tuple], float]:  # type: ignore[no-untyped-def]
    """The (model, targets, keyword arguments) of every place_hand call of ``run()``, and its wall
    time [s]."""
    calls: list[tuple] = []
    real = setup.place_hand

    def record(model, targets, **kw):  # type: ignore[no-untyped-def]
        calls.append((model, dict(targets), kw))
        return real(model, targets, **kw)

    setup.place_hand = record
    try:
        t0 = time.perf_counter()
        run()
        wall = time.perf_counter() - t0
    finally:
        setup.place_hand = real
    return calls, wall


def _command() -> tuple[list[tuple], float]:
    """The calls of the default ``softgrasp plan`` command (in this process) and its wall time."""
    from softgrasp.cli import main

    with tempfile.TemporaryDirectory() as out:
        return _recording(lambda: main(["plan", "--out", out]))


def _planner(h: float) -> tuple[list[tuple], float]:
    mesh, mat, mass = make_object("sphere", h)
    body = build_body(mesh, mat, mass=mass)
    return _recording(lambda: planner.plan_grasp(body, planner.PlanConfig()))


def _outcome(solve, model, targets, kw):  # type: ignore[no-untyped-def]
    """The placement with ``solve``, or the refusal's message."""
    real = placement._solve
    placement._solve = solve
    try:
        return placement.place_hand(model, targets, **kw)
    except InfeasibleGrasp as exc:
        return str(exc)
    finally:
        placement._solve = real


def _same(a, b) -> bool:  # type: ignore[no-untyped-def]
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    return bool(
        np.allclose(a.palm_pose, b.palm_pose, rtol=0, atol=1e-9)
        and all(np.allclose(a.q[f], b.q[f], rtol=0, atol=1e-9) for f in a.q)
    )


def _replay(label: str, calls: list[tuple], repeats: int) -> dict[str, float]:
    """Print the timings of each call; return the summed medians [s] per solve."""
    total = dict.fromkeys(SOLVES, 0.0)
    for k, (model, targets, kw) in enumerate(calls):
        times: dict[str, list[float]] = {s: [] for s in SOLVES}
        results = {s: _outcome(f, model, targets, kw) for s, f in SOLVES.items()}  # untimed: caches
        for _ in range(repeats):
            for s, f in SOLVES.items():
                t0 = time.perf_counter()
                _outcome(f, model, targets, kw)
                times[s].append(time.perf_counter() - t0)
        best = {s: 1e3 * min(t) for s, t in times.items()}
        med = {s: 1e3 * statistics.median(t) for s, t in times.items()}
        for s in total:
            total[s] += med[s] / 1e3
        print(
            f"{label:>8}  {k + 1:4d}  {best['compiled']:10.2f} / {med['compiled']:6.2f}"
            f"        {best['NumPy']:9.2f} / {med['NumPy']:6.2f}   {med['NumPy'] / med['compiled']:5.1f}x"
            f"  {_same(results['compiled'], results['NumPy'])}"
        )
    print(
        f"{label:>8}   all  {1e3 * total['compiled']:19.1f}        {1e3 * total['NumPy']:16.1f}   "
        f"{total['NumPy'] / total['compiled']:5.1f}x  (medians summed: the placements of one plan)"
    )
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7, help="timed replays of each call per solve")
    args = ap.parse_args()
    machine = f"{platform.machine()}, {os.cpu_count()} CPUs"
    print(f"place_hand benchmark on {machine}; compiled solve vs NumPy oracle")
    print("   nodes  call  compiled best/median ms   NumPy best/median ms   ratio  same outcome")
    calls, wall = _command()
    total = _replay("plan", calls, args.repeats)
    print(
        f"`softgrasp plan` (default, in this process): {wall:.2f} s wall, of which its placements take "
        f"{total['compiled']:.3f} s compiled; with the NumPy oracle they would take {total['NumPy']:.3f} s "
        f"(the command {wall:.2f} -> {wall - total['compiled'] + total['NumPy']:.2f} s)"
    )
    for h in SIZES:
        calls, _ = _planner(h)
        _replay(str(len(make_object("sphere", h)[0].points)), calls, args.repeats)


if __name__ == "__main__":
    main()
