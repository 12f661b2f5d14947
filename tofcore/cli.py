"""Command line: ``tofcore render …`` and ``tofcore presets`` (``python -m tofcore …`` is the same).

Examples::

    tofcore render --scene room --preset kinect_v2 --spp 64 --out out/room
    tofcore render --scene my_scene.npz --preset presets/o3d303.toml --target-error 0.002 --verbose
    tofcore presets
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from . import limits
from .console import say, use_safe_output
from .errors import ConfigError, TofError
from .progress import PassProgress


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
metres_type = number_type(float, "a finite number > 0 (metres)", _finite_positive)
radiance_type = number_type(float, f"a finite number >= 0, at most {limits.MAX_MAGNITUDE:g} (W m^-2 sr^-1)",
                            lambda v: 0 <= v <= limits.MAX_MAGNITUDE)


def formats_type(text: str) -> tuple[str, ...]:
    """``"exr,png"`` → ("exr", "png"): a non-empty comma list of known output formats."""
    from .output.writers import FORMATS

    names = [f.strip() for f in text.split(",")]
    unknown = [f for f in names if f and f not in FORMATS]
    chosen = tuple(dict.fromkeys(f for f in names if f))
    if unknown or not chosen:
        why = f" (unknown: {', '.join(map(repr, unknown))})" if unknown else " (none given)"
        raise argparse.ArgumentTypeError(f"must be a comma list of one or more of {', '.join(FORMATS)}, "
                                         f"got {text!r}{why}")
    return chosen


def check_exr(formats, flag: str = "--formats") -> None:
    """ConfigError unless the OpenEXR package is importable when ``formats`` holds "exr" (before rendering)."""
    from .output import writers

    if "exr" in formats and writers.OpenEXR is None:
        raise ConfigError(f"{flag}: 'exr' needs the OpenEXR package, which is not installed: pip install OpenEXR "
                          f"(or pip install 'tofcore[exr]'), or leave exr out, e.g. {flag} png,ply,json")


def check_output_folder(path: Path, flag: str = "--out") -> None:
    """ConfigError unless ``path`` is a folder, or could be made as one, that this user may write (nothing is made)."""
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


def _scene(name: str):
    from .scene.demo import NAMES, demo_scene
    from .scene.scene import Scene

    if name in NAMES:
        return demo_scene(name)
    path = Path(name)
    if path.suffix != ".npz":
        raise TofError(f"--scene: must be a demo scene {list(NAMES)} or a .npz file, got {name!r}")
    if not path.is_file():
        raise TofError(f"--scene: file not found: {path}")
    return Scene.load(path)


def _convergence_table(log: list[dict]) -> str:
    has_ref = any("rms_error_m" in r for r in log)
    head = "| pass | spp | seconds | est. depth error mm |" + (" RMS error vs reference mm |" if has_ref else "")
    rule = "|---|---|---|---|" + ("---|" if has_ref else "")
    lines = [head, rule]
    for r in log:
        est = f"{r['est_depth_error_m'] * 1000:.2f}" if r["est_depth_error_m"] is not None else "–"
        line = f"| {r['pass']} | {r['spp']} | {r['seconds']:.1f} | {est} |"
        if has_ref:
            ref = r.get("rms_error_m")
            line += f" {ref * 1000:.2f} |" if ref is not None else " – |"
        lines.append(line)
    return "\n".join(lines)


def cmd_render(args: argparse.Namespace) -> int:
    from .sensor.presets import load_preset
    from .render import render
    from .output.writers import write_frame
    from .scene.ambient import Ambient
    from .backend import select_device

    # Everything that can be checked is checked before the scene is loaded or a ray traced.
    formats = args.formats
    sensor = load_preset(args.preset)
    limits.check_render(sensor, max_depth=args.max_depth, spp=args.spp,
                        where=f"--preset {args.preset} with --max-depth {args.max_depth}")
    check_exr(formats)
    check_output_folder(args.out)
    scene = _scene(args.scene)
    ambient = Ambient(radiance_w_m2_sr=args.ambient) if args.ambient else None
    device = select_device(args.device)
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
    elif device.fallback_reason and not args.quiet:
        print(device_line, file=sys.stderr)  # --device auto fell back to the CPU: say which device ran and why
    with PassProgress(quiet=args.quiet) as progress:   # a tqdm bar on a terminal, plain lines in logs
        frame = render(scene, sensor, spp=args.spp, max_depth=args.max_depth, seed=args.seed,
                       time_budget_s=args.time_budget, target_error_m=args.target_error, ambient=ambient,
                       progress=progress, device=device, sampler=args.sampler,
                       adaptive=args.adaptive, light_paths=args.light_paths)
    try:
        files = write_frame(frame, args.out, formats=formats)
    except (OSError, RuntimeError) as exc:  # a full disk, a folder removed meanwhile; RuntimeError: OpenEXR
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise TofError(f"--out {args.out}: the frame was rendered but could not be written ({why}); files "
                       f"already in the folder are whole (each is written to a temp name and renamed), the "
                       f"others were not written") from None
    stats = frame.stats
    if not args.quiet:
        valid = frame.valid.mean() * 100
        err = frame.depth - frame.gt_depth
        rms = float(np.sqrt(np.nanmean(err[frame.valid] ** 2))) * 1000 if frame.valid.any() else float("nan")
        rate = stats["transport"]["rays_per_second"] / 1e6
        for line in (_convergence_table(stats["convergence"]),
                     f"{stats['spp']} spp in {stats['seconds']:.1f} s ({rate:.2f} M rays/s); valid {valid:.1f} %; "
                     f"RMS depth error vs ground truth {rms:.1f} mm",
                     f"wrote {len(files)} files to {args.out}/: {', '.join(sorted(p.name for p in files.values()))}"):
            if not say(line):
                break
    return 0


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


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults in the option help; the description and the examples (epilog) as written."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tofcore", description="Time-of-Flight camera simulator (also: python -m tofcore).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example:\n  tofcore render --scene room --preset kinect_v2 --spp 32 --out out/demo\n"
               "  tofcore presets\n\n`tofcore COMMAND --help` for a command's options.")
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="render one frame of a scene with a sensor preset",
                       formatter_class=_HelpFormatter,
                       epilog="example:\n  tofcore render --scene room --preset kinect_v2 --spp 32 --out out/demo "
                              "--verbose\n\nwrites frame.exr, PNGs, points.ply and frame.json to out/demo/; EXR needs the "
                              "OpenEXR package\n(pip install 'tofcore[exr]'), else use --formats png,ply,json")
    r.add_argument("--scene", required=True, help="demo scene (plane, corner, box_on_wall, room) or a .npz file")
    r.add_argument("--preset", default="kinect_v2", help="preset name (see `presets`) or a .toml file")
    r.add_argument("--out", type=Path, required=True, help="output folder")
    r.add_argument("--spp", type=spp_type, default=64, help="most samples per pixel (at most TOFCORE_MAX_SPP)")
    r.add_argument("--max-depth", type=max_depth_type, default=5,
                   help="surface vertices per path (1 = direct only; at most TOFCORE_MAX_DEPTH)")
    r.add_argument("--seed", type=seed_type, default=0, help="random seed >= 0 (same seed, same frame)")
    r.add_argument("--time-budget", type=seconds_type, default=None, metavar="S",
                   help="stop tracing after about S seconds")
    r.add_argument("--target-error", type=metres_type, default=None, metavar="M",
                   help="stop once the estimated RMS depth error (Monte Carlo) is at most M metres")
    r.add_argument("--ambient", type=radiance_type, default=0.0, metavar="W_M2_SR",
                   help="constant ambient radiance, W m^-2 sr^-1")
    r.add_argument("--formats", type=formats_type, default="exr,png,ply,json",
                   help="comma list of exr, png, ply, json (exr needs the OpenEXR package)")
    r.add_argument("--device", choices=("cpu", "gpu", "auto"), default="auto",
                   help="cpu (NumPy), gpu (CuPy on an NVIDIA GPU) or auto (the GPU when usable)")
    r.add_argument("--sampler", choices=("sobol", "independent"), default="sobol",
                   help="sobol: randomized quasi-Monte Carlo; independent: plain Monte Carlo (for comparisons)")
    r.add_argument("--no-adaptive", dest="adaptive", action="store_false",
                   help="every pixel gets the same samples (default: after 16 spp, samples go where the "
                        "estimated depth error is largest)")
    r.add_argument("--no-light-paths", dest="light_paths", action="store_false",
                   help="next-event estimation only (default: also connect to LED-lit points, with MIS)")
    r.add_argument("--verbose", action="store_true", help="print the scene, sensor, render plan and device")
    r.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    r.set_defaults(func=cmd_render)
    p = sub.add_parser("presets", help="list the sensor presets", formatter_class=_HelpFormatter,
                       epilog="example:\n  tofcore presets   # name, resolution, modulation, range, LEDs")
    p.set_defaults(func=cmd_presets)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command ``argv`` (default: the program's arguments); the exit code.

    Output any locale can show (:func:`tofcore.console.use_safe_output`). Ctrl-C (SIGINT) raises
    KeyboardInterrupt here from the first line (the entry points hold it during the imports before):
    one line, exit code 130; the tracer's worker processes ignore SIGINT and are stopped by this one.
    SIGTERM exits with 143.
    """
    use_safe_output()
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except (TofError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\ninterrupted (SIGINT): files are written atomically: none is left half-written", file=sys.stderr)
        return 130
