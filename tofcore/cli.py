"""Command line: ``tofcore render …`` and ``tofcore presets`` (``python -m tofcore …`` is the same).

Examples::

    tofcore render --scene room --preset kinect_v2 --spp 64 --out out/room
    tofcore render --scene my_scene.npz --preset my_sensor.toml --target-error 2mm --verbose
    tofcore render --scene chair.glb --resolution-scale 0.25 --out out/chair
    tofcore presets

Every error is one line, ``tofcore render: error: …``, and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import signal
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from . import limits
from .console import note_line, say, use_safe_output
from .errors import ConfigError, TofError
from .progress import COMPILE_TEXT, PassProgress
from .units import BARE_LENGTH_UNIT, implausible_error_warning, parse_length_m


# --------------------------------------------------------------------------- argument types
# Every flag is checked when it is parsed, before anything is loaded or rendered: argparse prints
# "tofcore render: error: argument --spp: must be …, got '…'" and exits with code 2.

def number_type(kind: type, rule: str, ok: Callable[[Any], bool] = lambda v: True,
                limit: limits.Limit | None = None) -> Callable[[str], Any]:
    """An argparse type: ``kind(text)`` that satisfies ``ok`` (described by ``rule``) and, if given, is at
    most ``limit``; every refusal says the rule and the text given."""
    def parse(text: str):
        try:
            value = kind(text)
        except (ValueError, OverflowError):
            raise argparse.ArgumentTypeError(f"must be {rule}, got {text!r}") from None
        if not ok(value):
            raise argparse.ArgumentTypeError(f"must be {rule}, got {text!r}")
        if limit is not None:
            try:
                too_large = limit.exceeded(value)
            except ConfigError as err:  # a malformed TOFCORE_MAX_… variable
                raise argparse.ArgumentTypeError(str(err)) from None
            if too_large:
                raise argparse.ArgumentTypeError(f"must be {limit.describe()}, got {text!r}")
        return value
    parse.__name__ = kind.__name__  # argparse names the type in its own messages
    return parse


def _finite_positive(v: float) -> bool:
    return 0 < v < math.inf


spp_type = number_type(int, "an integer >= 1", lambda v: v >= 1, limits.MAX_SPP)
max_depth_type = number_type(int, "an integer >= 1", lambda v: v >= 1, limits.MAX_DEPTH)
seed_type = number_type(int, "an integer >= 0", lambda v: v >= 0)
seconds_type = number_type(float, "a finite number > 0 (seconds)", _finite_positive)
radiance_type = number_type(float, f"a finite number >= 0, at most {limits.MAX_MAGNITUDE:g} (W m^-2 sr^-1)",
                            lambda v: 0 <= v <= limits.MAX_MAGNITUDE)
scale_type = number_type(float, "a finite number > 0 (image size factor)", _finite_positive)
pixels_type = number_type(int, "an integer >= 1 (pixels)", lambda v: v >= 1)


def length_type(text: str) -> float:
    """``"5mm"``, ``"0.5cm"``, ``"0.005m"`` or a bare number of millimetres → metres (> 0, finite)."""
    try:
        value = parse_length_m(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    if not _finite_positive(value):
        raise argparse.ArgumentTypeError(f"must be a length > 0 such as 5mm or 0.005m, got {text!r}")
    return value


length_type.__name__ = "length"


def resolution_type(text: str) -> tuple[int, int]:
    """``"128x106"`` → (128, 106): width and height, integers >= 1."""
    parts = text.lower().replace("×", "x").split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() and int(p) >= 1 for p in parts):
        raise argparse.ArgumentTypeError(f"must be WIDTHxHEIGHT in pixels, e.g. 128x106, got {text!r}")
    return int(parts[0]), int(parts[1])


def vector3_type(text: str) -> tuple[float, float, float]:
    """``"1,2.5,-3"`` → (1.0, 2.5, -3.0): three finite numbers (metres)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"must be three numbers X,Y,Z in metres, got {text!r}")
    return values


