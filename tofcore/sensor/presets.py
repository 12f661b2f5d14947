"""Sensor presets: the TOML files in ``presets/`` at the top of the repository.

====================  =======================================================================
function              meaning
====================  =======================================================================
:func:`list_presets`  names of the shipped presets (file stems), sorted
:func:`load_preset`   a :class:`~tofcore.sensor.Sensor` from a preset name or a .toml path
====================  =======================================================================

A preset is data only: every key is a :class:`~tofcore.sensor.Sensor` field
(tables for the sub-objects, ``[[leds]]`` for the emitters), and every number
carries its source in the ``[sources]`` table. Errors name the file (and, for
TOML syntax errors, the line).

Example
-------
>>> list_presets()
['kinect_v2', 'o3d303', 'xtion2']
>>> load_preset("o3d303").modulation.frequencies_hz
(30000000.0,)
"""

from __future__ import annotations

import difflib
import os
import tomllib
from pathlib import Path

from .. import limits
from ..errors import ConfigError
from .config import Sensor


def _presets_dir() -> Path:
    """``<repository>/presets`` in a checkout; ``tofcore/_presets`` in an installed wheel (copied at build)."""
    package = Path(__file__).resolve().parents[1]
    bundled = package / "_presets"
    return bundled if bundled.is_dir() else package.parent / "presets"


PRESETS_DIR = _presets_dir()
"""Where the shipped presets live: ``<repository>/presets`` (the single source; ``setup.py`` copies it
into wheels as ``tofcore/_presets``)."""


def list_presets() -> list[str]:
    """Names of the shipped presets (the ``*.toml`` stems in :data:`PRESETS_DIR`), sorted."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.toml"))


def preset_path(name_or_path: str | os.PathLike[str]) -> Path:
    """The file of a preset: a name from :func:`list_presets` (any case; ``-``, ``_`` and spaces alike), or a
    path (anything ending in ``.toml`` or containing a directory separator). An unknown name is a
    ConfigError listing the names, with the closest one as "did you mean"."""
    text = os.fspath(name_or_path)
    if isinstance(name_or_path, os.PathLike) or text.endswith(".toml") or "/" in text or os.sep in text:
        return Path(text)
    names = list_presets()
    by_folded = {_folded(name): name for name in names}
    name = by_folded.get(_folded(text))
    if name is None:
        close = difflib.get_close_matches(_folded(text), list(by_folded), n=1)
        hint = f" (did you mean {by_folded[close[0]]!r}?)" if close else ""
        raise ConfigError(f"preset: name must be one of {names} or a path to a .toml file, got {text!r}{hint}")
    return PRESETS_DIR / f"{name}.toml"


def _folded(name: str) -> str:
    """A preset name as compared: case and the separators ``-``, ``_``, space ignored (``Kinect-V2`` is
    ``kinect_v2``)."""
    return "".join(ch for ch in name.casefold() if ch not in "-_ ")


def load_preset(name_or_path: str | os.PathLike[str]) -> Sensor:
    """Read and validate a sensor preset.

    Parameters
    ----------
    name_or_path : str or path-like
        A preset name (``"kinect_v2"``, ``"o3d303"``, ``"xtion2"``; see
        :func:`list_presets`) or the path of a TOML file in the same format.

    Returns
    -------
    Sensor

    Raises
    ------
    ConfigError
        Unknown name (listing the available ones), unreadable file, invalid
        TOML (with the line), or an invalid sensor description (naming the
        file, table, key and value).
    """
    path = preset_path(name_or_path)
    try:
        text = limits.read_text_file(path, "a preset .toml file", ConfigError)
    except (OSError, UnicodeDecodeError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise ConfigError(f"{path}: cannot read the preset file ({reason})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:  # the message carries "(at line L, column C)"
        raise ConfigError(f"{path}: invalid TOML: {err}") from None
    return Sensor.from_dict(data, where=str(path))
