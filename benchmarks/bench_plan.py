"""Benchmark of the grasp planner: wall time of the default plan (rubber sphere, three fingers,
0.5 mm increments, 1 s implicit hold) at about 500, 2 000 and 8 000 nodes, for each solver.

Peers measured in the same run: the quasi-static solver is the reference; the dynamic solver
(the paper's explicit RK4 through every increment at 50 mm/s, then a static rest) is reported as a
ratio to it. The explicit step is bounded by the stiffest node (~1e-5 s on the default sphere), so
the dynamic solver's cost grows about as N^(4/3) per simulated second; above 1 000 nodes it is
skipped unless ``--all`` is given (it takes tens of minutes) and its time is estimated from the
measured cost per RK4 step and the number of steps.

Run: ``make bench`` or ``.venv/bin/python benchmarks/bench_plan.py [--quick] [--all]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from softgrasp.body import build_body
from softgrasp.contact.fingertip import Fingertip
from softgrasp.contact.model import FingertipContact
from softgrasp.grasp.planner import PlanConfig, plan_grasp
from softgrasp.objects import make_object
from softgrasp.planes import Plane, PlaneContact
from softgrasp.sim.integrators import simulate
from softgrasp.sim.scene import Scene
from softgrasp.sim.stability import stable_time_step

#: Sphere mesh sizes [m]: 549, 2 196 and 7 576 nodes.
SIZES = (0.014, 0.008, 0.005)
HEAD = ("nodes", "solver", "wall s", "incr", "ratio", "thumb N", "first N", "middle N")
NOTE = "(estimated; --all runs it)"


def _plan(body, solver: str):
    t0 = time.perf_counter()
    plan = plan_grasp(body, PlanConfig(solver=solver))
    return time.perf_counter() - t0, plan


def _estimate_dynamic(body, quasi) -> float:
    """Seconds the dynamic solver's closing would take: RK4 steps of the closing (travel / speed /
    dt, with dt the stable step of the scene with the table and the three fingertips where the
    plan put them) times the measured cost of one such step."""
    cfg = PlanConfig()
    tips = tuple(
        Fingertip(cfg.fingertip_radius, centre=c, velocity=np.zeros(3), name=f.name)
        for c, f in zip(quasi.centres, quasi.fingers, strict=True)
    )
    zmin = float(np.asarray(body.mesh.points)[:, 2].min())
    table = PlaneContact(Plane(np.array([0.0, 0.0, zmin]), np.array([0.0, 0.0, 1.0])), mu=0.5)
    scene = Scene(body, (table, FingertipContact(tips, cfg.contact)))
    dt = stable_time_step(scene, "rk4")
    state = scene.initial_state(quasi.positions)
    t0 = time.perf_counter()
    simulate(scene, state, 20 * dt, dt=dt, method="rk4")
    per_step = (time.perf_counter() - t0) / 20
    steps = quasi.travel.max() / cfg.closing_speed / dt
    return steps * per_step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only the ~500-node mesh")
    ap.add_argument("--all", action="store_true", help="also run the dynamic solver above 1 000 nodes")
    args = ap.parse_args()
    print(f"softgrasp plan benchmark on {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs")
    print(" ".join(f"{h:>{w}}" for h, w in zip(HEAD, (6, 12, 8, 5, 7, 8, 8, 8), strict=True)))
    for h in SIZES[:1] if args.quick else SIZES:
        mesh, mat, mass = make_object("sphere", h)
        body = build_body(mesh, mat, mass=mass)
        tq, quasi = _plan(body, "quasistatic")
        f = [x.force_norm for x in quasi.fingers]
        print(
            f"{body.n_nodes:>6} {'quasistatic':>12} {tq:>8.1f} {quasi.increments:>5} {1.0:>7.2f} "
            + " ".join(f"{v:>8.3f}" for v in f)
        )
        if body.n_nodes > 1000 and not args.all:
            est = _estimate_dynamic(body, quasi) + tq
            print(f"{body.n_nodes:>6} {'dynamic':>12} {est:>8.0f} {'-':>5} {est / tq:>7.1f}  {NOTE}")
            continue
        est = _estimate_dynamic(body, quasi) + tq
        td, dyn = _plan(body, "dynamic")
        g = [x.force_norm for x in dyn.fingers]
        print(
            f"{body.n_nodes:>6} {'dynamic':>12} {td:>8.1f} {dyn.increments:>5} {td / tq:>7.2f} "
            + " ".join(f"{v:>8.3f}" for v in g)
        )
        diff = np.max(np.abs(np.array(g) / np.array(f) - 1))
        print(f"{'':>6} largest finger-force difference dynamic vs quasistatic: {diff:.1%}")
        print(f"{'':>6} (the estimate used above 1 000 nodes gives {est:.0f} s here)")


if __name__ == "__main__":
    main()
