"""The trace set-up: the caller's settings, checked once, and what every stage reads (:class:`TraceSetup`).

:class:`TraceSettings` is what :func:`~tofcore.tracer.trace.trace_progressive` was asked for (its
keyword arguments, as one typed object); :func:`make_setup` checks them and derives :class:`TraceSetup`:
the scene's arrays on the tracing device, the pose, the LEDs in the scene frame, the correlation bank, the
sampler and the ray offset. Every stage takes the set-up explicitly; nothing in it changes during a trace.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from .. import backend
from ..backend import namespace
from ..errors import ConfigError
from ..scene.ambient import Ambient
from ..scene.camera import Camera
from ..scene.led import LED, leds_at_pinhole
from ..scene.pose import rigid_problem
from ..scene.scene import Scene
from . import qmc
from .light_paths import led_probabilities
from .sampler import Sampler
from .surface import MaterialTable

Correlation = Callable[[np.ndarray], np.ndarray]
"""g_j(τ): delay τ in seconds (float64 array) → correlation value per contribution (same shape)."""


@dataclass(frozen=True)
class CorrelationList:
    """Correlation functions g_j given one by one, evaluated as a bank: ``bank(tau)`` → (J, N).

    The tracer evaluates every channel of a contribution at once through a *bank*: a callable τ → (J, N)
    with ``len(bank) == J``. A sensor gives one (:meth:`tofcore.sensor.modulation.Modulation.correlation_bank`,
    one block per frequency); any other sequence of g_j(τ) is wrapped in this class.
    """

    functions: tuple[Correlation, ...]

    def __len__(self) -> int:
        return len(self.functions)

    def __call__(self, tau):
        return namespace(tau).stack([g_j(tau) for g_j in self.functions])


@dataclass(frozen=True)
class TraceSettings:
    """The keyword arguments of :func:`~tofcore.tracer.trace.trace_progressive` that set a trace up, documented
    there (the passes' policy and the tracer choice go to :mod:`tofcore.tracer.trace` itself)."""

    world_from_sensor: np.ndarray | None = None
    correlations: Sequence[Correlation] | Callable = ()
    ambient: Ambient | None = None
    max_depth: int = 5
    seed: int = 0
    chunk_size: int | None = None
    workers: int | None = None
    transient_bin_m: float | None = None
    transient_max_m: float | None = None
    cancel: Callable[[], bool] | None = None
    device: str | backend.Device = "cpu"
    sampler: str = "sobol"
    light_paths: bool = True
    activity: Callable[[dict], None] | None = None


@dataclass(frozen=True)
class TraceSetup:
    """Everything a stage needs, fixed for the whole trace."""

    scene: Scene
    table: MaterialTable        # the scene's arrays on the tracing device
    camera: Camera
    device: backend.Device      # where the wavefront runs; xp = device.xp
    world_from_sensor: np.ndarray  # 4×4 host pose, world frame
    rotation: object            # (3, 3) world_from_sensor rotation, device array
    lens_center: object         # (3,) scene frame (world − scene.origin_m, where the tracer works), device array
    led_positions: object       # (L, 3) scene frame, device array
    led_axis: object            # (3,) optical axis (+z of the sensor), device array
    leds: tuple[LED, ...]
    skip_first_shadow: np.ndarray  # (L,) bool: LED at the centre of a pinhole lens
    correlations: Callable      # bank: delays τ (N,) in seconds → (J, N) channels g_j(τ)
    n_channels: int             # J correlation channels summed per pixel
    ambient: Ambient | None     # None when black (no ambient work at all)
    max_depth: int
    sampler: Sampler            # the uniforms of every decision (tofcore.tracer.sampler)
    light_paths: bool           # connect camera vertices to light vertices (tofcore.tracer.light_paths)
    led_probability: np.ndarray  # (L,) host: probability of each LED emitting the light vertex
    transient_bins: int         # 0: no transient histogram
    transient_bin_m: float | None

    @property
    def xp(self):
        return self.device.xp


def make_setup(scene: Scene, camera: Camera, leds: Sequence[LED], settings: TraceSettings,
               device: backend.Device) -> TraceSetup:
    """Check the scene, camera, LEDs and settings (one-line :class:`ConfigError` each) and derive the set-up."""
    _check_inputs(scene, camera, leds, settings)
    leds = tuple(leds)
    pose = _checked_pose(settings.world_from_sensor)
    rot = pose[:3, :3]
    correlations = _checked_bank(settings.correlations)
    bins = _transient_bins(settings.transient_bin_m, settings.transient_max_m)
    positions = np.array([x.position_m for x in leds])
    lens_scene = pose[:3, 3] - np.asarray(scene.origin_m)  # the tracer works in the scene frame
    led_scene = positions @ rot.T + lens_scene
    xp, max_depth, ambient = device.xp, int(settings.max_depth), settings.ambient
    return TraceSetup(
        scene=scene, table=MaterialTable(scene, xp), camera=camera, device=device, world_from_sensor=pose,
        rotation=xp.asarray(rot), lens_center=xp.asarray(lens_scene),
        led_positions=xp.asarray(led_scene), led_axis=xp.asarray(rot[:, 2]), leds=leds,
        skip_first_shadow=leds_at_pinhole(camera, leds),
        correlations=correlations, n_channels=len(correlations),
        ambient=None if ambient is None or ambient.is_black else ambient,
        max_depth=max_depth, sampler=Sampler.for_seed(settings.seed, settings.sampler),
        light_paths=bool(settings.light_paths) and max_depth >= 2 and led_probabilities(leds).sum() > 0,
        led_probability=led_probabilities(leds),
        transient_bins=bins, transient_bin_m=settings.transient_bin_m)


def on_host(setup: TraceSetup) -> TraceSetup:
    """The same set-up with its arrays on the host (NumPy): what a GPU render's paths are traced from where the
    compiled wavefront cannot trace them (:class:`tofcore.tracer.parallel.HostTracer`)."""
    if not setup.device.is_gpu:
        return setup
    host = backend.select_device("cpu")
    return replace(setup, device=host, table=MaterialTable(setup.scene, np), rotation=backend.to_host(setup.rotation),
                   lens_center=backend.to_host(setup.lens_center), led_positions=backend.to_host(setup.led_positions),
                   led_axis=backend.to_host(setup.led_axis))


def _check_inputs(scene, camera, leds, settings: TraceSettings) -> None:
    if not isinstance(scene, Scene):
        raise ConfigError(f"trace: scene must be a tofcore.Scene, got {type(scene).__name__}")
    if not isinstance(camera, Camera):
        raise ConfigError(f"trace: camera must be a tofcore.Camera, got {type(camera).__name__}")
    leds = tuple(leds)
    if not leds or not all(isinstance(x, LED) for x in leds):
        raise ConfigError(f"trace: leds must be a non-empty sequence of tofcore.LED, got {leds!r}")
    if settings.sampler not in qmc.SAMPLERS:
        raise ConfigError(f"trace: sampler must be one of {list(qmc.SAMPLERS)}, got {settings.sampler!r}")
    max_depth = settings.max_depth
    if not isinstance(max_depth, (int, np.integer)) or max_depth < 1:
        raise ConfigError(f"trace: max_depth must be an integer >= 1, got {max_depth!r}")


def _checked_pose(world_from_sensor) -> np.ndarray:
    pose = np.eye(4) if world_from_sensor is None else np.asarray(world_from_sensor, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ConfigError(f"trace: world_from_sensor must be a finite 4x4 matrix, got shape {pose.shape}")
    problem = rigid_problem(pose)
    if problem is not None:
        raise ConfigError(f"trace: world_from_sensor must be a rigid transform (rotation + translation): {problem}")
    return pose


def _checked_bank(correlations) -> Callable:
    """The correlations as a bank τ → (J, N) with ``len``: a bank as given, or a sequence of g_j wrapped."""
    if not callable(correlations):
        correlations = CorrelationList(tuple(correlations))
        for j, g in enumerate(correlations.functions):
            if not callable(g):
                raise ConfigError(f"trace: correlations[{j}] must be callable g(tau_s), got {type(g).__name__}")
    elif not hasattr(correlations, "__len__"):
        raise ConfigError(f"trace: a correlation bank must have len() (its channel count), "
                          f"got {type(correlations).__name__}")
    return correlations


def _transient_bins(bin_m: float | None, max_m: float | None) -> int:
    if bin_m is None:
        return 0
    if not bin_m > 0 or not max_m or not max_m > bin_m:
        raise ConfigError(f"trace: transient_bin_m must be > 0 and transient_max_m > transient_bin_m, "
                          f"got {bin_m!r} and {max_m!r}")
    return int(np.ceil(max_m / bin_m))
