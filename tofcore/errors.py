"""One exception family for the simulator.

Messages follow ``"{where}: {field} must be {rule}, got {value!r}"`` so that a
user can find the file, object or array at fault without reading a traceback.
"""


class TofError(Exception):
    """Base class of every error raised on purpose by tofcore."""


class SceneError(TofError, ValueError):
    """A scene's arrays or materials are invalid."""


class ConfigError(TofError, ValueError):
    """A configuration value (camera, LED, material, preset, settings) is invalid."""


class Cancelled(TofError):
    """A render was cancelled by its caller (``cancel`` callback); nothing was written."""
