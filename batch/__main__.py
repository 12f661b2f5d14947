"""``python -m batch`` in a checkout, ``python -m tofcore_batch`` or the ``tofcore-batch`` command when
installed (the same package, ``batch/`` installs as ``tofcore_batch``): see the ``cli`` module.

Ctrl-C and SIGTERM are taken over by the first lines here, before any import of this package's
modules (those take a few hundred milliseconds): one line and exit code 130 / 143 until a command
installs its own handlers (``batch.cli.hold_signals``). Only the interpreter's own start-up comes first.
"""

import os
import signal


def _exit_at_once(signum, _frame) -> None:  # the same as batch.cli._exit_at_once, which is not imported yet
    os.write(2, f"\ninterrupted ({signal.Signals(signum).name}): nothing was written\n".encode())
    os._exit(128 + signum)


if __name__ == "__main__":
    signal.signal(signal.SIGINT, _exit_at_once)
    signal.signal(signal.SIGTERM, _exit_at_once)
    from .cli import main

    # Guarded: worker processes started with "spawn" import the parent's main module as __mp_main__.
    raise SystemExit(main())
