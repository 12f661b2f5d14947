"""From light transport to what the camera delivers: :func:`render` → :class:`~tofcore.output.frame.Frame`.

The stages (DESIGN.md, "The flow"):

1. **plan** what the scene and sensor need (:mod:`tofcore.plan`);
2. **trace** progressive passes (:func:`trace_progressive`, on the tracer that
   :func:`tofcore.compiled.tracer.choose` picks), each contribution correlated with
   the sensor's g_j (:mod:`tofcore.sensor.modulation`), bucketed by bounce count;
   after each pass estimate the depth standard error from the per-pixel
   variances and report it: the passes' schedule (:mod:`tofcore.tracer.trace`,
   given a :class:`~tofcore.tracer.trace.PassPolicy`) sizes and allocates the
   next pass from it and stops at ``target_error_m``, ``time_budget_s`` or ``spp``;
3. **raw images** per frequency and phase step: charge in electrons =
   responsivity × exposure × (LED signal correlation + ambient × gate duty),
   :func:`raw_images`;
4. **post-process** the raw images before decoding: lens scattering
   (:mod:`tofcore.sensor.optics`), shot and read noise (:mod:`tofcore.sensor.noise`),
   full-well saturation;
5. **decode** phase, amplitude, offset, distance, unwrapping, invalid pixels
   (:mod:`tofcore.sensor.decode`); radial distance → z-depth.

Besides the camera's output the frame carries noise-free ground truth: the
first-hit distance, the direct-only (k = 1) decoded distance and the decoded
distance for every max path length k = 1..K — all from the one render.

Error against run time: the tracer keeps the correlation sums of R
independent randomized-QMC replicates per pixel; the spread of the replicates,
projected through the decoder's linearisation (all frequencies with their
unwrapping weights, or the pulsed ratio), is the standard error of the depth
the camera outputs (:func:`depth_standard_error`). The convergence log holds,
per pass: elapsed seconds, spp, the RMS of that standard error over the
pixels that see a surface, and the RMS error against a reference distance
image when one is given.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from . import backend, limits
from .backend import gpu_errors, namespace
from .constants import SPEED_OF_LIGHT_M_S
from .errors import ConfigError
from .output.frame import Frame
from .plan import Plan, make_plan
from .scene.ambient import Ambient
from .scene.demo import suggested_pose
from .scene.scene import Scene
from .sensor import decode as decoding
from .sensor import denoise
from .sensor import noise as noise_models
from .sensor import optics
from .sensor import processing
from .sensor.raw import raw_images
from .compiled.tracer import choose
from .tracer import trace as tracing
from .tracer.estimator import rms_error
from .tracer.qmc import REPLICATES
from .tracer.trace import Passes, PassPolicy, PassReport
from .tracer.transport import Transport


def trace(scene: Scene, camera, leds, **settings) -> Transport:
    """The light transport of a whole frame, without the sensor model, on the tracer that
    :func:`tofcore.compiled.tracer.choose` picks: the compiled one wherever it can run the trace, else the NumPy
    reference (``transport.stats.tracer`` and ``tracer_reason`` say which, and why). The parameters are those of
    :func:`tofcore.tracer.trace.trace_progressive`."""
    settings.setdefault("tracer", choose)
    return tracing.trace(scene, camera, leds, **settings)


def trace_progressive(scene: Scene, camera, leds, **settings) -> Passes:
    """:func:`trace` in progressive passes: the accumulated transport after each
    (:func:`tofcore.tracer.trace.trace_progressive`, whose parameters these are)."""
    settings.setdefault("tracer", choose)
    return tracing.trace_progressive(scene, camera, leds, **settings)


def depth_standard_error(transport: Transport, sensor, n_raw: int) -> np.ndarray:
    r"""(H, W) Monte Carlo standard error (m) of each pixel's output depth, from the independent replicates.

    Notes
    -----
    The tracer keeps the channel sums of R independent randomized-QMC replicates per pixel
    (:mod:`tofcore.tracer.qmc`). Each replicate's mean gives raw images :math:`Q^{(r)}` (ambient included,
    :func:`raw_images`); the decoder's linearisation :math:`g = \partial d/\partial Q`
    (:func:`tofcore.sensor.decode.distance_gradient`: all frequencies and their unwrapping weights, or the
    pulsed ratio) projects each replicate's deviation onto the decoded distance,

    .. math:: \hat\sigma_d^2 = \frac{1}{R(R-1)} \sum_r \big(g \cdot (Q^{(r)} - \bar Q)\big)^2,

    the variance of the mean of R independent estimates. A CW distance wraps at the unambiguous range
    U (:meth:`~tofcore.sensor.modulation.Modulation.unambiguous_range_m`): noise that carries a distance d near
    0 or U across the boundary changes the output by U, so the expected squared error adds
    :math:`P\,U^2` with :math:`P = \Phi(-d/\hat\sigma_d) + \Phi(-(U - d)/\hat\sigma_d)` (normal tails,
    the central limit of the pixel mean; d from the noise-free first hit). At 16 spp the phase noise of
    a room with fireflies has heavier tails than that (tests/tofcore/test_render_error.py). The result
    is the RMS error of the output depth; for a z-depth sensor it is scaled by the pixel ray's z
    component (z = d·ω_z). NaN where a pixel has no signal or
    a replicate no sample yet. Scattering and sensor noise are not part of it: this is the render's own
    noise. A camera that filters its phasors (``processing.phasor_filter``) averages each replicate's
    deviation over the 3 × 3 neighbours too, frequency by frequency, with the filter's weights at the
    replicates' mean (:func:`_filtered_deviation`).
    """
    return render_error(transport, sensor, n_raw)[0]


FLIP_FRACTION = 1.0 / 8.0
"""Replicates whose decoded distances spread by more than this fraction of the smallest ambiguity distance
unwrapped to different intervals (:func:`unwrap_flips`): for the Kinect v2 1.25 m / 8 = 0.156 m, below the
0.205 m by which the nearest wrong combination of its wraps lies from consistent data, and far above the
continuous spread of the replicates (a few mm at 16 spp)."""


def unwrap_flips(transport: Transport, sensor, n_raw: int):
    r"""(H, W) bool: pixels whose R independent replicates unwrap to different ambiguity intervals.

    Notes
    -----
    Each replicate's mean raw images :math:`Q^{(r)}` (as in :func:`depth_standard_error`) are decoded by
    the camera's own phase estimation, phasor filter and unwrapping (no thresholds); where the decoded
    distances spread by more than :data:`FLIP_FRACTION` of the smallest ambiguity distance, the replicates
    disagree on the wrap, and the pixel mean can land on either: an error of a whole wrap combination
    (for the Kinect v2 ≥ 0.2 m, typically 1.2 m), which the linearised standard error cannot describe. Such
    pixels are counted apart (the share in the convergence log, the map in ``frame.unwrap_flip``). A
    single-frequency camera flips across its unambiguous range (0 ↔ U). A pulsed camera does not unwrap:
    all False. False where a replicate has no sample yet.
    """
    return render_error(transport, sensor, n_raw)[1]


BAND_MIN_ROWS = 32
"""Fewest rows of an image band :func:`render_error` hands a thread of its own (a band carries two rows of
halo: smaller bands would spend more on the halo than a thread saves)."""


def render_error(transport: Transport, sensor, n_raw: int, threads: int | None = None):
    """(:func:`depth_standard_error`, :func:`unwrap_flips`) of the transport so far, both from one computation
    of the replicates' raw images, on the transport's device.

    On a GPU, a transport of the compiled wavefront (``transport.stats.tracer == "compiled"``) of a
    continuous-wave sensor gets the compiled estimate, :mod:`tofcore.compiled.depth_error`: two kernels instead
    of ~400 array operations, equal to this array program to rounding. The CPU keeps the array program: its
    compiled build (which CI checks against this one) computes the demo frame's estimate in 0.45 s instead of
    0.84 s on 2 cores, ~1 % of a frame, for 11 s more of numba's one-time compile (docs/benchmarks.md).
    On the CPU the image is cut into bands of rows, one per thread (``threads``: default the CPUs this
    process may run on), each band with one row of its neighbours above and below, which the 3 × 3 phasor
    filter reads and which are dropped afterwards: every step of both estimates is per pixel but for that
    one filter, so each pixel's numbers are those of the whole image, bit for bit
    (tests/tofcore/test_render_error.py). NumPy releases the interpreter while it computes, so the bands run
    on all cores: the estimate after every pass is serial work the tracer's threads wait for.
    """
    kernels = _post_trace_kernels(transport, sensor)
    if kernels is not None:
        return kernels.render_error(transport, sensor, n_raw, flip_threshold_m(sensor))
    means, counts = transport.replicate_means()          # (R, J+2, H, W), (R, H, W)
    xp = namespace(means)
    distance = backend.device_copy(xp, transport.first_hit.distance_m)
    z = None
    if sensor.depth_output == "z":
        z = np.abs(backend.device_copy(xp, sensor.camera.pixel_center_directions())[..., 2])
    height = means.shape[-2]
    bands = 1 if xp is not np else max(1, min(threads or limits.usable_cpus(), height // BAND_MIN_ROWS))
    if bands == 1:
        return _band_error(means, counts, distance, z, sensor, n_raw)
    edges = [round(b * height / bands) for b in range(bands + 1)]

    def band(b: int):
        lo, hi = max(edges[b] - 1, 0), min(edges[b + 1] + 1, height)
        rows = slice(lo, hi)
        sigma, flips = _band_error(means[..., rows, :], counts[..., rows, :], distance[rows],
                                   None if z is None else z[rows], sensor, n_raw)
        keep = slice(edges[b] - lo, edges[b + 1] - lo)
        return sigma[keep], flips[keep]

    with ThreadPoolExecutor(bands) as pool:
        parts = list(pool.map(band, range(bands)))
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _on_the_gpu_wavefront(transport: Transport) -> bool:
    """Whether ``transport`` was traced by the compiled wavefront on a GPU (then numba's CUDA target is loaded,
    and the post-trace kernels of :mod:`tofcore.compiled` run beside it)."""
    return namespace(transport.replicate_sum) is not np and transport.stats.tracer == "compiled"


def _post_trace_kernels(transport: Transport, sensor):
    """:mod:`tofcore.compiled.depth_error` where it takes the post-trace work per pixel (the error estimate, the
    per-k ground truth): a transport of the GPU's compiled wavefront and a sensor it supports; else None (the
    array programs here and in the decoder; on the CPU too, see :func:`render_error`). The camera's decode has
    its own choice, :func:`_camera_decoder`."""
    if not _on_the_gpu_wavefront(transport):
        return None
    from .compiled import depth_error

    return None if depth_error.unsupported(sensor) else depth_error


def _band_error(means, counts, distance, z, sensor, n_raw: int):
    """(σ, flips) of :func:`render_error` for the rows of ``means`` (R, J+2, h, W), ``counts`` (R, h, W), the
    first-hit ``distance`` (h, W) and the pixel rays' |z| (h, W) of a z-depth sensor (else None)."""
    r, _, h, w = means.shape
    # all replicates as one (J, R·h, W) image stack: one raw_images call instead of R
    stacked = raw_images(means[:, 1:1 + n_raw].transpose(1, 0, 2, 3).reshape(n_raw, r * h, w),
                         means[:, -1].reshape(r * h, w), sensor).reshape(n_raw, r, h, w)
    sigma = _standard_error(stacked.transpose(1, 0, 2, 3), counts, distance, sensor)
    if z is not None:
        sigma = sigma * z
    return sigma, _flips(np.nan_to_num(stacked), counts, sensor)


