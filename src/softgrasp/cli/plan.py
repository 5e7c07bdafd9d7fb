"""``softgrasp plan``: a three-finger grasp and its force set-points (paper Sec. 2, 4.3), with
robust set-points over uncertain parameters (``--uncertain``)."""

from __future__ import annotations

import argparse
import time
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

from softgrasp.cli.args import add_common, limits, load, material_file, number, scheduler
from softgrasp.cli.progress import PLAN_SHARES, PhaseBar, kernels_phase
from softgrasp.errors import ConfigError

if TYPE_CHECKING:
    from softgrasp.viz.worker import FigureWorker

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    pl = sub.add_parser("plan", help="plan a three-finger grasp and its force set-points (paper Sec. 2, 4.3)")
    add_common(pl)
    pl.set_defaults(object=None, func=run)
    for action in pl._actions:
        if action.dest == "object":
            action.help = f"{action.help} (default: sphere, the paper's rubber sphere)"
        elif action.dest == "out":
            action.help = f"{action.help} (default: softgrasp-out/plan)"
    pl.add_argument(
        "--mu",
        type=number("mu"),
        default=None,
        help=f"fingertip friction coefficient, {limits('mu')} (default 0.8); wins over a --material "
        "file's, which wins over --config's",
    )
    pl.add_argument(
        "--contact-law",
        choices=("resolved", "paper"),
        default=None,
        help="fingertip normal law: resolved (default; Hertz's, the object's compliance counted once "
        "with its mesh) or paper (the paper's K delta^n in series with the meshed body, Eq. 9-11)",
    )
    pl.add_argument(
        "--max-pressure",
        type=number("max_pressure"),
        default=None,
        metavar="PA",
        help=f"largest peak contact pressure the grasp may put on the object [Pa], "
        f"{limits('max_pressure')} (Hertz's peak; fruit bruises at tens to hundreds of kPa); a plan "
        "above it fails",
    )
    pl.add_argument(
        "--max-strain",
        type=number("max_strain"),
        default=None,
        help=f"largest principal strain the grasp may cause in the object, {limits('max_strain')}; a "
        "plan above it fails",
    )
    pl.add_argument(
        "--fingertip-radius",
        type=number("fingertip_radius"),
        default=None,
        help=f"fingertip radius, {limits('fingertip_radius')} (default: the hand's fingertip spheres', "
        "0.008 without a hand); overrides the spheres'",
    )
    pl.add_argument(
        "--step",
        type=number("step"),
        default=None,
        help=f"closing increment, {limits('step')}, below the fingertip radius (default 0.0005)",
    )
    pl.add_argument(
        "--solver",
        choices=("quasistatic", "dynamic"),
        default=None,
        help="rest per increment by static Newton (default) or the paper's explicit Runge-Kutta",
    )
    pl.add_argument(
        "--safety-factor",
        type=number("safety_factor"),
        default=None,
        help=f"set-points are this multiple of the least normal forces that hold the object under "
        f"force control in softgrasp's model, {limits('safety_factor')} (default 1.25)",
    )
    pl.add_argument(
        "--hold-time",
        type=number("hold_time"),
        default=None,
        help=f"simulated holding time of the check, {limits('hold_time')} (default 1)",
    )
    pl.add_argument(
        "--max-squeeze",
        type=number("max_squeeze"),
        default=None,
        help=f"largest finger travel past first contact, fraction of its reach, {limits('max_squeeze')} "
        "(default 0.5)",
    )
    pl.add_argument(
        "--refine",
        type=number("refine"),
        default=None,
        help="most iterations of the solves for the least squeeze that holds "
        f"(each to a force tolerance of 1 %%), {limits('refine')} (default 12)",
    )
    pl.add_argument(
        "--hand",
        default=None,
        metavar="HAND",
        help="the hand: 'shadow_like' (default, packaged), 'parallel_jaw' (packaged two-finger gripper, "
        "0-85 mm), a URDF or MJCF file (fingertips: see --fingertips), or 'none' (free fingertips, no "
        "reachability check)",
    )
    pl.add_argument(
        "--fingertips",
        default=None,
        metavar="FINGER=LINK,...",
        help="the fingertip links (MJCF: bodies) of a hand file, e.g. "
        "thumb=th_tip,first=ff_tip,middle=mf_tip "
        "(a gripper: left=LINK,right=LINK); default: links named th_tip, ff_tip, mf_tip. Each link's "
        "collision sphere gives the fingertip radius",
    )
    pl.add_argument(
        "--grasp",
        default=None,
        metavar="PLAN.json",
        help="close from the initial grasp of an earlier plan (same object and mesh) instead of searching "
        "for one: the same contacts and closing lines for another material or friction",
    )
    pl.add_argument("--config", default=None, metavar="FILE.toml", help="TOML file with any of these options")
    rb = pl.add_argument_group(
        "robust set-points",
        "plan for uncertain parameters: the set-points that hold the object for every sampled parameter set",
    )
    rb.add_argument(
        "--uncertain",
        action="append",
        default=[],
        metavar="NAME=RANGE",
        help="an uncertain parameter (mu, E, nu, density, mass, a2, a3) and its range: LOW..HIGH (SI), "
        "±P%% of the nominal value, or ±D; repeat for several "
        "(e.g. --uncertain mu=0.4..0.8 --uncertain E=±20%%)",
    )
    rb.add_argument(
        "--samples",
        type=number("samples"),
        default=None,
        help=f"parameter sets sampled over the ranges, {limits('samples')} (default 64)",
    )
    rb.add_argument(
        "--quantile",
        type=number("quantile"),
        default=None,
        help=f"hold this share of the samples (e.g. 0.9) instead of every one, {limits('quantile')}",
    )
    rb.add_argument(
        "--seed",
        type=number("seed"),
        default=None,
        help=f"seed of the samples' draw, {limits('seed')} (default 0)",
    )
    rb.add_argument(
        "--workers",
        type=number("workers"),
        default=None,
        help=f"local Dask worker processes, {limits('workers')} (default 2)",
    )
    rb.add_argument(
        "--scheduler",
        type=scheduler,
        default=None,
        metavar="ADDRESS",
        help="a running Dask scheduler (tcp://host:port)",
    )


