"""One exception family for the simulator.

Messages follow ``"{where}: {field} must be {rule}, got {value!r}"`` so that a
user can find the file, object or array at fault without reading a traceback.
:func:`is_number` is the one test of "a number" that those checks apply.
"""

import numbers


class TofError(Exception):
    """Base class of every error raised on purpose by tofcore."""


class SceneError(TofError, ValueError):
    """A scene's arrays or materials are invalid."""


class ConfigError(TofError, ValueError):
    """A configuration value (camera, LED, material, preset, settings) is invalid."""


class LimitError(ConfigError):
    """A request is larger than a resource limit of :mod:`tofcore.limits`; refused before allocating.

    The message names the limit, the value asked for and the environment variable that raises it.
    """


class ExrError(TofError, ValueError):
    """A file that tofcore's EXR codec cannot read: not an EXR file, damaged, truncated, of a kind it does
    not cover, or declaring more than it holds (:mod:`tofcore.output.exr`). The message is one line:
    ``"{path}: {defect}"``."""


class Cancelled(TofError):
    """A render was cancelled by its caller (``cancel`` callback); nothing was written."""


def is_number(value: object) -> bool:
    """True for a real number (int, float, NumPy integer or floating), False for bool and anything else."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)
