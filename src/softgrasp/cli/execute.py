"""``softgrasp execute``: a plan executed under force control on a simulated hand, then lifted."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from softgrasp.cli.args import progress_bar
from softgrasp.errors import ConfigError

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    ex = sub.add_parser("execute", help="execute a plan under force control on a simulated hand and lift")
    ex.add_argument("plan", metavar="PLAN.json", help="a plan written by softgrasp plan")
    ex.add_argument("--backend", choices=("mujoco",), default="mujoco", help="the hand (default: mujoco)")
    ex.add_argument("--lift", type=float, default=0.10, help="lift height [m] (default 0.10)")
    ex.add_argument("--scale", type=float, default=1.0, help="multiply the set-points (default 1)")
    ex.add_argument(
        "--material",
        default=None,
        metavar="FILE.toml",
        help="grasp an object of this material (and fingertip mu) instead of the planned one",
    )
    ex.add_argument(
        "--out", default="softgrasp-out/execute", help="output directory (default softgrasp-out/execute)"
    )
    ex.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    ex.set_defaults(func=run)


def _execute_material(args: argparse.Namespace, plan):
    """The plan with the object's material and fingertip friction of --material FILE.toml over it
    (the hand then grasps an object that differs from the one planned for; mass as planned)."""
    from softgrasp.api.execution import with_material_file

    if args.material is None:
        return plan
    plan, changes = with_material_file(plan, args.material)
    if changes:
        print("object as in " + args.material + ": " + ", ".join(f"{k} = {v:g}" for k, v in changes.items()))
    return plan


def run(args: argparse.Namespace) -> int:
    from softgrasp.io.runfolder import run_folder

    with run_folder(args.out, "execute"):  # checked and locked before any work
        return _run(args, Path(args.out))


def _run(args: argparse.Namespace, out: Path) -> int:
    import math

    from softgrasp.api.execution import execute
    from softgrasp.io.planfile import load_plan_file

    if not (math.isfinite(args.scale) and args.scale > 0):
        raise ConfigError(f"--scale must be a number > 0, got {args.scale}")
    if not (math.isfinite(args.lift) and args.lift > 0):
        raise ConfigError(f"--lift must be a height > 0 m, got {args.lift}")
    planned = load_plan_file(args.plan)
    plan = _execute_material(args, planned)
    print(
        f"executing {args.plan} on {args.backend}: set-points "
        + ", ".join(f"{f.name} {args.scale * f.normal_force:.3f} N" for f in plan.fingers)
        + (f" (x {args.scale:g})" if args.scale != 1 else "")
    )
    bar, update = progress_bar("execute")
    try:
        run = execute(
            planned,
            lift_m=args.lift,
            scale=args.scale,
            material=args.material,
            backend=args.backend,
            progress=update,
        )
    finally:
        bar.close()
    pictures = run.save(out)
    doc, res, cfg = run.document, run.result, run.config
    print("finger    set-point N  measured N  error %   held N")
    for fd in doc["fingers"]:
        print(
            f"{fd['name']:<9}{fd['setpoint_N']:>12.3f}{fd['measured_N']:>12.3f}"
            f"{100 * fd['error_N'] / fd['setpoint_N']:>9.1f}{fd['held_N']:>9.3f}"
        )
    state = "DROPPED" if res.dropped else "lifted"
    print(
        f"{state}: object rose {res.rise * 1e3:.1f} mm of {cfg.lift * 1e3:.0f} mm; slip "
        f"{res.slip * 1e3:.2f} mm; set-points {'reached' if res.reached else 'NOT reached'} within "
        f"{cfg.tolerance:.0%}; {run.simulated_time_s:.2f} s simulated in {doc['wall_time_s']:.1f} s"
    )
    print(f"wrote {out}/execute.json, execute.csv, execute_forces.png, {', '.join(pictures)}")
    if res.dropped:
        print(
            "softgrasp: the object dropped: raise the set-points (plan with --safety-factor)", file=sys.stderr
        )
        return 1
    return 0
