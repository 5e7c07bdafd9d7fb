"""``softgrasp reproduce``: the paper's experiments end to end, and a report."""

from __future__ import annotations

import argparse

from softgrasp.cli.args import progress_bar

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    rp = sub.add_parser("reproduce", help="run the paper's experiments end to end and write a report")
    rp.add_argument(
        "--out", default=None, metavar="DIR", help="output folder (default softgrasp-out/reproduce)"
    )
    rp.add_argument(
        "--quick", action="store_true", help="coarse meshes: the whole run in well under 2 minutes"
    )
    rp.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from softgrasp.report.reproduce import reproduce

    out = args.out if args.out is not None else "softgrasp-out/reproduce"
    bar, update = progress_bar("reproduce")

    def progress(fraction: float, step: str) -> None:
        bar.set_description(f"reproduce: {step}")
        update(fraction)

    try:
        res = reproduce(out, quick=args.quick, progress=progress)
    finally:
        bar.close()
    for st in res.steps:
        extra = f": {st.message}" if st.message and st.status != "ok" else ""
        print(f"{st.status:>7}  {st.title} ({st.wall_time_s:.1f} s){extra}")
    print(f"wrote {res.report_md}, {res.report_html.name}, {res.data_json.name} ({res.wall_time_s:.1f} s)")
    return 1 if res.failed else 0
