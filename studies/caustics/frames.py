"""Set-up and decoding shared by the study's commands: the Kinect v2 room at a small resolution, the
tracer's set-up for it, per-class sums traced in worker processes, and the depth of any sum of classes.

Depth here is the noise-free, scatter-free decode of the mean correlation images (all three frequencies,
the camera's unwrapping weights; ``tofcore.render``'s ground-truth decode): the render's own error,
without sensor noise, lens scattering or the camera's spatial phasor filter.
"""

from __future__ import annotations

import dataclasses
import os
from concurrent.futures import ProcessPoolExecutor

import numpy as np

import tofcore
from tofcore import backend
from tofcore.scene.demo import suggested_pose
from tofcore.sensor import decode as decoding
from tofcore.sensor.raw import raw_images
from tofcore.tracer.setup import TraceSettings, make_setup

from classify import ClassSums, trace_classified
from light_tracer import trace_light


def sensor_at(scale: float, preset: str = "kinect_v2"):
    """The preset with its camera scaled by ``scale`` (intrinsics with it), sensor noise and scattering off."""
    sensor = tofcore.load_preset(preset)
    cam = sensor.camera
    w, h = max(8, round(cam.width * scale)), max(8, round(cam.height * scale))
    small = dataclasses.replace(cam, width=w, height=h, fx=cam.fx * w / cam.width, fy=cam.fy * h / cam.height,
                                cx=cam.cx * w / cam.width, cy=cam.cy * h / cam.height)
    return sensor.replace(camera=small, **{"noise.model": "none", "scattering.model": "none"})


def setup_for(scene, sensor, *, seed: int, max_depth: int = 5, light_paths: bool = True, sampler: str = "sobol",
              pose=None):
    """The tracer's :class:`~tofcore.tracer.setup.TraceSetup` for ``scene`` seen by ``sensor`` (CPU)."""
    settings = TraceSettings(world_from_sensor=suggested_pose(scene) if pose is None else pose,
                             correlations=sensor.modulation.correlation_bank(), seed=seed, max_depth=max_depth,
                             light_paths=light_paths, sampler=sampler)
    return make_setup(scene, sensor.camera, sensor.leds, settings, backend.select_device("cpu"))


# ------------------------------------------------------------------ worker processes
_WORKER = {}


def _init(scene_name: str, scale: float, seed: int, max_depth: int) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    scene = tofcore.demo_scene(scene_name)
    _WORKER["setup"] = setup_for(scene, sensor_at(scale), seed=seed, max_depth=max_depth)


def _pt_block(args) -> ClassSums:
    p0, p1, spp, ratio = args
    return trace_classified(_WORKER["setup"], p0, p1, spp, lt_ratio=ratio)


def _lt_block(args) -> ClassSums:
    first, n, caustic_only, ratio = args
    return trace_light(_WORKER["setup"], first, n, caustic_only=caustic_only, mis_ratio=ratio)


def traced(kind: str, scene_name: str, scale: float, seed: int, *, spp: int = 0, n_paths: int = 0,
           caustic_only: bool = True, mis_ratio: float | None = None, max_depth: int = 5, workers: int = 2,
           block: int = 65536) -> ClassSums:
    """Per-class sums of a whole frame, traced by ``workers`` processes in blocks of about ``block`` paths.

    ``kind`` "pt": the path tracer (:func:`classify.trace_classified`), ``spp`` samples per pixel;
    "lt": light tracing (:func:`light_tracer.trace_light`), ``n_paths`` light paths. ``mis_ratio`` = N/n
    gives both their three-strategy MIS weights (:mod:`mis`).
    """
    sensor = sensor_at(scale)
    n_pix = sensor.camera.width * sensor.camera.height
    if kind == "pt":
        step = max(1, block // spp)
        jobs, fn = [(p, min(p + step, n_pix), spp, mis_ratio) for p in range(0, n_pix, step)], _pt_block
    else:
        jobs = [(f, min(block, n_paths - f), caustic_only, mis_ratio) for f in range(0, n_paths, block)]
        fn = _lt_block
    with ProcessPoolExecutor(workers, initializer=_init, initargs=(scene_name, scale, seed, max_depth)) as pool:
        parts = list(pool.map(fn, jobs))
    if kind == "pt":
        return ClassSums(np.concatenate([p.signal for p in parts], axis=-1),
                         np.concatenate([p.correlation for p in parts], axis=-1), spp)
    total = parts[0]
    for p in parts[1:]:
        total += p
    return total


# ------------------------------------------------------------------ decoding
def mean_images(sums: ClassSums, classes, shape) -> tuple[np.ndarray, np.ndarray]:
    """(signal (H, W), correlation (J, H, W)) means of the classes ``classes`` summed over buckets."""
    sig = sums.signal[list(classes)].sum(axis=(0, 1)) / sums.samples
    corr = sums.correlation[list(classes)].sum(axis=(0, 1)) / sums.samples
    return sig.reshape(shape), corr.reshape((-1,) + shape)


def depth(sensor, correlation: np.ndarray) -> np.ndarray:
    """(H, W) radial distance decoded from mean correlation images (J, H, W); NaN where decoding fails."""
    raw = raw_images(correlation, np.zeros(correlation.shape[1:]), sensor)
    settings = decoding.DecodeSettings(unwrap_tolerance_m=sensor.invalid.unwrap_tolerance_m,
                                       unwrap_weights=sensor.processing.unwrap_weights)
    return decoding.decode(raw, sensor.modulation, settings, check=False).distance
