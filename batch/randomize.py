"""Randomized views of a scene: the ``[scenes.randomize]`` table of a set file.

A scene with a ``[scenes.randomize]`` table adds ``count`` randomized views (labels ``random0`` …) to
its poses. Each view draws — from its own seed — objects placed on the base scene's upward surfaces,
the materials of the base and of the objects by class, the ambient light and a camera orbiting an
object of interest; each frame (view × preset) then draws its sensor unit (``[scenes.randomize.sensor]``).
Everything drawn is recorded in the frame's record and ``frame.json`` (``randomization``).

Seeds: a view's seed is :func:`batch.jobs.derive_seed` of the set seed and a hash of the randomize
table and the view's index (the ``view`` of its jobs holds it: ``randomize_seed``), so the same set
draws the same scene for every preset, on any executor, in any order, and a resumed run renders the
same frame; a frame's sensor unit is drawn from its render seed (derived from the set seed and the job
id). Streams are split per part (objects, materials, ambient, camera), so a change to one part's
table leaves the others' draws as they were.

Example
-------
.. code-block:: toml

    [[scenes]]
    demo = "room"
    [scenes.randomize]
    count = 200                                    # randomized views of this scene
    [scenes.randomize.materials.walls]             # a material class: the materials whose name matches
    match = ["walls", "floor"]                     # glob patterns (default: the class name)
    reflectance = { dist = "uniform", low = 0.1, high = 0.9 }     # near-IR albedo
    roughness = { dist = "normal", mean = 0.4, std = 0.15 }       # truncated to [0, π/2]
    textures = "textures/"                         # reflectance images (.npy, .exr, .png) about the draw
    texture_probability = 0.5
    [scenes.randomize.materials.objects]
    match = ["box", "cylinder", "sphere", "cone"]
    metallic = { dist = "choice", values = [0.0, 1.0], weights = [0.8, 0.2] }
    [scenes.randomize.objects]
    shapes = ["box", "cylinder", "sphere", "cone"] # primitives made in code (tofcore.scene.primitives)
    library = "objects/"                           # and/or mesh files: .obj .ply .gltf .glb .stl .npz
    count = { dist = "uniform", low = 0.5, high = 6.5 }   # rounded: 1 … 6 objects, equally often
    size_m = { dist = "loguniform", low = 0.1, high = 0.5 }
    [scenes.randomize.camera]
    look_at = "object"                             # or "scene" (the bounding box centre)
    distance_m = { dist = "uniform", low = 1.0, high = 2.5 }   # default: 1.2·min … 0.6·max of the range
    [scenes.randomize.ambient]
    radiance_w_m2_sr = { dist = "loguniform", low = 0.001, high = 0.1 }
    [scenes.randomize.sensor]                      # the unit: a spread about each preset's value
    "camera.fx" = { dist = "normal", mean = 1.0, std = 0.01, apply = "scale" }
    "leds.position_m" = { dist = "uniform", low = -0.002, high = 0.002, apply = "offset" }

Schema
------
=================================  ==============  ==============================  ===============================
key                                type            default                         meaning
=================================  ==============  ==============================  ===============================
``count``                          int >= 1        –                               randomized views
``materials.<class>.match``        list of globs   ``[<class>]``                   material names of the class
``materials.<class>.<parameter>``  distribution    the material's own              reflectance, roughness,
                                                                                   metallic, ior, extinction,
                                                                                   coat, coat_roughness
``materials.<class>.textures``     folder          none                            reflectance textures
``….texture_probability``          [0, 1]          1 (with textures)               share of draws with a texture
``objects.shapes``                 list            none                            box, cylinder, sphere, cone
``objects.library``                folder          none                            mesh files (one object each)
``objects.count``                  distribution    –                               objects per view, rounded to
                                                                                   the nearest integer
``objects.size_m``                 distribution    0.1 … 0.5 uniform               largest bounding-box side, m
``objects.yaw_deg``                distribution    0 … 360 uniform                 turn about Z
``objects.tilt_deg``               distribution    0                               tilt about X before the turn
``objects.max_attempts``           int >= 1        50                              draws per object
``camera.look_at``                 string          object (else scene)             ``"object"`` or ``"scene"``
``camera.distance_m``              distribution    range-based (above)             eye to target, m
``camera.azimuth_deg``             distribution    0 … 360 uniform                 from +X towards +Y
``camera.elevation_deg``           distribution    5 … 45 uniform                  above the horizontal
``camera.clearance_m``             number >= 0     0.1                             no surface this close to the eye
                                                                                   (the LEDs sit beside the lens)
``camera.max_attempts``            int >= 1        100                             draws until the target is seen
``ambient.radiance_w_m2_sr``       distribution    the scene's                     constant ambient radiance
``ambient.environments``           folder          none                            equirectangular maps (W/m²/sr)
``ambient.environment_strength``   distribution    1                               scale of the map
``sensor."<table>.<field>"``       distribution    –                               with ``apply`` = ``"scale"``,
                                   + ``apply``                                     ``"offset"`` or ``"value"``;
                                                                                   any float field of the preset,
                                                                                   ``leds.intensity_w_sr`` and
                                                                                   ``leds.position_m`` (every LED,
                                                                                   one draw per axis)
=================================  ==============  ==============================  ===============================

Distributions: :mod:`batch.distributions`. Placement: :mod:`tofcore.scene.placement`. Camera views:
:mod:`tofcore.scene.viewpoint`.
"""

