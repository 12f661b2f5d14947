"""Command line: ``tofcore-batch run | validate | verify | compare | examples`` (in a checkout also
``python -m batch …``). The parser's help is :data:`HELP` (plain text: it is what an installed user reads).
"""

from __future__ import annotations

# Nothing heavy at module level: the installed command imports this module before main() can take
# over Ctrl-C (hold_signals); NumPy and tofcore are imported inside the commands.
import argparse
import importlib.util
import math
import os
import re
import signal
import sys
import threading
from pathlib import Path

from .interrupt import exit_at_once as _exit_at_once

HELP = """The tofcore dataset generator: scene-set files (TOML) to dataset folders.

Examples:

    tofcore-batch examples --copy sets/           # the example sets that ship with tofcore
    tofcore-batch validate sets/demo_set.toml
    tofcore-batch run sets/demo_set.toml --out datasets/demo --workers 2
    tofcore-batch verify datasets/demo            # checksums of every frame, index lines, stray folders
    tofcore-batch run sets/demo_set.toml --out datasets/demo --dask local --workers 2
    tofcore-batch run sets/demo_set.toml --out datasets/demo --scheduler tcp://10.0.0.5:8786
    tofcore-batch run sets/demo_set.toml --out datasets/demo --retry-failed
    tofcore-batch run sets/demo_set.toml --out datasets/demo --device gpu   # one worker per GPU
    tofcore-batch compare --scene room --presets kinect_v2,o3d303,xtion2 --out report/

The set-file format: tofcore-batch examples --schema.

Devices (--device): cpu (NumPy, the default); gpu (CuPy, one
worker process per visible GPU, each pinned with CUDA_VISIBLE_DEVICES; limit the
GPUs with CUDA_VISIBLE_DEVICES=0,2 or --workers); auto (the GPUs when usable,
else the CPU, the reason printed and stored in every record). On a Dask cluster
(--scheduler) start each worker with its own CUDA_VISIBLE_DEVICES.

Exit codes: 0 every frame ok; 1 some frames failed (they are in the index with
their error), or verify found a problem; 2 bad arguments or set file, or
--device gpu without a usable GPU (nothing rendered); 130 / 143 interrupted by
Ctrl-C / SIGTERM at any moment (one line, no traceback; finished frames are
kept, the lock released; rerun to continue).
"""

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2




def _exit_quietly(signum: int, _frame) -> None:
    """After the command's last line (interpreter shutdown, clean-up hooks): exit with the signal's code."""
    os._exit(128 + signum)


def hold_signals(handler=_exit_at_once) -> dict:
    """Route SIGINT and SIGTERM to ``handler`` (in the main thread only); the handlers they had before.

    ``python -m batch`` and :func:`main` install :func:`_exit_at_once` first thing, so a Ctrl-C while
    Python imports NumPy and the simulator, or parses the arguments, gives one line and exit code
    130 instead of a KeyboardInterrupt traceback. The commands then install their own handlers
    (:func:`batch.run.install_signal_handlers`: stop cleanly, keep what is finished).
    """
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}




#: Dask scheduler addresses: [tcp|tls|ucx|ws|wss://]HOST:PORT, HOST a name, IPv4 or [IPv6] (Dask needs the port).
_SCHEDULER = re.compile(r"(?:(?:tcp|tls|ucx|ws|wss)://)?(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})/?")


def _scheduler(text: str) -> str:
    """An argparse type: a Dask scheduler address, checked before anything is loaded or written."""
    match = _SCHEDULER.fullmatch(text.strip())
    if not match or not 0 < int(match.group(2)) < 65536:
        raise argparse.ArgumentTypeError(f"must be a Dask scheduler address tcp://HOST:PORT (or tls://, ucx://, "
                                         f"ws://, wss://; port 1-65535), got {text!r}")
    return text.strip()


