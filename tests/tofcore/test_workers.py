"""Worker processes of the CPU tracer (tofcore.tracer.workers): same frame bit for bit, shared memory, fallbacks."""

from __future__ import annotations

import gc
import os
import sys
from pathlib import Path

import numpy as np
import pytest

import tofcore
from tofcore import LED, Camera
from tofcore import limits
from tofcore.tracer import workers
from tofcore.errors import Cancelled
from tofcore.sensor.modulation import phasor_correlations


def corner(width=48, height=36):
    scene = tofcore.demo_scene("corner")
    return scene, Camera.from_fov(width, height, 60.0), dict(world_from_sensor=tofcore.suggested_pose(scene))


SUMS = ("sample_count", "signal_sum", "correlation_sum", "ambient_sum", "replicate_sum", "transient_sum")


def assert_same(a, b):
    for name in SUMS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.mark.parametrize("n_workers", [2, 3])
def test_processes_give_the_same_sums_bit_for_bit(n_workers):
    """Light vertices, ambient, the transient histogram and two LEDs: chunks of 2,000 paths on 2 or 3
    processes equal one in-process worker exactly (chunks own disjoint pixels)."""
    scene, cam, kw = corner()
    kw.update(correlations=phasor_correlations([80e6]), spp=8, max_depth=3, seed=4,
              ambient=tofcore.Ambient(radiance_w_m2_sr=0.5), transient_bin_m=0.1, transient_max_m=15.0)
    leds = [LED(position_m=(0.03, 0, 0)), LED(position_m=(-0.03, 0, 0), kind="lambertian")]
    one = tofcore.trace(scene, cam, leds, workers=1, **kw)
    many = tofcore.trace(scene, cam, leds, workers=n_workers, chunk_size=2_000, **kw)
    assert one.stats.parallel == "one" and many.stats.parallel == "processes"
    assert_same(one, many)


def test_adaptive_render_on_processes_equals_one_worker():
    sensor = tofcore.load_preset("kinect_v2")
    small = sensor.replace(camera=Camera.from_fov(40, 30, 70.0), **{"noise.model": "none"})
    scene = tofcore.demo_scene("room")
    a = tofcore.render(scene, small, spp=32, seed=1, workers=1)
    b = tofcore.render(scene, small, spp=32, seed=1, workers=2, chunk_size=3_000)
    assert b.stats["transport"]["parallel"] == "processes"
    assert a.samples.max() > a.samples.min()  # adaptive allocation was in play
    np.testing.assert_array_equal(a.raw, b.raw)
    np.testing.assert_array_equal(a.samples, b.samples)


def test_the_transport_outlives_its_shared_memory():
    """After the trace the sums are private copies: the shared blocks are gone, the arrays still read."""
    scene, cam, kw = corner()
    t = tofcore.trace(scene, cam, [LED()], spp=4, workers=2, chunk_size=2_000, **kw)
    assert t.stats.parallel == "processes"
    assert all(getattr(t, name).base is None for name in ("signal_sum", "replicate_sum"))
    assert np.isfinite(t.signal()).all() and t.signal().sum() > 0


def test_lambdas_fall_back_to_threads_and_say_why():
    scene, cam, kw = corner()
    a = tofcore.trace(scene, cam, [LED()], correlations=[lambda tau: np.cos(tau * 1e8)], spp=4, workers=1, **kw)
    b = tofcore.trace(scene, cam, [LED()], correlations=[lambda tau: np.cos(tau * 1e8)], spp=4, workers=2,
                      chunk_size=2_000, **kw)
    assert b.stats.parallel.startswith("threads: the trace context does not pickle")
    assert_same(a, b)


def test_threads_on_request(monkeypatch):
    monkeypatch.setenv("TOFCORE_PARALLEL", "threads")
    scene, cam, kw = corner()
    t = tofcore.trace(scene, cam, [LED()], spp=4, workers=2, chunk_size=2_000, **kw)
    assert t.stats.parallel == "threads: TOFCORE_PARALLEL=threads"