def run(args: argparse.Namespace) -> int:
    from softgrasp.api.planning import plan_options
    from softgrasp.viz.worker import FigureWorker

    # Every option (given, or from --config) is checked before any work starts.
    opts = plan_options(vars(args), args.config)
    args = argparse.Namespace(**{**vars(args), **opts, "mu_given": args.mu})
    if args.uncertain:
        from softgrasp.cli.extras import require

        require("sweep", "softgrasp plan --uncertain")  # robust set-points run on Dask
    # Matplotlib loads in a child process meanwhile (started by _plan); it then draws the figures
    # while the other files are written.
    # (The worker stops before the folder is committed or cleared: no figure lands after.)
    with ExitStack() as folder, FigureWorker(start=False) as figures:
        bar = PhaseBar("plan", PLAN_SHARES)
        try:
            return _plan(args, figures, folder, bar)
        finally:
            bar.close()


def _margin_line(mg: dict) -> str:
    """The margin as plan.json's ``margin`` states it, in one line: the least scale of the
    set-points held and the largest not held; or, when every scale tried held (down to the
    search's lowest), that the least that holds lies lower still."""
    held, not_held = mg["critical_scale"], mg["not_held_scale"]
    if not not_held > 0:
        return (
            f"margin: held at every scale tried, down to {held:.2f} x the set-points, the search's "
            f"lowest (softgrasp's model): the set-points are at least {mg['safety_factor']:g} x the "
            "least that holds"
        )
    digits = 2 if f"{held:.2f}" != f"{not_held:.2f}" else 3  # two scales apart, printed apart
    return (
        f"margin: set-points {mg['safety_factor']:g} x the least that holds: held down to "
        f"{held:.{digits}f} x the set-points, not at {not_held:.{digits}f} (softgrasp's model)"
    )


