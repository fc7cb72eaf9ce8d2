"""``python -m skygen`` = the ``skygen`` command."""

import sys

from .cli import main

sys.exit(main())
