"""`python -m softgrasp`: the command line."""

from softgrasp.cli.launch import entry

raise SystemExit(entry())