def add_quality_options(parser: argparse.ArgumentParser, *, seed_help: str, ambient_help: str,
                        scale_help: str) -> None:
    """The render-quality flags shared by ``compare`` and the Blender entry script."""
    from tofcore.cli import length_type, max_depth_type, number_type, radiance_type, seconds_type, seed_type, spp_type

    positive_float = number_type(float, "a finite number > 0", lambda v: 0 < v < math.inf)
    parser.add_argument("--spp", type=spp_type, default=64, metavar="N",
                        help="most samples per pixel (at most TOFCORE_MAX_SPP)")
    parser.add_argument("--max-depth", type=max_depth_type, default=5, metavar="N",
                        help="surface vertices per path (at most TOFCORE_MAX_DEPTH)")
    parser.add_argument("--seed", type=seed_type, default=0, metavar="N", help=seed_help)
    parser.add_argument("--time-budget", type=seconds_type, default=None, metavar="S",
                        help="stop each render after about S seconds of tracing")
    parser.add_argument("--target-error", type=length_type, default=None, metavar="LENGTH",
                        help="stop each render at this estimated RMS depth error: 5mm, 0.5cm, 0.005m; a bare "
                             "number is in mm, as in tofcore render and the Blender add-on")
    parser.add_argument("--ambient", type=radiance_type, default=None, metavar="W_M2_SR", help=ambient_help)
    parser.add_argument("--resolution-scale", type=positive_float, default=1.0, metavar="F", help=scale_help)


def _vector3(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"must be three comma-separated numbers x,y,z (metres), got {text!r}")
    return values


# --------------------------------------------------------------------------- commands

def cmd_validate(args: argparse.Namespace) -> int:
    from .dataset import Dataset
    from .jobs import expand, group_by_view
    from .setfile import load_set

    spec = load_set(args.set_file)
    expansion = expand(spec)
    jobs = expansion.jobs
    tasks = group_by_view(jobs)
    print(f"{spec.path}: ok — {len(spec.scenes)} scene(s), {len(tasks)} view(s), {len(jobs)} frame(s)")
    for scene in spec.scenes:
        n = sum(job.scene == scene.name for job in jobs)
        presets = ", ".join(f"{p.label} ({p.sensor.camera.width}x{p.sensor.camera.height})" for p in scene.presets)
        q = scene.quality
        stop = "".join([f", time budget {q.time_budget_s} s" if q.time_budget_s else "",
                        f", target error {q.target_error_m} m" if q.target_error_m else ""])
        print(f"  {scene.name} ({scene.kind}): {n} frame(s); presets {presets}; spp {q.spp}, max depth "
              f"{q.max_depth}{stop}")
    for note in expansion.notes:
        print(f"  note: {note}")
    if args.out is not None and (Path(args.out) / "index.jsonl").exists():
        data = Dataset(args.out)
        records, _ = data.read_index()
        done = sum(1 for job in jobs if job.job_id in records and records[job.job_id].get("status") == "ok"
                   and data.verify(records[job.job_id], "size") is None)
        failed = sum(1 for job in jobs if records.get(job.job_id, {}).get("status") == "failed")
        outside = len(records.keys() - {job.job_id for job in jobs})
        print(f"  {args.out}: {done} done, {failed} failed, {len(jobs) - done - failed} to render"
              + (f"; {outside} indexed frame(s) not in this set (an earlier version of it or another set: kept)"
                 if outside else ""))
    if args.list:
        for job in jobs:
            print(f"{job.job_id}  {job.label}  seed {job.seed}")
    return EXIT_OK


def cmd_verify(args: argparse.Namespace) -> int:
    from .dataset import Dataset

    data = Dataset(args.dataset)
    if not data.index_path.is_file():
        print(f"error: {data.root}: not a dataset folder (no index.jsonl)", file=sys.stderr)
        return EXIT_USAGE
    with data.reading():
        report = data.check(args.checksum)
    counts = report["counts"]
    print(f"{data.root}: {counts['records']} frame(s) indexed ({counts['ok']} ok, {counts['failed']} failed); "
          f"{args.checksum} of {counts['record_files']} record.json and {counts['files']} file(s) checked")
    for line in report["problems"][:args.show]:
        print(f"  {line}")
    if len(report["problems"]) > args.show:
        print(f"  … and {len(report['problems']) - args.show} more")
    for line in report["notes"]:
        print(f"  note: {line}")
    if report["problems"]:
        print(f"{len(report['problems'])} problem(s); running the set again repairs them (damaged frames are "
              f"rendered again, the index rebuilt from the frame folders): tofcore-batch run SET.toml --out "
              f"{args.dataset}")
        return EXIT_FAILED
    print(("ok: the index describes every frame folder and every file matches its checksum"
           if args.checksum == "sha256" else "ok: the index describes every frame folder and every size matches")
          + (f" ({counts['outside_set']} frame(s) not in the last run's set: see the note)"
             if counts["outside_set"] else ""))
    return EXIT_OK


