"""``python -m mcsm.cli``: the same as the ``mcsm`` command."""

from mcsm.cli.parser import main

raise SystemExit(main())