def _standard_error(raw, counts, distance, sensor):
    """:func:`depth_standard_error` of the replicates' raw images ``raw`` (R, J, h, W)."""
    replicates = raw.shape[0]
    xp = namespace(raw)
    centre = raw.mean(axis=0)
    grad = decoding.distance_gradient(np.nan_to_num(centre), sensor.modulation, sensor.processing.unwrap_weights,
                                      check=False)
    if sensor.processing.phasor_filter == "none" or not sensor.modulation.is_cw:
        deviation = (grad[None] * (raw - centre[None])).sum(axis=1)
    else:
        deviation = _filtered_deviation(raw - centre[None], np.nan_to_num(centre), sensor)
    var = (deviation**2).sum(axis=0) / (replicates * (replicates - 1))
    ok = (counts.min(axis=0) >= 1) & (np.abs(grad).sum(axis=0) > 0)
    if sensor.modulation.is_cw:
        unambiguous = sensor.modulation.unambiguous_range_m()
        d = np.nan_to_num(distance, nan=0.5 * unambiguous)
        sd = np.sqrt(var)
        with np.errstate(divide="ignore", invalid="ignore"):
            wrap = _normal_tail(d / sd) + _normal_tail((unambiguous - d) / sd)
        var = var + np.where(sd > 0, wrap, 0.0) * unambiguous**2
    return np.where(ok, np.sqrt(var), np.nan)