def cmd_run(args: argparse.Namespace) -> int:
    from .jobs import expand
    from .run import install_signal_handlers, run_jobs, summary
    from .setfile import load_set

    install_signal_handlers()
    from tofcore.cli import check_output_folder

    check_output_folder(args.out)
    _check_dask(args)
    spec = load_set(args.set_file)
    expansion = expand(spec)
    for note in expansion.notes:
        print(f"note: {note}", file=sys.stderr)
    result = run_jobs(expansion.jobs, args.out, workers=args.workers, threads_per_worker=args.threads_per_worker,
                      scheduler=args.scheduler, dask_local=args.dask == "local", device=args.device,
                      retry_failed=args.retry_failed, verify=args.verify, quiet=args.quiet, set_file=str(spec.path),
                      description=spec.description)
    print(summary(result, args.out), file=sys.stderr)
    return result.exit_code


def cmd_compare(args: argparse.Namespace) -> int:
    from .compare import compare
    from .run import install_signal_handlers
    from tofcore.units import implausible_error_warning

    install_signal_handlers()
    warning = implausible_error_warning(args.target_error, "--target-error") if args.target_error else None
    if warning:
        print(warning, file=sys.stderr)
    from tofcore.cli import check_output_folder

    check_output_folder(args.out)
    _check_dask(args)
    return compare(args)


def cmd_examples(args: argparse.Namespace) -> int:
    """List the example sets that ship with the package, print one, copy them, or print the set-file schema."""
    import shutil

    from . import setfile

    folder = Path(__file__).resolve().parent / "examples"
    sets = sorted(folder.glob("*.toml"))
    if args.schema:
        print(_plain_text(setfile.__doc__ or ""))
        return EXIT_OK
    if args.show is not None:
        chosen = [p for p in sets if args.show in (p.name, p.stem)]
        if not chosen:
            print(f"tofcore-batch examples: error: --show must be one of {[p.stem for p in sets]}, got {args.show!r}",
                  file=sys.stderr)
            return EXIT_USAGE
        print(chosen[0].read_text(encoding="utf-8"), end="")
        return EXIT_OK
    if args.copy is not None:
        from tofcore.cli import check_output_folder

        check_output_folder(args.copy, "--copy")
        args.copy.mkdir(parents=True, exist_ok=True)
        for path in sets:
            target = args.copy / path.name
            if target.exists():
                print(f"kept {target} (exists)")
                continue
            shutil.copyfile(path, target)
            print(f"wrote {target}")
        return EXIT_OK
    for path in sets:
        first = next((line.lstrip("# ").strip() for line in path.read_text(encoding="utf-8").splitlines()
                      if line.startswith("#")), "")
        print(f"{path.stem:<14} {first}")
    print(f"\n(in {folder}; tofcore-batch examples --copy DIR copies them, --show NAME prints one)")
    return EXIT_OK


def _plain_text(rst: str) -> str:
    """reStructuredText of a docstring as plain text for a terminal: ``code`` → code, :role:`x` → x."""
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", rst)
    text = "\n".join(line for line in text.splitlines() if not line.lstrip().startswith(".. "))
    return text.replace("``", "")


def _check_dask(args: argparse.Namespace) -> None:
    """ConfigError before anything is read or written when --scheduler/--dask asks for a missing package."""
    flag = "--scheduler" if args.scheduler is not None else "--dask" if args.dask is not None else None
    if flag and importlib.util.find_spec("distributed") is None:
        from tofcore.errors import ConfigError

        raise ConfigError(f"{flag}: needs the distributed package, which is not installed: "
                          f"pip install 'dask[distributed]' (or leave {flag} out for the local pool)")


# --------------------------------------------------------------------------- parser

class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions as written; every option's default in its help unless it is None or False."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.option_strings and all(action.default is not v for v in (None, False, argparse.SUPPRESS)) \
                and "%(default)" not in text:
            text += " (default: %(default)s)"
        return text


def add_device_option(parser: argparse.ArgumentParser, *, gpu_help: str) -> None:
    """``--device cpu|gpu|auto``, shared by ``run``, ``compare`` and the Blender entry script."""
    parser.add_argument("--device", choices=["cpu", "gpu", "auto"], default="cpu",
                        help="where frames render: cpu (NumPy), gpu (CuPy; " + gpu_help + "; no usable GPU: "
                             "error, exit code 2) or auto (the GPU when usable, else the CPU, the reason "
                             "recorded in every frame's record)")


