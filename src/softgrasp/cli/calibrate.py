"""``softgrasp calibrate``: fit the material (compression) and contact law (indentation) to
measurements."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from softgrasp.cli.args import add_common, counting_bar, limits, load, material_file, number

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    ca = sub.add_parser(
        "calibrate", help="fit the material (compression) and contact law (indentation) to measurements"
    )
    add_common(ca)
    ca.set_defaults(object="cube")
    ca.add_argument(
        "--compression",
        default=None,
        metavar="DATA.csv",
        help="compression curve: displacement_m|displacement_mm,force_N or strain,stress_Pa|_kPa|_MPa; "
        "optional lateral_strain (then nu is fitted too)",
    )
    ca.add_argument(
        "--indentation",
        default=None,
        metavar="DATA.csv",
        help="force-penetration curve: penetration_m|penetration_mm,force_N (optional tangential_force_N)",
    )
    ca.add_argument(
        "--nu",
        type=number("nu"),
        default=None,
        help=f"Poisson's ratio when not fitted, {limits('nu')} (default: the material's)",
    )
    ca.add_argument(
        "--law",
        choices=("polynomial", "linear"),
        default="polynomial",
        help="spring law to fit (default polynomial)",
    )
    ca.add_argument(
        "--plate-friction",
        type=number("plate_friction"),
        default=0.5,
        help=f"friction of the compression platens, {limits('plate_friction')} (default 0.5)",
    )
    ca.add_argument(
        "--steps",
        type=number("compress_steps", "--steps"),
        default=16,
        help=f"increments of each simulated compression, {limits('compress_steps')} (default 16)",
    )
    ca.add_argument(
        "--radius",
        type=number("radius"),
        default=0.008,
        help=f"fingertip radius, {limits('radius')} (default 0.008)",
    )
    ca.add_argument(
        "--speed",
        type=number("speed"),
        default=0.005,
        help=f"indentation speed, {limits('speed')} (default 0.005)",
    )
    ca.add_argument(
        "--mu",
        type=number("mu"),
        default=None,
        help=f"fingertip friction coefficient, {limits('mu')} (default 0.8, or the material file's); "
        "fitted instead when the indentation data have tangential_force_N",
    )
    ca.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from softgrasp.io.runfolder import run_folder

    out = args.out if args.out is not None else "softgrasp-out/calibrate"
    with run_folder(out, "calibrate"):  # checked and locked before any work
        return _run(args, Path(out))


def _run(args: argparse.Namespace, out: Path) -> int:
    from softgrasp.api.calibration import calibrate, check_calibrate, read_indentation

    t0 = time.perf_counter()
    check_calibrate(args.compression, args.indentation, args.nu, args.plate_friction)
    # The indentation file needs no specimen: it is checked before any meshing.
    ind_data = read_indentation(args.indentation) if args.indentation else None
    material_file(args)
    obj = load(args)
    cal = calibrate(
        obj,
        compression=args.compression,
        indentation=ind_data,
        nu=args.nu,
        law=args.law,
        plate_friction=args.plate_friction,
        steps=args.steps,
        radius_m=args.radius,
        speed_m_s=args.speed,
        mu=args.mu,
        progress=counting_bar,
        echo=print,
    )
    cal.save(out, started=t0)
    figs = ", ".join(cal.figures)
    print(f"wrote {out}/calibration.json, material.toml, {figs} ({time.perf_counter() - t0:.1f} s)")
    return 0