def flip_threshold_m(sensor) -> float:
    """The spread of the replicates' decoded distances above which they unwrapped to different intervals:
    :data:`FLIP_FRACTION` of the smallest ambiguity distance."""
    return FLIP_FRACTION * float(np.min(sensor.modulation.ambiguity_distances_m()))


def _flips(raw, counts, sensor):
    """:func:`unwrap_flips` of the replicates' raw images ``raw`` (J, R, h, W), NaN set to 0."""
    mod = sensor.modulation
    xp = namespace(raw)
    r = raw.shape[1]
    if not mod.is_cw or r < 2:
        return xp.zeros(raw.shape[2:], dtype=bool)
    cw = decoding.decode_cw(raw, mod, check=False)
    if sensor.processing.phasor_filter == "bilateral":
        cw = decoding.filtered_phases(cw, mod, sensor.invalid.min_amplitude_e)
    distance = decoding.unwrap(cw, mod, tolerance_m=sensor.invalid.unwrap_tolerance_m,
                               weights=sensor.processing.unwrap_weights).distance   # (R, h, W)
    signal = ~np.any(cw.amplitude <= decoding.NO_RETURN_RELATIVE_AMPLITUDE * cw.offset, axis=0).any(axis=0)
    spread = distance.max(axis=0) - distance.min(axis=0)
    return (spread > flip_threshold_m(sensor)) & signal & (counts.min(axis=0) >= 1)


def _filtered_deviation(delta, centre, sensor):
    r"""(R, H, W) distance deviation of each replicate, through the camera's phasor filter, linearised.

    Notes
    -----
    Per frequency i the replicate's phasor deviation :math:`\delta Z = \sum_k \delta Q_k e^{i\theta_k}`
    (``delta`` = Q^{(r)} − Q̄, ``centre`` = Q̄) is averaged like the phasors,
    :math:`\delta Z' = \sum_q w_q \delta Z_q` with the filter's weights at the mean
    (:func:`tofcore.sensor.processing.bilateral_weights`), and turned into a phase deviation of the filtered phasor
    :math:`Z' = \sum_q w_q \bar Z_q`: :math:`\delta\varphi' = \operatorname{Im}(\delta Z' \bar Z'^*)/|Z'|^2`;
    the distance deviation is :math:`\sum_i w_i\, c\, \delta\varphi'_i / (4\pi f_i)` with the unwrapping
    weights :math:`w_i` (:func:`tofcore.sensor.decode.unwrap_weights`).
    """
    mod = sensor.modulation
    xp = namespace(delta)
    unwrap_w = decoding.unwrap_weights(decoding.decode_cw(centre, mod, check=False), mod,
                                       sensor.processing.unwrap_weights)
    mean_re, mean_im, d_re, d_im = [], [], [], []   # per frequency: Z̄ (H, W) and δZ (R, H, W)
    start = 0
    for n in mod.phase_steps:
        theta = 2.0 * np.pi * np.arange(n) / n
        cos_k = xp.asarray(np.round(np.cos(theta), 15))[:, None, None]
        sin_k = xp.asarray(np.round(np.sin(theta), 15))[:, None, None]
        mean_re.append((cos_k * centre[start:start + n]).sum(axis=0))
        mean_im.append((sin_k * centre[start:start + n]).sum(axis=0))
        d_re.append((cos_k[None] * delta[:, start:start + n]).sum(axis=1))
        d_im.append((sin_k[None] * delta[:, start:start + n]).sum(axis=1))
        start += n
    # all frequencies at once: (F, H, W) phasors, (R, F, H, W) deviations, weights (3, 3, F, H − 2, W − 2)
    mean_re, mean_im = xp.stack(mean_re), xp.stack(mean_im)
    min_amplitude = sensor.invalid.min_amplitude_e * xp.asarray(np.asarray(mod.phase_steps, np.float64) / 2)
    weights = processing.bilateral_weights(mean_re, mean_im, min_amplitude=min_amplitude.reshape(-1, 1, 1))
    z_re, z_im = processing.neighbour_mean(mean_re, weights), processing.neighbour_mean(mean_im, weights)
    d_re = processing.neighbour_mean(xp.stack(d_re, axis=1), weights)
    d_im = processing.neighbour_mean(xp.stack(d_im, axis=1), weights)
    norm2 = z_re * z_re + z_im * z_im
    d_phase = np.where(norm2 > 0, (z_re * d_im - z_im * d_re) / np.where(norm2 > 0, norm2, 1.0), 0.0)
    f_hz = xp.asarray(np.asarray(mod.frequencies_hz, np.float64))[:, None, None]
    return (unwrap_w * SPEED_OF_LIGHT_M_S / (4.0 * np.pi * f_hz) * d_phase).sum(axis=1)


def _normal_tail(x):
    """P(Z > x) for a standard normal Z, |error| < 1.5e-7 (Abramowitz & Stegun 7.1.26 for erfc), any backend."""
    z = np.abs(x) / np.sqrt(2.0)
    t = 1.0 / (1.0 + 0.3275911 * z)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    upper = 0.5 * poly * np.exp(-z * z)
    return np.where(x >= 0, upper, 1.0 - upper)


