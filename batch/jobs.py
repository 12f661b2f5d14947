"""Jobs: a parsed set expanded into frames to render, grouped into one task per view.

A **job** is one frame: a scene, a view (a pose, or a Blender camera at an
animation frame) and a sensor. Its id is a short hash of everything that
defines the frame —

* the scene source: the demo name, or the SHA-256 of the .npz / .blend file
  (not its path: a moved file keeps its frames);
* the view: the 4×4 ``world_from_sensor``, or the camera name and frame;
* the full sensor description (``Sensor.to_dict()``, after overrides and the
  resolution scale), the quality settings, the ambient light, the output
  formats, the set seed and the tofcore version —

so an edited set re-renders exactly the frames it changed, and two entries
that describe the same frame render it once. Labels (scene name, preset
label) are not part of the id, nor is the render device (``--device``): the
CPU and the GPU render the same frame from the same seed (within float32
rounding), so a dataset may be resumed on another device; each record says
which device rendered it. Each job's render seed is derived from the set
seed and the job id (:func:`derive_seed`), so a frame does not depend on the
order, the executor or the number of workers.

A **view task** holds the jobs of one view (one per preset): a worker loads or
exports the scene once and renders all of them (:mod:`batch.worker`).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .file_hashes import file_sha256
from .setfile import PoseSpec, SceneSpec, SetFileError, SetSpec

#: Bumped when the meaning of a job definition or the frame folder changes.
JOB_FORMAT = 1
#: Hex digits of the SHA-256 kept as the job id (64 bits).
JOB_ID_HEX = 16


@dataclass(frozen=True, kw_only=True)
class Job:
    """One frame to render; plain data (picklable, JSON-ready fields)."""

    job_id: str
    scene: str                       # scene label
    source: dict                     # {"kind": "demo"|"npz"|"blend", "name"|"path": …, "sha256": …}
    view: dict                       # {"label", "camera", "frame", "pose_kind", "pose_index"} (present ones)
    world_from_sensor: list | None   # 4×4 rows; None: the Blender camera's pose, known after export
    preset: str                      # preset label
    sensor: dict                     # Sensor.to_dict() (overrides and resolution scale applied)
    resolution_scale: float
    quality: dict                    # spp, max_depth, time_budget_s, target_error_m
    ambient_w_m2_sr: float | None    # None: none (demo/npz) or the .blend world's
    seed: int                        # the render seed (derived)
    set_seed: int
    formats: tuple[str, ...]
    output: dict = field(default_factory=dict)   # [output] options: exr_half, exr_channels, transient_bin_m/max_m
    randomize: dict | None = None                # batch.randomize spec of a randomized view (its draws: at render)

    @property
    def label(self) -> str:
        """``scene/view/preset``: what people read in logs (not unique if two presets share a label)."""
        return f"{self.scene}/{self.view['label']}/{self.preset}"


@dataclass(frozen=True, kw_only=True)
class ViewTask:
    """The jobs of one view, rendered by one worker call after one scene load or export."""

    view_id: str
    scene: str
    source: dict
    view: dict
    world_from_sensor: list | None
    ambient_w_m2_sr: float | None
    jobs: tuple[Job, ...]
    dataset: str = ""                 # absolute dataset folder, set by the runner
    render_threads: int | None = None  # tofcore tracer threads; None: its default (CPU count)
    device: str = "cpu"               # tofcore.render's device: "cpu", "gpu" or "auto" (batch.devices)
    fallback_reason: str | None = None  # "auto" that the runner already resolved to the CPU, and why
    randomize: dict | None = None     # batch.randomize spec: the worker draws the view's scene and pose

    @property
    def label(self) -> str:
        return f"{self.scene}/{self.view['label']}"


@dataclass(frozen=True)
class BlendInfo:
    """What the expansion needs to know about a .blend file (read in a bpy process)."""

    cameras: tuple[str, ...]
    tof_cameras: tuple[str, ...]
    addon: bool                       # the ToF add-on's camera settings were readable
    frame_current: int
    frame_start: int
    frame_end: int


@dataclass
class Expansion:
    """Jobs in set order, and notes for the user (duplicates merged, defaults taken)."""

    jobs: list[Job]
    notes: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- identities

def canonical_json(data: Any) -> str:
    """Sorted keys, no spaces, shortest float repr: the same data gives the same text."""
    return json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)


def short_hash(data: Any) -> str:
    return hashlib.sha256(canonical_json(data).encode()).hexdigest()[:JOB_ID_HEX]


def derive_seed(set_seed: int, job_id: str) -> int:
    """The render seed of a job: 48 bits of SHA-256(set seed, job id); the same inputs, the same seed."""
    return int.from_bytes(hashlib.sha256(f"tofbatch-seed/{set_seed}/{job_id}".encode()).digest()[:6], "big")



def source_of(scene: SceneSpec) -> dict:
    """The scene source as it enters jobs: kind, demo name or absolute path, and content hash."""
    if scene.kind == "demo":
        return {"kind": "demo", "name": scene.source}
    return {"kind": scene.kind, "path": scene.source, "sha256": file_sha256(scene.source)}


def _source_identity(source: dict) -> dict:
    return {k: v for k, v in source.items() if k != "path"}


# --------------------------------------------------------------------------- poses

def random_poses(pose: PoseSpec) -> list[np.ndarray]:
    """``pose.count`` world_from_sensor matrices: eyes uniform in the box, looking at the (jittered) target.

    Reproducible: the generator is seeded with the entry's ``seed`` only.
    """
    from tofcore.scene.pose import look_at

    rng = np.random.default_rng(np.random.SeedSequence([pose.seed, 0x905E]))
    lo, hi = np.asarray(pose.box_min), np.asarray(pose.box_max)
    eyes = lo + rng.random((pose.count, 3)) * (hi - lo)
    jitter = (rng.random((pose.count, 3)) * 2.0 - 1.0) * pose.target_jitter_m
    out = []
    for i, (eye, dt) in enumerate(zip(eyes, jitter)):
        try:
            out.append(look_at(eye, np.asarray(pose.target) + dt, pose.up))
        except Exception as err:  # eye on the target or looking along up
            raise SetFileError(f"{pose.where}: random pose #{i} (eye {eye.tolist()}): {err}") from None
    return out


def suggested_pose(scene: SceneSpec, where: str) -> np.ndarray:
    """The pose stored with a demo scene or in an .npz scene's metadata; a mesh file's view framed for the
    scene's presets (:func:`tofcore.suggested_pose`: their narrowest field of view, the range all measure)."""
    import tofcore

    if scene.kind == "demo":
        return tofcore.suggested_pose(tofcore.demo_scene(scene.source))
    from tofcore.scene.mesh_files import load_mesh

    loaded = load_mesh(scene.source) if scene.kind == "mesh" else tofcore.Scene.load(scene.source)
    if loaded.metadata.get("framing") is not None:
        return tofcore.suggested_pose(loaded, [preset.sensor for preset in scene.presets])
    pose = loaded.metadata.get("world_from_sensor")
    if pose is None:
        raise SetFileError(f"{where}: {scene.source} has no suggested pose (metadata 'world_from_sensor'); "
                           f"add [[scenes.poses]] entries")
    return np.asarray(pose, dtype=np.float64)