def test_cancel_stops_the_workers_and_the_next_render_works():
    scene, cam, kw = corner()
    calls = {"n": 0}

    def cancel():
        calls["n"] += 1
        return calls["n"] > 3

    with pytest.raises(Cancelled):
        tofcore.trace(scene, cam, [LED()], spp=16, workers=2, chunk_size=1_000, cancel=cancel, **kw)
    again = tofcore.trace(scene, cam, [LED()], spp=4, workers=2, chunk_size=2_000, **kw)
    assert again.stats.parallel == "processes" and again.signal().sum() > 0


def test_usable_cpus_respects_the_cgroup_quota(tmp_path):
    assert 1 <= limits.usable_cpus() <= (os.cpu_count() or 1)
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert limits._cgroup_quota(tmp_path) == 2          # 1.5 CPUs → 2 workers
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert limits._cgroup_quota(tmp_path) is None
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("400000")
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000")
    assert limits._cgroup_quota(v1) == 4


def test_python_executable_inside_blender(monkeypatch, tmp_path):
    """Blender's binary is not a Python: the workers start with the interpreter bundled in sys.prefix/bin."""
    blender = tmp_path / "blender"
    blender.write_text("")
    monkeypatch.setattr(sys, "executable", str(blender))
    monkeypatch.setattr(sys, "prefix", str(tmp_path / "python"))
    assert workers.python_executable() is None
    ok, why = workers.process_support()
    assert not ok and "no Python interpreter" in why
    bindir = tmp_path / "python" / "bin"
    bindir.mkdir(parents=True)
    python = bindir / f"python{sys.version_info.major}.{sys.version_info.minor}"
    python.write_text("")
    assert workers.python_executable() == str(python)


def test_shared_arrays_are_views_of_one_block():
    """Arrays over the threshold travel as shared-memory names; a worker's write is seen by the parent."""
    big = np.arange(100_000, dtype=np.float64)
    small = np.ones(3)
    shared = workers.Shared({"big": big, "small": small}, always=[small])
    try:
        assert len(shared.blocks) == 3  # big, small (always), the pickle itself
        view = shared.view(small)
        out = list(workers.run(2, shared, "test-key", _add_one, [(i,) for i in range(3)]))
        assert sorted(out) == [0, 1, 2]
        np.testing.assert_array_equal(view, [2.0, 2.0, 2.0])
        np.testing.assert_array_equal(shared.view(big), big)
    finally:
        shared.close()


def _add_one(objects, i):
    objects["small"][i] += 1.0
    return i


def test_workers_do_not_rerun_the_main_script(tmp_path):
    """A script without a __main__ guard renders once: the spawned workers do not import it again."""
    script = tmp_path / "unguarded.py"
    marker = tmp_path / "runs.txt"
    script.write_text(
        "import tofcore\n"
        f"open({str(marker)!r}, 'a').write('run\\n')\n"
        "scene = tofcore.demo_scene('corner')\n"
        "cam = tofcore.Camera.from_fov(48, 36, 60.0)\n"
        "t = tofcore.trace(scene, cam, [tofcore.LED()], spp=4, workers=2, chunk_size=2000,\n"
        "                  world_from_sensor=tofcore.suggested_pose(scene))\n"
        "print(t.stats.parallel)\n")
    assert run_script(script).endswith("processes")
    assert marker.read_text().count("run") == 1


def test_a_daemonic_process_traces_on_threads(tmp_path):
    """Inside a multiprocessing.Pool (or Dask) worker, which may not start processes: threads, and why."""
    script = tmp_path / "daemon.py"
    script.write_text(
        "import multiprocessing as mp\n"
        "def job(_):\n"
        "    import tofcore\n"
        "    scene = tofcore.demo_scene('corner')\n"
        "    t = tofcore.trace(scene, tofcore.Camera.from_fov(48, 36, 60.0), [tofcore.LED()], spp=4, workers=2,\n"
        "                      chunk_size=2000, world_from_sensor=tofcore.suggested_pose(scene))\n"
        "    return t.stats.parallel\n"
        "if __name__ == '__main__':\n"
        "    with mp.get_context('spawn').Pool(1) as p:\n"
        "        print(p.map(job, [0])[0])\n")
    assert run_script(script).startswith("threads: this is a daemonic process")


