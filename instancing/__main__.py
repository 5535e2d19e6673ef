"""``python -m instancing``: the command line (see :mod:`instancing.cli`)."""

import sys

from .cli import main

sys.exit(main())
