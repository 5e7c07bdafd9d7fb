"""``softgrasp view``: an interactive 3-D page of a plan run."""

from __future__ import annotations

import argparse

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    vw = sub.add_parser(
        "view", help="write an interactive 3-D page of a plan run (closing increments, forces)"
    )
    vw.add_argument(
        "run_dir", metavar="RUN", help="a plan run: the folder softgrasp plan --out wrote, or its plan.json"
    )
    vw.add_argument(
        "--out", default=None, metavar="FILE.html", help="the page (default view.html in the run's folder)"
    )
    vw.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import os

    from softgrasp.cli.args import run_folder_of
    from softgrasp.io.runfolder import check_out_file, write_failure
    from softgrasp.viz.view import write_view

    if args.out is not None:
        check_out_file(args.out)
    run_dir = run_folder_of(args.run_dir)
    out = args.out if args.out is not None else os.path.join(run_dir, "view.html")
    try:
        path = write_view(run_dir, args.out)
    except OSError as exc:  # a full disk, say
        raise write_failure(exc, out, "--out" if args.out is not None else "the page") or exc from None
    print(f"wrote {path} (open it in a browser; it needs no network)")
    return 0