def _poses(scene: SceneSpec, set_path: str) -> list[tuple[str, np.ndarray]]:
    """(pose kind, matrix) for every expanded pose entry of a scene, in order."""
    out = []
    for pose in scene.poses:
        where = f"{set_path}: {pose.where}"
        if pose.kind == "suggested":
            out.append((pose.kind, suggested_pose(scene, where)))
        elif pose.kind == "random":
            out.extend((pose.kind, m) for m in random_poses(replace(pose, where=where)))
        else:
            out.append((pose.kind, np.asarray(pose.world_from_sensor, dtype=np.float64)))
    return out


# --------------------------------------------------------------------------- .blend inspection

def inspect_blend_subprocess(path: str) -> BlendInfo:
    """Read cameras and frames of a .blend in a child process (this process must stay free of bpy)."""
    cmd = [sys.executable, "-m", f"{__package__}.blend", "inspect", str(path)]  # batch or tofcore_batch
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[1])]
                                        + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        detail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise SetFileError(f"{path}: cannot read the .blend file through bpy ({detail})")
    data = json.loads(lines[-1])
    return BlendInfo(cameras=tuple(data["cameras"]), tof_cameras=tuple(data["tof_cameras"]), addon=data["addon"],
                     frame_current=data["frame_current"], frame_start=data["frame_start"],
                     frame_end=data["frame_end"])


