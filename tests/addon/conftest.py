"""Shared set-up for the add-on tests (they need the PyPI ``bpy`` module).

``import bpy`` writes to ``~/.config/blender`` and ``~/.cache``: the user
resource, config and cache folders are pointed at one temporary folder for the
whole session, at conftest import time, i.e. before any test module imports
bpy. Tests that need Blender use::

    bpy = pytest.importorskip("bpy")
    pytestmark = pytest.mark.bpy

and the ``clean_bpy`` fixture, which gives a factory-empty scene per test.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import pytest

#: The repository's top folder: ``import addon.export`` and ``addon/build.py`` live below it.
REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

#: One temporary home for Blender's user folders during the whole session.
BLENDER_TEMP_HOME = tempfile.mkdtemp(prefix="tof-bpy-home-")
for _name in ("BLENDER_USER_RESOURCES", "XDG_CONFIG_HOME", "XDG_CACHE_HOME"):
    os.environ[_name] = os.path.join(BLENDER_TEMP_HOME, _name.lower())
    os.makedirs(os.environ[_name], exist_ok=True)


@pytest.fixture
def clean_bpy():
    """The ``bpy`` module with a factory-empty scene (no objects, no world).

    Skips the test when bpy is not installed.
    """
    bpy = pytest.importorskip("bpy")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    yield bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
