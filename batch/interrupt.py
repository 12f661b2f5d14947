"""Ctrl-C before a command has started: one line and exit code 128 + signal number, no traceback.

Imports nothing but ``os`` and ``signal``, so the entry points (:mod:`batch.entry`, ``python -m batch``)
can install it before NumPy, tofcore or argparse load; :mod:`batch.cli` keeps it until a command takes
over (``tofcore._interrupt`` is the same for ``python -m tofcore``, which cannot import this package).
"""

import os
import signal


def exit_at_once(signum, _frame) -> None:
    """Before a command writes anything (imports, parsing, reading): say so and exit."""
    os.write(2, f"\ninterrupted ({signal.Signals(signum).name}): nothing was written\n".encode())
    os._exit(128 + signum)


def hold() -> None:
    """Route SIGINT and SIGTERM to :func:`exit_at_once`."""
    signal.signal(signal.SIGINT, exit_at_once)
    signal.signal(signal.SIGTERM, exit_at_once)
    # A parent that started us with them blocked (inherited through exec) would hold Ctrl-C back for good.
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