from __future__ import annotations

import copy
import fnmatch
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from tofcore.errors import TofError, is_number

from . import distributions as dists
from .file_hashes import file_sha256
from .image_files import SUFFIXES as IMAGE_SUFFIXES
from .image_files import read_grey
from .set_checks import check_keys, integer

TOP_KEYS = ("count", "materials", "objects", "camera", "ambient", "sensor")
MATERIAL_KEYS = ("match", "reflectance", "roughness", "metallic", "ior", "extinction", "coat", "coat_roughness",
                 "textures", "texture_probability")
OBJECT_KEYS = ("shapes", "library", "count", "size_m", "yaw_deg", "tilt_deg", "max_attempts")
CAMERA_KEYS = ("look_at", "distance_m", "azimuth_deg", "elevation_deg", "clearance_m", "max_attempts")
AMBIENT_KEYS = ("radiance_w_m2_sr", "environments", "environment_strength")
APPLY = ("scale", "offset", "value")
LIBRARY_SUFFIXES = (".obj", ".ply", ".gltf", ".glb", ".stl", ".npz")
_LED_KEYS = ("leds.intensity_w_sr", "leds.position_m")


class RandomizeError(TofError):
    """A randomized view cannot be drawn (no camera view sees its target): one line, the frame fails."""


# --------------------------------------------------------------------------- parsing

def _folder(ctx, value, path, suffixes, what) -> dict:
    """``{"folder": absolute path, "files": [[name, sha256], …]}`` of a folder of ``suffixes`` files."""
    if not isinstance(value, str) or not value.strip():
        raise ctx.fail(path, f"a folder of {what} (a path relative to the set file)", value)
    folder = (ctx.base / value).resolve()
    if not folder.is_dir():
        raise ctx.error(path, f"folder not found: {folder}")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)
    if not files:
        raise ctx.error(path, f"{folder} holds no {what} (files ending in {', '.join(suffixes)})")
    return {"folder": str(folder), "files": [[p.name, file_sha256(p)] for p in files]}


def _dist(ctx, value, path, valid=(-math.inf, math.inf), unit="") -> dict:
    def fail(key, rule, got):
        return ctx.fail(path + [key] if key else path, rule, got)
    return dists.parse(value, ".".join(map(str, path)), fail, valid, unit).as_dict()


def _check(ctx, value, path, keys, what) -> dict:
    return check_keys(ctx, value, path, keys, what)


def _attempts(ctx, table, path, default) -> int:
    return integer(ctx, table["max_attempts"], path + ["max_attempts"], 1) if "max_attempts" in table else default