class OneLineParser(argparse.ArgumentParser):
    """argparse with one-line errors: ``"tofcore render: error: …"`` and exit code 2 (no usage block); no
    abbreviated flags (``--resolution`` is not ``--resolution-scale``)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def formats_type_of(known: tuple[str, ...]) -> Callable[[str], tuple[str, ...]]:
    """An argparse type: ``"exr,png"`` → ("exr", "png"), a non-empty comma list of the formats ``known``."""
    def formats(text: str) -> tuple[str, ...]:
        names = [f.strip() for f in text.split(",")]
        unknown = [f for f in names if f and f not in known]
        chosen = tuple(dict.fromkeys(f for f in names if f))
        if unknown or not chosen:
            why = f" (unknown: {', '.join(map(repr, unknown))})" if unknown else " (none given)"
            raise argparse.ArgumentTypeError(f"must be a comma list of one or more of {', '.join(known)}, "
                                             f"got {text!r}{why}")
        return chosen

    return formats


#: ``tofcore render --formats``: every format of :func:`tofcore.write_frame` (``transient``, the transient.npy
#: histogram, needs ``--transient-bin``: :func:`_checked_render_settings`).
formats_type = formats_type_of(("exr", "png", "ply", "json", "transient"))


def check_output_folder(path: Path, flag: str = "--out") -> None:
    """ConfigError unless ``path`` is a folder, or could be made as one, that this user may write (nothing is
    left behind).

    The permission bits do not tell it all (root passes ``os.access`` on ``/proc`` and on read-only
    mounts): the nearest existing folder is tried with a temporary file (``path`` itself) or folder (an
    ancestor), removed at once, so a render never ends in "could not be written".
    """
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{flag}: must be a folder, got the existing file {str(path)!r}")
    parent = path
    while not parent.exists():
        if parent.parent == parent:
            break
        parent = parent.parent
    if parent.exists() and (not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK)):
        raise ConfigError(f"{flag}: must be a folder this user can write, got {str(path)!r} "
                          f"({str(parent)!r} is {'not a folder' if not parent.is_dir() else 'not writable'})")
    import tempfile

    try:
        if parent == path:
            with tempfile.TemporaryFile(dir=path, prefix=".tofcore-probe-"):
                pass
        else:
            os.rmdir(tempfile.mkdtemp(dir=parent, prefix=".tofcore-probe-"))
    except OSError as exc:
        raise ConfigError(f"{flag}: must be a folder this user can write, got {str(path)!r} (writing in "
                          f"{str(parent)!r}: {exc.strerror or exc})") from None


FALL_BACK_COST = ("the compiled tracer renders the same frame about 2x faster on 2 CPU cores and 4x faster on "
                  "an H200: docs/benchmarks.md")


def fell_back(transport: dict) -> bool:
    """Whether a frame was traced by the NumPy reference although the user did not ask for it
    (``TOFCORE_TRACER=numpy``): the compiled tracer could not run it, or numba is missing."""
    reason = transport.get("tracer_reason") or ""
    return transport.get("tracer") == "numpy" and not reason.startswith("TOFCORE_TRACER=numpy")


def _scene(name: str):
    """(scene, pose or None, ambient or None) of ``--scene``: a demo scene, .npz, mesh file or .blend."""
    from .scene.demo import NAMES, demo_ambient, demo_scene
    from .scene.mesh_files import MESH_SUFFIXES, load_mesh
    from .scene.scene import Scene

    if name in NAMES:
        return demo_scene(name), None, demo_ambient(name)
    path = Path(name)
    suffix = path.suffix.lower()
    if suffix not in (".npz", ".blend", *MESH_SUFFIXES):
        raise TofError(f"--scene: must be a demo scene {list(NAMES)}, a .npz, .blend or mesh file "
                       f"({', '.join(sorted(MESH_SUFFIXES))}), got {name!r}")
    if not path.is_file():
        raise TofError(f"--scene: file not found: {path}")
    if suffix == ".blend":
        return _blend_scene(path)
    return (Scene.load(path) if suffix == ".npz" else load_mesh(path)), None, None


#: What to install for ``--scene FILE.blend``: Blender's Python module (Python 3.11 wheels need NumPy < 2).
BPY_HINT = "pip install bpy \"numpy<2\" (Python 3.11), or render the file in Blender with the ToF add-on"


def _blend_scene(path: Path):
    """The add-on's export of a .blend seen from its active camera, read in a child process (this one stays free of
    bpy, as for set files): (scene, the camera's pose, the world's ambient light)."""
    import importlib.util
    import pickle
    import subprocess
    import tempfile

    if importlib.util.find_spec("bpy") is None:
        raise TofError(f"--scene {path}: a .blend file is read through Blender's Python module bpy, which is not "
                       f"installed: {BPY_HINT}")
    package = "tofcore_batch" if importlib.util.find_spec("tofcore_batch") else "batch"
    with tempfile.TemporaryDirectory(prefix="tofcore-blend-") as tmp:
        out = Path(tmp) / "export.pickle"
        proc = subprocess.run([sys.executable, "-m", f"{package}.blend", "export", str(path), "--out", str(out)],
                              capture_output=True, text=True)
        if proc.returncode != 0 or not out.is_file():
            tail = (proc.stderr.strip().splitlines() or [f"exit code {proc.returncode}"])[-1]
            raise TofError(f"--scene {path}: exporting the .blend file through bpy failed: {tail}")
        scene, pose, ambient, warnings = pickle.loads(out.read_bytes())  # written by our own child process
    for warning in warnings:
        print(f"warning: {path}: {warning}", file=sys.stderr)
    return scene, pose, ambient


def _preset(args: argparse.Namespace):
    """The preset as loaded (``--no-noise`` applied), not resized yet."""
    from .sensor.presets import load_preset

    sensor = load_preset(args.preset)
    return sensor.replace(**{"noise.model": "none"}) if args.no_noise else sensor


def _size(args: argparse.Namespace, preset) -> tuple[int, int]:
    """The image size ``--resolution-scale`` or ``--width``/``--height`` ask for (:meth:`Sensor.resized` checks it)."""
    cam = preset.camera
    if args.width is not None or args.height is not None:
        width = args.width if args.width is not None else max(1, round(cam.width * args.height / cam.height))
        height = args.height if args.height is not None else max(1, round(cam.height * args.width / cam.width))
        return width, height
    return preset.scaled_size(args.resolution_scale)


def _check_aspect(args: argparse.Namespace, cam, width: int, height: int) -> None:
    """ConfigError when a width and height both given change the preset's aspect by more than a pixel's rounding.

    The resized sensor is the preset's camera at another resolution (:meth:`tofcore.Sensor.resized`): another
    aspect would stretch its pixels (fx ≠ fy for square ones: 100x100 of a Kinect gave fx 71.4, fy 86.2) or,
    cropped instead, show another field of view than the preset's; neither is done silently. The line names
    the sizes that keep the aspect.
    """
    true_height = cam.height * width / cam.width
    if abs(height - true_height) <= 1.0:
        return
    flag = "--resolution" if args.resolution is not None else "--width/--height"
    raise ConfigError(f"{flag}: must keep the preset's aspect {cam.width}x{cam.height} (it scales the camera; "
                      f"another aspect would stretch its pixels), got {width}x{height}; give "
                      f"{width}x{max(1, round(true_height))} or {max(1, round(cam.width * height / cam.height))}"
                      f"x{height}, or --width or --height alone")


def _convergence_table(log: list[dict]) -> str:
    has_ref = any("rms_error_m" in r for r in log)
    has_flips = any("unwrap_flip_share" in r for r in log)
    head = ("| pass | spp | seconds | est. depth error mm |" + (" unwrap flips possible % |" if has_flips else "")
            + (" RMS error vs reference mm |" if has_ref else ""))
    rule = "|---|---|---|---|" + ("---|" if has_flips else "") + ("---|" if has_ref else "")
    lines = [head, rule]
    for r in log:
        est = f"{r['est_depth_error_m'] * 1000:.2f}" if r["est_depth_error_m"] is not None else "–"
        line = f"| {r['pass']} | {r['spp']} | {r['seconds']:.1f} | {est} |"
        if has_flips:
            share = r.get("unwrap_flip_share")
            line += f" {100 * share:.2f} |" if share is not None else " – |"
        if has_ref:
            ref = r.get("rms_error_m")
            line += f" {ref * 1000:.2f} |" if ref is not None else " – |"
        lines.append(line)
    return "\n".join(lines)


def _checked_render_settings(args: argparse.Namespace):
    """The render's formats, sensor and transient range, every flag checked before the scene is loaded."""
    formats = args.formats
    if "transient" in formats and args.transient_bin is None:
        raise ConfigError("--formats transient: the histogram needs the width of its bins: add --transient-bin "
                          "LENGTH (e.g. 5cm)")
    if args.transient_bin is not None and "transient" not in formats:
        formats = (*formats, "transient")
    if args.resolution is not None:
        if args.width is not None or args.height is not None:
            raise ConfigError("--resolution: give it or --width/--height, not both")
        args.width, args.height = args.resolution
    if args.resolution_scale != 1.0 and (args.width is not None or args.height is not None):
        raise ConfigError("--resolution-scale: give it or --width/--height/--resolution, not one with another")
    if (args.eye is None) != (args.target is None):
        raise ConfigError("--eye and --target go together")
    if args.target_error is not None and not args.quiet:
        warning = implausible_error_warning(args.target_error, "--target-error")
        if warning:
            print(warning, file=sys.stderr)
    preset = _preset(args)
    transient_max = None
    if args.transient_bin is not None:
        transient_max = args.transient_max if args.transient_max is not None else 4 * preset.range_m[1]
        if transient_max <= args.transient_bin:
            raise ConfigError(f"--transient-max must be longer than --transient-bin, got {transient_max:g} m "
                              f"and {args.transient_bin:g} m")
    from .render import transient_bins

    # The budget at the size asked, before the camera of that size is made (its distortion check builds
    # per-pixel tables: 3.5 GB and about a minute at 4096 x 4096).
    width, height = _size(args, preset)
    limits.check_render_size(width, height, preset.modulation.raw_count, max_depth=args.max_depth, spp=args.spp,
                             where=f"--preset {args.preset} with --max-depth {args.max_depth}",
                             transient_bins=transient_bins(args.transient_bin, transient_max))
    _check_aspect(args, preset.camera, width, height)
    sensor = preset.resized(width, height)
    if args.exr_channels is not None:
        from .output.writers import exr_channel_names

        names = exr_channel_names(sensor.modulation.raw_labels(), args.max_depth)
        unknown = [c for c in args.exr_channels if c not in names]
        if unknown or not args.exr_channels:
            raise ConfigError(f"--exr-channels: must be a comma list of {', '.join(names)}, got unknown "
                              f"{', '.join(unknown) or '(none given)'}")
    check_output_folder(args.out)
    return formats, sensor, transient_max


