"""Scene-set files: the TOML document that says what a dataset holds.

A set file lists scenes, the views of each scene (fixed poses, random poses,
Blender cameras and animation frames), the sensor presets every view is
rendered with, the render quality, the outputs and the seed. Parsing checks
everything that can be checked without rendering; a bad file raises one
:class:`SetFileError` naming the file, the line where it can be found, the
dotted key path, the rule and the value — and nothing is rendered.

Example
-------
.. code-block:: toml

    description = "corner and room, two sensors"   # free text for the dataset card
    seed = 0                                        # set seed: per-frame seeds derive from it
    presets = ["kinect_v2", "o3d303"]               # every view is rendered with each of these
    resolution_scale = 0.25                         # scales width/height and fx, fy, cx, cy

    [quality]
    spp = 64
    max_depth = 5
    # time_budget_s = 60
    # target_error_m = 0.005

    [output]
    formats = ["exr", "png", "ply", "json"]

    [[scenes]]
    demo = "room"                                   # exactly one of demo / npz / blend
    [[scenes.poses]]
    suggested = true                                # the scene's suggested pose
    [[scenes.poses]]
    eye = [0.0, -1.8, 1.6]
    target = [0.0, 1.0, 0.8]
    [[scenes.poses]]
    count = 8                                       # random poses in a box, looking at a target
    box_min = [-1.5, -1.8, 1.0]
    box_max = [1.5, -1.0, 2.0]
    target = [0.0, 1.0, 0.8]
    seed = 1

    [[scenes]]
    npz = "scenes/kitchen.npz"                      # paths are relative to the set file
    presets = [{ preset = "kinect_v2", label = "kinect_clean", overrides = { "noise.model" = "none" } }]
    [[scenes.poses]]
    world_from_sensor = [[1, 0, 0, 0], [0, 0, 1, -2], [0, -1, 0, 1.5], [0, 0, 0, 1]]

    [[scenes]]
    blend = "shots/office.blend"
    cameras = ["TofCam", "TofCam.001"]              # default: the file's ToF cameras, else all cameras
    frames = "1-10"                                 # "a-b", "1,4,7-9", an int or a list; default: current frame

Schema
------
Top level

==================  ===============  ===========================  =================================================
key                 type             default                      meaning
==================  ===============  ===========================  =================================================
``description``     string           ``""``                       free text for the dataset card
``seed``            int >= 0         0                            set seed; each frame's seed is derived from it and
                                                                  the frame's job id
``presets``         list             ``["kinect_v2"]``            presets for every scene (see "preset entries")
``resolution_scale``  number > 0     1.0                          image size factor; fx, fy, cx, cy scale with it
``[quality]``       table            see below                    render quality for every scene
``[output]``        table            see below                    what is written per frame
``[[scenes]]``      array of tables  –                            at least one scene
==================  ===============  ===========================  =================================================

``[quality]`` (also ``[scenes.quality]``, overriding key by key)

==================  =============  =======  ==========================================================
``spp``             int >= 1       64       most samples per pixel
``max_depth``       int >= 1       5        surface vertices per path (1 = direct light only)
``time_budget_s``   number > 0, s  none     render each frame in about this long (set-up to frame)
``target_error_m``  number > 0, m  none     stop once the estimated RMS depth error is at most this
==================  =============  =======  ==========================================================

A time budget makes frames depend on the machine's speed: such a set is not
reproducible bit for bit (spp and target error are).

``[output]``

===================  ==============  ==================================  ========================================
``formats``          list of string  ``["exr", "png", "ply", "json"]``   any of exr, png, ply, json; json (the
                                                                         frame's record with checksums) is always
                                                                         written
``exr_half``         bool            false                               EXR channels as 16-bit half floats
``exr_channels``     list of string  all                                 only these channels in frame.exr, e.g.
                                                                         ``["depth", "amplitude", "valid"]``
``transient_bin_m``  number > 0, m   none                                also write transient.npy: the
                                                                         time-resolved histogram over optical
                                                                         path length, bins of this width
``transient_max_m``  number > 0, m   none                                its longest path length (with the bin)
``labels``           bool            false                               also write labels.npz: multipath error,
                                                                         direct-only depth, normals, material and
                                                                         object ids (:mod:`batch.labels`)
===================  ==============  ==================================  ========================================

``[[scenes]]``

===================  ==============  ===============  ====================================================
``name``             string          source's name    label in the index (unique)
``demo``             string          –                a demo scene: plane, corner, box_on_wall, room
``npz``              path            –                a scene saved with ``tofcore.Scene.save``
``mesh``             path            –                an OBJ, PLY, glTF/GLB or STL file (``pip install trimesh``;
                                                      materials: :mod:`tofcore.scene.mesh_files`)
``blend``            path            –                a Blender file (opened through ``bpy`` in a worker)
``presets``          list            set's presets    presets for this scene only
``ambient_w_m2_sr``  number >= 0     0 (blend: file)  constant ambient radiance; for a .blend the default
                                                      is what the exporter reads from the world
``cameras``          list of string  ToF cameras      blend: camera objects to render (default: cameras with
                                                      ToF settings when the add-on is registered, else all)
``frames``           see above       current frame    blend: animation frames
``[scenes.quality]`` table           set's quality    overrides
``[[scenes.poses]]`` array           suggested        views (demo/npz; for a blend they replace the cameras)
``[scenes.randomize]`` table         none             randomized views: objects, materials, ambient light,
                                                      camera and sensor unit drawn per frame
                                                      (:mod:`batch.randomize`); with it the suggested
                                                      pose is not added unless poses are given
===================  ==============  ===============  ====================================================

Pose entries (``[[scenes.poses]]``), the kind given by the keys present:

* ``suggested = true`` — the pose stored with the scene (demo scenes, or
  ``metadata["world_from_sensor"]`` of an .npz scene);
* ``world_from_sensor = [[...] × 4]`` — a 4×4 rigid transform, sensor frame =
  OpenCV (x right, y down, z forward), world = Blender's (Z up), metres;
* ``eye``, ``target`` [, ``up`` = [0, 0, 1]] — ``tofcore.look_at``, metres;
* ``count``, ``box_min``, ``box_max``, ``target`` [, ``up``, ``seed`` = set seed,
  ``target_jitter_m`` = 0] — ``count`` eyes uniform in the box, looking at
  the target (moved uniformly within ± jitter per axis).

Preset entries: a preset name (``"kinect_v2"``; see ``python -m tofcore
presets``), a path to a preset ``.toml`` (relative to the set file), or a
table ``{ preset = NAME_OR_PATH, label = "…", overrides = { "table.field" =
value, … }, resolution_scale = x }``; ``overrides`` are
``tofcore.Sensor.replace`` keys, checked when the file is read.
"""

