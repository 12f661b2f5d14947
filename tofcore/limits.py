"""Resource limits: what one render, scene file or scene set may ask for, checked before allocating.

Every limit is checked where the request is read (argument parsing, preset
loading, scene-file loading, set-file parsing), before any memory is taken for
it, and a request above it raises :class:`~tofcore.errors.LimitError` (a
``ConfigError``) with one line naming the request, the limit and how to raise it.
Each limit is read from its environment variable when it is checked, so
``TOFCORE_MAX_PIXELS=50000000 tofcore render …`` raises it for one command.

=========================  ===========================  ===================  ==========================================
limit                      environment variable         default              what it bounds
=========================  ===========================  ===================  ==========================================
:data:`MAX_PIXELS`         ``TOFCORE_MAX_PIXELS``       16,777,216 (4096²)   width × height of a camera (presets,
                                                                             overrides, resolution scales)
:data:`MAX_RAW_IMAGES`     ``TOFCORE_MAX_RAW_IMAGES``   64                   raw images per frame (sum of phase_steps)
:data:`MAX_DEPTH`          ``TOFCORE_MAX_DEPTH``        64                   surface vertices per path (max_depth)
:data:`MAX_SPP`            ``TOFCORE_MAX_SPP``          1,048,576 (2²⁰)      samples per pixel
:data:`MAX_RENDER_BYTES`   ``TOFCORE_MAX_RENDER_BYTES`` 3/4 of the RAM       estimated memory of one render's per-pixel
                                                                             buffers (:func:`render_bytes`)
:data:`MAX_SCENE_BYTES`    ``TOFCORE_MAX_SCENE_BYTES``  4 GiB                uncompressed size of the arrays of a scene
                                                                             file (.npz), read from the zip directory
                                                                             and the .npy headers
:data:`MAX_EXR_BYTES`      ``TOFCORE_MAX_EXR_BYTES``    4 GiB                size of an EXR file read, and the pixel
                                                                             bytes its header declares (checked
                                                                             before anything is allocated or inflated)
:data:`MAX_SET_FRAMES`     ``TOFCORE_MAX_SET_FRAMES``   100,000              frames of one scene set (poses × frames ×
                                                                             cameras × presets), and any one pose count
                                                                             or frame range
:data:`MAX_WORKERS`        ``TOFCORE_MAX_WORKERS``      4 × usable CPUs,     worker processes or tracer workers
                                                        at least 8
=========================  ===========================  ===================  ==========================================

Values are plain integers (``TOFCORE_MAX_RENDER_BYTES=34359738368``); underscores are allowed
(``TOFCORE_MAX_PIXELS=50_000_000``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .errors import ConfigError, LimitError


def usable_cpus() -> int:
    """CPUs this process may use: its affinity mask, capped by a cgroup v2/v1 CPU quota where one is set."""
    try:
        count = len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        count = os.cpu_count() or 1
    quota = _cgroup_quota()
    return max(1, min(count, quota) if quota else count)


def _cgroup_quota(root: Path = Path("/sys/fs/cgroup")) -> int | None:
    """Whole CPUs allowed by the cgroup's quota (cpu.max or cfs_quota/period), rounded up; None if unlimited."""
    try:
        text = (root / "cpu.max").read_text().split()
        if text and text[0] != "max":
            return max(1, -(-int(text[0]) // int(text[1])))
    except (OSError, ValueError, IndexError):
        pass
    try:
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        if quota > 0 and period > 0:
            return max(1, -(-quota // period))
    except (OSError, ValueError):
        pass
    return None


def _physical_memory_bytes() -> int | None:
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


@dataclass(frozen=True)
class Limit:
    """One resource limit: its name, environment variable, default, unit and the reason for it."""

    name: str
    env: str
    default: int
    unit: str
    why: str

    @property
    def value(self) -> int:
        """The limit in force: ``$env`` when set (a positive integer), else the default."""
        text = os.environ.get(self.env)
        if text is None or not text.strip():
            return self.default
        try:
            value = int(text.strip())
        except ValueError:
            value = 0
        if value < 1:
            raise ConfigError(f"environment: {self.env} must be a positive integer ({self.unit}), got {text!r}")
        return value

    def describe(self, value: int | None = None) -> str:
        """``"at most 64 vertices (TOFCORE_MAX_DEPTH; raise it with TOFCORE_MAX_DEPTH=N)"``."""
        limit = self.value if value is None else value
        return f"at most {limit:,} {self.unit} (limit {self.name}; raise it with the environment variable {self.env}=N)"

    def exceeded(self, value: int) -> bool:
        return value > self.value

    def check(self, value: int, where: str, field: str, shown: object = None) -> None:
        """Raise :class:`LimitError` ``"{where}: {field} must be at most …, got {shown!r}"`` if value > limit."""
        if value > self.value:
            got = value if shown is None else shown
            shown = got if isinstance(got, str) else repr(got)
            raise LimitError(f"{where}: {field} must be {self.describe()}, got {shown}")


MAX_PIXELS = Limit(
    "max_pixels", "TOFCORE_MAX_PIXELS", 4096 * 4096, "pixels",
    "a camera with distortion checks its inverse at every pixel when it is made (~200 B/pixel) and a "
    "render holds kilobytes per pixel; 4096 x 4096 is 77x the largest preset (512 x 424)")
MAX_RAW_IMAGES = Limit(
    "max_raw_images", "TOFCORE_MAX_RAW_IMAGES", 64, "raw images",
    "every raw image is a per-pixel, per-bounce accumulator; real sensors take 2 to 12")
MAX_DEPTH = Limit(
    "max_depth", "TOFCORE_MAX_DEPTH", 64, "surface vertices",
    "the accumulators hold one bucket per bounce count; after a few bounces nothing measurable is left")
MAX_SPP = Limit(
    "max_spp", "TOFCORE_MAX_SPP", 1 << 20, "samples per pixel",
    "a typo guard: 2^20 spp at 512x424 is months on a CPU; the convergence log keeps one row per pass")
MAX_RENDER_BYTES = Limit(
    "max_render_bytes", "TOFCORE_MAX_RENDER_BYTES",
    (lambda ram: 3 * ram // 4 if ram else 16 << 30)(_physical_memory_bytes()), "bytes",
    "a render that does not fit in memory is killed by the system, or swaps for hours")
MAX_SCENE_BYTES = Limit(
    "max_scene_bytes", "TOFCORE_MAX_SCENE_BYTES", 4 << 30, "bytes",
    "a small .npz can decompress to gigabytes (a zip bomb); 4 GiB is ~100 M triangles")
MAX_EXR_BYTES = Limit(
    "max_exr_bytes", "TOFCORE_MAX_EXR_BYTES", 4 << 30, "bytes",
    "a 200-byte header can declare 320 GiB of pixels; tofcore's largest frame.exr (4096 x 4096, every "
    "channel) is about 3 GiB")
MAX_SET_FRAMES = Limit(
    "max_set_frames", "TOFCORE_MAX_SET_FRAMES", 100_000, "frames",
    "jobs are expanded in memory (a few kB each) before rendering starts")
MAX_WORKERS = Limit(
    "max_workers", "TOFCORE_MAX_WORKERS", max(8, 4 * usable_cpus()), "processes",
    "every worker process is started at once and holds 65-150 MB; more than the CPUs only adds memory")



def render_bytes(pixels: int, raw_images: int, max_depth: int, transient_bins: int = 0) -> int:
    """Estimated peak memory of one render's per-pixel buffers, bytes.

    Notes
    -----
    .. math:: B = 8\\,P\\,\\bigl(7\\,K\\,(R + 1) + 8\\,(R + 2)\\bigr)

    P pixels, K = ``max_depth``, R raw images: per bounce bucket the signal and
    correlation sums and their per-k decoding, per replicate the sums of the
    error estimate, plus the frame's outputs. Fitted to tracemalloc peaks of
    the Kinect v2 preset (R = 9) on the room: 3.2 kB/pixel at K = 5, 5.8 kB at
    K = 10; the formula gives 3.5 and 6.3 kB. A transient histogram of T bins adds its buffers,
    20 P T bytes: the float64 sums, their float64 mean and the frame's float32 copy.
    """
    return (8 * int(pixels) * (7 * int(max_depth) * (int(raw_images) + 1) + 8 * (int(raw_images) + 2))
            + 20 * int(pixels) * int(transient_bins))


def check_render(sensor, *, max_depth: int, where: str, spp: int | None = None, transient_bins: int = 0) -> None:
    """Raise :class:`LimitError` if a render of ``sensor`` with these settings is above a limit.

    ``where`` prefixes the message (e.g. ``"render"``, a set file's key path).
    """
    cam = sensor.camera
    check_render_size(cam.width, cam.height, sensor.modulation.raw_count, max_depth=max_depth, where=where, spp=spp,
                      transient_bins=transient_bins)


def check_render_size(width: int, height: int, raw_images: int, *, max_depth: int, where: str,
                      spp: int | None = None, transient_bins: int = 0) -> None:
    """:func:`check_render` for a sensor of ``width`` × ``height`` pixels and ``raw_images`` raw images that is
    not made yet: a caller that resizes a preset checks the budget first, before the camera of that size builds
    its per-pixel tables (its distortion check: ~200 bytes and ~4 µs a pixel)."""
    if spp is not None:
        MAX_SPP.check(int(spp), where, "spp")
    MAX_DEPTH.check(int(max_depth), where, "max_depth")
    need = render_bytes(width * height, raw_images, max_depth, transient_bins)
    if MAX_RENDER_BYTES.exceeded(need):
        transient = f", {transient_bins} transient bins" if transient_bins else ""
        raise LimitError(f"{where}: the estimated render memory ({width} x {height} pixels, "
                         f"{raw_images} raw images, max_depth {max_depth}{transient}) must be "
                         f"{MAX_RENDER_BYTES.describe()}, got {need:,} bytes; lower the resolution or max_depth"
                         + (" or widen the transient bins" if transient_bins else ""))


#: Largest magnitude accepted for a physical scale factor (LED intensity, responsivity, exposure, full well,
#: read noise, ambient radiance). Not adjustable: the charge of a pixel is the product of several of them
#: and of the geometry (1/r² up to ~1e12 for surfaces a micrometre away), summed over samples; with each
#: factor at most 1e30 the product stays below ~1e110, far inside float64 (1.8e308), so no setting can
#: overflow the radiometric chain into inf/NaN deep inside a render.
MAX_MAGNITUDE = 1e30

#: Largest preset or set file read (TOML text); not adjustable: real ones are a few kilobytes, and a path such
#: as /dev/zero must not be read into memory.
MAX_TEXT_FILE_BYTES = 16 << 20


def read_text_file(path, what: str, error: type[Exception]) -> str:
    """The UTF-8 text of a small configuration file (a preset, a set file), checked before it is read: a
    regular file (``/dev/zero`` would fill the memory) of at most :data:`MAX_TEXT_FILE_BYTES`.

    Raises ``error("{path}: must be {what}, got …")`` for a folder, a special file or a file too large;
    ``OSError`` (``FileNotFoundError`` included) and ``UnicodeDecodeError`` reach the caller.
    """
    if path.exists() and not path.is_file():
        raise error(f"{path}: must be {what}, got {'a folder' if path.is_dir() else 'a special file'}")
    if path.exists() and path.stat().st_size > MAX_TEXT_FILE_BYTES:
        raise error(f"{path}: must be {what} of at most {MAX_TEXT_FILE_BYTES:,} bytes, got "
                    f"{path.stat().st_size:,} bytes")
    return path.read_text(encoding="utf-8")