def _say_setup(args: argparse.Namespace, scene, sensor, ambient, device) -> None:
    """What will run (scene, sensor, plan, device, estimator) with --verbose; else why --device auto fell back."""
    device_line = f"device: {device.description}" + (f" (auto: {device.fallback_reason})"
                                                     if device.fallback_reason else "")
    if args.verbose:
        from .plan import make_plan
        from .tracer.qmc import REPLICATES

        say(f"scene {scene.name!r}: {scene.triangle_count:,} triangles, {len(scene.materials)} materials")
        say(f"sensor {sensor.name!r}: {sensor.camera.width}x{sensor.camera.height}, {sensor.modulation.kind}, "
            f"raw images {', '.join(sensor.modulation.raw_labels())}")
        say(make_plan(scene, sensor, max_depth=args.max_depth, ambient=ambient).describe())
        say(device_line)
        say(f"estimator: sampler {args.sampler} in {REPLICATES} replicates, light vertices "
            f"{'on' if args.light_paths and args.max_depth >= 2 else 'off'}, adaptive sampling "
            f"{'on after 16 spp' if args.adaptive else 'off'}")
    elif device.fallback_reason and not args.quiet and importlib.util.find_spec("cupy") is not None:
        # --device auto fell back although CuPy is installed: say which device ran and why. Without CuPy
        # a CPU render is what the user installed, not news (--verbose still says it).
        print(device_line, file=sys.stderr)
    if not device.is_gpu and not args.quiet:
        from . import compiled

        if compiled.cpu_kernels_cached() is False:  # the progress bar shows the compile's seconds meanwhile
            print("compiling the tracer for this process only (about 15 s on 2 cores; its cache cannot be used, "
                  "see the note)" if compiled.cache_problem() else
                  f"{COMPILE_TEXT}: about 15 s on 2 cores; later renders load the kernels in about a second "
                  f"(`tofcore warmup` compiles them ahead)", file=sys.stderr)