def render(scene: Scene, sensor, pose: np.ndarray | None = None, **settings) -> Frame:
    """Render one ToF frame; the parameters are those of :func:`render_progressive`."""
    frame = None
    for frame in render_progressive(scene, sensor, pose, every_pass=False, **settings):
        pass
    return frame


def render_progressive(scene: Scene, sensor, pose: np.ndarray | None = None, *, spp: int = 64,
                       max_depth: int = 5, seed: int = 0, time_budget_s: float | None = None,
                       target_error_m: float | None = None, ambient: Ambient | None = None,
                       reference_distance: np.ndarray | None = None,
                       progress: Callable[[dict], None] | None = None, cancel: Callable[[], bool] | None = None,
                       workers: int | None = None, chunk_size: int | None = None,
                       every_pass: bool = True, device: str | backend.Device = "cpu",
                       adaptive: bool = True, sampler: str = "sobol", light_paths: bool = True,
                       transient_bin_m: float | None = None, transient_max_m: float | None = None,
                       preview_denoise: bool = False, preview_frames: bool = False,
                       activity: Callable[[dict], None] | None = None) -> Iterator[Frame]:
    """Render one ToF frame in progressive passes, yielding the complete :class:`Frame` after each pass.

    The last frame yielded is the result (``frame.stats["final"]`` is True on it only).

    Parameters
    ----------
    scene : the geometry (:class:`~tofcore.scene.Scene`).
    sensor : a :class:`~tofcore.sensor.Sensor` (e.g. ``tofcore.load_preset("kinect_v2")``).
    pose : 4×4 ``world_from_sensor`` (OpenCV sensor frame); default: the scene's suggested pose, else identity.
    spp : most samples per pixel (the mean over the pixels); fewer when a target error or time budget stops
        the render first.
    max_depth : surface vertices per path (1 = direct light only).
    seed : non-negative int; the same seed gives the same frame (tracing, then sensor noise).
    time_budget_s : seconds for the whole render (set-up to final frame): the passes are sized from their
        measured cost so that the budget is used (:mod:`tofcore.tracer.budget`); the frame then has the
        samples that fit, up to ``spp``. Not reproducible across machines.
    target_error_m : stop once the RMS estimated depth standard error (Monte Carlo) is at most this.
    ambient : unmodulated background light.
    reference_distance : (H, W) converged radial distance to log the RMS error against, per pass.
    progress : called after every pass with the convergence-log row (dict).
    activity : called while a pass runs, in the rendering thread: ``{"stage": "compile", "seconds": s}``
        about twice a second while the compiled tracer's kernels compile (once per install: later renders
        load them in about a second), and ``{"stage": "trace", "pass": n, "spp": s, "spp_max": m}`` after
        every block of pixels of a CPU pass, ``s`` the mean samples per pixel traced so far
        (:class:`tofcore.tracer.trace.PassActivity`). ``frame.stats["transport"]["compile"]`` says how long
        a compile took.
    cancel : polled between chunks of rays; when it returns True the render raises
        :class:`~tofcore.errors.Cancelled` within about a second.
    workers, chunk_size : passed to the tracer.
    every_pass : build and yield a frame after every pass (False: only the final one, which saves
        decoding the intermediate passes).
    adaptive : after a uniform pilot of 16 spp, give each pass's samples to the pixels whose estimated
        depth error is largest (:mod:`tofcore.tracer.estimator`); False: every pixel gets ``spp``.
    sampler : ``"sobol"`` (randomized QMC, default) or ``"independent"`` (:mod:`tofcore.tracer.qmc`).
    light_paths : connect the camera paths to light vertices with MIS (:mod:`tofcore.tracer.light_paths`).
    transient_bin_m, transient_max_m : also keep the transient (time-resolved) histogram, bins of this
        width (m of optical path length LED → … → lens) up to this length; ``frame.transient`` is then
        (H, W, B) mean radiance per bin, bin b centred at (b + ½)·width (:meth:`Transport.transient`).
    preview_denoise : for interactive previews only: smooth ``depth`` and ``distance`` with a joint bilateral
        filter guided by the amplitude (:mod:`tofcore.sensor.denoise`), which removes render noise at the
        price of a bias at depth edges (``studies/preview_denoise.py`` measures it). Never for datasets
        unless wanted; ``frame.stats["preview_denoise"]`` records the filter's parameters (None: off).
    preview_frames : the frames before the final one are for display: without ``direct_distance`` and
        ``distance_per_k`` (None), which take K extra decodes, ≈ 10 % of a progressive render's time with
        a frame per pass (docs/benchmarks.md). The final frame is always complete; a preview frame is
        otherwise the same frame, bit for bit. :func:`tofcore.write_frame` refuses a preview frame.
    device : ``"cpu"`` (NumPy), ``"gpu"`` (CuPy: tracing, sensor, scattering, noise and decoding on the
        GPU; the noise is counter-based, :class:`~tofcore.sensor.noise.NoiseStream`, so both devices give
        the same frame) or
        ``"auto"`` (the GPU when usable, else the CPU). The frame's arrays are NumPy either way;
        ``frame.stats["device"]`` records where it ran and, for ``"auto"``, why it fell back.
        GPU failures (no CuPy, no device, out of memory, CUDA errors) raise
        :class:`~tofcore.backend.GpuUnavailable` with one line naming the cause; with ``"auto"``
        a failure before the first frame falls back to the CPU (recorded in ``fallback_reason``).
    """
    _check_settings(spp, time_budget_s, target_error_m, max_depth=max_depth, seed=seed, sensor=sensor,
                    transient_bins=transient_bins(transient_bin_m, transient_max_m))
    for name, value in (("preview_denoise", preview_denoise), ("preview_frames", preview_frames)):
        if not isinstance(value, bool):
            raise ConfigError(f"render: {name} must be True or False, got {value!r}")
    dev = backend.select_device(device)
    settings = RenderSettings(spp=spp, max_depth=max_depth, seed=seed, time_budget_s=time_budget_s,
                              target_error_m=target_error_m, ambient=ambient, reference_distance=reference_distance,
                              progress=progress, cancel=cancel, workers=workers, chunk_size=chunk_size,
                              every_pass=every_pass, adaptive=adaptive, sampler=sampler, light_paths=light_paths,
                              transient_bin_m=transient_bin_m, transient_max_m=transient_max_m,
                              preview_denoise=preview_denoise, preview_frames=preview_frames, activity=activity)
    yield from _render_on(scene, sensor, pose, settings, dev)