def _executor_options(parser: argparse.ArgumentParser) -> None:
    from tofcore import limits
    from tofcore.cli import number_type

    workers_type = number_type(int, "an integer >= 1", lambda v: v >= 1, limits.MAX_WORKERS)
    parser.add_argument("--workers", type=workers_type, default=None, metavar="N",
                        help="worker processes (local pool, or LocalCluster workers with --dask local); "
                             "each render also uses tracer threads (default: 1; with --device gpu/auto one "
                             "per visible GPU: a smaller N uses the first N GPUs, a larger N is clamped)")
    add_device_option(parser, gpu_help="one worker process per visible GPU, pinned with CUDA_VISIBLE_DEVICES; "
                                       "on a --scheduler cluster each worker uses the GPU its environment shows")
    parser.add_argument("--threads-per-worker", type=workers_type, default=None, metavar="N",
                        help="tracer worker processes per render (threads in a Dask worker; default: usable "
                             "CPUs / workers, so frames x tracer workers never exceed the CPUs; on a --scheduler "
                             "cluster each machine's CPU count); frames do not depend on it")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--scheduler", type=_scheduler, default=None, metavar="tcp://HOST:PORT",
                       help="run on an existing Dask distributed cluster (needs dask[distributed]; workers "
                            "must see the dataset and scene files at the same paths)")
    where.add_argument("--dask", choices=["local"], default=None,
                       help="start a Dask LocalCluster of --workers processes (with --device gpu/auto: "
                            "one per GPU, each pinned with CUDA_VISIBLE_DEVICES)")
    parser.add_argument("--quiet", action="store_true", help="log one line per frame instead of a progress bar")


