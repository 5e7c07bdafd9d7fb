"""Plan a grasp of the paper's rubber sphere and execute it on a simulated hand (MuJoCo).

The hand closes its fingertips under force control to the plan's set-points, lifts the sphere
10 cm and holds it. The example prints the set-points, the forces the fingertips measured when
the closing ended, whether the sphere was lifted and how far it slipped.

Run:  python examples/02_execute_plan.py [OUT_DIR]   (OUT_DIR: also write the plan's and the run's files)
"""

from __future__ import annotations

import sys
from pathlib import Path

import softgrasp as sg


def main() -> None:
    # The set-points carry the default safety factor (1.25) over the least forces that hold.
    plan = sg.plan(sg.load_object("sphere"), hand=sg.load_hand("shadow_like"), mu=0.8)
    if len(sys.argv) > 1:
        plan.save(Path(sys.argv[1]) / "plan")
    run = sg.execute(plan, lift_m=0.10)
    for finger, setpoint in plan.setpoints_N.items():
        print(f"{finger} set-point {setpoint:.6f} N, measured {run.measured_N[finger]:.6f} N")
    print(f"lifted {run.lifted}")
    print(f"slip {run.slip_m * 1e3:.6f} mm")
    if len(sys.argv) > 1:
        run.save(Path(sys.argv[1]) / "execute")


if __name__ == "__main__":
    main()
