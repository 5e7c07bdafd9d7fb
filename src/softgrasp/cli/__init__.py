"""Command-line interface: parse, call the library's API (:mod:`softgrasp.api`), print. No physics
and no file formats here.

One module per command (``compress``, ``indent``, ``plan``, ``calibrate``, ``execute``, ``view``,
``reproduce``, ``sweep``, ``server``), the program in :mod:`softgrasp.cli.launch` (a ``plan`` runs
in a child of the warm server, :mod:`softgrasp.cli.zygote`, its lock file in
:mod:`softgrasp.cli.serverlock`), the parser and dispatch in :mod:`softgrasp.cli.main`, shared options in
:mod:`softgrasp.cli.args`, the help texts and global options (``--verbose``, ``--debug``,
``--threads``, before or after the command) in :mod:`softgrasp.cli.help`, progress by phase in
:mod:`softgrasp.cli.progress`, the optional extras a command needs in :mod:`softgrasp.cli.extras`.
Every deliberate error (:class:`softgrasp.errors.SoftgraspError`) becomes one line on stderr and
an exit status by its kind (:mod:`softgrasp.cli.status`): 1 for a computation that ends without
its result on valid input, 2 for bad input, including every option outside its physical range
(:mod:`softgrasp.model.ranges`, stated in ``--help``), refused before any work; 3 for an internal
error; an interrupted run exits 130. Lengths are given in metres on the command line (a mesh
file's coordinates and a shape's sizes in ``--units``) and printed in millimetres for people.
"""

from __future__ import annotations

from softgrasp.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
