"""The ``--help`` texts that span the commands: each command's one-line description and an
example, the global options, and the exit statuses."""

from __future__ import annotations

import argparse
import textwrap

from softgrasp.cli.status import EXIT_CODES

__all__ = ["COMMANDS", "add_global_options", "describe", "exit_codes_epilog"]

#: Each command: its one-line description and an example command line.
COMMANDS: dict[str, tuple[str, str]] = {
    "plan": (
        "Plan a three-finger grasp of a soft object and the force set-points that hold it "
        "(paper Sec. 2, 4.3).",
        "softgrasp plan --object fruit.stl --units mm --material foam --out runs/fruit",
    ),
    "execute": (
        "Execute a plan under force control on a simulated MuJoCo hand, lift the object and check it "
        "stays held (needs the 'execute' extra).",
        "softgrasp execute runs/fruit --lift 0.05",
    ),
    "view": (
        "Write an interactive, self-contained 3-D page of a plan run (closing increments, forces).",
        "softgrasp view runs/fruit",
    ),
    "sweep": (
        "Plan every case of a grid or random draw over plan options on a Dask cluster (needs the "
        "'sweep' extra).",
        "softgrasp sweep sweep.toml --workers 2 --out runs/sweep",
    ),
    "calibrate": (
        "Fit the material (compression) and the contact law (indentation) to measured curves.",
        "softgrasp calibrate --object cube --compression compression.csv --out runs/calibration",
    ),
    "compress": (
        "Simulate a compression test of the object between rigid plates (paper Fig. 8-9).",
        "softgrasp compress --object cube --material foam --strain 0.3",
    ),
    "indent": (
        "Simulate one fingertip pressed into the object (paper Fig. 10-11).",
        "softgrasp indent --object cube --depth 0.005",
    ),
    "reproduce": (
        "Run the paper's experiments end to end and write a report beside the paper's numbers.",
        "softgrasp reproduce --quick --out runs/reproduce",
    ),
    "server": (
        "Start, list or stop the warm server a plan runs in: its modules imported and kernels loaded "
        "once, a forked child per command (Linux).",
        "softgrasp server status",
    ),
}


def exit_codes_epilog() -> str:
    """The exit statuses, one line each, for an epilog."""
    lines = (
        textwrap.fill(text, 78, initial_indent=f"  {code:<4}", subsequent_indent=" " * 6)
        for code, text in EXIT_CODES.items()
    )
    return "exit status:\n" + "\n".join(lines)


def describe(name: str, parser: argparse.ArgumentParser) -> None:
    """Give command ``name``'s parser its one-line description (unless it has a longer one), its
    example and the exit statuses as the epilog."""
    line, example = COMMANDS[name]
    parser.description = textwrap.fill(parser.description or line, 78)
    parser.epilog = f"example:\n  {example}\n\n{exit_codes_epilog()}"
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def _threads(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--threads must be a whole number >= 1, got {text!r}") from None
    if not 1 <= n <= 1024:
        raise argparse.ArgumentTypeError(f"--threads must be from 1 to 1024, got {n}")
    return n


def add_global_options(parser: argparse.ArgumentParser, *, command: bool = False) -> None:
    """``--verbose``, ``--debug``, ``--threads`` and ``--no-server``, accepted before the command and after it
    (``command``: on a command's parser, where an option not given leaves the value given before
    the command)."""
    unset = {"default": argparse.SUPPRESS} if command else {}
    parser.add_argument(
        "--debug", action="store_true", help="show the traceback of an internal error", **unset
    )
    parser.add_argument(
        "--verbose",
        action="store_true",
        help="print the static solver's progress to stderr (every Newton iteration, friction pass "
        "and split load increment)",
        **unset,
    )
    parser.add_argument(
        "--threads",
        type=_threads,
        metavar="N",
        help="threads of the solvers and compiled kernels (default: the cores this process may use)",
        **({"default": argparse.SUPPRESS} if command else {"default": None}),
    )
    parser.add_argument(
        "--no-server",
        action="store_true",
        help="run in this process, not in softgrasp's warm server (softgrasp server)",
        **unset,
    )
