"""``softgrasp execute``: a plan executed under force control on a simulated hand, then lifted."""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

from softgrasp.cli.args import plan_file, progress_bar
from softgrasp.errors import SoftgraspWarning
from softgrasp.io.limits import EXECUTE_RANGES, MAX_SETPOINT_N

__all__ = ["add_parser", "run"]


def _number(name: str):
    def conv(s: str) -> float:
        try:
            return float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {s!r}") from None

    return conv


def add_parser(sub) -> None:
    ex = sub.add_parser(
        "execute",
        help="execute a plan under force control on a simulated hand and lift",
        description="Execute a plan under force control on a simulated hand and lift. Before "
        "simulating, every number read from the plan is checked against its physical range and the "
        "plan's parts against each other (fingers, object.vtu, hand and palm pose); a simulation "
        "that blows up or runs past its time bound stops with an error.",
    )
    ex.add_argument(
        "plan", metavar="RUN", help="a plan: the plan.json softgrasp plan wrote, or the folder holding it"
    )
    ex.add_argument("--backend", choices=("mujoco",), default="mujoco", help="the hand (default: mujoco)")
    lift, scale = EXECUTE_RANGES["--lift"], EXECUTE_RANGES["--scale"]
    ex.add_argument(
        "--lift",
        type=_number("--lift"),
        default=0.10,
        help=f"lift height [m] (default 0.10; {lift.describe('LIFT')})",
    )
    ex.add_argument(
        "--hold",
        type=_number("--hold"),
        default=2.0,
        help=f"hold the lifted object [s] (default 2; {EXECUTE_RANGES['--hold'].describe('HOLD')})",
    )
    ex.add_argument(
        "--scale",
        type=_number("--scale"),
        default=1.0,
        help=f"multiply the set-points (default 1; {scale.describe('SCALE')}, each scaled set-point "
        f"<= {MAX_SETPOINT_N:g} N)",
    )
    ex.add_argument(
        "--material",
        default=None,
        metavar="FILE.toml",
        help="grasp an object of this material (and fingertip mu) instead of the planned one",
    )
    ex.add_argument(
        "--out", default="softgrasp-out/execute", help="output directory (default softgrasp-out/execute)"
    )
    ex.add_argument(
        "--save-scene",
        default=None,
        metavar="FILE.xml",
        help="also write the simulated scene as MJCF (object, table, hand; self-contained): "
        "mujoco.MjModel.from_xml_path loads it",
    )
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


#: Share of MuJoCo's steps whose constraint solve stopped at its iteration cap above which a drop
#: is put down to MuJoCo's unresolved contact forces (a plan that lifts has a few per mille).
CAPPED_SHARE = 0.05


def _drop_advice(args: argparse.Namespace, run) -> str:
    """Why the object dropped, and what to change: set-points not reached are not cured by
    raising them; another object than planned needs its own plan; MuJoCo's constraint solver
    stopping at its iteration cap on many steps makes the simulation itself untrustworthy."""
    res, cfg = run.result, run.config
    capped = float(run.document.get("mujoco_solver_capped_share") or 0.0)
    if capped > CAPPED_SHARE:
        return (
            f"MuJoCo's constraint solver stopped at its iteration cap in {capped:.0%} of the steps, so "
            "its contact forces were not resolved (a heavy, soft object sinks into the table and the "
            "fingers miss it): this simulation does not tell whether the plan holds"
        )
    if not res.reached:
        short = [f"{n} {res.measured[n]:.3g} of {res.setpoints[n]:.3g} N" for n in res.fingers]
        if all(res.measured[n] <= 0 for n in res.fingers):
            return (
                f"the fingers never pressed the object in {cfg.max_close_time:g} s of closing: their "
                "closing lines miss it; check that the plan and its object.vtu belong together, or re-plan"
            )
        closing = res.series["force"][res.series["phase"] == 1]
        if len(closing) and all(closing[:, j].max() >= res.setpoints[n] for j, n in enumerate(res.fingers)):
            return (
                f"every finger pressed as hard as its set-point, but they did not stay within "
                f"{cfg.tolerance:.0%} of them together in {cfg.max_close_time:g} s of closing (at its end "
                f"{', '.join(short)}): the contact force jumped by more than that from one reading to the "
                "next, as on a stiff object under small set-points; larger set-points (--scale, or plan "
                "with a larger --safety-factor) make the jumps relatively smaller"
            )
        return (
            f"the fingers did not reach their set-points in {cfg.max_close_time:g} s of closing "
            f"({', '.join(short)}): the hand could not press that hard along its closing lines; re-plan"
        )
    if args.material is not None:
        return (
            f"the object of {args.material} slipped out at the set-points planned for another "
            f"material: plan for it (softgrasp plan --material {args.material}) or raise --scale"
        )
    if args.scale < 1:
        return f"the set-points scaled by {args.scale:g} do not hold it: raise --scale"
    return "raise the set-points (plan with --safety-factor)"


