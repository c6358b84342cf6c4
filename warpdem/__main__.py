"""``python -m warpdem``: see :mod:`warpdem.cli`."""

from .cli import main

raise SystemExit(main())