def _materials(ctx, value, path) -> list[dict]:
    from tofcore.scene.material import PARAMETERS

    ranges = {p.name: (p.low, p.high, p.unit) for p in PARAMETERS}
    if not isinstance(value, Mapping) or not value:
        raise ctx.fail(path, "a table of material classes ([scenes.randomize.materials.<class>])", value)
    classes = []
    for name, entry in value.items():
        where = path + [name]
        table = _check(ctx, entry, where, MATERIAL_KEYS, "a material class table")
        match = table.get("match", [name])
        if isinstance(match, str):
            match = [match]
        if not isinstance(match, list) or not match or not all(isinstance(m, str) and m for m in match):
            raise ctx.fail(where + ["match"], "a list of material-name glob patterns", match)
        params = {key: _dist(ctx, table[key], where + [key], ranges[key][:2], ranges[key][2])
                  for key in ranges if key in table}
        textures = (_folder(ctx, table["textures"], where + ["textures"], IMAGE_SUFFIXES, "images")
                    if "textures" in table else None)
        probability = 1.0
        if "texture_probability" in table:
            probability = table["texture_probability"]
            if not (is_number(probability) and 0 <= probability <= 1):
                raise ctx.fail(where + ["texture_probability"], "a number in [0, 1]", probability)
            if textures is None:
                raise ctx.error(where + ["texture_probability"], "needs 'textures' (a folder of images)")
        if not params and textures is None:
            raise ctx.error(where, f"randomizes nothing: give one of {list(MATERIAL_KEYS[1:-1])}")
        classes.append({"class": name, "match": list(match), "params": params, "textures": textures,
                        "texture_probability": float(probability)})
    return classes


def _objects(ctx, value, path) -> dict:
    from tofcore.scene.primitives import NAMES

    table = _check(ctx, value, path, OBJECT_KEYS, "an objects table")
    shapes = table.get("shapes", [])
    if not isinstance(shapes, list) or not all(s in NAMES for s in shapes):
        raise ctx.fail(path + ["shapes"], f"a list of primitive names among {list(NAMES)}", shapes)
    library = _folder(ctx, table["library"], path + ["library"], LIBRARY_SUFFIXES, "mesh files") \
        if "library" in table else None
    if not shapes and library is None:
        raise ctx.error(path, "needs 'shapes' (primitives made in code) or 'library' (a folder of mesh files)")
    if library is not None:
        _check_library(ctx, library, path + ["library"])
    if "count" not in table:
        raise ctx.error(path, "missing key 'count' (objects per view: a number or a distribution)")
    return {"shapes": list(dict.fromkeys(shapes)), "library": library,
            "count": _dist(ctx, table["count"], path + ["count"], (0, 1000)),
            "size_m": _dist(ctx, table.get("size_m", {"dist": "uniform", "low": 0.1, "high": 0.5}),
                            path + ["size_m"], (1e-3, 100.0), "m"),
            "yaw_deg": _dist(ctx, table.get("yaw_deg", {"dist": "uniform", "low": 0.0, "high": 360.0}),
                             path + ["yaw_deg"], (-360.0, 720.0), "degrees"),
            "tilt_deg": _dist(ctx, table.get("tilt_deg", 0.0), path + ["tilt_deg"], (-180.0, 180.0), "degrees"),
            "max_attempts": _attempts(ctx, table, path, 50)}


def _check_library(ctx, library: dict, path) -> None:
    """Load each mesh file once so a damaged one is reported when the set is read."""
    from tofcore.errors import ConfigError, SceneError

    for name, _ in library["files"]:
        try:
            load_object(str(Path(library["folder"]) / name))
        except (SceneError, ConfigError) as err:
            raise ctx.error(path, str(err)) from None


def _camera(ctx, value, path, presets, has_objects: bool) -> dict:
    table = _check(ctx, value, path, CAMERA_KEYS, "a camera table")
    look = table.get("look_at", "object" if has_objects else "scene")
    if look not in ("object", "scene"):
        raise ctx.fail(path + ["look_at"], "\"object\" or \"scene\"", look)
    if look == "object" and not has_objects:
        raise ctx.error(path + ["look_at"], "\"object\" needs [scenes.randomize.objects]")
    if "distance_m" in table:
        distance = _dist(ctx, table["distance_m"], path + ["distance_m"], (1e-3, 1e4), "m")
    else:
        near = max(p.sensor.range_m[0] for p in presets)
        far = min(p.sensor.range_m[1] for p in presets)
        low, high = max(1.2 * near, 0.05), 0.6 * far
        if not low < high:
            raise ctx.error(path, f"the presets' ranges leave no default camera distance (1.2 x {near:g} m to "
                                  f"0.6 x {far:g} m); give distance_m")
        distance = {"dist": "uniform", "low": low, "high": high}
    clearance = 0.1
    if "clearance_m" in table:
        clearance = table["clearance_m"]
        if not (is_number(clearance) and 0 <= clearance <= 10):
            raise ctx.fail(path + ["clearance_m"], "a number in [0, 10] (m)", clearance)
    return {"look_at": look, "distance_m": distance, "clearance_m": float(clearance),
            "azimuth_deg": _dist(ctx, table.get("azimuth_deg", {"dist": "uniform", "low": 0.0, "high": 360.0}),
                                 path + ["azimuth_deg"], (-360.0, 720.0), "degrees"),
            "elevation_deg": _dist(ctx, table.get("elevation_deg", {"dist": "uniform", "low": 5.0, "high": 45.0}),
                                   path + ["elevation_deg"], (-89.0, 89.0), "degrees"),
            "max_attempts": _attempts(ctx, table, path, 100)}


