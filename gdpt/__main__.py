"""``python -m gdpt``: the gdpt command line (see :mod:`gdpt.cli`)."""

from gdpt.cli import main

raise SystemExit(main())
