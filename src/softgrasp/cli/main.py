"""The ``softgrasp`` argument parser and the dispatch to the commands (one module each)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from softgrasp import __version__, interrupt
from softgrasp.cli import calibrate, compress, execute, indent, plan, reproduce, server, sweep, view
from softgrasp.cli.args import Parser
from softgrasp.cli.help import add_global_options, describe, exit_codes_epilog
from softgrasp.cli.status import BAD_INPUT, INTERNAL, INTERRUPTED, exit_status
from softgrasp.errors import SoftgraspError

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The ``softgrasp`` argument parser."""
    p = Parser(
        prog="softgrasp",
        description="Grasp planning for soft objects (SI units; lengths in m).\n"
        "'softgrasp COMMAND --help' gives a command's options and an example.",
        epilog=exit_codes_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"softgrasp {__version__}")
    add_global_options(p)
    sub = p.add_subparsers(dest="command", parser_class=Parser, metavar="COMMAND")
    for command in (compress, indent, plan, calibrate, view, reproduce, sweep, execute, server):
        command.add_parser(sub)
    for name, parser in sub.choices.items():
        describe(name, parser)
        add_global_options(parser, command=True)
    return p


def _log_progress() -> None:
    """The solvers' DEBUG records (:mod:`softgrasp.sim.static`) to stderr, one line each."""
    import logging

    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("softgrasp: %(message)s"))
    log = logging.getLogger("softgrasp")
    log.addHandler(handler)
    log.setLevel(logging.DEBUG)


def _set_threads(n: int) -> None:
    """``--threads N``: the solvers' and compiled kernels' thread count in this process
    (:func:`softgrasp.linalg.threads.set_threads`) and in the worker processes it starts."""
    import os

    from softgrasp.linalg.threads import THREADS_ENV, set_threads

    set_threads(n)
    os.environ[THREADS_ENV] = str(n)  # Dask's and the figures' worker processes read it at import
    import numba

    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``softgrasp`` command; returns its exit status (``softgrasp --help``
    lists them: :mod:`softgrasp.cli.status`)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or an argument refused in one line
        return exc.code if isinstance(exc.code, int) else BAD_INPUT
    if not getattr(args, "func", None):
        parser.print_help()
        return BAD_INPUT
    if args.verbose:
        _log_progress()
    if argv is None:  # the process's own command: a Ctrl-C is recorded too (softgrasp.interrupt)
        interrupt.install()
        if args.func is plan.run:  # its start-up: no collector passes until the kernels are loaded
            from softgrasp.cli.warm import pause_collector

            pause_collector()
    try:
        if args.threads is not None:
            _set_threads(args.threads)
        status = int(args.func(args))
        interrupt.raise_if_interrupted()
        return status
    except KeyboardInterrupt:
        return _interrupted(argv)
    except Exception as exc:
        # a Ctrl-C a library turned into its own error (NumPy's ImportError when it lands in its
        # initialisation), which softgrasp may have turned into its own (a missing extra)
        if interrupt.interrupted():
            return _interrupted(argv)
        if isinstance(exc, SoftgraspError):
            print(f"softgrasp: error: {exc}", file=sys.stderr)
            return exit_status(exc)
        if args.debug:  # a bug: keep it to one line unless asked
            raise
        print(
            f"softgrasp: internal error: {type(exc).__name__}: {exc} (rerun with --debug for details)",
            file=sys.stderr,
        )
        return INTERNAL
    finally:
        # The command is over, its files written or left as they were: a Ctrl-C while the
        # interpreter exits would only kill the process by the signal.
        _ignore_sigint(argv)
        if argv is None:
            # The interpreter's exit collects garbage over every object the libraries made (about
            # 0.3 s after a plan); frozen, they are left to the operating system.
            import gc

            from softgrasp.cli.warm import resume_collector

            resume_collector()  # a command that ended before its kernels were loaded
            gc.freeze()


def _interrupted(argv: Sequence[str] | None) -> int:
    """Say the command was interrupted; its exit status."""
    _ignore_sigint(argv)  # a second Ctrl-C must not break the exit
    print("softgrasp: interrupted", file=sys.stderr)
    return INTERRUPTED


def _ignore_sigint(argv: Sequence[str] | None) -> None:
    """Ignore Ctrl-C from now on in the process's own command (a caller passing ``argv`` keeps
    its handler)."""
    import threading

    if argv is None and threading.current_thread() is threading.main_thread():
        import signal

        signal.signal(signal.SIGINT, signal.SIG_IGN)