def _ambient(ctx, value, path) -> dict:
    from tofcore.limits import MAX_MAGNITUDE

    table = _check(ctx, value, path, AMBIENT_KEYS, "an ambient table")
    if not table:
        raise ctx.error(path, f"randomizes nothing: give one of {list(AMBIENT_KEYS)}")
    out = {"radiance_w_m2_sr": (_dist(ctx, table["radiance_w_m2_sr"], path + ["radiance_w_m2_sr"],
                                      (0.0, MAX_MAGNITUDE), "W m^-2 sr^-1") if "radiance_w_m2_sr" in table else None),
           "environments": (_folder(ctx, table["environments"], path + ["environments"], (".npy", ".exr"),
                                    "environment maps") if "environments" in table else None),
           "environment_strength": _dist(ctx, table.get("environment_strength", 1.0),
                                         path + ["environment_strength"], (0.0, MAX_MAGNITUDE))}
    if out["environments"] is not None:
        for name, _ in out["environments"]["files"]:
            try:
                read_grey(Path(out["environments"]["folder"]) / name)
            except TofError as err:
                raise ctx.error(path + ["environments"], str(err)) from None
    return out


def _sensor(ctx, value, path, presets) -> dict:
    import tofcore

    if not isinstance(value, Mapping) or not value:
        raise ctx.fail(path, 'a table of "table.field" = { dist = …, apply = "scale" | "offset" | "value" }', value)
    out = {}
    for key, entry in value.items():
        where = path + [key]
        if not isinstance(entry, Mapping) or "apply" not in entry:
            raise ctx.fail(where, 'a distribution table with apply = "scale", "offset" or "value"', entry)
        if entry["apply"] not in APPLY:
            raise ctx.fail(where + ["apply"], f"one of {list(APPLY)}", entry["apply"])
        for preset in presets:
            data = preset.sensor.to_dict()
            table, _, field = key.partition(".")
            if key not in _LED_KEYS and not (isinstance(data.get(table), dict) and isinstance(
                    data[table].get(field), float)):
                floats = sorted(f"{t}.{f}" for t, v in data.items() if isinstance(v, dict)
                                for f, x in v.items() if isinstance(x, float))
                raise ctx.error(where, f"must name a float field of the preset {preset.label!r} or one of "
                                       f"{list(_LED_KEYS)}; float fields are {floats}")
        dist = _dist(ctx, {k: v for k, v in entry.items() if k != "apply"}, where)
        spec = {**dist, "apply": entry["apply"]}
        for preset in presets:  # the distribution's ends must give a valid sensor
            for end in _ends(dists.from_dict(dist)):
                try:
                    tofcore.Sensor.from_dict(apply_unit(preset.sensor.to_dict(), key, spec["apply"],
                                                        [end] * 3 if key == "leds.position_m" else end),
                                             where="sensor")
                except TofError as err:
                    raise ctx.error(where, f"the draw {end:g} ({spec['apply']}) makes the preset "
                                           f"{preset.label!r} invalid: {err}") from None
        out[key] = spec
    return out


def _ends(dist: dists.Distribution) -> list[float]:
    if dist.kind == "choice":
        return list(dist.values)
    if dist.kind == "normal":  # finite truncation bounds, else mean ± 3σ
        return [dist.low if math.isfinite(dist.low) else dist.mean - 3 * dist.std,
                dist.high if math.isfinite(dist.high) else dist.mean + 3 * dist.std]
    return [dist.low, dist.high]


