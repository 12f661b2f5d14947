"""Ctrl-C while ``python -m tofcore`` imports the simulator: one line and exit code 130, no traceback.

The package's ``__init__`` calls :func:`hold_until_the_command_starts` first thing when this process
was started as ``python -m tofcore`` (never when tofcore is imported as a library);
:func:`tofcore.cli.main` then takes SIGINT back. The installed ``tofcore`` command does the same from
``tofcore_batch.entry``.
"""

import os
import signal


def _exit_at_once(signum, _frame) -> None:
    os.write(2, f"\ninterrupted ({signal.Signals(signum).name}): nothing was written\n".encode())
    os._exit(128 + signum)


def hold_until_the_command_starts() -> None:
    """Route SIGINT and SIGTERM to one line on stderr and exit code 128 + signal number."""
    signal.signal(signal.SIGINT, _exit_at_once)
    signal.signal(signal.SIGTERM, _exit_at_once)
    # A parent that started us with them blocked (inherited through exec) would hold Ctrl-C back for good.
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
