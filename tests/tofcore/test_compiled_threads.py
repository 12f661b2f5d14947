"""Two compiled renders on two Python threads at once, under numba's ``workqueue`` threading layer.

That layer (numba's fall-back where neither TBB nor OpenMP loads) aborts the whole process when two threads
run ``parallel=True`` code at once; before tofcore.compiled.cpu.PARALLEL_LOCK two overlapping renders did
(exit 134, "Concurrent access has been detected"), as Blender's add-on can when a live preview starts while
the one it cancelled still traces. The renders run in a child process, since a failure is an abort: the
test passes when both frames come back, both compiled, each equal to the same render done alone.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from tofcore import compiled

pytestmark = pytest.mark.skipif(compiled.numba_version() is None, reason="numba is not installed")

CHILD = textwrap.dedent("""
    import dataclasses, threading
    import numpy as np
    import tofcore

    sensor = tofcore.load_preset("kinect_v2")
    cam = sensor.camera
    cam = dataclasses.replace(cam, width=96, height=80, fx=cam.fx * 96 / cam.width, fy=cam.fy * 80 / cam.height,
                              cx=cam.cx * 96 / cam.width, cy=cam.cy * 80 / cam.height)
    sensor = sensor.replace(camera=cam, **{"noise.model": "none"})
    scene = tofcore.demo_scene("room", detail=2)
    render = lambda seed: tofcore.render(scene, sensor, spp=8, seed=seed, max_depth=3, workers=2)
    alone = [render(seed) for seed in (0, 1)]          # also compiles or loads the kernels
    barrier, frames = threading.Barrier(2), {}

    def work(seed):
        barrier.wait()
        frames[seed] = [render(seed) for _ in range(3)]   # several passes' chunks: the threads overlap

    threads = [threading.Thread(target=work, args=(seed,)) for seed in (0, 1)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    import numba
    assert numba.threading_layer() == "workqueue", numba.threading_layer()
    for seed in (0, 1):
        for frame in frames[seed]:
            assert frame.stats["transport"]["tracer"] == "compiled"
            assert np.array_equal(frame.depth, alone[seed].depth, equal_nan=True)
    print("both threads done")
""")


def test_two_threads_render_compiled_under_workqueue():
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue", "TOFCORE_TRACER": "compiled"}
    proc = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0 and "both threads done" in proc.stdout, (proc.returncode, proc.stderr[-2000:])