def parse_randomize(ctx, value, path: list, presets) -> dict:
    """The plain (JSON-ready) randomize spec of a ``[scenes.randomize]`` table; SetFileError naming the key."""
    table = _check(ctx, value, path, TOP_KEYS, "a randomize table")
    if "count" not in table:
        raise ctx.error(path, "missing key 'count' (randomized views of this scene)")
    objects = _objects(ctx, table["objects"], path + ["objects"]) if "objects" in table else None
    return {
        "count": integer(ctx, table["count"], path + ["count"], 1),
        "materials": _materials(ctx, table["materials"], path + ["materials"]) if "materials" in table else [],
        "objects": objects,
        "camera": _camera(ctx, table.get("camera", {}), path + ["camera"], presets, objects is not None),
        "ambient": _ambient(ctx, table["ambient"], path + ["ambient"]) if "ambient" in table else None,
        "sensor": _sensor(ctx, table["sensor"], path + ["sensor"], presets) if "sensor" in table else {},
    }


def identity(spec: dict) -> dict:
    """What of the spec enters job ids and view seeds: all but folder paths (files count by name and
    content) and the number of views, so a set grown from 100 to 1,000 views keeps its first 100 frames."""
    return _without_folders({k: v for k, v in spec.items() if k != "count"})


def _without_folders(value):
    if isinstance(value, dict):
        return {k: _without_folders(v) for k, v in value.items() if k != "folder"}
    if isinstance(value, list):
        return [_without_folders(v) for v in value]
    return value


# --------------------------------------------------------------------------- drawing a view

_OBJECTS: dict[str, object] = {}


def load_object(path: str):
    """A library object (mesh file or tofcore .npz scene), cached per path for this process."""
    if path not in _OBJECTS:
        from tofcore.scene.mesh_files import load_mesh
        from tofcore.scene.scene import Scene

        _OBJECTS[path] = Scene.load(path) if path.lower().endswith(".npz") else load_mesh(path)
    return _OBJECTS[path]


def _library(objects: dict) -> dict:
    from tofcore.scene.primitives import primitive

    meshes = {name: primitive(name) for name in objects["shapes"]}
    if objects["library"] is not None:
        for name, _ in objects["library"]["files"]:
            meshes[name] = load_object(str(Path(objects["library"]["folder"]) / name))
    return meshes


def _draw(spec: dict, rng: np.random.Generator) -> float:
    return dists.from_dict(spec).sample(rng)


def _class_of(name: str, classes: list[dict]) -> dict | None:
    return next((c for c in classes if any(fnmatch.fnmatchcase(name, m) for m in c["match"])), None)


def _randomized_material(material, cls: dict, rng: np.random.Generator, images: dict):
    """(new material, what was drawn) for one material of class ``cls``."""
    import dataclasses

    from tofcore.scene.material import PARAMETER_NAMES, Texture

    drawn = {"material": material.name, "class": cls["class"]}
    values = {key: _draw(cls["params"][key], rng) for key in PARAMETER_NAMES if key in cls["params"]}
    drawn.update(values)
    changes = dict(values)
    texture = None
    if cls["textures"] is not None and rng.random() < cls["texture_probability"]:
        name = cls["textures"]["files"][int(rng.integers(len(cls["textures"]["files"])))][0]
        path = str(Path(cls["textures"]["folder"]) / name)
        if path not in images:
            images[path] = read_grey(Path(path))
        image = images[path]
        changes["reflectance_texture"] = Texture(texture_about(image, values.get("reflectance", material.reflectance)),
                                                 name=name)
        texture = name
    drawn["texture"] = texture
    return dataclasses.replace(material, **changes), drawn


def texture_about(image: np.ndarray, reflectance: float) -> np.ndarray:
    """The image's pattern about ``reflectance``: :math:`t = \\rho + c\\,(I - \\bar I)`, mean exactly ρ,
    contrast :math:`c = \\min(1, \\rho / (\\bar I - I_{min}), (1 - \\rho) / (I_{max} - \\bar I))`, so every texel
    stays a valid albedo in [0, 1] (an image brighter or darker than the draw keeps its shape, not its level)."""
    image = np.asarray(image, np.float64)
    mean = float(image.mean())
    below, above = mean - float(image.min()), float(image.max()) - mean
    contrast = min(1.0, reflectance / below if below > 0 else 1.0, (1.0 - reflectance) / above if above > 0 else 1.0)
    return np.clip(reflectance + contrast * (image - mean), 0.0, 1.0).astype(np.float32)  # clip: rounding only


