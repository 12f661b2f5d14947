"""Progress output (tofcore/progress.py) and the render command's progress: a tqdm bar on a terminal only,
plain lines in logs (no carriage returns), nothing with --quiet, and tofcore working without tqdm."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tofcore import progress as progress_module
from tofcore.progress import PassProgress

REPO = Path(__file__).resolve().parents[2]


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _rows(spp_max: int = 32, stop_at: int | None = None):
    """Convergence-log rows of the pass schedule 1, 1, 2, 4, 8, 16, … up to ``spp_max`` (or ``stop_at``)."""
    spp, size, n = 0, 1, 0
    while spp < min(spp_max, stop_at or spp_max):
        n += 1
        spp += min(size, spp_max - spp)
        if n > 1:
            size = min(2 * size, 16)
        yield {"pass": n, "spp": spp, "spp_max": spp_max, "seconds": 0.25 * n,
               "est_depth_error_m": None if n < 3 else 0.02 / n}


def test_plain_lines_in_a_log_one_per_pass():
    log = io.StringIO()
    with PassProgress(stream=log, plain_interval_s=0) as show:
        for row in _rows(32):
            show(row)
    text = log.getvalue()
    assert "\r" not in text and "\033" not in text
    lines = text.splitlines()
    assert len(lines) == 6 and lines[0] == "pass 1: 1/32 spp  est. error – mm  0.2 s  ETA 8 s"
    assert lines[-1] == "pass 6: 32/32 spp  est. error 3.33 mm  1.5 s  ETA 0 s"


def test_plain_lines_are_thinned_to_the_interval_and_the_last_pass_is_printed():
    log = io.StringIO()
    with PassProgress(stream=log, plain_interval_s=1e9) as show:    # stopped early (target error): 8 of 64 spp
        for row in _rows(64, stop_at=8):
            show(row)
    assert [line.split(":")[0] for line in log.getvalue().splitlines()] == ["pass 1", "pass 4"]
    assert "8/64 spp  est. error 5.00 mm" in log.getvalue()


def test_quiet_prints_nothing_even_on_a_terminal():
    terminal = _Terminal()
    with PassProgress(stream=terminal, quiet=True) as show:
        for row in _rows(8):
            show(row)
    assert terminal.getvalue() == ""


def test_a_terminal_gets_a_tqdm_bar_with_the_estimated_error():
    pytest.importorskip("tqdm")
    terminal = _Terminal()
    with PassProgress(stream=terminal) as show:
        assert show.bar
        for row in _rows(32):
            show(row)
    text = terminal.getvalue()
    assert "\r" in text and "32/32" in text and "est. error 3.33 mm" in text and text.endswith("\n")


def test_the_bar_is_drawn_at_once_timed_from_the_start_and_redrawn_every_pass(monkeypatch):
    """Given the render's spp, the bar shows 0/32 before the first pass ends, its clock starts then (not at the
    first pass), and every pass is drawn, however quickly the passes come."""
    pytest.importorskip("tqdm")
    terminal = _Terminal()
    before = time.time()                        # tqdm's clock
    show = PassProgress(stream=terminal, total=32)
    assert "0/32" in terminal.getvalue() and "est. error – mm" in terminal.getvalue()
    assert before <= show._tqdm.start_t <= time.time()
    draws = []
    for row in _rows(32):
        show(row)
        draws.append(terminal.getvalue().rsplit("\r", 1)[-1])
    show.close()
    assert show._tqdm is None
    assert [d.split("|")[2].split()[0] for d in draws] == [f"{row['spp']}/32" for row in _rows(32)]


def test_a_terminal_without_tqdm_gets_plain_lines(monkeypatch):
    monkeypatch.setitem(sys.modules, "tqdm", None)          # import tqdm raises ImportError
    assert progress_module.tqdm_class() is None
    terminal = _Terminal()
    with PassProgress(stream=terminal, plain_interval_s=0) as show:
        assert not show.bar
        for row in _rows(4):
            show(row)
    assert "\r" not in terminal.getvalue() and terminal.getvalue().count("\n") == 3


def _render_cli(tmp_path: Path, *flags: str, python_code: str | None = None) -> subprocess.CompletedProcess:
    args = ["render", "--scene", "corner", "--preset", "kinect_v2", "--spp", "4", "--max-depth", "1",
            "--target-error", "1e-9m", "--device", "cpu", "--formats", "json", "--out", str(tmp_path / "out"), *flags]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO)] + ([os.environ["PYTHONPATH"]]
                                                                      if os.environ.get("PYTHONPATH") else [])))
    cmd = [sys.executable, "-m", "tofcore", *args] if python_code is None else \
        [sys.executable, "-c", python_code, *args]
    return subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)


def test_render_command_logs_plain_lines_when_stderr_is_not_a_terminal(tmp_path):
    proc = _render_cli(tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr and "\r" not in proc.stdout
    warning, *lines = proc.stderr.splitlines()   # a target of 1 nm (never reached: every pass runs) is implausible
    assert warning.startswith("warning: --target-error 1e-06 mm is implausible for a depth error")
    lines = [line for line in lines if " spp so far " not in line]  # inside a pass longer than 5 s (activity)
    assert lines[0].startswith("pass 1: 1/4 spp  est. error ") and lines[-1].startswith("pass 3: 4/4 spp")
    # The summary the command prints at the end is kept: one named line per number.
    assert "| pass | spp | seconds | est. depth error mm |" in proc.stdout
    assert "wrote 4 files to" in proc.stdout  # frame.json and the camera files
    for name in ("samples per pixel:", "render time:", "render noise (estimated):", "sensor noise:", "valid pixels:",
                 "invalid pixels by reason:", "depth error vs ground truth:"):
        assert sum(line.startswith(name) for line in proc.stdout.splitlines()) == 1, name


def test_render_command_quiet_prints_nothing(tmp_path):
    proc = _render_cli(tmp_path, "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert (proc.stdout, proc.stderr) == ("", "")
    assert (tmp_path / "out" / "frame.json").is_file()


def test_tofcore_renders_without_tqdm_and_never_imports_it(tmp_path):
    """Blender's Python has no tqdm: the package, the render and the command line work without it."""
    code = ("import sys; sys.modules['tqdm'] = None\n"          # any import of tqdm now raises ImportError
            "import tofcore, tofcore.cli\n"
            "frame = tofcore.render(tofcore.demo_scene('corner'), tofcore.load_preset('kinect_v2'), spp=1, max_depth=1)\n"
            "sys.exit(tofcore.cli.main(sys.argv[1:]))\n")
    proc = _render_cli(tmp_path, python_code=code)
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr and proc.stderr.splitlines()[1].startswith("pass 1: 1/4 spp")
    code = ("import sys, tofcore, tofcore.cli, tofcore.progress\n"
            "tofcore.render(tofcore.demo_scene('corner'), tofcore.load_preset('kinect_v2'), spp=1, max_depth=1)\n"
            "assert 'tqdm' not in sys.modules, 'tofcore imported tqdm'\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr


def test_the_bar_moves_while_the_tracer_compiles_and_inside_a_pass():
    """The first compiled render compiles for minutes inside its first pass: the bar says so with the seconds,
    then advances by blocks of pixels before the pass ends (issue 36)."""
    term = _Terminal()
    with PassProgress(stream=term, total=16) as show:
        show.activity({"stage": "compile", "seconds": 0.0})
        show.activity({"stage": "compile", "seconds": 41.6})
        compiling = term.getvalue().rsplit("\r", 1)[-1]
        show.activity({"stage": "trace", "pass": 1, "spp": 6.4, "spp_max": 16})
        inside = term.getvalue().rsplit("\r", 1)[-1]
        show({"pass": 1, "spp": 16, "spp_max": 16, "seconds": 50.0, "est_depth_error_m": 0.004})
    assert compiling.startswith(f"{progress_module.COMPILE_TEXT}:") and "42 s" in compiling
    assert inside.startswith("render:") and " 6/16 " in inside and "compiling" not in inside
    assert "16/16" in term.getvalue().rsplit("\r", 1)[-1]


def test_plain_lines_say_the_compile_at_once_and_the_pass_inside_at_the_interval():
    log = io.StringIO()
    with PassProgress(stream=log, plain_interval_s=3600) as show:
        show.activity({"stage": "compile", "seconds": 0.0})
        show.activity({"stage": "compile", "seconds": 0.5})   # held back: the interval
        show.activity({"stage": "trace", "pass": 1, "spp": 4.0, "spp_max": 16})
    lines = log.getvalue().splitlines()
    assert lines == [f"{progress_module.COMPILE_TEXT}: 0 s"]
    log = io.StringIO()
    with PassProgress(stream=log, plain_interval_s=0.05) as show:
        show.activity({"stage": "trace", "pass": 1, "spp": 1.0, "spp_max": 16})  # a short render: no line
        time.sleep(0.06)
        show.activity({"stage": "trace", "pass": 1, "spp": 4.0, "spp_max": 16})
    assert log.getvalue().splitlines()[0].startswith("pass 1: 4.0/16 spp so far")


def test_render_tells_activity_after_every_block_of_pixels(monkeypatch):
    """``activity`` inside a pass: the samples per pixel traced so far rise chunk by chunk to the pass's end."""
    import tofcore
    from tofcore.scene.demo import demo_scene

    monkeypatch.setenv("TOFCORE_TRACER", "numpy")
    sensor = tofcore.load_preset("kinect_v2")
    sensor = sensor.scaled(16 / sensor.camera.width)
    events, rows = [], []
    tofcore.render(demo_scene("corner"), sensor, spp=4, max_depth=1, chunk_size=64, workers=1, adaptive=False,
                   activity=events.append, progress=rows.append)
    pixels = sensor.camera.width * sensor.camera.height
    assert {e["stage"] for e in events} == {"trace"} and len(events) >= pixels * 4 // 64
    spp = [e["spp"] for e in events]
    assert spp == sorted(spp) and spp[-1] == rows[-1]["spp"] == 4
    assert {e["pass"] for e in events} == set(range(1, len(rows) + 1))


def test_a_compile_on_a_thread_ticks_until_it_ends_and_its_failure_reaches_the_caller():
    from tofcore.compiled.tracer import TICK_S, compile_in_thread

    ticks = []
    seconds = compile_in_thread(lambda: time.sleep(3 * TICK_S), ticks.append)
    assert len(ticks) >= 3 and ticks == sorted(ticks) and ticks[0] < TICK_S and seconds >= 3 * TICK_S

    def fails():
        raise RuntimeError("LLVM said no")

    with pytest.raises(RuntimeError, match="LLVM said no"):
        compile_in_thread(fails, ticks.append)
