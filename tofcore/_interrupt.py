"""Ctrl-C while ``python -m tofcore`` imports the simulator: one line and exit code 130, no traceback.

The package's ``__init__`` calls :func:`hold_until_the_command_starts` first thing when this process
was started as ``python -m tofcore`` (never when tofcore is imported as a library);
:func:`tofcore.cli.main` then takes SIGINT back. The installed ``tofcore`` command does the same from
``tofcore_batch.entry``.

Only ``_signal`` (the interpreter's built-in module, loaded at start-up) and ``os`` (loaded by ``site``)
are used: the ``signal`` module builds its enums when imported (~7 ms of ``enum`` and ``functools``), and a
Ctrl-C in those milliseconds was a KeyboardInterrupt traceback (issue 35).
"""

import os
import _signal

#: Signal numbers → names, for the one line (``signal.Signals`` would import the enum machinery).
NAMES = {_signal.SIGINT: "SIGINT", _signal.SIGTERM: "SIGTERM"}


def _exit_at_once(signum, _frame) -> None:
    os.write(2, f"\ninterrupted ({NAMES.get(signum, signum)}): nothing was written\n".encode())
    os._exit(128 + signum)


def hold_until_the_command_starts() -> None:
    """Route SIGINT and SIGTERM to one line on stderr and exit code 128 + signal number."""
    _signal.signal(_signal.SIGINT, _exit_at_once)
    _signal.signal(_signal.SIGTERM, _exit_at_once)
    # A parent that started us with them blocked (inherited through exec) would hold Ctrl-C back for good.
    _signal.pthread_sigmask(_signal.SIG_UNBLOCK, {_signal.SIGINT, _signal.SIGTERM})
