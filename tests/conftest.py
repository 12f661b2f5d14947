"""Suite-wide set-up.

The tests exercise the NumPy reference tracer (the one that defines the frame) unless ``TOFCORE_TRACER``
is set: with numba installed a render would otherwise pick the compiled tracer, which
tests/tofcore/test_compiled.py checks against this reference. ``TOFCORE_TRACER=auto make test`` runs
the whole suite on the compiled tracer instead.

Every test must leave this process's SIGINT and SIGTERM as it found them (:func:`signals_are_restored`):
an ignored or blocked SIGINT is inherited by every child a later test starts (a Ctrl-C test's child then
never sees its Ctrl-C), a leftover handler turns a later SIGTERM into something else.
"""

import os
import signal

import pytest

os.environ.setdefault("TOFCORE_TRACER", "numpy")


def _signal_state() -> tuple:
    """SIGINT's and SIGTERM's handlers and whether SIGINT/SIGTERM are blocked in this thread."""
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, []) if hasattr(signal, "pthread_sigmask") else set()
    return (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM),
            sorted(int(s) for s in blocked if s in (signal.SIGINT, signal.SIGTERM)))


@pytest.fixture(autouse=True)
def signals_are_restored():
    """Fails the test (at its teardown) that changed SIGINT's or SIGTERM's handler or blocked them."""
    before = _signal_state()
    yield
    after = _signal_state()
    assert after == before, f"the test left (SIGINT handler, SIGTERM handler, blocked) {before} as {after}"