from __future__ import annotations

import difflib
import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tofcore import limits
from tofcore.errors import ConfigError, LimitError, SceneError, is_number

from .set_checks import check_keys as _check_keys
from .set_checks import integer as _int

#: Formats a frame can be written in (``tofcore.write_frame``).
FORMATS = ("exr", "png", "ply", "json")
#: Mesh-file suffixes a ``mesh`` scene may have (read by tofcore.scene.mesh_files through trimesh).
MESH_SUFFIXES = (".obj", ".ply", ".gltf", ".glb", ".stl")
#: Demo scene names (``tofcore.demo_scene``); kept here so parsing needs no scene code.
DEMO_SCENES = ("plane", "corner", "box_on_wall", "room")

DEFAULT_PRESETS = ("kinect_v2",)
DEFAULT_SPP = 64
DEFAULT_MAX_DEPTH = 5

_TOP_KEYS = ("description", "seed", "presets", "resolution_scale", "quality", "output", "scenes")
_QUALITY_KEYS = ("spp", "max_depth", "time_budget_s", "target_error_m")
_OUTPUT_KEYS = ("formats", "exr_half", "exr_channels", "transient_bin_m", "transient_max_m", "labels")
_SCENE_KEYS = ("name", "demo", "npz", "blend", "mesh", "presets", "ambient_w_m2_sr", "cameras", "frames", "quality",
               "poses", "randomize")
_PRESET_KEYS = ("preset", "label", "overrides", "resolution_scale")
_POSE_KEYS = {
    "suggested": ("suggested",),
    "matrix": ("world_from_sensor",),
    "look_at": ("eye", "target", "up"),
    "random": ("count", "box_min", "box_max", "target", "up", "seed", "target_jitter_m"),
}


class SetFileError(ConfigError):
    """A set file (or a set built in code) is invalid; the message names file, line, key path, rule and value."""


# --------------------------------------------------------------------------- the parsed set

@dataclass(frozen=True, kw_only=True)
class Quality:
    """Render settings of ``tofcore.render`` (see the module docstring)."""

    spp: int = DEFAULT_SPP
    max_depth: int = DEFAULT_MAX_DEPTH
    time_budget_s: float | None = None
    target_error_m: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"spp": self.spp, "max_depth": self.max_depth, "time_budget_s": self.time_budget_s,
                "target_error_m": self.target_error_m}


