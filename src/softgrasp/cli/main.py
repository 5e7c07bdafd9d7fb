"""The ``softgrasp`` argument parser and the dispatch to the commands (one module each)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from softgrasp import __version__
from softgrasp.cli import calibrate, compress, execute, indent, plan, reproduce, sweep, view
from softgrasp.cli.args import Parser
from softgrasp.errors import SoftgraspError

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The ``softgrasp`` argument parser."""
    p = Parser(prog="softgrasp", description="Grasp planning for soft objects (SI units; lengths in m).")
    p.add_argument("--version", action="version", version=f"softgrasp {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    p.add_argument(
        "--verbose",
        action="store_true",
        help="print the static solver's progress to stderr (every Newton iteration, friction pass "
        "and split load increment)",
    )
    sub = p.add_subparsers(dest="command", parser_class=Parser)
    for command in (compress, indent, plan, calibrate, view, reproduce, sweep, execute):
        command.add_parser(sub)
    return p


def _log_progress() -> None:
    """The solvers' DEBUG records (:mod:`softgrasp.sim.static`) to stderr, one line each."""
    import logging

    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("softgrasp: %(message)s"))
    log = logging.getLogger("softgrasp")
    log.addHandler(handler)
    log.setLevel(logging.DEBUG)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``softgrasp`` command; returns its exit status (2: a refused argument,
    option or input; 0 after ``--help``)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or an argument refused in one line
        return exc.code if isinstance(exc.code, int) else 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    if getattr(args, "verbose", False):
        _log_progress()
    try:
        return int(args.func(args))
    except SoftgraspError as exc:
        print(f"softgrasp: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        import signal

        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not break the exit
        print("softgrasp: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: keep it to one line unless asked
        if args.debug:
            raise
        print(
            f"softgrasp: internal error: {type(exc).__name__}: {exc} (rerun with --debug for details)",
            file=sys.stderr,
        )
        return 3
