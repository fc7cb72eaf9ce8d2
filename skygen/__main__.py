"""``python -m skygen`` = the ``skygen`` command."""

import sys

from skygen.cli import main

sys.exit(main())
