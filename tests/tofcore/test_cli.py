"""tofcore render for a first-time user: resolution flags, one-line errors, .blend and help text, make demo."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tofcore.cli import build_parser, main

REPO = Path(__file__).resolve().parents[2]


def _run(argv, capsys) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _tiny(tmp_path, *extra):
    return ["render", "--scene", "plane", "--out", str(tmp_path / "out"), "--spp", "1", "--max-depth", "1",
            "--formats", "json", "--quiet", *extra]


@pytest.mark.parametrize("flags, size", [(("--resolution", "64x53"), (64, 53)),
                                         (("--width", "64", "--height", "54"), (64, 54)),  # within a pixel
                                         (("--width", "128"), (128, 106)),
                                         (("--resolution-scale", "0.125"), (64, 53))])
def test_resolution_flags(tmp_path, capsys, flags, size):
    code, _, err = _run(_tiny(tmp_path, *flags), capsys)
    assert code == 0, err
    document = json.loads((tmp_path / "out" / "frame.json").read_text())
    assert (document["width"], document["height"]) == size
    intrinsics = document["metadata"]["intrinsics"]
    assert (intrinsics["width"], intrinsics["height"]) == size
    assert abs(intrinsics["fx"] - 365.5 * size[0] / 512) < 1.0     # the preset's fx, scaled with the width


@pytest.mark.parametrize("argv, needle", [
    (["--resolution", "128by106"], "argument --resolution: must be WIDTHxHEIGHT in pixels, e.g. 128x106"),
    (["--resolution", "64x53", "--width", "10"], "--resolution: give it or --width/--height, not both"),
    # Issue 36: 100x100 of a 512x424 sensor made non-square pixels (fx 71.4, fy 86.2) without a word.
    (["--resolution", "100x100"], "--resolution: must keep the preset's aspect 512x424 (it scales the camera; another "
                                  "aspect would stretch its pixels), got 100x100; give 100x83 or 121x100, or --width "
                                  "or --height alone"),
    (["--width", "64", "--height", "40"], "--width/--height: must keep the preset's aspect 512x424"),
    (["--resolution-scale", "0.5", "--width", "10"], "--resolution-scale: give it or --width/--height/--resolution"),
    (["--resolution-sc", "0.5"], "unrecognized arguments: --resolution-sc 0.5"),     # no abbreviations
    (["--no-such-flag"], "unrecognized arguments: --no-such-flag"),
    (["--eye", "1,2,3"], "--eye and --target go together"),
    (["--exr-channels", "dpeth", "--formats", "exr"], "--exr-channels: must be a comma list of depth, distance"),
    (["--transient-bin", "5m", "--transient-max", "1m"], "--transient-max must be longer than --transient-bin"),
])
def test_errors_are_one_line_with_exit_code_2(tmp_path, capsys, argv, needle):
    code, out, err = _run(_tiny(tmp_path, *argv), capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and needle in lines[0], err
    assert "usage:" not in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_a_blend_scene_without_bpy_names_the_install(tmp_path, capsys, monkeypatch):
    blend = tmp_path / "room.blend"
    blend.write_bytes(b"BLENDER-v500")
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "bpy" else real(name, *a))
    code, _, err = _run(["render", "--scene", str(blend), "--out", str(tmp_path / "out"), "--formats", "json"], capsys)
    assert code == 2 and err.count("\n") == 1
    assert f"--scene {blend}: a .blend file is read through Blender's Python module bpy, which is not installed: " \
           f"pip install bpy" in err


def test_help_has_no_raw_markup_and_no_repository_paths():
    """What an installed user reads: no ``code``/:role:`x` markup, no paths into the repository."""
    from batch.cli import build_parser as batch_parser

    texts = []
    for parser in (build_parser(), batch_parser()):
        texts.append(parser.format_help())
        for action in parser._subparsers._group_actions:
            texts += [sub.format_help() for sub in action.choices.values()]
    for text in texts:
        assert "``" not in text and not re.search(r":[a-z]+:`", text), text
        assert not re.search(r"(?<![\w-])batch/|presets/\w+\.toml|tofcore/\w+\.py", text), text
    tofcore_help = "\n".join(texts)
    assert "a bare number is in mm, as in the Blender add-on" in re.sub(r"\s+", " ", tofcore_help)


def test_make_demo_installs_the_runtime_and_the_compiled_tracer_only():
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}  # `make test` runs us
    proc = subprocess.run(["make", "--no-print-directory", "-n", "demo", "VENV=/nonexistent/venv"], cwd=REPO,
                          capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 0, proc.stderr
    steps = proc.stdout
    assert "requirements-dev.txt" not in steps and "bpy" not in steps and "pytest" not in steps
    assert '-m pip install --quiet -e ".[compiled]"' in steps   # NumPy, tqdm and numba: no development stack
    render = steps.strip().splitlines()[-1]
    assert ("tofcore render --scene room --preset kinect_v2 --spp 64 --target-error 2mm --no-noise"   # as the README shows
            in render)


def test_readme_quotes_the_demo_command_of_the_makefile():
    render = next(line for line in (REPO / "Makefile").read_text().splitlines() if "tofcore render" in line)
    command = render.split("-m tofcore ", 1)[1]
    assert f".venv/bin/tofcore {command}" in (REPO / "README.md").read_text()


def test_a_transient_histogram_beyond_the_memory_limit_is_refused_before_rendering(tmp_path, capsys, monkeypatch):
    """512 x 424 pixels x 10 m / 1 mm = 10,000 bins: 20 bytes each is 43 GB; with a 1 GB limit it is refused."""
    monkeypatch.setenv("TOFCORE_MAX_RENDER_BYTES", str(1 << 30))
    code, _, err = _run(["render", "--scene", "plane", "--out", str(tmp_path / "out"), "--transient-bin", "1mm",
                         "--transient-max", "10m", "--formats", "json"], capsys)
    assert code == 2 and err.count("\n") == 1 and "10000 transient bins" in err and "widen the transient bins" in err
    assert not (tmp_path / "out").exists()


def _no_distortion_tables(monkeypatch) -> None:
    """Make the per-pixel distortion check of a camera larger than a preset's fail the test: it must not run
    before the budget is checked."""
    from tofcore.scene.camera import Camera

    check = Camera._check_invertible

    def checked(self):
        if self.width * self.height > 1 << 20:
            raise AssertionError(f"the {self.width} x {self.height} camera built its distortion tables")
        check(self)

    monkeypatch.setattr(Camera, "_check_invertible", checked)


@pytest.mark.parametrize("flags, size", [(("--resolution", "4096x4096"), "4096 x 4096"),
                                         (("--resolution-scale", "8"), "4096 x 3392")])
def test_a_render_beyond_the_memory_budget_is_refused_before_the_camera_is_made(tmp_path, capsys, monkeypatch,
                                                                                  flags, size):
    """4096 x 4096 Kinect v2 (53 GB estimated): refused in one line, before the distortion check builds its
    per-pixel tables (53-74 s and 3.5 GB before the refusal, issue 35)."""
    monkeypatch.setenv("TOFCORE_MAX_RENDER_BYTES", str(8 << 30))
    _no_distortion_tables(monkeypatch)
    code, _, err = _run(["render", "--scene", "plane", "--preset", "kinect_v2", "--out", str(tmp_path / "out"),
                         "--formats", "json", *flags], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"error: --preset kinect_v2 with --max-depth 5: the estimated render memory ({size} "
                          f"pixels, 9 raw images, max_depth 5) must be at most 8,589,934,592 bytes"), err


def test_a_sensor_resized_beyond_any_render_is_refused_before_the_camera_is_made(monkeypatch):
    """Sensor.resized (the set files' resolution_scale, the add-on's resolution): even max_depth 1 must fit."""
    from tofcore import LimitError, load_preset

    monkeypatch.setenv("TOFCORE_MAX_RENDER_BYTES", str(8 << 30))
    _no_distortion_tables(monkeypatch)
    with pytest.raises(LimitError, match=r"^Sensor.resized: the estimated render memory \(4096 x 4096 pixels, 9 raw "
                                         r"images, max_depth 1\) must be at most 8,589,934,592 bytes"):
        load_preset("kinect_v2").resized(4096, 4096)


def test_formats_take_transient_as_the_help_says(tmp_path, capsys):
    """--formats exr,json,transient was refused ("unknown: 'transient'") though --help lists it."""
    argv = _tiny(tmp_path, "--resolution", "16x13")
    argv[argv.index("--formats") + 1] = "exr,json,transient"
    code, _, err = _run(argv, capsys)
    assert code == 2 and err == ("error: --formats transient: the histogram needs the width of its bins: add "
                                 "--transient-bin LENGTH (e.g. 5cm)\n"), err
    code, _, err = _run([*argv, "--transient-bin", "50cm"], capsys)
    assert code == 0, err
    written = {p.name for p in (tmp_path / "out").iterdir()}
    assert {"depth.exr", "frame.exr", "frame.json", "transient.npy"} <= written and "depth_mm.png" not in written


def test_preview_denoise_and_time_budget_in_the_summary(tmp_path, capsys):
    argv = [a for a in _tiny(tmp_path, "--resolution", "32x27", "--preview-denoise", "--time-budget", "600")
            if a != "--quiet"]
    argv[argv.index("--spp") + 1] = "8"
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    stats = json.loads((tmp_path / "out" / "frame.json").read_text())["stats"]
    assert stats["preview_denoise"]["filter"] == "joint bilateral, amplitude-guided"
    assert "preview denoise:            on" in out
    assert re.search(r"render time: +[\d.]+ s \([\d.]+ M rays/s\), \d+ % of the 600 s budget", out), out


def test_warmup_renders_a_tiny_frame_and_names_the_tracer(capsys):
    from tofcore.cli import main

    assert main(["warmup", "--device", "cpu"]) == 0
    out = capsys.readouterr().out.strip()
    # the suite runs the NumPy reference (tests/conftest.py): the line says so and why
    assert out.startswith("numpy tracer on the CPU (TOFCORE_TRACER=numpy): ready in "), out


def test_main_called_as_a_function_gives_the_signal_handlers_back(capsys):
    """main(argv) installs its SIGINT/SIGTERM handlers for the command and puts the caller's back after, also
    when argparse exits: a test calling it must not leave this process with a SIGTERM that calls sys.exit."""
    import signal

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    assert main(["presets"]) == 0 and "kinect_v2" in capsys.readouterr().out
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    with pytest.raises(SystemExit):
        main(["no-such-command"])
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_a_render_the_compiled_tracer_could_not_run_says_why_and_what_it_costs(tmp_path, capsys, monkeypatch):
    """Without --verbose, a frame traced by the NumPy reference although the user did not ask for it gets one
    note: the reason and the cost; a frame the user asked NumPy for (TOFCORE_TRACER=numpy) gets none."""
    from tofcore.compiled import tracer

    argv = [a for a in _tiny(tmp_path) if a != "--quiet"]
    code, out, _ = _run(argv, capsys)  # the suite's default: TOFCORE_TRACER=numpy
    assert code == 0 and "note: traced by the NumPy reference" not in out
    monkeypatch.setenv("TOFCORE_TRACER", "auto")
    monkeypatch.setattr(tracer, "numba_version", lambda: None)
    code, out, _ = _run(argv, capsys)
    assert code == 0
    assert "note: traced by the NumPy reference, not the compiled tracer: numba is not installed" in out
    assert "about 2x faster on 2 CPU cores" in out


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
@pytest.mark.parametrize("command", [[sys.executable, "-m", "tofcore", "render", "--scene", "corner",
                                      "--resolution-scale", "0.0625", "--spp", "1"],
                                     [sys.executable, "-m", "batch", "run", str(REPO / "batch" / "examples"
                                                                                / "demo_set.toml")]])
def test_an_unwritable_out_is_one_line_before_anything_renders(command, tmp_path):
    """``/proc`` passes the permission bits for root (os.access), yet nothing can be made in it: the folder is
    tried before the render, in both commands (issue 36: found after the render, with a raw [Errno 2])."""
    env = dict(os.environ, PYTHONPATH=str(REPO), TOFCORE_TRACER="numpy")
    proc = subprocess.run([*command, "--out", "/proc/tofcore-test/out"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.splitlines()  # root: "(writing in '/proc': No such file …)"; others: "('/proc' is not …)"
    assert len(lines) == 1 and lines[0].startswith("error: --out: must be a folder this user can write, got "
                                                   "'/proc/tofcore-test/out' (")
    assert proc.stdout == ""


def test_help_shows_no_default_on_switches(capsys):
    """Issue 36: "--no-adaptive … (default: True)" read as if the switch were on by default."""
    with pytest.raises(SystemExit):
        main(["render", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: True)" not in text and "(default: False)" not in text
    assert "--no-adaptive every pixel gets the same samples (default: after 16 spp" in text
    assert "most samples per pixel (at most TOFCORE_MAX_SPP) (default: 64)" in text  # valued options keep theirs


@pytest.mark.skipif(importlib.util.find_spec("cupy") is not None, reason="CuPy is installed here")
def test_a_cpu_render_without_cupy_does_not_say_so_every_time(tmp_path, capsys):
    """Issue 36: every CPU render printed that CuPy is not installed (--device auto's fall-back); --verbose
    still names the device and why."""
    argv = [a for a in _tiny(tmp_path) if a != "--quiet"]
    code, _, err = _run(argv, capsys)
    assert code == 0 and "CuPy" not in err, err
    code, out, err = _run([*argv, "--verbose"], capsys)
    assert code == 0 and "(auto: GPU: CuPy is not installed" in out + err
