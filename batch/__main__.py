"""``python -m batch`` in a checkout, ``python -m tofcore_batch`` or the ``tofcore-batch`` command when
installed (the same package, ``batch/`` installs as ``tofcore_batch``): see the ``cli`` module.

Ctrl-C and SIGTERM are taken over by the first lines here, before any import of this package's
modules (those take a few hundred milliseconds): one line and exit code 130 / 143 until a command
installs its own handlers (``batch.entry``, ``batch.cli.hold_signals``). Only the interpreter's own
start-up comes first.
"""

if __name__ == "__main__":
    try:
        from .entry import tofcore_batch
    except KeyboardInterrupt:  # Ctrl-C while entry's own imports (signal, os) were loading: no handler yet
        import os
        os.write(2, b"\ninterrupted (SIGINT): nothing was written\n")
        os._exit(130)

    # Guarded: worker processes started with "spawn" import the parent's main module as __mp_main__.
    raise SystemExit(tofcore_batch())
