"""``python -m fusion`` = the ``fusion`` command."""

import sys

from .cli import main

sys.exit(main())