def _plan(args: argparse.Namespace, figures: FigureWorker, folder: ExitStack, bar: PhaseBar) -> int:
    from softgrasp.cli.warm import resume_collector, warm_up_in_background

    warm = warm_up_in_background()  # the compiled kernels load while the object is meshed

    def start_figures() -> None:  # the figure process, unless the kernels compile (a first run)
        if warm.checked.is_set() and not warm.cold:
            figures.start()

    start_figures()
    from softgrasp.api.planning import plan
    from softgrasp.io.options import contact_params

    t0 = time.perf_counter()
    mu_given = args.mu_given
    from softgrasp.io.runfolder import run_folder

    # The folder is checked and locked before any work; the files replace its earlier ones at the end.
    folder.enter_context(run_folder(str(args.out), "plan"))
    out = Path(str(args.out))
    bar.phase("meshing", quiet=True)  # a refused mesh or material stays one line
    obj = load(args)
    start_figures()
    m = obj.material
    bar.write(f"object   {obj.summary()}")
    bar.write(f"material {m.name}: E = {m.E / 1e3:.4g} kPa, nu = {m.nu:g}")
    # mu from --mu, else the material file, else --config or 0.8
    mf = material_file(args)
    mu = mu_given if mu_given is not None or (mf is not None and "mu" in mf.contact) else args.mu
    uncertain = _uncertain(args, obj, contact_params(mf, mu).mu)

    def phase(name: str) -> None:  # the planner's phases, every option checked by then
        if not bar.phases or bar.phases[-1] == "meshing":
            kernels_phase(bar, warm)
            figures.start()  # (after the compiling, on a first run)
            resume_collector()  # the start-up is over: softgrasp.cli.warm.pause_collector
        bar.phase(name)

    with bar.part("planning") as update:
        result = plan(
            obj,
            hand=args.hand,
            fingertips=args.fingertips,
            mu=mu,
            fingertip_radius_m=args.fingertip_radius,
            step_m=args.step,
            solver=args.solver,
            safety_factor=args.safety_factor,
            hold_time_s=args.hold_time,
            max_squeeze=args.max_squeeze,
            refine=args.refine,
            grasp=args.grasp,
            contact_law=args.contact_law,
            max_pressure_Pa=args.max_pressure,
            max_strain=args.max_strain,
            progress=update,
            phase=phase,
        )
    g, doc = result.grasp, result.document
    bar.write(result.table())  # the set-points as soon as they exist
    eq = doc["equilibrium"]
    bar.write(
        f"held: residual {eq['force_residual_N']:.2e} N, {eq['torque_residual_Nm']:.2e} N m; "
        f"friction margin {eq['friction_margin']:.2f}; centre of mass moved "
        f"{g.com_drift * 1e3:.2f} mm in {g.hold_time:g} s"
    )
    mg = doc["margin"]
    bar.write(_margin_line(mg))
    if g.damage is not None:
        j = int(g.damage.pressure.argmax())
        bar.write(
            f"load on the object: peak contact pressure {g.damage.pressure[j] / 1e3:.3g} kPa "
            f"({g.fingers[j].name}), peak strain {g.damage.strain:.3g}"
        )
    for travel, why in g.hold_checks:  # the least travel held was searched for among held ones too
        if why != "held":
            bar.write(f"not held at {travel * 1e3:.2f} mm of travel: {why}; closed further")
    # The closing's held state is the least squeeze that holds, at the friction limit by design;
    # what a hand needs to know is whether its set-points leave room: a warning when a scale of
    # them within the force controller's tolerance does not hold.
    from softgrasp.execution.controller import ExecuteConfig

    reach = ExecuteConfig().tolerance
    if mg["not_held_scale"] >= 1.0 - reach:
        bar.write(
            f"note: at {mg['not_held_scale']:.2f} x the set-points the object is not held, within the force "
            f"controller's {reach:.0%} tolerance of them: for a real hand, whose forces and friction vary, "
            "plan with a larger --safety-factor"
        )
    bar.phase("figures")  # then the files, the figures and the view's data
    result.save(out, figures=figures, started=t0)
    bar.close()
    if uncertain:
        from softgrasp.cli.robust import robust

        return robust(args, result, uncertain, out, t0)
    print(
        f"wrote {out}/plan.json, history.csv, object.vtu, closing.pvd (and closing/), frames.npz, "
        "forces.png, force_penetration.png, grasp.png "
        f"({g.increments} increments, {time.perf_counter() - t0:.1f} s)"
    )
    return 0


def _uncertain(args: argparse.Namespace, obj, mu: float) -> list:
    """The --uncertain parameters (checked before the nominal plan runs)."""
    if not args.uncertain:
        for flag in ("quantile", "scheduler", "samples", "seed", "workers"):
            if getattr(args, flag) is not None:
                raise ConfigError(f"--{flag} applies to robust set-points: give --uncertain NAME=RANGE too")
        return []
    from softgrasp.api.robust import ROBUST_DEFAULTS, uncertain_parameters

    for key, default in ROBUST_DEFAULTS.items():
        if getattr(args, key) is None:
            setattr(args, key, default)
    if args.scheduler is not None:
        from softgrasp.sweep.engine import check_scheduler

        check_scheduler(args.scheduler)  # before the nominal plan
    return uncertain_parameters(
        obj, mu, args.uncertain, samples=args.samples, quantile=args.quantile, workers=args.workers
    )