@dataclass(frozen=True, kw_only=True)
class PresetSpec:
    """One sensor a view is rendered with: its label and the final sensor (overrides and scale applied)."""

    label: str
    source: str                # preset name or absolute .toml path
    sensor: Any                # tofcore.Sensor
    resolution_scale: float
    overrides: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class PoseSpec:
    """One pose entry; ``kind`` is suggested, matrix, look_at or random (see the module docstring)."""

    kind: str
    where: str
    world_from_sensor: tuple[tuple[float, ...], ...] | None = None  # matrix / look_at, resolved
    count: int = 1
    box_min: tuple[float, float, float] | None = None
    box_max: tuple[float, float, float] | None = None
    target: tuple[float, float, float] | None = None
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    seed: int = 0
    target_jitter_m: float = 0.0


@dataclass(frozen=True, kw_only=True)
class SceneSpec:
    """One ``[[scenes]]`` entry."""

    name: str
    kind: str                  # "demo", "npz", "mesh" or "blend"
    source: str                # demo name, or absolute file path
    presets: tuple[PresetSpec, ...]
    quality: Quality
    poses: tuple[PoseSpec, ...]
    cameras: tuple[str, ...] | None = None
    frames: tuple[int, ...] | None = None
    ambient_w_m2_sr: float | None = None
    where: str = ""
    randomize: dict | None = None   # [scenes.randomize], parsed (batch.randomize): randomized views


@dataclass(frozen=True, kw_only=True)
class SetSpec:
    """A parsed set file."""

    path: Path | None
    description: str
    seed: int
    formats: tuple[str, ...]
    scenes: tuple[SceneSpec, ...]
    resolution_scale: float = 1.0
    output: dict = field(default_factory=dict)   # exr_half, exr_channels, transient_bin_m, transient_max_m (given)


# --------------------------------------------------------------------------- errors with lines

class _Locator:
    """Best-effort line numbers for dotted key paths of a TOML text.

    Tracks ``[table]`` and ``[[array.of.tables]]`` headers (with their indices)
    and ``key =`` lines. Paths inside inline tables or multi-line arrays resolve
    to the line of the enclosing key.
    """

    _AOT = re.compile(r"^\s*\[\[\s*([^\]]+?)\s*\]\]")
    _TABLE = re.compile(r"^\s*\[\s*([^\]\[]+?)\s*\]")
    _KEY = re.compile(r"^\s*(\"[^\"]*\"|'[^']*'|[A-Za-z0-9_-]+)\s*=")

    def __init__(self, text: str):
        self.sections: dict[tuple, int] = {(): 0}
        self.keys: dict[tuple, int] = {}
        counts: dict[tuple, int] = {}
        current: tuple = ()
        for number, line in enumerate(text.splitlines(), start=1):
            aot = self._AOT.match(line)
            table = None if aot else self._TABLE.match(line)
            if aot or table:
                parts = [p.strip().strip("\"'") for p in (aot or table).group(1).split(".")]
                path: tuple = ()
                for i, part in enumerate(parts):
                    path += (part,)
                    last = i == len(parts) - 1
                    if aot and last:
                        counts[path] = counts.get(path, -1) + 1
                        path += (counts[path],)
                    elif path in counts:  # an enclosing array of tables: its latest element
                        path += (counts[path],)
                current = path
                self.sections.setdefault(current, number)
                continue
            key = self._KEY.match(line)
            if key:
                self.keys.setdefault(current + (key.group(1).strip("\"'"),), number)

    def line(self, path: Sequence[str | int]) -> int | None:
        """The line of the longest prefix of ``path`` that is a key or a section, or None."""
        path = tuple(path)
        for n in range(len(path), 0, -1):
            prefix = path[:n]
            if prefix in self.keys:
                return self.keys[prefix]
            if prefix in self.sections:
                return self.sections[prefix]
        return None


def _dotted(path: Sequence[str | int]) -> str:
    out = ""
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + part
    return out or "(top level)"


class _Context:
    """Where errors point: the file, the line locator, and the set file's folder for relative paths."""

    def __init__(self, path: Path | None, text: str | None):
        self.path = path
        self.base = path.parent if path is not None else Path.cwd()
        self.locator = _Locator(text) if text is not None else None

    def error(self, path: Sequence[str | int], message: str) -> SetFileError:
        where = str(self.path) if self.path is not None else "set"
        line = self.locator.line(path) if self.locator is not None else None
        if line:
            where += f":{line}"
        return SetFileError(f"{where}: {_dotted(path)}: {message}")

    def fail(self, path: Sequence[str | int], rule: str, value: object) -> SetFileError:
        return self.error(path, f"must be {rule}, got {value!r}")


# --------------------------------------------------------------------------- value checks

def _limit(ctx: _Context, limit: limits.Limit, value: int, path: list, what: str = "") -> None:
    """SetFileError naming the key, the limit and how to raise it, if ``value`` is above ``limit``."""
    try:
        too_large = limit.exceeded(value)
    except ConfigError as err:  # a malformed TOFCORE_MAX_… variable
        raise ctx.error(path, str(err)) from None
    if too_large:
        raise ctx.error(path, f"must be {limit.describe()}, got {value!r}{(' ' + what) if what else ''}")


