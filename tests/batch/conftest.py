"""Shared set-up for the batch tests.

The runs go through real subprocesses (``python -m batch …``): the pytest
process may have imported bpy (the add-on tests do), and a process that did
must not start worker processes. Blender's user folders point at a temporary
folder (set before anything imports bpy; subprocesses inherit it).

Everything renders tiny: resolution scale 1/16 (Kinect v2: 32 × 27 px),
2 spp, max path length 2.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

from batch_helpers import TINY, write_set

_HOME = tempfile.mkdtemp(prefix="tof-batch-bpy-home-")
for _name in ("BLENDER_USER_RESOURCES", "XDG_CONFIG_HOME", "XDG_CACHE_HOME"):
    os.environ.setdefault(_name, os.path.join(_HOME, _name.lower()))
    os.makedirs(os.environ[_name], exist_ok=True)


def pytest_configure(config):
    config.addinivalue_line("markers", "dask: needs dask[distributed]; skipped when it is not installed")
    config.addinivalue_line("markers", "bpy: needs the Blender Python module (bpy); skipped when it is not installed")


@pytest.fixture
def small_set(tmp_path: Path) -> Path:
    """2 scenes × 2 poses × 2 presets = 8 frames."""
    return write_set(tmp_path, """
seed = 7
presets = ["kinect_v2", "o3d303"]
""" + TINY + """
[[scenes]]
demo = "corner"
[[scenes.poses]]
suggested = true
[[scenes.poses]]
eye = [1.2, 0.9, 1.3]
target = [0.0, 0.0, 1.2]
[[scenes]]
demo = "box_on_wall"
[[scenes.poses]]
suggested = true
[[scenes.poses]]
count = 1
box_min = [-0.5, -2.2, 1.2]
box_max = [0.5, -1.8, 1.8]
target = [0.0, 0.0, 1.5]
""")
