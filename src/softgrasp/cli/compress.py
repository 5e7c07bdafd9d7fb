"""``softgrasp compress``: a compression test between rigid plates (paper Fig. 8-9)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from softgrasp.cli.args import add_common, limits, load, number, progress_bar

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    c = sub.add_parser("compress", help="compression test between rigid plates (paper Fig. 8-9)")
    add_common(c)
    c.add_argument(
        "--strain",
        type=number("strain"),
        default=0.3,
        help=f"final compressive strain, {limits('strain')} (default 0.3)",
    )
    c.add_argument(
        "--steps",
        type=number("compress_steps", "--steps"),
        default=30,
        help=f"load increments, {limits('compress_steps')} (default 30)",
    )
    c.add_argument(
        "--plate-friction",
        type=number("plate_friction"),
        default=0.5,
        help=f"plate friction coefficient, {limits('plate_friction')} (default 0.5, rubber on steel "
        "platens; faces stick at rest). 0 is a lubricated test, whose free sliding and rolling only "
        "weak tethers hold",
    )
    c.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from softgrasp.io.runfolder import run_folder

    out = args.out if args.out is not None else "softgrasp-out/compress"
    with run_folder(out, "compress"):  # checked and locked before any work
        return _run(args, Path(out))


def _run(args: argparse.Namespace, out: Path) -> int:
    from softgrasp.api.experiments import compress

    t0 = time.perf_counter()
    obj = load(args)
    print(f"object   {obj.summary()}")
    m = obj.material
    print(f"material {m.name}: E = {m.E / 1e3:.4g} kPa, nu = {m.nu:g}, density = {m.density:.4g} kg/m^3")
    bar, update = progress_bar("compress")
    try:
        test = compress(
            obj, strain=args.strain, steps=args.steps, plate_friction=args.plate_friction, progress=update
        )
    finally:
        bar.close()
    test.save(out, started=t0)
    res = test.result
    print(f"height {res.height_m * 1e3:.1f} mm, area {res.area_m2 * 1e6:.0f} mm^2, strain {args.strain:.0%}")
    print(
        f"apparent E {res.apparent_E_Pa / 1e3:.4g} kPa (initial slope), peak force {res.force_N.max():.3g} N"
    )
    print(f"wrote {out}/compress.csv, compress.json, compress.png ({time.perf_counter() - t0:.1f} s)")
    return 0
