"""A cancellable trace has uncached CPU kernels compiled by a child process (tofcore.compiled.child_compile).

The child is stood in for by a small Python script (the real compile takes 30 s to 3 min): one that
"caches the kernels" by creating a file after a while, one that fails. What is checked: a cancel ends the
wait at once while the child goes on; the next wait joins the same child; a failing child is reported
with its exit status and last line, so the render can compile in its own process; the trace says how
its kernels came.
"""

from __future__ import annotations

import sys
import time

import pytest

import tofcore
from tofcore import compiled
from tofcore.compiled import child_compile
from tofcore.sensor.modulation import phasor_correlations


@pytest.fixture
def fake_child(tmp_path, monkeypatch):
    """The kernels count as cached once ``tmp_path/cached`` exists; the child script is the test's to set."""
    marker = tmp_path / "cached"
    monkeypatch.setattr(compiled, "cpu_kernels_cached", lambda: marker.exists())
    monkeypatch.setattr(child_compile, "_child", {})

    def use(script: str):
        monkeypatch.setattr(child_compile, "command", lambda python: [python, "-c", script, str(marker)])

    yield use
    child_compile.stop()


def test_cancel_ends_the_wait_and_the_next_wait_joins_the_same_child(fake_child):
    fake_child("import sys, time; time.sleep(3.0); open(sys.argv[1], 'w').close()")
    asked = time.monotonic()
    with pytest.raises(tofcore.Cancelled, match="goes on"):
        child_compile.wait(lambda: time.monotonic() - asked > 0.2)
    assert time.monotonic() - asked < 2.5          # not after the child's 3 s (slack for a loaded machine)
    first = child_compile._child["process"]
    assert child_compile.running()                  # the compile goes on without the cancelled render
    assert child_compile.wait(lambda: False) == ""  # the next render waits for the same child
    assert child_compile._child["process"] is first and first.returncode == 0


def test_cached_kernels_start_no_child(fake_child, tmp_path):
    (tmp_path / "cached").touch()
    fake_child("raise SystemExit(9)")
    assert child_compile.wait(lambda: False) == ""
    assert "process" not in child_compile._child


def test_a_failing_child_says_why_so_the_render_compiles_itself(fake_child):
    fake_child("import sys; print('numba: something went wrong', file=sys.stderr); sys.exit(3)")
    why = child_compile.wait(lambda: False)
    assert "exit status 3" in why and why.endswith("numba: something went wrong"), why


def test_the_state_says_running_then_done_or_failed_with_the_seconds(fake_child, tmp_path):
    assert child_compile.state() is None                            # no child in this process yet
    fake_child("import sys, time; time.sleep(0.5); open(sys.argv[1], 'w').close()")
    assert child_compile.start() == ""
    state, seconds, why = child_compile.state()
    assert state == "running" and 0 <= seconds < 5 and why == ""
    assert child_compile.wait(lambda: False) == ""
    time.sleep(0.2)                                                 # its watcher notes the end
    state, seconds, why = child_compile.state()
    assert state == "done" and 0.4 < seconds < 10 and why == ""
    assert child_compile.state()[1] == seconds                      # the end is kept, not "now"
    (tmp_path / "cached").unlink()                                  # not cached any more: a new child
    fake_child("import sys; print('numba: out of memory', file=sys.stderr); sys.exit(3)")
    assert child_compile.start() == ""
    child_compile._child["process"].wait()
    state, _, why = child_compile.state()
    assert state == "failed" and "exit status 3" in why and why.endswith("numba: out of memory")


def test_the_child_imports_what_this_process_imports():
    env = child_compile.child_environment()
    assert env["PYTHONPATH"].split(":")[:3] == [p for p in sys.path if p][:3]
    assert env["TOFCORE_TRACER"] == "compiled"
    assert child_compile.command("py") == ["py", "-m", "tofcore", "warmup", "--device", "cpu"]


@pytest.mark.skipif(compiled.numba_version() is None, reason="numba is not installed")
def test_a_cancellable_trace_waits_for_the_child_and_says_so(monkeypatch):
    """Only a trace with ``cancel`` and uncached kernels waits; it records how the kernels came."""
    calls = []
    cached = {"value": False}
    monkeypatch.setattr(compiled, "cpu_kernels_cached", lambda: cached["value"])

    def wait(cancel, tick=None):
        calls.append(cancel)
        cached["value"] = True
        return ""

    monkeypatch.setattr(child_compile, "wait", wait)
    monkeypatch.setenv("TOFCORE_TRACER", "auto")
    scene = tofcore.demo_scene("corner")
    cam = tofcore.Camera.from_fov(8, 6, 60.0)
    pose = tofcore.suggested_pose(scene)

    def stats(**kw):
        return tofcore.trace(scene, cam, [tofcore.LED()], world_from_sensor=pose, spp=1, max_depth=2, workers=1,
                             correlations=phasor_correlations([80e6]), **kw).stats

    from tofcore.compiled import kernels

    compiles_here = not kernels.trace_pixels.overloads  # an earlier test may have compiled them in this process
    note = stats().compile                                          # no cancel: numba compiles here, and says so
    assert calls == [] and (note.startswith("compiled in this process in ") if compiles_here else note == "")
    traced = stats(cancel=lambda: False)
    assert traced.tracer == "compiled" and len(calls) == 1
    assert traced.compile.startswith("compiled by a child process in ")
    assert stats(cancel=lambda: False).compile == "" and len(calls) == 1  # cached now: no child