def _box_uvs(scene) -> np.ndarray:
    """Texture coordinates by box projection (1 texture repeat a metre): each vertex takes the two world
    axes across the dominant axis of the mean normal of its triangles."""
    v = scene.vertices.astype(np.float64) + np.asarray(scene.origin_m)
    acc = np.zeros_like(v)
    for corner in range(3):
        np.add.at(acc, scene.triangles[:, corner], scene.face_normals.astype(np.float64))
    axis = np.argmax(np.abs(acc), axis=1)
    pairs = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    return np.take_along_axis(v, pairs, axis=1).astype(np.float32)


def _with_materials(scene, materials: list, needs_uvs: bool):
    import dataclasses

    new = dataclasses.replace(scene, materials=tuple(materials),
                              uvs=_box_uvs(scene) if needs_uvs and scene.uvs is None else scene.uvs)
    if "bvh" in scene.__dict__:  # the same geometry: keep its BVH
        new.__dict__["bvh"] = scene.__dict__["bvh"]
    return new


def _camera_view(scene, camera: dict, placed: list, first_object: int, rng: np.random.Generator):
    """(world_from_sensor, what was drawn) of a camera that sees its target; RandomizeError after the attempts."""
    from tofcore.scene.pose import look_at
    from tofcore.scene.viewpoint import clear, orbit_eye, sees

    lo, hi = scene.bounds
    centre = 0.5 * (lo.astype(np.float64) + hi) + np.asarray(scene.origin_m)
    for attempt in range(1, camera["max_attempts"] + 1):
        if camera["look_at"] == "object" and placed:
            k = int(rng.integers(len(placed)))
            b_lo, b_hi = (np.asarray(b) for b in placed[k].bounds_m)
            target, object_id, name = 0.5 * (b_lo + b_hi), first_object + k, f"{placed[k].mesh} #{k}"
        else:
            target, object_id, name = centre, None, None
        distance = _draw(camera["distance_m"], rng)
        azimuth, elevation = _draw(camera["azimuth_deg"], rng), _draw(camera["elevation_deg"], rng)
        eye = orbit_eye(target, distance, math.radians(azimuth), math.radians(elevation))
        if sees(scene, eye, target, object_id) and clear(scene, eye, camera["clearance_m"]):
            return look_at(eye, target), {
                "target_m": target.tolist(), "target_object": name, "eye_m": eye.tolist(), "distance_m": distance,
                "azimuth_deg": azimuth, "elevation_deg": elevation, "attempts": attempt}
    raise RandomizeError(f"randomize.camera: no view in {camera['max_attempts']} attempts sees its target from "
                         f"{camera['clearance_m']:g} m clear of every surface "
                         f"(look_at {camera['look_at']!r}, distance {camera['distance_m']}); widen the distance or "
                         f"elevation, or raise max_attempts")


def build_view(base, spec: dict, seed: int):
    """(scene, world_from_sensor, ambient or None, drawn) of one randomized view of ``base``.

    ``ambient`` is None when the spec does not randomize it (the scene's own applies). ``drawn`` is
    JSON-ready: every value drawn, with the view's ``seed``.
    """
    import tofcore
    from tofcore.scene.placement import compose, place_objects

    rng_objects, rng_materials, rng_ambient, rng_camera = (
        np.random.default_rng(s) for s in np.random.SeedSequence([seed, 0x7A4D]).spawn(4))
    drawn: dict = {"seed": seed}
    scene, placed = base, []
    first_object = max(int(base.object_ids.max()) + 1, len(base.object_names))
    if spec["objects"] is not None:
        objects = spec["objects"]
        meshes = _library(objects)
        count = int(round(_draw(objects["count"], rng_objects)))
        result = place_objects(base, sorted(meshes.items()), count, rng_objects,
                               draw_size=lambda r: _draw(objects["size_m"], r),
                               draw_yaw=lambda r: math.radians(_draw(objects["yaw_deg"], r)),
                               draw_tilt=lambda r: math.radians(_draw(objects["tilt_deg"], r)),
                               max_attempts=objects["max_attempts"])
        placed = result.placements
        scene = compose(base, meshes, placed)
        drawn["objects"] = {"asked": count, "placed": len(placed), "skipped": result.skipped, "list": [
            {"object_id": first_object + i, "name": f"{p.mesh} #{i}", "mesh": p.mesh, "size_m": p.size_m,
             "yaw_deg": math.degrees(p.yaw_rad), "tilt_deg": math.degrees(p.tilt_rad),
             "position_m": list(p.support_m)} for i, p in enumerate(placed)]}
    if spec["materials"]:
        images: dict = {}
        materials, records = [], []
        for material in scene.materials:
            cls = _class_of(material.name, spec["materials"])
            if cls is None:
                materials.append(material)
                continue
            new, record = _randomized_material(material, cls, rng_materials, images)
            materials.append(new)
            records.append(record)
        scene = _with_materials(scene, materials, any(m.textures for m in materials))
        drawn["materials"] = records
    ambient = None
    if spec["ambient"] is not None:
        a = spec["ambient"]
        radiance = _draw(a["radiance_w_m2_sr"], rng_ambient) if a["radiance_w_m2_sr"] is not None else 0.0
        environment = strength = None
        if a["environments"] is not None:
            files = a["environments"]["files"]
            environment = files[int(rng_ambient.integers(len(files)))][0]
            strength = _draw(a["environment_strength"], rng_ambient)
        ambient = tofcore.Ambient(
            radiance_w_m2_sr=radiance, environment_strength=1.0 if strength is None else strength,
            environment=None if environment is None else read_grey(Path(a["environments"]["folder"]) / environment))
        drawn["ambient"] = {"radiance_w_m2_sr": radiance, "environment": environment,
                            "environment_strength": strength}
    pose, drawn["camera"] = _camera_view(scene, spec["camera"], placed, first_object, rng_camera)
    return scene, pose, ambient, drawn


