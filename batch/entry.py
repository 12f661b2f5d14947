"""The installed commands' entry points: ``tofcore`` and ``tofcore-batch`` (``[project.scripts]``).

A console script runs ``from MODULE import FUNCTION`` before it calls anything, so Ctrl-C can only be
taken over once that import is done. ``tofcore.cli`` is inside ``tofcore``, whose ``__init__`` imports
NumPy and the whole simulator (a few hundred milliseconds); this module is in the package installed
as ``tofcore_batch``, whose ``__init__`` imports nothing. Each function routes SIGINT and SIGTERM to
one line (``interrupted (SIGINT): nothing was written``) and exit code 130 / 143 first, then imports
the command, whose own handlers take over (the tracer's workers ignore SIGINT; the parent stops them).
Only the interpreter's own start-up (some 10-30 ms) comes before.
"""

try:
    from .interrupt import hold
except KeyboardInterrupt:  # Ctrl-C while that small module loads: no handler of ours yet
    import os

    os.write(2, b"\ninterrupted (SIGINT): nothing was written\n")
    os._exit(130)


def tofcore() -> int:
    """The ``tofcore`` command (:func:`tofcore.cli.main`)."""
    hold()
    from tofcore.cli import main

    return main()


def tofcore_batch() -> int:
    """The ``tofcore-batch`` command (:func:`batch.cli.main`)."""
    hold()
    from .cli import main

    return main()
