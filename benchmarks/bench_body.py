"""Benchmark of the foundation: explicit steps and static solves versus node count.

For boxes of about 500, 2 000, 8 000 and 32 000 nodes (the foam-cube geometry with the rubber
material, so the time step is the one of the paper's soft sphere), it measures
* the wall time of one explicit RK4 step of the body resting on the table (four force evaluations),
  and the node-steps per second;
* the wall time of one static solve: a 1 % compression increment between plates (Newton with the
  AMG-preconditioned solver), and its Newton iterations.

Run: ``make bench`` or ``.venv/bin/python benchmarks/bench_body.py [--quick]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from softgrasp.linalg.solve import SolverCache
from softgrasp.model.material import preset
from softgrasp.model.mesh import box
from softgrasp.physics.body import build_body
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.physics.supports import Tether
from softgrasp.sim.explicit import RK4
from softgrasp.sim.scene import Scene
from softgrasp.sim.stability import stable_time_step
from softgrasp.sim.static import solve_static

#: BCC box divisions giving about 500, 2 000, 8 000 and 32 000 nodes.
DIVISIONS = {500: 5, 2000: 8, 8000: 14, 32000: 24}


def bench_explicit(body, steps: int) -> tuple[float, float]:
    scene = Scene(body, (PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.5, name="table"),))
    state = scene.initial_state()
    dt = stable_time_step(scene, "rk4")
    integ = RK4()
    state = integ.step(scene, state, dt)  # warm-up
    t0 = time.perf_counter()
    for _ in range(steps):
        state = integ.step(scene, state, dt)
    return (time.perf_counter() - t0) / steps, dt


def bench_static(body) -> tuple[float, int]:
    x0 = np.asarray(body.mesh.points)
    zmax = float(x0[:, 2].max())
    bottom = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.0, name="bottom")
    top = PlaneContact(Plane([0, 0, zmax], [0, 0, -1], velocity=[0, 0, -1.0]), mu=0.0, name="top")
    scene = Scene(body, (bottom, top, Tether("xy")))
    cache = SolverCache()
    state, _ = solve_static(scene, scene.initial_state(), t=0.0, cache=cache)  # settle (warm-up)
    t0 = time.perf_counter()
    state, info = solve_static(scene, state, t=0.01 * zmax, cache=cache)
    return time.perf_counter() - t0, info.newton_iterations


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only the two smallest sizes")
    args = ap.parse_args()
    sizes = list(DIVISIONS.items())[: 2 if args.quick else None]
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, NumPy {np.__version__}"
    )
    print(
        f"{'target':>7} {'nodes':>7} {'tets':>7} {'dt [s]':>9} {'RK4 step [ms]':>14} {'node-steps/s':>13} "
        f"{'static [s]':>10} {'Newton it':>9}"
    )
    for target, n in sizes:
        t0 = time.perf_counter()
        body = build_body(box(0.05, n), preset("rubber"))
        build = time.perf_counter() - t0
        steps = max(5, int(2000 / (1 + body.n_nodes / 200)))
        t_step, dt = bench_explicit(body, steps)
        t_static, iters = bench_static(body)
        print(
            f"{target:>7} {body.n_nodes:>7} {body.mesh.n_tets:>7} {dt:>9.2e} {1e3 * t_step:>14.2f} "
            f"{body.n_nodes / t_step:>13.3g} {t_static:>10.2f} {iters:>9}   (build {build:.1f} s)"
        )


if __name__ == "__main__":
    main()
