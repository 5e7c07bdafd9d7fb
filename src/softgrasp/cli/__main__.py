"""`python -m softgrasp.cli`: the command line."""

from softgrasp.cli.launch import entry

raise SystemExit(entry())