# --------------------------------------------------------------------------- the sensor unit

def apply_unit(sensor: dict, key: str, how: str, value) -> dict:
    """A copy of a sensor dict with ``key`` changed by ``value`` (``how``: scale, offset or value)."""
    out = copy.deepcopy(sensor)

    def change(old, draw):
        return old * draw if how == "scale" else old + draw if how == "offset" else draw

    if key == "leds.intensity_w_sr":
        for led in out["leds"]:
            led["intensity_w_sr"] = change(led["intensity_w_sr"], value)
    elif key == "leds.position_m":
        for led in out["leds"]:
            led["position_m"] = [change(p, v) for p, v in zip(led["position_m"], value)]
    else:
        table, _, field = key.partition(".")
        out[table][field] = change(out[table][field], value)
    return out


def vary_sensor(sensor: dict, unit: dict, seed: int) -> tuple[dict, dict]:
    """(the sensor dict of this unit, ``{key: {"apply", "draw"}}``) for a frame's render ``seed``; keys drawn in
    sorted order (``leds.position_m``: three draws, x y z)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5E45]))
    draws = {}
    for key in sorted(unit):
        spec = unit[key]
        dist = dists.from_dict({k: v for k, v in spec.items() if k != "apply"})
        value = [dist.sample(rng) for _ in range(3)] if key == "leds.position_m" else dist.sample(rng)
        sensor = apply_unit(sensor, key, spec["apply"], value)
        draws[key] = {"apply": spec["apply"], "draw": value}
    return sensor, draws


def scalar_draws(randomization: dict) -> dict[str, list[float]]:
    """The numbers a frame's ``randomization`` holds, by name (``camera.distance_m``,
    ``material.walls.reflectance``, ``objects.size_m`` …): what the dataset card draws histograms of."""
    out: dict[str, list[float]] = {}

    def add(name, value):
        if is_number(value) and math.isfinite(value):
            out.setdefault(name, []).append(float(value))

    for key in ("distance_m", "azimuth_deg", "elevation_deg"):
        add(f"camera.{key}", (randomization.get("camera") or {}).get(key))
    objects = randomization.get("objects")
    if objects:
        add("objects.placed", objects.get("placed"))
        for entry in objects.get("list", []):
            add("objects.size_m", entry.get("size_m"))
    for entry in randomization.get("materials") or []:
        for key, value in entry.items():
            if key not in ("material", "class", "texture"):
                add(f"material.{entry['class']}.{key}", value)
    ambient = randomization.get("ambient") or {}
    add("ambient.radiance_w_m2_sr", ambient.get("radiance_w_m2_sr"))
    add("ambient.environment_strength", ambient.get("environment_strength"))
    for key, entry in (randomization.get("sensor") or {}).items():
        value = entry.get("draw")
        for v in (value if isinstance(value, list) else [value]):
            add(f"sensor.{key} ({entry.get('apply')})", v)
    return out
