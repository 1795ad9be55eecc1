"""``python -m plenocl``: the command line."""

from .cli import main

raise SystemExit(main())
