"""``python -m tofcore``: see :mod:`tofcore.cli`."""

import sys

from .cli import main

sys.exit(main())