def run(args: argparse.Namespace) -> int:
    from softgrasp.cli.extras import require
    from softgrasp.io.runfolder import run_folder
    from softgrasp.offscreen import prefer_headless_gl

    prefer_headless_gl()  # MuJoCo renders the pictures offscreen: chosen before it is imported
    require("execute", "softgrasp execute")
    args.plan = plan_file(args.plan)

    with run_folder(args.out, "execute"):  # checked and locked before any work
        return _run(args, Path(args.out))


def _run(args: argparse.Namespace, out: Path) -> int:
    from softgrasp.api.execution import check_options, execute
    from softgrasp.execution.plan_check import check_plan
    from softgrasp.io.planfile import load_plan_file

    EXECUTE_RANGES["--lift"].check(args.lift, "--lift")
    EXECUTE_RANGES["--hold"].check(args.hold, "--hold")
    EXECUTE_RANGES["--scale"].check(args.scale, "--scale")
    if args.save_scene is not None:
        from softgrasp.io.runfolder import check_out_file

        check_out_file(args.save_scene, "--save-scene")
    planned = load_plan_file(args.plan)
    check_options(planned, args.lift, args.scale, args.backend)
    plan = _execute_material(args, planned)
    check_plan(plan)
    print(
        f"executing {args.plan} on {args.backend}: set-points "
        + ", ".join(f"{f.name} {args.scale * f.normal_force:.3f} N" for f in plan.fingers)
        + (f" (x {args.scale:g})" if args.scale != 1 else "")
    )
    bar, update = progress_bar("execute")
    try:
        with warnings.catch_warnings(record=True) as caught:  # the pictures' fallback, one line
            warnings.simplefilter("always", SoftgraspWarning)
            run = execute(
                planned,
                lift_m=args.lift,
                hold_s=args.hold,
                scale=args.scale,
                material=args.material,
                backend=args.backend,
                progress=update,
            )
    finally:
        bar.close()
    for w in caught:
        if issubclass(w.category, SoftgraspWarning):
            print(f"softgrasp: warning: {w.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    pictures = run.save(out)
    if args.save_scene is not None:
        run.save_scene(args.save_scene)
        print(f"wrote the scene {args.save_scene}")
    doc, res, cfg = run.document, run.result, run.config
    print("finger    set-point N  measured N  error %   held N")
    for fd in doc["fingers"]:
        print(
            f"{fd['name']:<9}{fd['setpoint_N']:>12.3f}{fd['measured_N']:>12.3f}"
            f"{100 * fd['error_N'] / fd['setpoint_N']:>9.1f}{fd['held_N']:>9.3f}"
        )
    state = "DROPPED" if res.dropped else "lifted"
    if "released" in res.events:  # the run ends once nothing can lift the object any more
        state += f" (out of the hand at t = {res.events['released']:.2f} s, where the run ended)"
    print(
        f"{state}: object rose {res.rise * 1e3:.1f} mm of {cfg.lift * 1e3:.0f} mm; slip "
        f"{res.slip * 1e3:.2f} mm; set-points {'reached' if res.reached else 'NOT reached'} within "
        f"{cfg.tolerance:.0%}; {run.simulated_time_s:.2f} s simulated in {doc['wall_time_s']:.1f} s"
    )
    print(f"wrote {out}/execute.json, execute.csv, execute_forces.png, {', '.join(pictures)}")
    if res.dropped:
        print(f"softgrasp: the object dropped: {_drop_advice(args, run)}", file=sys.stderr)
        return 1
    return 0
