"""``python -m torm``: the ``torm`` command line (see :mod:`torm.cli`)."""

import sys

from torm.cli import main

sys.exit(main())
