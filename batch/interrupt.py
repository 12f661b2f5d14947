"""Ctrl-C before a command has started: one line and exit code 128 + signal number, no traceback.

Imports nothing but ``os`` (loaded by ``site``) and ``_signal`` (the interpreter's built-in signal module,
loaded at start-up; the ``signal`` module would first build its enums, ~7 ms in which a Ctrl-C was a
traceback), so the entry points (:mod:`batch.entry`, ``python -m batch``) can install it before NumPy,
tofcore or argparse load; :mod:`batch.cli` keeps it until a command takes over (``tofcore._interrupt`` is
the same for ``python -m tofcore``, which cannot import this package).
"""

import os
import _signal

#: Signal numbers → names, for the one line (``signal.Signals`` would import the enum machinery).
NAMES = {_signal.SIGINT: "SIGINT", _signal.SIGTERM: "SIGTERM"}


def exit_at_once(signum, _frame) -> None:
    """Before a command writes anything (imports, parsing, reading): say so and exit."""
    os.write(2, f"\ninterrupted ({NAMES.get(signum, signum)}): nothing was written\n".encode())
    os._exit(128 + signum)


def hold() -> None:
    """Route SIGINT and SIGTERM to :func:`exit_at_once`."""
    _signal.signal(_signal.SIGINT, exit_at_once)
    _signal.signal(_signal.SIGTERM, exit_at_once)
    # A parent that started us with them blocked (inherited through exec) would hold Ctrl-C back for good.
    _signal.pthread_sigmask(_signal.SIG_UNBLOCK, {_signal.SIGINT, _signal.SIGTERM})
