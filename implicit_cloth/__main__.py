"""``python -m implicit_cloth``: the command-line interface (see :mod:`implicit_cloth.cli`)."""

import sys

from .cli import main

sys.exit(main())