def _positive(ctx: _Context, value: object, path: list, unit: str = "", allow_zero: bool = False) -> float:
    ok = is_number(value) and math.isfinite(value) and (value >= 0 if allow_zero else value > 0)
    if not ok:
        raise ctx.fail(path, f"a finite number {'>=' if allow_zero else '>'} 0{(' (' + unit + ')') if unit else ''}",
                       value)
    return float(value)


def _string(ctx: _Context, value: object, path: list) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ctx.fail(path, "a non-empty string", value)
    return value


def _vector3(ctx: _Context, value: object, path: list) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3 or not all(is_number(v) and math.isfinite(v) for v in value):
        raise ctx.fail(path, "a list of 3 finite numbers (metres, world frame)", value)
    return tuple(float(v) for v in value)


def _matrix(ctx: _Context, value: object, path: list) -> tuple[tuple[float, ...], ...]:
    rule = "a 4x4 rigid transform (4 rows of 4 numbers, last row [0, 0, 0, 1], orthonormal rotation)"
    if (not isinstance(value, list) or len(value) != 4
            or not all(isinstance(r, list) and len(r) == 4 and all(is_number(v) for v in r) for r in value)):
        raise ctx.fail(path, rule, value)
    m = np.array(value, dtype=np.float64)
    rotation = m[:3, :3]
    if (not np.isfinite(m).all() or not np.allclose(m[3], [0, 0, 0, 1])
            or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-5) or np.linalg.det(rotation) < 0):
        raise ctx.fail(path, rule, value)
    return tuple(tuple(float(v) for v in row) for row in m)


_NPZ_CHECKED: dict[tuple[str, int, int], None] = {}


def _check_npz(ctx: _Context, source: str, path: list) -> None:
    """Load the scene file (.npz or mesh) once (per path, size and time) so that a damaged one is reported here,
    naming the key, and not as a failed frame after the run has started."""
    from tofcore.scene.mesh_files import is_mesh_file, load_mesh
    from tofcore.scene.scene import Scene

    st = Path(source).stat()
    key = (source, st.st_size, st.st_mtime_ns)
    if key in _NPZ_CHECKED:
        return
    try:
        load_mesh(source) if is_mesh_file(source) else Scene.load(source)
    except (SceneError, ConfigError) as err:
        raise ctx.error(path, str(err)) from None
    _NPZ_CHECKED[key] = None


def _count_frames(scenes: Sequence[SceneSpec]) -> int:
    """Frames the scenes expand to (a lower bound for a .blend whose cameras are not named)."""
    total = 0
    for scene in scenes:
        views = (sum(p.count for p in scene.poses) if scene.poses else 0 if scene.randomize
                 else len(scene.cameras or ()) or 1) + (scene.randomize["count"] if scene.randomize else 0)
        total += len(scene.frames or (None,)) * views * len(scene.presets)
    return total


def _file(ctx: _Context, value: object, path: list, suffixes: tuple[str, ...]) -> str:
    text = _string(ctx, value, path)
    if not text.lower().endswith(suffixes):
        raise ctx.fail(path, f"a path ending in {' or '.join(suffixes)}", value)
    file = (ctx.base / text).resolve()
    if not file.is_file():
        raise ctx.error(path, f"file not found: {file}")
    return str(file)


def _frames(ctx: _Context, value: object, path: list) -> tuple[int, ...]:
    rule = "an animation frame (int), a list of ints, or a string like \"1-10\" or \"1,4,7-9\""
    if isinstance(value, int) and not isinstance(value, bool):
        return (value,)
    if isinstance(value, list) and value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return tuple(dict.fromkeys(value))
    if isinstance(value, str):
        try:
            return parse_frames(value)
        except LimitError as err:
            raise ctx.error(path, str(err).removeprefix("frames: ")) from None
        except ValueError:
            raise ctx.fail(path, rule, value) from None
    raise ctx.fail(path, rule, value)


def parse_frames(text: str) -> tuple[int, ...]:
    """``"1-3,7"`` → (1, 2, 3, 7); ValueError when malformed or a range is reversed.

    Raises :class:`~tofcore.errors.LimitError` (a ValueError) before building anything when the ranges hold
    more than :data:`tofcore.limits.MAX_SET_FRAMES` frames.
    """
    ranges: list[tuple[int, int]] = []
    for part in text.split(","):
        part = part.strip()
        match = re.fullmatch(r"(-?\d+)(?:\s*-\s*(-?\d+))?", part)
        if not match:
            raise ValueError(f"frames: {part!r} is not a frame or a range a-b")
        start = int(match.group(1))
        end = int(match.group(2)) if match.group(2) is not None else start
        if end < start:
            raise ValueError(f"frames: range {part!r} ends before it starts")
        ranges.append((start, end))
    count = sum(end - start + 1 for start, end in ranges)
    limits.MAX_SET_FRAMES.check(count, "frames", "the frame ranges", f"{text!r} ({count:,} frames)")
    return tuple(dict.fromkeys(frame for start, end in ranges for frame in range(start, end + 1)))


