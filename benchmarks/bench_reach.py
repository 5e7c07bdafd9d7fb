"""Benchmark of the hand's placement: the compiled floating-palm WDLS against the NumPy reference.

A default plan of the rubber sphere asks ``place_hand`` to place the Shadow-like hand on three or
four initial-grasp candidates (the hand refuses the first two or three: it reaches them only with
joints inside the object). This script records those calls (their fingertip targets and the
settled object) during one plan per mesh size, then replays each of them with the compiled kernels
(``softgrasp.hand.placement_compiled``) and with the NumPy reference (what ``place_hand`` runs where
:func:`softgrasp.backend.compiled` is false), alternating, and prints per call the best and median times, the
ratio, and whether both gave the same outcome (the same refusal, or the same placement to 1e-9).

Run: ``make bench`` or ``.venv/bin/python benchmarks/bench_reach.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import statistics
import time

import numpy as np

import softgrasp.grasp.planner as planner
from softgrasp import backend
from softgrasp.physics.body import build_body
from softgrasp.errors import InfeasibleGrasp
from softgrasp.hand.placement import place_hand
from softgrasp.model.objects import make_object

@contextlib.contextmanager
def _kernels(name: str):
    """The compiled solve (``"numba"``) or the NumPy reference (``"numpy"``:
    :func:`softgrasp.backend.compiled` false for the block)."""
    if name == "numba":
        yield
        return
    real = backend.compiled
    backend.compiled = lambda: False
    try:
        yield
    finally:
        backend.compiled = real


#: Sphere mesh sizes [m]: 549 and 2 196 nodes.
SIZES = (0.014, 0.008)


def _recorded_calls(h: float) -> list[tuple]:
    """The (model, targets, keyword arguments) of every place_hand call of a default plan."""
    mesh, mat, mass = make_object("sphere", h)
    body = build_body(mesh, mat, mass=mass)
    calls: list[tuple] = []
    real = planner.place_hand

    def record(model, targets, **kw):
        calls.append((model, dict(targets), kw))
        return real(model, targets, **kw)

    planner.place_hand = record
    try:
        planner.plan_grasp(body, planner.PlanConfig())
    finally:
        planner.place_hand = real
    return calls


def _outcome(model, targets, kw):
    """The placement, or the refusal's message."""
    try:
        return place_hand(model, targets, **kw)
    except InfeasibleGrasp as exc:
        return str(exc)


def _same(a, b) -> bool:
    if isinstance(a, str) or isinstance(b, str):
        return a == b
    return bool(
        np.allclose(a.palm_pose, b.palm_pose, rtol=0, atol=1e-9)
        and all(np.allclose(a.q[f], b.q[f], rtol=0, atol=1e-9) for f in a.q)
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7, help="timed replays of each call per backend")
    args = ap.parse_args()
    print(f"place_hand benchmark on {platform.machine()}, {os.cpu_count()} CPUs; kernels: compiled vs NumPy")
    print(" nodes  call  compiled best/median ms   NumPy best/median ms   ratio  same outcome")
    for h in SIZES:
        calls = _recorded_calls(h)
        n_nodes = len(make_object("sphere", h)[0].points)
        total = {"numba": 0.0, "numpy": 0.0}
        for k, (model, targets, kw) in enumerate(calls):
            times: dict[str, list[float]] = {"numba": [], "numpy": []}
            results = {}
            for name in ("numba", "numpy"):  # one untimed call each: loading, caches
                with _kernels(name):
                    results[name] = _outcome(model, targets, kw)
            for _ in range(args.repeats):
                for name in ("numba", "numpy"):
                    with _kernels(name):
                        t0 = time.perf_counter()
                        _outcome(model, targets, kw)
                        times[name].append(time.perf_counter() - t0)
            best = {b: 1e3 * min(t) for b, t in times.items()}
            med = {b: 1e3 * statistics.median(t) for b, t in times.items()}
            for b in total:
                total[b] += med[b]
            same = _same(results["numba"], results["numpy"])
            ratio = med["numpy"] / med["numba"]
            print(
                f"{n_nodes:6d}  {k + 1:4d}  {best['numba']:10.2f} / {med['numba']:6.2f}"
                f"        {best['numpy']:9.2f} / {med['numpy']:6.2f}   {ratio:5.1f}x  {same}"
            )
        print(
            f"{n_nodes:6d}   all  {total['numba']:19.1f}        {total['numpy']:16.1f}   "
            f"{total['numpy'] / total['numba']:5.1f}x  (medians summed: the placements of one plan)"
        )


if __name__ == "__main__":
    main()