def build_parser() -> argparse.ArgumentParser:
    from tofcore.cli import OneLineParser

    parser = OneLineParser(prog="tofcore-batch", description=HELP, formatter_class=_Formatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="{run,validate,verify,compare,examples}",
                                parser_class=OneLineParser)

    run = sub.add_parser("run", help="render a scene set into a dataset folder (resumable)",
                         description="Render every frame of a scene-set file into DATASET/ (frames/<job_id>/, "
                                     "index.jsonl, README.md). Rerunning skips frames whose files verify.",
                         formatter_class=_Formatter,
                         epilog="example:\n  tofcore-batch run sets/demo_set.toml --out out/demo_dataset\n\n"
                                "tofcore-batch examples --copy sets/ copies the shipped example sets there")
    run.add_argument("set_file", type=Path, metavar="SET.toml",
                     help="scene-set file (format: tofcore-batch examples --schema)")
    run.add_argument("--out", type=Path, required=True, metavar="DATASET", help="dataset folder")
    _executor_options(run)
    run.add_argument("--retry-failed", action="store_true",
                     help="render only the frames recorded as failed (after fixing the cause)")
    run.add_argument("--verify", choices=["sha256", "size"], default="sha256",
                     help="how finished frames are checked before being skipped")
    run.set_defaults(func=cmd_run)

    val = sub.add_parser("validate", help="check a scene-set file without rendering",
                         description="Read and check a set file (keys, types, files, presets, poses, .blend "
                                     "cameras) and list what it would render.",
                         formatter_class=_Formatter,
                         epilog="example:\n  tofcore-batch validate sets/demo_set.toml --list\n\n"
                                "tofcore-batch examples --copy sets/ copies the shipped example sets there")
    val.add_argument("set_file", type=Path, metavar="SET.toml", help="scene-set file")
    val.add_argument("--out", type=Path, default=None, metavar="DATASET",
                     help="also say how many frames an existing dataset already has")
    val.add_argument("--list", action="store_true", help="list every frame: job id, scene/view/preset, seed")
    val.set_defaults(func=cmd_validate)

    ver = sub.add_parser("verify", help="check a dataset folder against its index (changes nothing)",
                         description="Check every index line (a frame record?), every ok frame (record.json and "
                                     "each file against the index's sizes and SHA-256), and the frames/ folder "
                                     "(published folders missing from the index, leftovers of a killed run). "
                                     "Exit code 0 when all is well, 1 when something is not; running the set "
                                     "again repairs what it finds.",
                         formatter_class=_Formatter,
                         epilog="example:\n  tofcore-batch verify out/demo_dataset --checksum size")
    ver.add_argument("dataset", type=Path, metavar="DATASET", help="dataset folder")
    ver.add_argument("--checksum", choices=["sha256", "size"], default="sha256",
                     help="sha256 reads every file; size only compares sizes")
    from tofcore.cli import number_type

    ver.add_argument("--show", type=number_type(int, "an integer >= 0", lambda v: v >= 0), default=20, metavar="N",
                     help="problems listed")
    ver.set_defaults(func=cmd_verify)

    cmp = sub.add_parser("compare", help="render one view with several presets; side-by-side PNG and tables",
                         description="Render one view with each preset and write compare.png (rows: presets; "
                                     "columns: depth, error against ground truth, invalid pixels), compare.md "
                                     "and compare.json (RMS/median error, multipath error, invalid %, time).",
                         formatter_class=_Formatter,
                         epilog="example:\n  tofcore-batch compare --scene room --presets kinect_v2,o3d303,xtion2 "
                                "--out out/compare --spp 32 --resolution-scale 0.5")
    cmp.add_argument("--scene", required=True,
                     help="demo scene (plane, corner, box_on_wall, room), a .npz scene, a mesh file (.obj, .ply, "
                          ".gltf, .glb, .stl; needs trimesh) or a .blend file")
    cmp.add_argument("--presets", default="kinect_v2,o3d303,xtion2",
                     help="comma-separated preset names or .toml files")
    cmp.add_argument("--out", type=Path, required=True, metavar="REPORT", help="report folder")
    cmp.add_argument("--eye", type=_vector3, default=None, metavar="X,Y,Z",
                     help="sensor position (world, metres); with --target; default: the scene's suggested pose")
    cmp.add_argument("--target", type=_vector3, default=None, metavar="X,Y,Z", help="point looked at")
    cmp.add_argument("--camera", default=None, help=".blend: camera object (default: the first ToF camera)")
    cmp.add_argument("--frame", type=int, default=None, metavar="N", help=".blend: animation frame (default: current)")
    add_quality_options(cmp, seed_help="set seed",
                        ambient_help="constant ambient radiance (default: none; a .blend's world)",
                        scale_help="image size factor for every preset (intrinsics scaled)")
    _executor_options(cmp)
    cmp.set_defaults(func=cmd_compare)

    ex = sub.add_parser("examples", help="list, print or copy the example scene sets that ship with tofcore",
                        description="The example scene-set files installed with tofcore: list them, print one "
                                    "(--show), copy them into a folder to edit and run (--copy), or print the "
                                    "set-file format (--schema).",
                        formatter_class=_Formatter,
                        epilog="example:\n  tofcore-batch examples --copy sets/ && tofcore-batch run "
                               "sets/demo_set.toml --out out/demo_dataset")
    what = ex.add_mutually_exclusive_group()
    what.add_argument("--copy", type=Path, default=None, metavar="DIR", help="copy every example set into DIR")
    what.add_argument("--show", default=None, metavar="NAME", help="print one example set")
    what.add_argument("--schema", action="store_true", help="print the set-file format (keys, types, defaults)")
    ex.set_defaults(func=cmd_examples)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command ``argv`` (default: the program's arguments); the exit code.

    Ctrl-C or SIGTERM at any moment gives one line and 130 / 143, never a traceback (see
    :func:`hold_signals`). Called as the program (``argv`` None), a signal after the command's last
    line ends the process quietly with that code; called with ``argv``, the caller's handlers are back
    on return.
    """
    previous = hold_signals()
    import warnings

    from tofcore.console import note_line, use_safe_output

    use_safe_output()  # any locale: what the terminal cannot show is spelled in ASCII
    format_before, warnings.formatwarning = warnings.formatwarning, note_line  # a warning is one line
    try:
        return _command(build_parser().parse_args(argv))
    finally:
        warnings.formatwarning = format_before
        if argv is None:
            hold_signals(_exit_quietly)
        else:
            for sig, handler in previous.items():
                if handler is not None:
                    signal.signal(sig, handler)


def _command(args: argparse.Namespace) -> int:
    from tofcore.errors import TofError

    from .run import Interrupted

    try:
        return args.func(args)
    except Interrupted as exc:
        hold_signals(_exit_quietly)  # a second Ctrl-C while this is said
        print(f"\n{exc.message()}", file=sys.stderr)
        return exc.exit_code
    except (TofError, OSError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
