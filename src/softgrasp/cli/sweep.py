"""``softgrasp sweep``: many plans (a grid or random draw over any plan option) on Dask."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from softgrasp.cli.args import counting_bar, limits, number, scheduler

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    sw = sub.add_parser("sweep", help="plan many cases (grid or random over any plan option) on Dask")
    sw.add_argument("sweep", metavar="SWEEP.toml", help="the sweep: [sweep], [base], [grid] or [random]")
    sw.add_argument(
        "--scheduler",
        type=scheduler,
        default=None,
        metavar="ADDRESS",
        help="a running Dask scheduler (tcp://host:port)",
    )
    sw.add_argument(
        "--workers",
        type=number("workers"),
        default=2,
        help=f"local worker processes, {limits('workers')} (default 2)",
    )
    sw.add_argument("--out", default=None, metavar="DIR", help="output folder (default softgrasp-out/sweep)")
    sw.add_argument(
        "--resume",
        action="store_true",
        help="keep the finished rows in DIR (one per case; the same sweep file only), run the rest",
    )
    sw.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from softgrasp.cli.extras import require
    from softgrasp.io.runfolder import run_folder
    from softgrasp.sweep.spec import read_sweep, sweep_cases

    require("sweep", "softgrasp sweep")
    spec = read_sweep(args.sweep)
    if spec.execute:
        require("execute", "a sweep that executes its plans (execute = true)")
    if args.scheduler is not None:
        from softgrasp.sweep.engine import check_scheduler

        check_scheduler(args.scheduler)  # before any work
    out = args.out if args.out is not None else "softgrasp-out/sweep"
    with run_folder(out, "sweep") as folder:  # checked and locked before any work
        return _run(args, spec, sweep_cases(spec), Path(out), folder.stage)


def _run(args: argparse.Namespace, spec, cases: list, out: Path, stage: Path) -> int:
    from softgrasp.sweep.engine import run_sweep
    from softgrasp.sweep.report import sweep_figures

    where = args.scheduler or f"a local Dask cluster of {args.workers} worker process(es)"
    print(
        f"sweep {args.sweep}: {len(cases)} cases ({spec.mode} over {', '.join(spec.varied)}) on {where}"
        + (", executing each plan" if spec.execute else "")
    )
    with counting_bar("sweep", " cases", total=len(cases)) as update:
        res = run_sweep(
            spec,
            cases,
            out,
            scheduler=args.scheduler,
            workers=args.workers,
            resume=args.resume,
            progress=lambda done, total: update(done),
        )
    figures = sweep_figures(spec, res.rows, stage)
    per_min = 60.0 * res.ran / res.wall_time_s if res.wall_time_s > 0 else float("nan")
    print(
        f"{len(res.rows)} cases: {len(res.rows) - res.failed} planned, {res.failed} failed"
        + (f" ({res.resumed} from the earlier run)" if res.resumed else "")
        + f"; {res.ran} run in {res.wall_time_s:.1f} s ({per_min:.1f} cases/min on {res.workers} workers)"
    )
    for r in res.rows:
        if r["status"] == "failed":
            print(f"  case {r['case']} failed: {r['error']}")
    names = ", ".join(["results.csv", "results.parquet", "sweep.json", *(f.name for f in figures)])
    print(f"wrote {out}/{names}")
    if res.failed:
        print(
            f"softgrasp: error: {res.failed} of {len(res.rows)} cases failed (their errors above and in "
            "results.csv)",
            file=sys.stderr,
        )
        return 1
    return 0