def cmd_render(args: argparse.Namespace) -> int:
    from .render import render
    from .output.writers import write_frame
    from .scene.ambient import Ambient
    from .backend import select_device
    from .scene.pose import look_at

    formats, sensor, transient_max = _checked_render_settings(args)
    scene, file_pose, file_ambient = _scene(args.scene)
    if args.scene.lower().endswith(".blend") and file_pose is None and args.eye is None:
        raise ConfigError(f"--scene {args.scene}: the file has no active camera; set one in Blender, or give "
                          f"--eye X,Y,Z --target X,Y,Z")
    pose = look_at(np.array(args.eye), np.array(args.target)) if args.eye is not None else file_pose
    ambient = Ambient(radiance_w_m2_sr=args.ambient) if args.ambient else file_ambient
    device = select_device(args.device)
    _say_setup(args, scene, sensor, ambient, device)
    with PassProgress(quiet=args.quiet, total=args.spp) as progress:   # a tqdm bar on a terminal, plain lines in logs
        frame = render(scene, sensor, pose, spp=args.spp, max_depth=args.max_depth, seed=args.seed,
                       time_budget_s=args.time_budget, target_error_m=args.target_error, ambient=ambient,
                       progress=progress, device=device, sampler=args.sampler,
                       adaptive=args.adaptive, light_paths=args.light_paths,
                       transient_bin_m=args.transient_bin, transient_max_m=transient_max,
                       preview_denoise=args.preview_denoise, activity=progress.activity)
    try:
        files = write_frame(frame, args.out, formats=formats, exr_half=args.exr_half,
                            exr_channels=args.exr_channels)
    except OSError as exc:  # a full disk, a folder removed meanwhile
        raise TofError(f"--out {args.out}: the frame was rendered but could not be written "
                       f"({exc.strerror or exc}); files already in the folder are whole (each is written to a "
                       f"temp name and renamed), the others were not written") from None
    from .output.coverage import low_coverage

    coverage = low_coverage(frame)
    if coverage:  # the figures below hold for a handful of pixels: say why so few, first
        print(f"warning: {coverage}", file=sys.stderr)
    lines = []
    tracer = frame.stats["transport"]
    if args.verbose:
        lines.append(f"tracer: {tracer['tracer']}" + (f" ({tracer['tracer_reason']})" if tracer["tracer_reason"]
                                                      else ""))
    elif fell_back(tracer) and not args.quiet:
        lines.append(f"note: traced by the NumPy reference, not the compiled tracer: {tracer['tracer_reason']} "
                     f"({FALL_BACK_COST})")
    if tracer.get("compile") and not args.quiet:
        lines.append(f"compiled tracer: {tracer['compile']} (once per install: later renders load the kernels)")
    if not args.quiet:
        lines += [_convergence_table(frame.stats["convergence"]), summary(frame),
                  f"wrote {len(files)} files to {args.out}/: {', '.join(sorted(p.name for p in files.values()))}"]
    for line in lines:  # a stdout that fails (a full disk) is one note: the frame is written
        if not say(line):
            break
    return 0


