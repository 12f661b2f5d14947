"""Suite-wide set-up.

The tests exercise the NumPy reference tracer (the one that defines the frame) unless ``TOFCORE_TRACER``
is set: with numba installed a render would otherwise pick the compiled tracer, which
tests/tofcore/test_compiled.py checks against this reference. ``TOFCORE_TRACER=auto make test`` runs
the whole suite on the compiled tracer instead.
"""

import os

os.environ.setdefault("TOFCORE_TRACER", "numpy")
