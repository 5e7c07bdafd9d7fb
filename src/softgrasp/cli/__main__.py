"""`python -m softgrasp.cli`: the command line."""

from softgrasp.cli import main

raise SystemExit(main())