def summary(frame) -> str:
    """The render's numbers, one named line each (what ``tofcore render`` prints after the table)."""
    from .output.frame import Reason

    stats = frame.stats
    seen = np.isfinite(frame.gt_depth)
    valid = frame.valid
    with_gt = valid & seen  # a valid pixel at an edge can have samples on a surface its centre misses: no truth
    err = (frame.depth - frame.gt_depth)[with_gt]
    rms = f"{float(np.sqrt(np.mean(err ** 2))) * 1000:.1f} mm" if with_gt.any() else \
        "– (no valid pixel with a ground truth)"
    est = stats["convergence"][-1]["est_depth_error_m"] if stats.get("convergence") else None
    flips = stats["convergence"][-1].get("unwrap_flip_share") if stats.get("convergence") else None
    noise = (stats.get("plan") or {}).get("raw_noise") or (stats.get("plan") or {}).get("distance_noise")
    reasons = ", ".join(f"{r.name.lower().replace('_', ' ')} {100 * np.mean(frame.reason == r):.1f} %"
                        for r in Reason if r and np.any(frame.reason == r)) or "none"
    causes = ["render noise", *(["sensor noise"] if noise else []), *(["multipath"] if stats.get("max_depth", 1) > 1
                                                                       else [])]
    lines = [
        f"samples per pixel:          {stats['spp']} (mean over the pixels)",
        f"render time:                {stats['seconds']:.1f} s ({stats['transport']['rays_per_second'] / 1e6:.2f} "
        f"M rays/s)" + (f", {100 * stats['seconds'] / stats['time_budget_s']:.0f} % of the {stats['time_budget_s']:g} s "
                        f"budget" if stats.get("time_budget_s") else ""),
        f"render noise (estimated):   {'–' if est is None else f'{est * 1000:.2f} mm'} RMS Monte Carlo error of the "
        f"depth over the pixels that see a surface" + (
            f" (a wrap flip possible at {100 * flips:.1f} % of them, counted apart)" if flips else ""),
        f"sensor noise:               {'on (shot and read noise, as the preset says)' if noise else 'off'}",
        f"valid pixels:               {100 * valid.mean():.1f} % of all, "
        f"{100 * valid[seen].mean() if seen.any() else 0:.1f} % of those that see a surface",
        f"invalid pixels by reason:   {reasons}",
        f"depth error vs ground truth: {rms} RMS over the valid pixels ({' + '.join(causes)})",
    ]
    if stats.get("preview_denoise"):
        lines.append("preview denoise:            on (depth and distance smoothed, tofcore/sensor/denoise.py)")
    return "\n".join(lines)


