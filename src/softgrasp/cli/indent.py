"""``softgrasp indent``: one fingertip pressed into the object (paper Fig. 10-11)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from softgrasp.cli.args import add_common, limits, load, material_file, number, progress_bar

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    i = sub.add_parser("indent", help="one fingertip pressed into the object (paper Fig. 10-11)")
    add_common(i)
    i.set_defaults(object="cube", func=run)
    for action in i._actions:  # the shared options, with this command's defaults
        if action.dest == "object":
            action.help = f"{action.help} (default: cube, the paper's foam cube)"
        elif action.dest == "out":
            action.help = f"{action.help} (default: softgrasp-out/indent)"
    i.add_argument(
        "--depth",
        type=number("depth"),
        default=0.005,
        help=f"penetration beyond first contact, {limits('depth')}, below the object's height "
        "(default 0.005)",
    )
    i.add_argument(
        "--radius",
        type=number("radius"),
        default=0.008,
        help=f"fingertip radius, {limits('radius')} (default 0.008)",
    )
    i.add_argument(
        "--speed",
        type=number("speed"),
        default=0.005,
        help=f"fingertip speed, {limits('speed')} (default 0.005)",
    )
    i.add_argument(
        "--steps",
        type=number("indent_steps", "--steps"),
        default=None,
        metavar="N",
        help=f"load increments, {limits('indent_steps')} (default: ~0.25 mm each, >= 10)",
    )
    i.add_argument(
        "--mu",
        type=number("mu"),
        default=None,
        help=f"fingertip friction coefficient, {limits('mu')} (default 0.8, or the material file's)",
    )
    i.add_argument(
        "--rule",
        choices=("patch", "facet"),
        default="patch",
        help="force rule over touched facets (default patch; facet is the paper's literal rule, "
        "whose force jumps as facets enter contact, so static solves may fail)",
    )
    i.add_argument(
        "--contact-law",
        choices=("resolved", "paper"),
        default="resolved",
        help="fingertip normal law: resolved (default; Hertz's, the object's compliance counted once "
        "with its mesh) or paper (K delta^n in series with the meshed body, Eq. 9-11)",
    )
    i.add_argument(
        "--contact-mesh-size",
        type=_contact_size,
        default="auto",
        metavar="SIZE|auto|none",
        help="mesh the object again with elements of SIZE [m] where the fingertip presses and where it "
        "rests on the table, so that the mesh resolves the contact patches (a built-in object or a "
        "shape; boxes are then meshed by gmsh). auto (default): a third of the Hertz contact radius "
        "at --depth, under the resolved law on an object softgrasp meshes (a mesh file and the paper "
        "law keep the mesh as it is); none: the object's own mesh",
    )
    i.add_argument(
        "--data",
        default=None,
        metavar="FILE",
        help="measured CSV with a header: penetration_m (or penetration_mm) and force_N; "
        "penetrations must lie within 0..--depth; overlaid and compared (mean absolute error)",
    )


def _contact_size(text: str) -> float | str | None:
    """An argument type: ``auto``, ``none`` (None) or an element size in metres (--mesh-size's
    range)."""
    if text == "auto":
        return text
    if text == "none":
        return None
    try:
        float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--contact-mesh-size must be auto, none or a length in metres, got {text!r}"
        ) from None
    return number("mesh_size", "--contact-mesh-size")(text)


def run(args: argparse.Namespace) -> int:
    from softgrasp.io.runfolder import run_folder

    out = args.out if args.out is not None else "softgrasp-out/indent"
    with run_folder(out, "indent"):  # checked and locked before any work
        return _run(args, Path(out))


def _run(args: argparse.Namespace, out: Path) -> int:
    from softgrasp.api.experiments import check_indent, indent, read_force_curve
    from softgrasp.model.objects import is_mesh_file

    t0 = time.perf_counter()
    check_indent(args.mu, args.steps)
    material_file(args)  # a bad material file is reported before the data and the meshing
    measured = read_force_curve(args.data, args.depth) if args.data else None
    obj = load(args)
    print(f"object   {obj.summary()}")
    m = obj.material
    print(f"material {m.name}: E = {m.E / 1e3:.4g} kPa, nu = {m.nu:g}, density = {m.density:.4g} kg/m^3")
    bar, update = progress_bar("indent")
    try:
        test = indent(
            obj,
            depth_m=args.depth,
            radius_m=args.radius,
            speed_m_s=args.speed,
            steps=args.steps,
            mu=args.mu,
            rule=args.rule,
            contact_law=args.contact_law,
            data=measured,
            contact_mesh_size_m=args.contact_mesh_size,
            progress=update,
        )
    finally:
        bar.close()
    test.save(out, started=t0)
    res = test.result
    if test.object.refinement is not None:
        size = test.object.refinement.size_m
        print(f"mesh     {test.object.summary()}, {size * 1e3:.3g} mm at the fingertip and the table")
    elif args.contact_mesh_size == "auto" and is_mesh_file(test.object.source):
        print(
            "note: a mesh file is indented on its own mesh; mesh it finer where the fingertip presses and "
            "where it rests to resolve the contact patches"
        )
    print(
        f"finger   R = {args.radius * 1e3:.3g} mm, depth {args.depth * 1e3:.3g} mm in {test.steps} "
        "increments, "
        f"mu = {test.contact.mu:g}, {args.rule} rule, {test.contact.law} law"
    )
    if res.turned:
        print(
            "note: the mesh does not stand as given (its centre of mass is not above its lowest nodes): "
            "it is pressed turned onto its most stable facet, as plan places it"
        )
    if res.point_shift_m > 0:
        print(
            f"note: press point moved {res.point_shift_m * 1e6:.3g} um off a mesh vertex/edge, where the "
            "facet contact test cannot see the fingertip"
        )
    print(
        f"force at {res.depth_m * 1e3:.3g} mm: {res.force_N[-1]:.4g} N (peak {res.peak_force_N:.4g} N), "
        f"K = {res.K_N_m1_5:.4g} N/m^1.5, contact depth {res.contact_depth_m[-1] * 1e3:.3g} mm"
    )
    if measured is not None and test.mean_abs_error_N is not None:
        print(
            f"mean absolute force error vs {measured.points} measured points: {test.mean_abs_error_N:.3g} N"
        )
    print(f"wrote {out}/indent.csv, indent.json, indent.png ({time.perf_counter() - t0:.1f} s)")
    return 0
