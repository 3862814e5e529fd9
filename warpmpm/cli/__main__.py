"""``python -m warpmpm.cli``: the ``warpmpm`` command."""

from . import main

raise SystemExit(main())