def cmd_presets(args: argparse.Namespace) -> int:
    from .sensor.presets import list_presets, load_preset

    for name in list_presets():
        s = load_preset(name)
        mod = s.modulation
        freqs = ", ".join(f"{f / 1e6:g}" for f in mod.frequencies_hz) + " MHz" if mod.frequencies_hz else \
            f"t0 {mod.pulse_width_s * 1e9:g} ns"
        if not say(f"{name:<12} {s.camera.width}x{s.camera.height}  {mod.kind:<9} {freqs:<22} "
                   f"range {s.range_m[0]:g}-{s.range_m[1]:g} m  {len(s.leds)} LED(s)  {s.description}"):
            break
    return 0


def cmd_warmup(args: argparse.Namespace) -> int:
    """Compile (or load) everything a first render compiles on a device, by rendering a small frame; say how long
    it took.

    The frame is the demo corner through the sensor ``--preset`` (Kinect v2) at 4 spp, so that the render-error
    estimate runs too. On the CPU it is 16 pixels wide: numba compiles per argument type, not per image size (a
    Kinect room frame at any size, 1 or 2 tracer threads, then compiles nothing more: tests/tofcore/
    test_warmup.py). On the GPU it has the preset's full size: some of CuPy's kernels (its CUB reductions) are
    compiled per array size. Then, on either device, both builds of the BVH build's compiled loops (numba, on the
    CPU; meshes of 4,096 triangles or more: :func:`tofcore.scene.bvh_build.warm_up`), in a child process beside
    the render where the machine has two CPUs or more (:func:`bvh_build_aside`). Batch runs call this once
    before their workers start (batch/warmup.py), the Blender add-on after installing numba or CuPy."""
    import subprocess
    import time

    from . import compiled
    from .backend import select_device
    from .render import render
    from .scene import bvh_build
    from .scene.demo import demo_scene
    from .sensor.presets import load_preset

    start = time.perf_counter()
    chosen = select_device(args.device)
    sensor = load_preset(args.preset)
    if chosen.name == "cpu":
        sensor = sensor.scaled(16 / sensor.camera.width)
    bvh_child = bvh_build_aside() if bvh_build.available() else None
    try:
        frame = render(demo_scene("corner"), sensor, spp=4, device=chosen)  # 4 spp: the error estimate runs too
        if bvh_child is not None:
            bvh_child.wait(timeout=BVH_CHILD_TIMEOUT_S)
    except subprocess.TimeoutExpired:  # a stuck child: killed below, and warm_up compiles here
        pass
    finally:
        if bvh_child is not None and bvh_child.poll() is None:  # interrupted: the child's compile is not wanted
            bvh_child.kill()
            bvh_child.wait()
    transport, device = frame.stats["transport"], frame.stats["device"]["name"]
    where = ""
    if transport["tracer"] == "compiled" and device == "cpu":
        where = (f"; kernels cached in {compiled.cache_location()}" if compiled.cpu_kernels_cached() else
                 "; kernels not cached: every process compiles them again (see the note)")
    elif transport["tracer"] == "compiled":
        where = f"; kernels cached in {compiled.cache_location()}"
    if bvh_build.available():
        bvh_build.warm_up()  # loads what the child compiled; compiles here where it could not
        where += f"; the BVH build in {getattr(bvh_build._split_level_serial._cache, 'cache_path', 'no cache')}"
    why = f" ({transport['tracer_reason']})" if transport.get("tracer_reason") else ""
    say(f"{transport['tracer']} tracer on the {device.upper()}{why}: ready in {time.perf_counter() - start:.1f} s"
        f"{where}")
    return 0


BVH_WARM_UP = "from tofcore.scene import bvh_build; bvh_build.warm_up()"
"""What the child of :func:`bvh_build_aside` runs."""

