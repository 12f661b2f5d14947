"""Render the open .blend file's ToF cameras into a dataset, the Blender way.

Usage::

    blender -b scene.blend --python batch/blender_entry.py -- --preset kinect_v2 --out DATASET/ \\
        [--frames 1-10] [--cameras Cam1,Cam2] [--spp 64] [--max-depth 5] [--seed 0] \\
        [--time-budget S] [--target-error LENGTH] [--ambient W_M2_SR] [--resolution-scale F] \\
        [--formats exr,png,ply,json] [--device cpu|gpu|auto] [--retry-failed] [--verify sha256|size] [--quiet]

Blender passes everything after ``--`` to the script untouched. Cameras: the
ones named, else the cameras whose ToF settings are enabled (``camera.tof``,
when the add-on is available), else every camera. Frames: the range given,
else the current frame. ``--preset`` takes a comma-separated list to render
every view with several sensors.

This process has imported bpy, so it starts no worker process: the views are
rendered here one after another (tofcore's tracer still uses threads).
``--device gpu`` renders on this process's GPU (the first one
``CUDA_VISIBLE_DEVICES`` shows; CuPy must be importable from Blender's Python),
``auto`` falls back to the CPU when it cannot. The
dataset layout, index, resume rules and job ids are those of ``python -m
batch run``: the same file, camera, frame, preset, quality and seed give the
same job id and the same frame either way.

Blender's own Python needs ``tofcore`` importable (this repository is put on
``sys.path``; NumPy ships with Blender); EXR files are written by tofcore's own
codec (:mod:`tofcore.output.exr`), no OpenEXR package is loaded into Blender.

Exit code (``sys.exit``): 0 all frames ok, 1 some failed, 2 bad arguments, 130/143 interrupted.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

_REPO_ROOT = Path(__file__).resolve().parents[1]
if str(_REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(_REPO_ROOT))


def script_args(argv: list[str]) -> list[str]:
    """The arguments Blender leaves to the script: everything after the first ``--``."""
    return argv[argv.index("--") + 1:] if "--" in argv else []


def build_parser() -> argparse.ArgumentParser:
    from batch.cli import _Formatter, add_device_option, add_quality_options
    from tofcore.cli import formats_type_of

    from batch.setfile import FORMATS  # a set's formats: transient.npy comes with [output] transient_bin_m

    parser = argparse.ArgumentParser(
        prog="blender -b FILE.blend --python batch/blender_entry.py --",
        description="Render the open file's ToF cameras and frames into a dataset folder.",
        formatter_class=_Formatter)
    parser.add_argument("--preset", default="kinect_v2",
                        help="preset name(s) or .toml file(s), comma-separated: every view is rendered with each")
    parser.add_argument("--out", type=Path, required=True, metavar="DATASET", help="dataset folder")
    parser.add_argument("--frames", default=None, help='frames, e.g. "1-10" or "1,5,9-12" (default: current)')
    parser.add_argument("--cameras", default=None,
                        help="camera objects, comma-separated (default: ToF cameras, else all cameras)")
    add_quality_options(parser, seed_help="set seed (per-frame seeds derive from it)",
                        ambient_help="constant ambient radiance (default: the exporter's, from the world)",
                        scale_help="image size factor (intrinsics scaled)")
    parser.add_argument("--formats", type=formats_type_of(FORMATS), default="exr,png,ply,json",
                        help="comma list of exr, png, ply, json")
    add_device_option(parser, gpu_help="on this process's GPU, the first CUDA_VISIBLE_DEVICES shows")
    parser.add_argument("--retry-failed", action="store_true", help="render only the frames recorded as failed")
    parser.add_argument("--verify", choices=["sha256", "size"], default="sha256",
                        help="how finished frames are checked before being skipped")
    parser.add_argument("--quiet", action="store_true", help="log lines instead of a progress bar")
    return parser


def set_data(args: argparse.Namespace, blend_path: str) -> dict:
    """The arguments as a set-file dict (one blend scene), checked by :func:`batch.setfile.parse_set`."""
    quality = {"spp": args.spp, "max_depth": args.max_depth}
    if args.time_budget is not None:
        quality["time_budget_s"] = args.time_budget
    if args.target_error is not None:
        quality["target_error_m"] = args.target_error
    scene: dict = {"blend": blend_path}
    if args.cameras:
        scene["cameras"] = [c.strip() for c in args.cameras.split(",") if c.strip()]
    if args.frames:
        scene["frames"] = args.frames
    if args.ambient is not None:
        scene["ambient_w_m2_sr"] = args.ambient
    return {"seed": args.seed, "presets": [p.strip() for p in args.preset.split(",") if p.strip()],
            "resolution_scale": args.resolution_scale, "quality": quality,
            "output": {"formats": list(args.formats)},
            "scenes": [scene]}


def main(argv: list[str] | None = None) -> int:
    import bpy

    from batch import blend
    from batch.jobs import BlendInfo, expand
    from batch.run import Interrupted, install_signal_handlers, run_jobs, summary
    from batch.setfile import FLAG_OF_KEY, flag_error
    from batch.setfile import parse_set
    from tofcore.errors import TofError

    FLAGS = dict(FLAG_OF_KEY, **{"presets": "--preset", "scenes.frames": "--frames", "scenes.cameras": "--cameras",
                                 "scenes.blend": "the open .blend file"})

    args = build_parser().parse_args(script_args(sys.argv if argv is None else argv))
    path = bpy.data.filepath
    if not path:
        print("error: the open file has never been saved: save it as a .blend first (the dataset's job ids "
              "hash the file)", file=sys.stderr)
        return 2
    try:
        install_signal_handlers()
        spec = parse_set(set_data(args, path), path=None)
        expansion = expand(spec, inspect_blend=lambda p: BlendInfo(**{k: (tuple(v) if isinstance(v, list) else v)
                                                                       for k, v in blend.inspect(p).items()}))
        for note in expansion.notes:
            print(f"note: {note}", file=sys.stderr)
        result = run_jobs(expansion.jobs, args.out, inline=True, device=args.device, retry_failed=args.retry_failed,
                          verify=args.verify, quiet=args.quiet, set_file=f"{path} (blender_entry.py)")
    except Interrupted as exc:
        print(f"\ninterrupted ({exc}): finished frames are kept; rerun to continue", file=sys.stderr)
        return exc.exit_code
    except (TofError, OSError, RuntimeError) as exc:
        print(f"error: {flag_error(str(exc), FLAGS)}", file=sys.stderr)
        return 2
    print(summary(result, args.out), file=sys.stderr)
    return result.exit_code


if __name__ == "__main__":
    sys.exit(main())
