"""``python -m batch``: see :mod:`batch.cli`."""

import sys

from .cli import main

# Guarded: worker processes started with "spawn" import the parent's main module as __mp_main__.
if __name__ == "__main__":
    sys.exit(main())