def _render_on(scene: Scene, sensor, pose, settings: RenderSettings, dev: backend.Device) -> Iterator[Frame]:
    """:func:`render_progressive` on the resolved device; with ``"auto"``, a GPU failure before the first frame
    renders on the CPU instead."""
    if not dev.is_gpu:
        yield from _render_passes(scene, sensor, pose, settings, dev)
        return
    started = False
    try:
        with gpu_errors():
            for frame in _render_passes(scene, sensor, pose, settings, dev):
                started = True
                yield frame
    except backend.GpuUnavailable as exc:
        if dev.requested != "auto" or started:
            raise
        yield from _render_passes(scene, sensor, pose, dataclasses.replace(settings, chunk_size=None),
                                  backend.cpu_device("auto", str(exc)))


@dataclass(frozen=True)
class RenderSettings:
    """The keyword arguments of :func:`render_progressive` (documented there), as one object."""

    spp: int
    max_depth: int
    seed: int
    time_budget_s: float | None
    target_error_m: float | None
    ambient: Ambient | None
    reference_distance: np.ndarray | None
    progress: Callable[[dict], None] | None
    cancel: Callable[[], bool] | None
    workers: int | None
    chunk_size: int | None
    every_pass: bool
    adaptive: bool
    sampler: str
    light_paths: bool
    transient_bin_m: float | None
    transient_max_m: float | None
    preview_denoise: bool = False
    preview_frames: bool = False
    activity: Callable[[dict], None] | None = None


def _render_passes(scene: Scene, sensor, pose, settings: RenderSettings, device: backend.Device) -> Iterator[Frame]:
    """:func:`render_progressive` on one resolved device."""
    if sensor.noise.model == "li" and sensor.modulation.kind == "pulsed":
        raise ConfigError(f"render: sensor {sensor.name!r}: noise model 'li' (eq. 2.43) needs a continuous-wave "
                          f"sensor, got modulation kind 'pulsed'; use noise model 'raw'")
    if pose is None:  # framed for this sensor where the scene stores its box (mesh files)
        pose = suggested_pose(scene, sensor)
    s = settings
    plan = make_plan(scene, sensor, max_depth=s.max_depth, ambient=s.ambient)
    correlations = sensor.modulation.correlation_bank()
    n_raw = len(correlations)
    reference = _checked_reference(s.reference_distance, sensor)
    setup = frame_setup(sensor, plan, device.xp)
    log: list[dict] = []
    policy = PassPolicy(spp=s.spp, progressive=s.every_pass, time_budget_s=s.time_budget_s,
                        target_error_m=s.target_error_m, adaptive=s.adaptive)
    frame_s = None  # the latest frame's build (s): the time budget keeps as much for the final one
    start = _clock()
    passes = trace_progressive(scene, sensor.camera, sensor.leds, world_from_sensor=pose,
                               correlations=correlations, ambient=s.ambient if plan.ambient else None,
                               max_depth=s.max_depth, seed=s.seed, workers=s.workers, chunk_size=s.chunk_size,
                               cancel=s.cancel, device=device, sampler=s.sampler, light_paths=s.light_paths,
                               transient_bin_m=s.transient_bin_m, transient_max_m=s.transient_max_m, policy=policy,
                               activity=s.activity)
    try:
        for transport in passes:
            elapsed = _clock() - start
            counts = backend.to_host(transport.sample_count)
            sigma, flips = _depth_error(transport, sensor, n_raw, counts)
            estimate_s = _clock() - start - elapsed
            row = _convergence_row(transport, sensor, n_raw, sigma, counts, reference, elapsed, setup, flips)
            log.append(row)
            if s.progress is not None:
                s.progress(dict(row, spp_max=s.spp))
            done = passes.report(PassReport(error_m=sigma, estimate_s=estimate_s, frame_s=frame_s, apart=flips))
            if not (done or s.every_pass):
                continue
            frame_start = _clock()
            frame = _frame(transport, sensor, pose, plan, s.seed, n_raw, setup, per_k=done or not s.preview_frames)
            frame.metadata["objects"] = object_table(scene)
            if transport.transient_sum is not None:
                frame.transient = backend.to_host(transport.transient()).astype(np.float32)
                frame.transient_bin_m = float(transport.transient_bin_m)
            frame.unwrap_flip = flips.astype(np.uint8)
            _add_render_stats(frame, transport, sigma, counts, dict(s.__dict__, final=done, trace_seconds=elapsed,
                                                            seconds=_clock() - start, plan=plan.as_dict(),
                                                            convergence=list(log), device=device.as_dict()))
            if s.preview_denoise:
                _denoise(frame)
            frame_s = _clock() - frame_start
            yield frame
            if done:
                return
    finally:  # also on an exception or Ctrl-C between passes: the workers' shared memory is released now
        passes.close()


