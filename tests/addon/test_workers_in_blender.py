"""The tracer's worker processes from a process that imported ``bpy`` (issue 11).

Such a process must not fork: the workers are spawned with the interpreter, import only tofcore and
NumPy, and give the same sums as one in-process worker. Run in a subprocess so that the test session's
own state (pools, imported modules) does not matter.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

#: The repository's top folder (a module named ``conftest`` is whichever folder's conftest was imported last).
REPO_ROOT = Path(__file__).resolve().parents[2]

pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

SCRIPT = """
import json, sys
import bpy  # noqa: F401  (the point: bpy is imported before the workers start)
import numpy as np, tofcore
scene = tofcore.demo_scene("corner")
cam = tofcore.Camera.from_fov(48, 36, 60.0)
kw = dict(spp=8, max_depth=3, seed=2, world_from_sensor=tofcore.suggested_pose(scene))
one = tofcore.trace(scene, cam, [tofcore.LED()], workers=1, **kw)
many = tofcore.trace(scene, cam, [tofcore.LED()], workers=2, chunk_size=2000, **kw)
print(json.dumps({"parallel": many.stats.parallel,
                  "same": bool(np.array_equal(one.signal_sum, many.signal_sum)
                               and np.array_equal(one.replicate_sum, many.replicate_sum))}))
"""


def test_workers_spawn_from_a_bpy_process():
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["parallel"] == "processes"
    assert result["same"]
