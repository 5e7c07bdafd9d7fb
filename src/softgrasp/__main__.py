"""`python -m softgrasp`: the command line."""

from softgrasp.cli import main

raise SystemExit(main())
