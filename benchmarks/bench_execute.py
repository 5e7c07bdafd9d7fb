"""Benchmark of ``softgrasp execute``: wall time of the default execution (the default plan's
set-points reached by force control on the simulated hand, 0.10 m lift, 2 s hold) and the
real-time factor (simulated seconds per wall second) at the mesh size used.

Peer measured in the same run: MuJoCo stepping the same scene with no controller in the loop
(the same number of steps with the servo targets frozen), so the ratio shows what softgrasp's
Python controller (tactile readout, WDLS per finger per period) adds to the engine's own cost.

Run: ``make bench`` or ``.venv/bin/python benchmarks/bench_execute.py [--sizes 0.016 0.012]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

from softgrasp.cli import main as cli
from softgrasp.execution.controller import ExecuteConfig, closing_lines, execute_plan
from softgrasp.execution.mujoco.hand import MujocoHand
from softgrasp.io.planfile import load_plan_file


def run(mesh_size: float | None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        args = ["plan", "--out", tmp] + ([] if mesh_size is None else ["--mesh-size", str(mesh_size)])
        if cli(args) != 0:
            print(f"plan failed at mesh size {mesh_size}")
            return
        plan = load_plan_file(Path(tmp) / "plan.json")
        t0 = time.perf_counter()
        hand = MujocoHand.from_plan(plan)
        t_load = time.perf_counter() - t0
        lines = closing_lines(plan)
        t0 = time.perf_counter()
        res = execute_plan(hand, lines, ExecuteConfig(), palm_to_world=hand.palm_to_world)
        wall = time.perf_counter() - t0
        sim = hand.time
        steps = round(sim / float(hand.scene.model.opt.timestep))
        # Peer: the engine alone, same scene and state, same number of steps.
        t0 = time.perf_counter()
        hand.scene.step(steps)
        engine = time.perf_counter() - t0
        n = int(hand.scene.model.flex_vertnum[0])
        print(
            f"{n:>6} {t_load:>7.2f} {sim:>7.2f} {wall:>8.1f} {sim / wall:>7.3f} {engine:>8.1f} "
            f"{sim / engine:>7.3f} {wall / engine:>6.2f}  "
            f"{'lifted' if res.lifted else 'DROPPED'} slip {res.slip * 1e3:.2f} mm, "
            + ", ".join(f"{k} {res.measured[k]:.3f}/{res.setpoints[k]:.3f} N" for k in res.fingers)
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="*", default=[], help="extra sphere mesh sizes [m]")
    args = ap.parse_args()
    machine = platform.processor() or platform.machine()
    print(f"softgrasp execute benchmark on {machine}, {os.cpu_count()} CPUs")
    print(" nodes  load s   sim s   wall s     RTF  engine s  eng RTF  ratio  result")
    for h in [None, *args.sizes]:
        run(h)


if __name__ == "__main__":
    main()
