"""``python -m batch`` in a checkout, ``python -m tofcore_batch`` or the ``tofcore-batch`` command when
installed (the same package, ``batch/`` installs as ``tofcore_batch``): see the ``cli`` module."""

import sys

from .cli import main

# Guarded: worker processes started with "spawn" import the parent's main module as __mp_main__.
if __name__ == "__main__":
    sys.exit(main())