# --------------------------------------------------------------------------- sensors

def _preset(ctx: _Context, entry: object, path: list, default_scale: float):
    import tofcore
    from tofcore.sensor.presets import list_presets, preset_path

    if isinstance(entry, str):
        entry = {"preset": entry}
    table = _check_keys(ctx, entry, path, _PRESET_KEYS, "a preset name, a .toml path or a table")
    if "preset" not in table:
        raise ctx.error(path, f"missing key 'preset' (a name from {list_presets()} or a .toml path)")
    name = _string(ctx, table["preset"], path + ["preset"])
    is_path = name.endswith(".toml") or "/" in name
    if is_path:
        source = str((ctx.base / name).resolve())
        if not Path(source).is_file():
            raise ctx.error(path + ["preset"] if "label" in table or len(table) > 1 else path,
                            f"preset file not found: {source}")
    else:
        try:
            source = preset_path(name).stem   # any case: "Kinect_V2" is kinect_v2
        except ConfigError:
            close = difflib.get_close_matches(name.casefold(), list_presets(), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ctx.error(path, f"unknown preset {name!r}{hint}; presets are {list_presets()} "
                                  f"or a path to a .toml file") from None
    try:
        sensor = tofcore.load_preset(source)
    except ConfigError as err:
        raise ctx.error(path, f"invalid preset: {err}") from None
    label = _string(ctx, table["label"], path + ["label"]) if "label" in table else Path(source).stem
    overrides = table.get("overrides", {})
    if not isinstance(overrides, Mapping):
        raise ctx.fail(path + ["overrides"], 'a table of "table.field" = value (tofcore.Sensor.replace keys)',
                       overrides)
    if overrides:
        try:
            sensor = sensor.replace(**dict(overrides))
        except ConfigError as err:
            raise ctx.error(path + ["overrides"], f"invalid override: {err}") from None
    scale = (_positive(ctx, table["resolution_scale"], path + ["resolution_scale"])
             if "resolution_scale" in table else default_scale)
    try:
        sensor = sensor.scaled(scale)
    except ConfigError as err:
        key = path + ["resolution_scale"] if "resolution_scale" in table else ["resolution_scale"]
        reason = str(err).removeprefix("Camera: ").removeprefix("Sensor.scaled: ").removeprefix("Sensor.resized: ")
        raise ctx.error(key, f"cannot scale the sensor {label!r} by {scale}: {reason}") from None
    return PresetSpec(label=label, source=source, sensor=sensor, resolution_scale=scale,
                      overrides=dict(overrides))


def _presets(ctx: _Context, value: object, path: list, default_scale: float) -> tuple[PresetSpec, ...]:
    if not isinstance(value, list) or not value:
        raise ctx.fail(path, "a non-empty list of presets (names, .toml paths or tables)", value)
    specs = tuple(_preset(ctx, entry, path + [i], default_scale) for i, entry in enumerate(value))
    labels = [s.label for s in specs]
    for i, label in enumerate(labels):
        if label in labels[:i]:
            raise ctx.error(path + [i], f"label {label!r} is used twice; give one of them a 'label'")
    return specs


# --------------------------------------------------------------------------- tables

def _quality(ctx: _Context, value: object, path: list, base: Quality) -> Quality:
    table = _check_keys(ctx, value, path, _QUALITY_KEYS)
    values = base.as_dict()
    for key, item in table.items():
        if key in ("spp", "max_depth"):
            values[key] = _int(ctx, item, path + [key], 1)
            _limit(ctx, limits.MAX_SPP if key == "spp" else limits.MAX_DEPTH, values[key], path + [key])
        else:
            values[key] = _positive(ctx, item, path + [key], "s" if key == "time_budget_s" else "m")
    return Quality(**values)


def _pose(ctx: _Context, value: object, path: list, set_seed: int) -> PoseSpec:
    from tofcore.scene.pose import look_at

    all_keys = sorted({k for keys in _POSE_KEYS.values() for k in keys})
    if not isinstance(value, Mapping):
        raise ctx.fail(path, f"a pose table with keys among {all_keys}", value)
    if "world_from_sensor" in value:
        kind = "matrix"
    elif "count" in value or "box_min" in value or "box_max" in value:
        kind = "random"
    elif "eye" in value:
        kind = "look_at"
    elif "suggested" in value:
        kind = "suggested"
    else:
        raise ctx.error(path, "a pose needs one of: suggested = true; world_from_sensor = 4x4; eye + target "
                              f"[+ up]; count + box_min + box_max + target [+ up, seed, target_jitter_m]; "
                              f"got keys {sorted(value)}")
    table = _check_keys(ctx, value, path, _POSE_KEYS[kind], f"a {kind} pose")
    where = _dotted(path)
    if kind == "suggested":
        if table["suggested"] is not True:
            raise ctx.fail(path + ["suggested"], "true", table["suggested"])
        return PoseSpec(kind=kind, where=where)
    if kind == "matrix":
        return PoseSpec(kind=kind, where=where, world_from_sensor=_matrix(ctx, table["world_from_sensor"],
                                                                          path + ["world_from_sensor"]))
    for key in ("target",) + (("eye",) if kind == "look_at" else ("count", "box_min", "box_max")):
        if key not in table:
            raise ctx.error(path, f"missing key {key!r} for a {kind} pose; keys are {list(_POSE_KEYS[kind])}")
    target = _vector3(ctx, table["target"], path + ["target"])
    up = _vector3(ctx, table["up"], path + ["up"]) if "up" in table else (0.0, 0.0, 1.0)
    if kind == "look_at":
        eye = _vector3(ctx, table["eye"], path + ["eye"])
        try:
            matrix = look_at(eye, target, up)
        except ConfigError as err:
            # The pose's own keys: up when up is parallel to the view (if the pose sets it), else eye.
            key = "up" if str(err).startswith("look_at: up") else "eye"
            raise ctx.error(path + [key] if key in table else path, str(err)) from None
        return PoseSpec(kind=kind, where=where, world_from_sensor=tuple(map(tuple, matrix.tolist())),
                        target=target, up=up)
    box_min = _vector3(ctx, table["box_min"], path + ["box_min"])
    box_max = _vector3(ctx, table["box_max"], path + ["box_max"])
    if any(lo > hi for lo, hi in zip(box_min, box_max)):
        raise ctx.fail(path + ["box_max"], f">= box_min {list(box_min)} on every axis", list(box_max))
    jitter = (_positive(ctx, table["target_jitter_m"], path + ["target_jitter_m"], "m", allow_zero=True)
              if "target_jitter_m" in table else 0.0)
    count = _int(ctx, table["count"], path + ["count"], 1)
    _limit(ctx, limits.MAX_SET_FRAMES, count, path + ["count"], "poses")
    return PoseSpec(kind=kind, where=where, count=count,
                    box_min=box_min, box_max=box_max, target=target, up=up,
                    seed=_int(ctx, table["seed"], path + ["seed"], 0) if "seed" in table else set_seed,
                    target_jitter_m=jitter)


def _scene(ctx: _Context, value: object, path: list, *, presets, quality: Quality, scale: float,
           set_seed: int) -> SceneSpec:
    table = _check_keys(ctx, value, path, _SCENE_KEYS)
    sources = [k for k in ("demo", "npz", "mesh", "blend") if k in table]
    if len(sources) != 1:
        raise ctx.error(path, f"needs exactly one of 'demo', 'npz', 'mesh', 'blend', got {sources or 'none'}")
    kind = sources[0]
    if kind == "demo":
        source = table["demo"]
        if source not in DEMO_SCENES:
            raise ctx.fail(path + ["demo"], f"one of {list(DEMO_SCENES)}", source)
        default_name = source
    else:
        source = _file(ctx, table[kind], path + [kind], MESH_SUFFIXES if kind == "mesh" else (f".{kind}",))
        if kind in ("npz", "mesh"):
            _check_npz(ctx, source, path + [kind])
        default_name = Path(source).stem
    name = _string(ctx, table["name"], path + ["name"]) if "name" in table else default_name
    scene_presets = (_presets(ctx, table["presets"], path + ["presets"], scale) if "presets" in table
                     else presets)
    if scene_presets is None:
        scene_presets = tuple(_preset(ctx, p, ["presets", i], scale) for i, p in enumerate(DEFAULT_PRESETS))
    scene_quality = _quality(ctx, table["quality"], path + ["quality"], quality) if "quality" in table else quality
    ambient = (_positive(ctx, table["ambient_w_m2_sr"], path + ["ambient_w_m2_sr"], "W m^-2 sr^-1", allow_zero=True)
               if "ambient_w_m2_sr" in table else None)
    if ambient is not None and ambient > limits.MAX_MAGNITUDE:
        raise ctx.fail(path + ["ambient_w_m2_sr"], f"at most {limits.MAX_MAGNITUDE:g} (W m^-2 sr^-1)", ambient)
    for preset in scene_presets:  # before any job is expanded or frame rendered
        try:
            limits.check_render(preset.sensor, max_depth=scene_quality.max_depth, where=f"preset {preset.label!r}")
        except ConfigError as err:
            raise ctx.error(path + ["presets"] if "presets" in table else ["presets"], str(err)) from None
    cameras = frames = None
    for key in ("cameras", "frames"):
        if key in table and kind != "blend":
            raise ctx.error(path + [key], f"only a blend scene has {key}; this is a {kind} scene")
    if "cameras" in table:
        cams = table["cameras"]
        if not isinstance(cams, list) or not cams or not all(isinstance(c, str) and c for c in cams):
            raise ctx.fail(path + ["cameras"], "a non-empty list of camera object names", cams)
        cameras = tuple(dict.fromkeys(cams))
    if "frames" in table:
        frames = _frames(ctx, table["frames"], path + ["frames"])
    poses: tuple[PoseSpec, ...] = ()
    if "poses" in table:
        entries = table["poses"]
        if not isinstance(entries, list) or not entries:
            raise ctx.fail(path + ["poses"], "a non-empty array of pose tables ([[scenes.poses]])", entries)
        poses = tuple(_pose(ctx, p, path + ["poses", i], set_seed) for i, p in enumerate(entries))
        if cameras is not None:
            raise ctx.error(path + ["poses"], "a blend scene takes either cameras or poses, not both")
        if kind == "blend" and any(p.kind == "suggested" for p in poses):
            raise ctx.error(path + ["poses"], "a blend scene has no suggested pose; name cameras instead")
    elif kind != "blend" and "randomize" not in table:
        poses = (PoseSpec(kind="suggested", where=_dotted(path + ["poses"])),)
    randomize = None
    if "randomize" in table:
        from .randomize import parse_randomize

        if kind == "blend":
            raise ctx.error(path + ["randomize"], "a blend scene cannot be randomized yet (demo, npz or mesh)")
        randomize = parse_randomize(ctx, table["randomize"], path + ["randomize"], scene_presets)
    return SceneSpec(name=name, kind=kind, source=source, presets=scene_presets, quality=scene_quality,
                     poses=poses, cameras=cameras, frames=frames, ambient_w_m2_sr=ambient, where=_dotted(path),
                     randomize=randomize)


def parse_set(data: Mapping[str, Any], path: Path | None = None, text: str | None = None) -> SetSpec:
    """Check a set given as a dict (e.g. parsed TOML) and resolve presets, files and poses.

    Parameters
    ----------
    data : the set's tables (see the module docstring).
    path : the set file, for messages and for relative paths (default: relative to the current folder).
    text : the file's text, for line numbers in messages.

    Raises
    ------
    SetFileError : on the first problem, naming file, line, key path, rule and value.
    """
    ctx = _Context(path, text)
    top = _check_keys(ctx, data, [], _TOP_KEYS)
    description = top.get("description", "")
    if not isinstance(description, str):
        raise ctx.fail(["description"], "a string", description)
    seed = _int(ctx, top["seed"], ["seed"], 0) if "seed" in top else 0
    scale = _positive(ctx, top["resolution_scale"], ["resolution_scale"]) if "resolution_scale" in top else 1.0
    presets = _presets(ctx, top["presets"], ["presets"], scale) if "presets" in top else None
    quality = _quality(ctx, top["quality"], ["quality"], Quality()) if "quality" in top else Quality()
    formats = FORMATS
    if "output" in top:
        output = _check_keys(ctx, top["output"], ["output"], _OUTPUT_KEYS)
        if "formats" in output:
            value = output["formats"]
            if (not isinstance(value, list) or not value
                    or not all(isinstance(f, str) and f in FORMATS for f in value)):
                raise ctx.fail(["output", "formats"], f"a non-empty list of {list(FORMATS)}", value)
            formats = tuple(f for f in FORMATS if f in value or f == "json")
        options = _output_options(ctx, output)
    else:
        options = {}
    if "scenes" not in top:
        raise ctx.error(["scenes"], "missing: a set needs at least one [[scenes]] table")
    entries = top["scenes"]
    if not isinstance(entries, list) or not entries:
        raise ctx.fail(["scenes"], "a non-empty array of tables ([[scenes]])", entries)
    scenes = tuple(_scene(ctx, entry, ["scenes", i], presets=presets, quality=quality, scale=scale, set_seed=seed)
                   for i, entry in enumerate(entries))
    if "exr_channels" in options:
        _check_exr_channels(ctx, options["exr_channels"], scenes)
    total = _count_frames(scenes)
    _limit(ctx, limits.MAX_SET_FRAMES, total, ["scenes"], "frames (views x frames x presets, all scenes)")
    names = [s.name for s in scenes]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise ctx.error(["scenes", i, "name"] if "name" in entries[i] else ["scenes", i],
                            f"scene name {name!r} is used twice; give each scene a unique 'name'")
    return SetSpec(path=path, description=description, seed=seed, formats=formats, scenes=scenes,
                   resolution_scale=scale, output=options)


def _check_exr_channels(ctx: _Context, channels: list[str], scenes) -> None:
    """Every ``exr_channels`` name is a channel of every frame the set renders (raw labels per preset)."""
    from tofcore.output.writers import exr_channel_names

    for scene in scenes:
        for preset in scene.presets:
            names = exr_channel_names(preset.sensor.modulation.raw_labels(), scene.quality.max_depth)
            unknown = [c for c in channels if c not in names]
            if unknown:
                raise ctx.fail(["output", "exr_channels"], f"channels of frame.exr for preset {preset.label!r} "
                                                           f"(unknown: {unknown}; valid: {names})", channels)


def _output_options(ctx: _Context, output: dict) -> dict:
    """The ``[output]`` options besides ``formats``, checked; only those given (job ids of sets without them
    stay as they were)."""
    options: dict = {}
    if "exr_half" in output:
        if not isinstance(output["exr_half"], bool):
            raise ctx.fail(["output", "exr_half"], "true or false", output["exr_half"])
        options["exr_half"] = output["exr_half"]
    if "exr_channels" in output:
        value = output["exr_channels"]
        if not isinstance(value, list) or not value or not all(isinstance(c, str) and c for c in value):
            raise ctx.fail(["output", "exr_channels"], "a non-empty list of frame.exr channel names", value)
        options["exr_channels"] = list(dict.fromkeys(value))
    if "labels" in output:
        if not isinstance(output["labels"], bool):
            raise ctx.fail(["output", "labels"], "true or false (write labels.npz: batch.labels)", output["labels"])
        options["labels"] = output["labels"]
    for key in ("transient_bin_m", "transient_max_m"):
        if key in output:
            options[key] = _positive(ctx, output[key], ["output", key], "m")
    if ("transient_bin_m" in options) != ("transient_max_m" in options):
        raise ctx.error(["output"], "transient_bin_m and transient_max_m go together (bin width and longest "
                                    "optical path length, metres)")
    if "transient_bin_m" in options and options["transient_max_m"] <= options["transient_bin_m"]:
        raise ctx.fail(["output", "transient_max_m"], f"longer than transient_bin_m "
                                                      f"({options['transient_bin_m']:g} m)", options["transient_max_m"])
    return options


def load_set(path: str | Path) -> SetSpec:
    """Read and check a set file; see :func:`parse_set`. TOML syntax errors carry the line and column."""
    path = Path(path).resolve()
    try:
        text = limits.read_text_file(path, "a set file (.toml)", SetFileError)
    except FileNotFoundError:
        raise SetFileError(f"{path}: set file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise SetFileError(f"{path}: cannot read the set file ({err})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:  # "… (at line L, column C)"
        raise SetFileError(f"{path}: invalid TOML: {err}") from None
    return parse_set(data, path, text)


#: The keys of the one-scene set that ``compare`` and the Blender entry script build from their flags.
FLAG_OF_KEY = {
    "scenes.npz": "--scene", "scenes.blend": "--scene", "scenes.demo": "--scene", "scenes.poses": "--eye/--target",
    "scenes.cameras": "--camera", "scenes.frames": "--frame", "scenes.ambient_w_m2_sr": "--ambient",
    "presets": "--presets", "resolution_scale": "--resolution-scale", "quality.spp": "--spp",
    "quality.max_depth": "--max-depth", "quality.time_budget_s": "--time-budget",
    "quality.target_error_m": "--target-error", "seed": "--seed", "output.formats": "--formats", "scenes": "--scene",
    "scenes.mesh": "--scene",
}


def flag_error(text: str, flags: dict[str, str]) -> str:
    """A set error of a set built from flags, ``"set: scenes[0].npz: …"``, as ``"--scene: …"``.

    ``flags`` maps dotted keys without indices to flags; the longest matching prefix wins; a key without
    a flag stays, as ``"arguments: key: …"``.
    """
    if not text.startswith("set: "):
        return text
    key, _, rest = text[len("set: "):].partition(": ")
    parts = re.sub(r"\[\d+\]", "", key).split(".")
    for n in range(len(parts), 0, -1):
        flag = flags.get(".".join(parts[:n]))
        if flag:
            return f"{flag}: {rest}"
    return f"arguments: {key}: {rest}"