def _depth_error(transport: Transport, sensor, n_raw: int, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) host :func:`depth_standard_error` and :func:`unwrap_flips` of the transport so far, read back in
    one copy; NaN and False while no pixel has a sample in every replicate (the 1 and 2 spp passes: ~1.5 s
    saved)."""
    shape = (sensor.camera.height, sensor.camera.width)
    if counts.max() < REPLICATES:
        return np.full(shape, np.nan), np.zeros(shape, dtype=bool)
    sigma, flips = render_error(transport, sensor, n_raw)
    both = backend.to_host(namespace(sigma).stack([sigma, flips.astype(sigma.dtype)]))
    return both[0], both[1] > 0.5


_clock = time.perf_counter  # the render's clock (seconds); tests replace it to check the budgeted passes


def _denoise(frame: Frame) -> None:
    """The preview filter on the frame's output depth (:mod:`tofcore.sensor.denoise`); the radial distance
    follows it (distance = z / ω_z for a z-depth camera)."""
    frame.depth = denoise.preview_denoise(frame.depth, frame.amplitude, frame.render_error)
    if frame.depth_output == "z":
        with np.errstate(invalid="ignore", divide="ignore"):
            frame.distance = (frame.depth / np.abs(frame.ray_directions[..., 2])).astype(np.float32)
    else:
        frame.distance = frame.depth.copy()
    frame.stats["preview_denoise"] = {"filter": "joint bilateral, amplitude-guided", "radius_px": denoise.RADIUS_PX,
                                      "amplitude_sigma": denoise.AMPLITUDE_SIGMA, "depth_sigmas": denoise.DEPTH_SIGMAS}


def _checked_reference(reference_distance, sensor) -> np.ndarray | None:
    if reference_distance is None:
        return None
    reference = np.asarray(reference_distance, dtype=np.float64)
    shape = (sensor.camera.height, sensor.camera.width)
    if reference.shape != shape:
        raise ConfigError(f"render: reference_distance must have shape {shape}, got {reference.shape}")
    return reference


def _convergence_row(transport: Transport, sensor, n_raw: int, sigma: np.ndarray, counts: np.ndarray, reference,
                     elapsed: float, setup: FrameSetup, flips: np.ndarray | None = None) -> dict:
    """One row of the convergence log: pass, seconds, spp, RMS estimated depth error (the continuous part, over
    the pixels that see a surface and whose replicates agree on the unwrapping), the share and count of the
    pixels whose replicates unwrap to different intervals (:func:`unwrap_flips`), rays (and RMS error)."""
    seen = np.isfinite(transport.first_hit.distance_m)
    flips = np.zeros(seen.shape, dtype=bool) if flips is None else flips
    row = {"pass": transport.stats.passes, "seconds": elapsed, "spp": int(round(counts.mean())),
           "est_depth_error_m": rms_error(np.where(flips, np.nan, sigma), transport.first_hit.distance_m),
           "unwrap_flips": int((flips & seen).sum()),
           "unwrap_flip_share": float((flips & seen).sum() / seen.sum()) if seen.any() else 0.0,
           "rays": transport.stats.rays}
    if reference is not None:
        current = backend.to_host(_decode_clean(transport, sensor, n_raw, setup).distance)
        both = np.isfinite(current) & np.isfinite(reference)
        row["rms_error_m"] = _rms(current[both] - reference[both])
    return row


def _add_render_stats(frame: Frame, transport: Transport, sigma: np.ndarray, counts: np.ndarray, run: dict) -> None:
    """The render's own error, samples (``counts``, host) and statistics on the frame (``run``: the settings
    and timings)."""
    cam_shape = frame.depth.shape
    frame.render_error = sigma.astype(np.float32)
    frame.samples = counts.reshape(cam_shape).astype(np.int32)
    frame.stats.update({
        "final": run["final"], "trace_seconds": run["trace_seconds"], "seconds": run["seconds"],
        "spp": int(round(counts.mean())), "spp_max": run["spp"], "max_depth": run["max_depth"], "seed": run["seed"],
        "time_budget_s": run["time_budget_s"], "target_error_m": run["target_error_m"], "plan": run["plan"],
        "convergence": run["convergence"], "transport": transport.stats.as_dict(), "device": run["device"],
        "sampler": run["sampler"], "adaptive": run["adaptive"], "light_paths": run["light_paths"],
        "preview_denoise": None,
        "samples_per_pixel": {"min": int(counts.min()), "median": float(np.median(counts)),
                              "max": int(counts.max())},
    })


def transient_bins(bin_m: float | None, max_m: float | None) -> int:
    """Bins of a transient histogram of width ``bin_m`` up to ``max_m`` (0 without one, or for values the
    tracer refuses with its own message)."""
    if bin_m is None or max_m is None or not 0 < bin_m < max_m < np.inf:
        return 0
    return int(np.ceil(max_m / bin_m))


def _check_settings(spp, time_budget_s, target_error_m, *, max_depth=1, seed=0, sensor=None,
                    transient_bins: int = 0) -> None:
    """Every setting checked, and the resource limits (:mod:`tofcore.limits`), before anything is allocated."""
    for name, value, lowest in (("spp", spp, 1), ("max_depth", max_depth, 1), ("seed", seed, 0)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < lowest:
            raise ConfigError(f"render: {name} must be an integer >= {lowest}, got {value!r}")
    limits.MAX_SPP.check(int(spp), "render", "spp")
    limits.MAX_DEPTH.check(int(max_depth), "render", "max_depth")
    if sensor is not None and hasattr(sensor, "camera") and hasattr(sensor, "modulation"):
        limits.check_render(sensor, max_depth=int(max_depth), where="render", transient_bins=transient_bins)
    for name, value in (("time_budget_s", time_budget_s), ("target_error_m", target_error_m)):
        if value is not None and (not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0):
            raise ConfigError(f"render: {name} must be a number > 0, got {value!r}")


def object_table(scene: Scene) -> list[dict]:
    """What the ``object_id`` image's values mean: ``[{"id", "name", "materials"}]`` for every object id of
    ``scene`` (names from ``scene.object_names``, ``"object <id>"`` where the scene has none; the names of
    the materials its triangles use, in material-index order). ``object_id`` −1 is no surface."""
    object_ids = np.asarray(scene.object_ids)
    material_ids = np.asarray(scene.material_ids)
    count = max(int(object_ids.max()) + 1 if object_ids.size else 0, len(scene.object_names))
    table = []
    for i in range(count):
        used = np.unique(material_ids[object_ids == i])
        name = scene.object_names[i] if i < len(scene.object_names) and scene.object_names[i] else f"object {i}"
        table.append({"id": i, "name": name, "materials": [scene.materials[m].name for m in used.tolist()]})
    return table


def _rms(values: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(np.square(values)))) if values.size else None


@dataclass(frozen=True, eq=False)
class FrameSetup:
    """What every pass and frame of one render shares after the trace, checked and built once per render."""

    camera: decoding.DecodeSettings  # the camera's decoding: thresholds, range, unwrapping, phasor filter
    clean: decoding.DecodeSettings   # ground truth: no thresholds, no range limit, no spatial filter
    psf: np.ndarray | None           # the lens-scattering kernel (host; uploaded once), None without scattering


def frame_setup(sensor, plan: Plan, xp=np) -> FrameSetup:
    """The :class:`FrameSetup` of ``sensor`` for a render on the array module ``xp``."""
    full_well = sensor.readout.full_well_e
    scale = _range_scale(sensor)
    camera = decoding.DecodeSettings(
        min_amplitude_e=sensor.invalid.min_amplitude_e, min_amplitude_snr=sensor.invalid.min_amplitude_snr,
        read_noise_e=sensor.noise.read_noise_e, gain_noise=sensor.noise.gain_noise,
        saturation_e=full_well if sensor.invalid.invalidate_saturated else None, range_m=tuple(sensor.range_m),
        range_scale=None if scale is None else xp.asarray(scale),
        unwrap_tolerance_m=sensor.invalid.unwrap_tolerance_m, unwrap_weights=sensor.processing.unwrap_weights,
        phasor_filter=sensor.processing.phasor_filter, amplitude_test=sensor.invalid.amplitude_test,
        dealias_tolerance_rad=sensor.invalid.dealias_tolerance_rad, edge_filter=sensor.invalid.edge_filter,
        edge_delta_scale=1.0 if sensor.invalid.edge_filter_fx_px is None
        else sensor.invalid.edge_filter_fx_px / sensor.camera.fx)
    clean = decoding.DecodeSettings(unwrap_tolerance_m=sensor.invalid.unwrap_tolerance_m,
                                    unwrap_weights=sensor.processing.unwrap_weights)
    psf = scattering_kernel(sensor.scattering) if plan.scattering else None
    return FrameSetup(camera=camera, clean=clean, psf=psf)


@functools.lru_cache(maxsize=16)
def scattering_kernel(scattering) -> np.ndarray:
    """:func:`tofcore.sensor.optics.psf_kernel` of a sensor's (frozen, hashable) ``scattering`` table, computed
    once per table and read-only: the Kinect v2's Airy kernel took 1.6 ms of every frame on the 2-core machine
    (a 1-spp GPU frame spends ≈ 13 ms on host bookkeeping), frame_setup now 0.1 ms."""
    kernel = optics.psf_kernel(scattering.model, strength=scattering.strength, radius_px=scattering.radius_px,
                               negative_lobe=scattering.negative_lobe, sigmas_px=scattering.sigmas_px,
                               weights=scattering.weights)
    kernel.setflags(write=False)
    return kernel


def _decode_clean(transport: Transport, sensor, n_raw: int, setup: FrameSetup):
    """Decode the noise-free, scatter-free raw images of all bounces (the convergence log's current depth).

    The camera's frequency weights apply; its spatial phasor filter does not (ground truth is per pixel)."""
    raw = raw_images(transport.correlation()[:n_raw], transport.ambient(), sensor)
    return decoding.decode(raw, sensor.modulation, setup.clean, check=False)


def _decode_clean_per_k(transport: Transport, sensor, n_raw: int, setup: FrameSetup):
    """(K, H, W) noise-free decoded distance for every max path length k = 1..K, decoded as one batch.

    The raw images of bounces ≤ k are the running sums over the bounce buckets; the K images are
    decoded together (one decode of K·H rows) instead of K times. On a GPU, the wavefront's transport of a
    continuous-wave sensor is decoded by one kernel instead (:func:`tofcore.compiled.depth_error.clean_per_k`:
    11.6 → 1.4 ms for the Kinect v2 frame on an H200), the same distances in float32.
    """
    kernels = _post_trace_kernels(transport, sensor)
    if kernels is not None:
        return kernels.clean_per_k(transport, sensor, n_raw)
    xp = namespace(transport.correlation_sum)
    per_bounce = transport.correlation_per_bounce()[:, :n_raw]          # (K, J, H, W)
    cumulative = xp.cumsum(per_bounce, axis=0).transpose(1, 0, 2, 3)     # (J, K, H, W)
    k, h, w = cumulative.shape[1:]
    ambient = xp.broadcast_to(transport.ambient(), (k, h, w)).reshape(k * h, w)
    raw = raw_images(cumulative.reshape(-1, k * h, w), ambient, sensor)
    decoded = decoding.decode(raw, sensor.modulation, setup.clean, check=False)
    return decoded.distance.reshape(k, h, w)


def _range_scale(sensor) -> np.ndarray | None:
    """What ``range_m`` limits: the output depth, so z for a z-depth camera (libfreenect2 compares z with its
    min_depth/max_depth), the radial distance otherwise (None)."""
    if sensor.depth_output != "z":
        return None
    return np.abs(sensor.camera.pixel_center_directions()[..., 2]).astype(np.float64)


def _read_back(images: dict) -> dict:
    """The frame's device images on the host in one copy (float32, stacked; one synchronisation instead of
    one per image); NumPy images pass through."""
    xp = namespace(*images.values())
    if xp is np:
        return images
    planes = {name: image.reshape((-1,) + image.shape[-2:]) for name, image in images.items()}
    host = backend.to_host(xp.concatenate([p.astype(np.float32) for p in planes.values()]))
    out, start = {}, 0
    for name, p in planes.items():
        out[name] = host[start:start + p.shape[0]].reshape(images[name].shape)
        start += p.shape[0]
    return out


def _camera_raw(transport: Transport, sensor, plan: Plan, stream, n_raw: int, setup: FrameSetup):
    """The camera's raw images (R, H, W) of the transport so far, on its device: with lens scattering, shot, read
    and gain noise drawn from ``stream`` (a :class:`~tofcore.sensor.noise.NoiseStream`), clipped at full well."""
    raw = raw_images(transport.correlation()[:n_raw], transport.ambient(), sensor)
    if setup.psf is not None:
        raw = optics.apply_scattering(raw, setup.psf)
    if plan.raw_noise:
        raw = noise_models.add_raw_noise(raw, read_noise_e=sensor.noise.read_noise_e, rng=stream, check=False)
        if sensor.noise.gain_noise > 0:  # Keller's β (eq. 3.1), after the shot and read noise of the same stream
            raw = noise_models.keller_amplitude_noise(raw, alpha_e=0.0, beta=sensor.noise.gain_noise, rng=stream,
                                                      check=False)
    return np.minimum(raw, sensor.readout.full_well_e)


def _camera_decoder(transport: Transport, sensor, settings: decoding.DecodeSettings, shape: tuple[int, ...]):
    """The function that decodes the camera's raw images of image ``shape`` with ``settings``:
    :func:`tofcore.compiled.camera_decode.decode` (three kernels instead of ~270 array operations, the decoder's
    outputs to rounding) for a transport of the GPU's compiled wavefront and a decode that module
    :func:`~tofcore.compiled.camera_decode.unsupported` does not refuse; else the decoder, :func:`tofcore.sensor.decode.decode`
    (on the CPU too: docs/benchmarks.md, "The camera's decode compiled")."""
    if not _on_the_gpu_wavefront(transport):
        return decoding.decode
    from .compiled import camera_decode

    return decoding.decode if camera_decode.unsupported(sensor.modulation, settings, shape) else camera_decode.decode


def _camera_images(transport: Transport, sensor, plan: Plan, seed: int, n_raw: int, setup: FrameSetup,
                   directions: np.ndarray) -> dict:
    """The camera's images of the transport so far, on its device: raw images with scattering, noise and
    saturation, decoded (depth, distance, amplitude, offset, intensity, confidence, reason, raw)."""
    mod = sensor.modulation
    stream = noise_models.NoiseStream.from_seed(seed)  # apart from the tracer's; the same numbers on every device
    raw = _camera_raw(transport, sensor, plan, stream, n_raw, setup)
    xp = namespace(raw)
    decode = _camera_decoder(transport, sensor, setup.camera, raw.shape[1:])
    decoded = decode(raw, mod, setup.camera, check=False)
    distance = decoded.distance.astype(np.float64)
    if plan.distance_noise:
        # Eq. 2.43 takes the signal A and the non-signal charge B; the decoded offset (eq. 2.41) is A + B
        # for the ideal raw images simulated here (tests/tofcore/test_noise.py derives the mapping).
        amplitude = decoded.amplitude.astype(np.float64)
        sigma = noise_models.li_sigma_m(amplitude, decoded.offset.astype(np.float64) - amplitude,
                                        max(mod.frequencies_hz), sensor.noise.modulation_contrast)
        distance = np.where(decoded.valid, noise_models.add_distance_noise(distance, sigma, stream, check=False),
                            np.nan)
    depth = decoding.radial_to_z(distance, backend.device_copy(xp, directions)) if sensor.depth_output == "z" \
        else distance.astype(np.float32)
    return {
        "depth": depth, "distance": distance.astype(np.float32), "amplitude": decoded.amplitude,
        "offset": decoded.offset, "intensity": decoded.intensity, "confidence": decoded.confidence,
        "reason": decoded.reason, "raw": raw.astype(np.float32)}


def _frame(transport: Transport, sensor, pose: np.ndarray, plan: Plan, seed: int, n_raw: int,
           setup: FrameSetup, per_k: bool = True) -> Frame:
    """The frame of the transport so far, computed on the transport's device and read back once; without
    ``direct_distance`` and ``distance_per_k`` (a preview frame) unless ``per_k``."""
    mod = sensor.modulation
    cam = sensor.camera
    directions = cam.pixel_center_directions()
    if per_k and namespace(transport.correlation_sum) is np and limits.usable_cpus() > 1:
        # On the CPU the per-k ground truth (K decodes of the clean images) is decoded on a thread of its own
        # beside the camera's images: NumPy leaves the interpreter while it computes, so both cores work.
        with ThreadPoolExecutor(1) as pool:
            ground_truth = pool.submit(_decode_clean_per_k, transport, sensor, n_raw, setup)
            images = _camera_images(transport, sensor, plan, seed, n_raw, setup, directions)
            images["per_k"] = ground_truth.result().astype(np.float32)
    else:
        images = _camera_images(transport, sensor, plan, seed, n_raw, setup, directions)
        if per_k:
            images["per_k"] = _decode_clean_per_k(transport, sensor, n_raw, setup).astype(np.float32)
    images = _read_back(images)
    reason = images["reason"].astype(np.uint8)
    per_k = images.get("per_k")
    gt = transport.first_hit.distance_m
    as_depth = (lambda d: decoding.radial_to_z(d, directions)) if sensor.depth_output == "z" else (lambda d: d)
    return Frame(
        depth=images["depth"], distance=images["distance"],
        amplitude=images["amplitude"], offset=images["offset"],
        intensity=images["intensity"], valid=reason == int(decoding.Reason.VALID), reason=reason,
        confidence=images["confidence"], raw=images["raw"],
        raw_labels=tuple(mod.raw_labels()), gt_distance=gt.astype(np.float32),
        gt_depth=np.asarray(as_depth(gt), np.float32), distance_per_k=per_k,
        direct_distance=None if per_k is None else per_k[0],
        ray_directions=directions, object_id=transport.first_hit.object_id, depth_output=sensor.depth_output,
        material_id=transport.first_hit.material_id, normal=transport.first_hit.normal,
        world_from_sensor=np.asarray(pose, dtype=np.float64),
        metadata={"sensor": sensor.to_dict(), "world_from_sensor": np.asarray(pose).tolist(),
                  "intrinsics": {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
                                 "cx": cam.cx, "cy": cam.cy, "k1": cam.k1, "k2": cam.k2, "p1": cam.p1,
                                 "p2": cam.p2, "k3": cam.k3},
                  "units": {"distance": "m", "depth": "m", "amplitude": "electrons", "raw": "electrons"}},
        stats={})