def _blend_views(scene: SceneSpec, info: BlendInfo, set_path: str,
                 notes: list[str]) -> list[tuple[dict, np.ndarray | None]]:
    frames = scene.frames or (info.frame_current,)
    if scene.poses:
        return [({"label": f"pose{k}@{frame}", "frame": frame, "pose_kind": kind, "pose_index": k}, matrix)
                for frame in frames for k, (kind, matrix) in enumerate(_poses(scene, set_path))]
    if scene.cameras is not None:
        for i, cam in enumerate(scene.cameras):
            if cam not in info.cameras:
                raise SetFileError(f"{set_path}: {scene.where}.cameras[{i}]: camera {cam!r} is not a camera "
                                   f"object of {scene.source}; cameras are {list(info.cameras)}")
        cameras = scene.cameras
    elif info.tof_cameras:
        cameras = info.tof_cameras
    elif info.cameras:
        cameras = info.cameras
        notes.append(f"{scene.name}: no camera has ToF settings "
                     f"({'add-on not available' if not info.addon else 'none enabled'}): rendering all cameras "
                     f"{list(cameras)}")
    else:
        raise SetFileError(f"{set_path}: {scene.where}: {scene.source} has no camera objects; add "
                           f"[[scenes.poses]] entries")
    return [({"label": f"{cam}@{frame}", "camera": cam, "frame": frame}, None) for frame in frames for cam in cameras]


# --------------------------------------------------------------------------- expansion

def make_job(*, scene: str, source: dict, view: dict, world_from_sensor, preset: str, sensor: dict,
             resolution_scale: float, quality: dict, ambient_w_m2_sr: float | None, set_seed: int,
             formats: tuple[str, ...], output: dict | None = None, randomize: dict | None = None) -> Job:
    """A job with its id and derived seed (the one place where ids are made)."""
    import tofcore

    pose = None if world_from_sensor is None else np.asarray(world_from_sensor, dtype=np.float64).tolist()
    if randomize is not None:  # the pose is drawn by the worker from the view's seed
        view_identity = {"randomized": view["pose_index"], "randomize_seed": view["randomize_seed"]}
    elif pose is None:
        view_identity = {"camera": view["camera"], "frame": view["frame"]}
    else:
        view_identity = {"world_from_sensor": pose, "frame": view.get("frame")}
    # Not in the definition: labels, and the render device. CPU and GPU give the same frame from the same
    # seed (within float32 rounding, tests/tofcore/test_gpu.py), so they are the same job: a dataset can
    # be resumed on another device, and the record says which device rendered each frame.
    definition = {"format": JOB_FORMAT, "tofcore": tofcore.__version__, "source": _source_identity(source),
                  "view": view_identity, "sensor": sensor, "quality": quality, "ambient_w_m2_sr": ambient_w_m2_sr,
                  "set_seed": set_seed, "formats": sorted(formats)}
    if output:  # only when given: the ids of sets without output options stay as they were
        definition["output"] = output
    if randomize is not None:
        from .randomize import identity

        definition["randomize"] = identity(randomize)
    job_id = short_hash(definition)
    return Job(job_id=job_id, scene=scene, source=source, view=view, world_from_sensor=pose, preset=preset,
               sensor=sensor, resolution_scale=resolution_scale, quality=quality, ambient_w_m2_sr=ambient_w_m2_sr,
               seed=derive_seed(set_seed, job_id), set_seed=set_seed, formats=tuple(formats),
               output=dict(output or {}), randomize=randomize)