BVH_CHILD_TIMEOUT_S = 600.0
"""How long ``tofcore warmup`` waits for that child after its own render (it takes about 8 s on 2 cores)."""


def bvh_build_aside():
    """The BVH build's compile (:func:`tofcore.scene.bvh_build.warm_up`, about 8 s on 2 cores) started in a
    child process, so that it runs beside the kernels' compile (about 14 s) instead of after it; the child's
    ``Popen``, or None where its loops are cached, the machine has one CPU or no Python can be started (then
    the warm-up compiles them itself, afterwards). numba writes its cache files by atomic renames: a child
    that is stopped or fails leaves nothing half-written, and the parent's own ``warm_up`` then compiles
    what is missing."""
    import subprocess

    from .compiled import bvh_build_cached
    from .compiled.child_compile import child_environment
    from .limits import usable_cpus
    from .tracer.workers import python_executable

    python = python_executable()
    if python is None or usable_cpus() < 2 or bvh_build_cached():
        return None
    try:
        return subprocess.Popen([python, "-c", BVH_WARM_UP], env=child_environment(), stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        return None


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults in the option help; the description and the examples (epilog) as written. A switch
    (``--no-adaptive``: store_true/store_false) says what it does, not "(default: True)"."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            return action.help or ""
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="tofcore", description="Time-of-Flight camera simulator (also: python -m tofcore).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example:\n  tofcore render --scene room --preset kinect_v2 --spp 32 --out out/demo\n"
               "  tofcore presets\n\n`tofcore COMMAND --help` for a command's options.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    r = sub.add_parser("render", help="render one frame of a scene with a sensor preset",
                       formatter_class=_HelpFormatter,
                       epilog="example:\n  tofcore render --scene room --preset kinect_v2 --spp 32 --out out/demo "
                              "--verbose\n  tofcore render --scene chair.glb --resolution-scale 0.25 "
                              "--target-error 5mm --out out/chair\n\nwrites frame.exr, depth.exr, PNGs, points.ply, camera YAML files and "
                              "frame.json to the folder")
    r.add_argument("--scene", required=True,
                   help="demo scene (plane, corner, box_on_wall, room), a .npz scene, a mesh file (.obj, .ply, .gltf, "
                        ".glb, .stl; needs trimesh) or a .blend file (needs bpy)")
    r.add_argument("--preset", default="kinect_v2",
                   help="preset name (see `tofcore presets`; any case) or a .toml file")
    r.add_argument("--out", type=Path, required=True, help="output folder")
    r.add_argument("--spp", type=spp_type, default=64, help="most samples per pixel (at most TOFCORE_MAX_SPP)")
    r.add_argument("--max-depth", type=max_depth_type, default=5,
                   help="surface vertices per path (1 = direct only; at most TOFCORE_MAX_DEPTH)")
    r.add_argument("--seed", type=seed_type, default=0, help="random seed >= 0 (same seed, same frame)")
    r.add_argument("--resolution-scale", type=scale_type, default=1.0, metavar="F",
                   help="image size factor; fx, fy, cx, cy scale with it (0.25: a quarter of each side)")
    r.add_argument("--width", type=pixels_type, default=None, metavar="PX",
                   help="image width in pixels (the height follows the aspect unless --height is given)")
    r.add_argument("--height", type=pixels_type, default=None, metavar="PX",
                   help="image height in pixels (the width follows the aspect unless --width is given)")
    r.add_argument("--resolution", type=resolution_type, default=None, metavar="WxH",
                   help="image size in pixels, e.g. 128x106 (the same as --width 128 --height 106); it keeps "
                        "the preset's aspect within a pixel")
    r.add_argument("--time-budget", type=seconds_type, default=None, metavar="S",
                   help="render for about S seconds (set-up to final frame): the passes are sized to use it")
    r.add_argument("--target-error", type=length_type, default=None, metavar="LENGTH",
                   help=f"stop once the estimated RMS depth error (Monte Carlo) is at most this: 5mm, 0.5cm, "
                        f"0.005m; a bare number is in {BARE_LENGTH_UNIT}, as in the Blender add-on")
    r.add_argument("--ambient", type=radiance_type, default=0.0, metavar="W_M2_SR",
                   help="constant ambient radiance, W m^-2 sr^-1")
    r.add_argument("--no-noise", action="store_true",
                   help="no sensor noise (shot and read noise off): the render's own Monte Carlo noise only")
    r.add_argument("--preview-denoise", action="store_true",
                   help="smooth depth and distance with an amplitude-guided joint bilateral filter: less render "
                        "noise, some bias at depth edges (for previews, not for datasets)")
    r.add_argument("--eye", type=vector3_type, default=None, metavar="X,Y,Z",
                   help="sensor position, world metres (with --target; default: the scene's suggested view)")
    r.add_argument("--target", type=vector3_type, default=None, metavar="X,Y,Z", help="point looked at (with --eye)")
    r.add_argument("--formats", type=formats_type, default="exr,png,ply,json",
                   help="comma list of exr (frame.exr + depth.exr), png, ply, json (+ camera YAML files), transient "
                        "(transient.npy; needs --transient-bin, which adds it)")
    r.add_argument("--exr-half", action="store_true",
                   help="EXR channels as 16-bit half floats (about 4 mm steps at 4 m)")
    r.add_argument("--exr-channels", type=lambda text: tuple(c.strip() for c in text.split(",") if c.strip()),
                   default=None, metavar="NAMES", help="only these channels in frame.exr, e.g. depth,amplitude,valid")
    r.add_argument("--transient-bin", type=length_type, default=None, metavar="LENGTH",
                   help="also write transient.npy: the time-resolved histogram over optical path length, bins "
                        "of this width (e.g. 5cm); memory H x W x bins x 8 bytes")
    r.add_argument("--transient-max", type=length_type, default=None, metavar="LENGTH",
                   help="longest optical path length of the histogram (default: 4 x the preset's far range)")
    r.add_argument("--device", choices=("cpu", "gpu", "auto"), default="auto",
                   help="cpu (NumPy), gpu (CuPy on an NVIDIA GPU) or auto (the GPU when usable)")
    r.add_argument("--sampler", choices=("sobol", "independent"), default="sobol",
                   help="sobol: randomized quasi-Monte Carlo; independent: plain Monte Carlo (for comparisons)")
    r.add_argument("--no-adaptive", dest="adaptive", action="store_false",
                   help="every pixel gets the same samples (default: after 16 spp, samples go where the "
                        "estimated depth error is largest)")
    r.add_argument("--no-light-paths", dest="light_paths", action="store_false",
                   help="next-event estimation only (default: also connect to LED-lit points, with MIS)")
    r.add_argument("--verbose", action="store_true", help="print the scene, sensor, render plan, device and tracer (compiled or NumPy, and why)")
    r.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    r.set_defaults(func=cmd_render)
    p = sub.add_parser("presets", help="list the sensor presets", formatter_class=_HelpFormatter,
                       epilog="example:\n  tofcore presets   # name, resolution, modulation, range, LEDs")
    p.set_defaults(func=cmd_presets)
    w = sub.add_parser("warmup", help="compile the tracer's kernels once (numba caches them for later processes)",
                       formatter_class=_HelpFormatter,
                       epilog="example:\n  tofcore warmup --device gpu   # ~30 s the first time, ~2 s once cached")
    w.add_argument("--device", choices=("cpu", "gpu", "auto"), default="auto",
                   help="cpu (compiled CPU kernels), gpu (the CUDA build) or auto")
    w.add_argument("--preset", default="kinect_v2",
                   help="the sensor preset (name or .toml file) of the frame rendered; on the GPU at its full size")
    w.set_defaults(func=cmd_warmup)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command ``argv`` (default: the program's arguments); the exit code.

    Output any locale can show (:func:`tofcore.console.use_safe_output`). Ctrl-C (SIGINT) raises
    KeyboardInterrupt here from the first line (the entry points hold it during the imports before):
    one line, exit code 130; the tracer's worker processes ignore SIGINT and are stopped by this one.
    SIGTERM exits with 143. Called with ``argv`` (as a function, e.g. by a test) it gives the caller its
    SIGINT and SIGTERM handlers back on return.
    """
    use_safe_output()
    previous = {signal.SIGINT: signal.signal(signal.SIGINT, signal.default_int_handler),
                signal.SIGTERM: signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))}
    format_before, warnings.formatwarning = warnings.formatwarning, note_line  # a warning is one line
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except (TofError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\ninterrupted (SIGINT): files are written atomically: none is left half-written", file=sys.stderr)
        return 130
    finally:
        if argv is not None:
            warnings.formatwarning = format_before
            for sig, handler in previous.items():
                if handler is not None:  # None: a handler not set from Python, which cannot be put back
                    signal.signal(sig, handler)
