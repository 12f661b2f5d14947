"""``python -m batch`` in a checkout, ``python -m tofcore_batch`` or the ``tofcore-batch`` command when
installed (the same package, ``batch/`` installs as ``tofcore_batch``): see the ``cli`` module.

Ctrl-C is handled from the first line here, before the imports (a few hundred milliseconds): see
:func:`batch.cli.hold_signals`. Only the interpreter's own start-up comes before it.
"""

import signal

if __name__ == "__main__":
    from .cli import hold_signals  # cli imports nothing heavy at module level

    hold_signals()
    from .cli import main

    # Guarded: worker processes started with "spawn" import the parent's main module as __mp_main__.
    raise SystemExit(main())
elif __name__ == "__mp_main__":
    # A worker process (local pool or Dask LocalCluster): the terminal's Ctrl-C reaches every process of
    # the group; the parent stops the workers itself, so they ignore it from their first line.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