def run_script(script: Path) -> str:
    """Run a Python script in a fresh interpreter with tofcore importable; its stripped stdout."""
    import subprocess
    env = dict(os.environ, PYTHONPATH=str(Path(tofcore.__file__).resolve().parents[1]))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip()


def test_no_room_in_dev_shm_means_threads(monkeypatch):
    """A container's small /dev/shm would crash a worker with SIGBUS: refuse up front, trace on threads."""
    import shutil
    from collections import namedtuple

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(1 << 20, 1 << 20, 0))
    scene, cam, kw = corner()
    t = tofcore.trace(scene, cam, [LED()], spp=4, workers=2, chunk_size=2_000, **kw)
    assert t.stats.parallel.startswith("threads: no shared memory for worker processes (/dev/shm has 0 MiB free")


@pytest.fixture
def python_sigint_handler():
    """SIGINT as an interactive Python has it (KeyboardInterrupt), whatever this test process inherited: a
    background job of a non-interactive shell starts with SIGINT ignored, and Python then keeps it so."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_sigint_held_defers_a_ctrl_c_delivered_to_another_thread(python_sigint_handler):
    """The terminal's SIGINT may reach any thread that does not block it (NumPy's BLAS threads); the main
    thread must not raise inside the block (a worker would be spawned but never sent its start-up data),
    but right after it, once."""
    import signal
    import threading
    import time

    go = threading.Event()

    def other_thread_gets_sigint():  # started before the block, as NumPy's BLAS threads are: SIGINT unblocked
        go.wait()
        signal.pthread_kill(threading.get_ident(), signal.SIGINT)

    thread = threading.Thread(target=other_thread_gets_sigint)
    thread.start()
    finished_body = False
    with pytest.raises(KeyboardInterrupt):
        with workers.sigint_held():
            assert signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])  # children inherit the mask
            go.set()
            thread.join()
            for _ in range(50):  # Python runs a tripped handler at the next bytecodes: give it many
                time.sleep(0.001)
            finished_body = True
    assert finished_body
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])


def test_sigint_held_without_a_signal_changes_nothing(python_sigint_handler):
    import signal

    with workers.sigint_held():
        pass
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])


def test_sigint_held_keeps_an_ignored_sigint_ignored():
    """Where SIGINT is ignored (a background job), a Ctrl-C during the block stays ignored after it."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with workers.sigint_held():
            signal.raise_signal(signal.SIGINT)   # blocked in this thread: pending until the block ends
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_the_resource_tracker_is_never_entered_with_the_garbage_collector_on(monkeypatch):
    """A stopped pool's semaphores unregister from the tracker when the collector frees them; a collection
    inside another tracker call is a reentrant call (Python 3.13: a warning and a leaked semaphore). So the
    pool's start, the shared blocks' creation and their unlinking hold the collector off."""
    from multiprocessing import resource_tracker

    calls = []

    def recording(name, original):
        def call(*args):
            calls.append((name, args[-1], gc.isenabled()))
            return original(*args)
        return call

    for name in ("register", "unregister"):
        monkeypatch.setattr(resource_tracker, name, recording(name, getattr(resource_tracker, name)))
    workers.shutdown()  # a new pool: its semaphores register
    scene, cam, kw = corner(24, 18)
    tofcore.trace(scene, cam, [LED()], spp=2, workers=2, chunk_size=100, **kw)
    kinds = {(name, kind) for name, kind, _ in calls}
    assert {("register", "semaphore"), ("register", "shared_memory"), ("unregister", "shared_memory")} <= kinds
    # the semaphores' own unregistering (their finalizers, when a stopped pool is freed) is what must not
    # happen inside these calls; it may run with the collector on
    ours = [call for call in calls if call[:2] != ("unregister", "semaphore")]
    assert not [call for call in ours if call[2]], "tracker calls with the collector on"
    assert gc.isenabled()