def randomized_views(scene: SceneSpec, set_seed: int) -> list[tuple[dict, None]]:
    """The views of a scene's ``[scenes.randomize]``: label ``random<k>``, each with its own seed
    (:func:`derive_seed` of the set seed and a hash of the randomize table and k); poses drawn at render."""
    from .randomize import identity

    spec = identity(scene.randomize)
    return [({"label": f"random{k}", "pose_kind": "randomized", "pose_index": k,
              "randomize_seed": derive_seed(set_seed, short_hash({"randomize": spec, "index": k}))}, None)
            for k in range(scene.randomize["count"])]


def expand(spec: SetSpec, inspect_blend: Callable[[str], BlendInfo] = inspect_blend_subprocess) -> Expansion:
    """Every frame of the set, in set order (scenes, views, presets); duplicates merged.

    ``inspect_blend`` reads a .blend's cameras and frames; the default runs a
    child process so that this one never imports bpy.
    """
    set_path = str(spec.path) if spec.path is not None else "set"
    jobs: list[Job] = []
    notes: list[str] = []
    seen: set[str] = set()
    infos: dict[str, BlendInfo] = {}
    for scene in spec.scenes:
        source = source_of(scene)
        if scene.kind == "blend":
            if scene.source not in infos:
                infos[scene.source] = inspect_blend(scene.source)
            views = _blend_views(scene, infos[scene.source], set_path, notes)
        else:
            views = [({"label": f"pose{k}", "pose_kind": kind, "pose_index": k}, matrix)
                     for k, (kind, matrix) in enumerate(_poses(scene, set_path))]
        if scene.randomize is not None:
            views += randomized_views(scene, spec.seed)
        for view, matrix in views:
            for preset in scene.presets:
                job = make_job(scene=scene.name, source=source, view=view, world_from_sensor=matrix,
                               preset=preset.label, sensor=preset.sensor.to_dict(),
                               resolution_scale=preset.resolution_scale, quality=scene.quality.as_dict(),
                               ambient_w_m2_sr=scene.ambient_w_m2_sr, set_seed=spec.seed, formats=spec.formats,
                               output=spec.output,
                               randomize=scene.randomize if view.get("pose_kind") == "randomized" else None)
                if job.job_id in seen:
                    notes.append(f"{job.label}: the same frame as an earlier entry (job {job.job_id}); rendered once")
                    continue
                seen.add(job.job_id)
                jobs.append(job)
    return Expansion(jobs=jobs, notes=notes)


def group_by_view(jobs: list[Job], dataset: str = "", render_threads: int | None = None, device: str = "cpu",
                  fallback_reason: str | None = None) -> list[ViewTask]:
    """One task per view (same source, view and ambient), jobs in their given order, tasks in first-job order.

    ``dataset``, ``render_threads``, ``device`` and ``fallback_reason`` are copied into every task.
    """
    tasks: dict[str, list[Job]] = {}
    for job in jobs:
        key = short_hash({"source": _source_identity(job.source), "view": job.view,
                          "pose": job.world_from_sensor, "ambient": job.ambient_w_m2_sr})
        tasks.setdefault(key, []).append(job)
    return [ViewTask(view_id=key, scene=group[0].scene, source=group[0].source, view=group[0].view,
                     world_from_sensor=group[0].world_from_sensor, ambient_w_m2_sr=group[0].ambient_w_m2_sr,
                     jobs=tuple(group), dataset=dataset, render_threads=render_threads, device=device,
                     fallback_reason=fallback_reason, randomize=group[0].randomize)
            for key, group in tasks.items()]
