"""``tofcore warmup``: after it, a first render compiles nothing more (issue 33, item 3).

What compiles in tofcore: the kernels of ``tofcore/compiled/kernels.py`` and ``depth_error.py`` (numba on the CPU,
numba-cuda on the GPU: ``@fn``, ``@cpu_parallel``, ``@gpu_kernel``), the BVH's level split
(``tofcore/scene/bvh_build.py``, numba, meshes of 4,096 triangles or more) and, on the GPU, CuPy's kernels
(``tofcore/fused.py``, ``tofcore/gpu/traversal.py`` and every array operation). Nothing else: the writers, the
batch and the add-on are NumPy. These tests count numba's compiles (its ``numba:compile`` event, which a load from
the cache does not fire); the GPU's are for the GPU machine (docs/benchmarks.md, "Cold start").
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

numba = pytest.importorskip("numba")

REPO_ROOT = Path(__file__).resolve().parents[2]


class _Compiles:
    """numba's compiles while registered: the dispatchers' names."""

    def __init__(self):
        from numba.core import event

        class Listener(event.Listener):
            def on_start(listener, e):
                self.names.append(getattr(e.data.get("dispatcher"), "__name__", "?"))

            def on_end(listener, e):
                pass

        self.names: list[str] = []
        self.listener = Listener()

    def __enter__(self):
        from numba.core import event

        event.register("numba:compile", self.listener)
        return self

    def __exit__(self, *exc):
        from numba.core import event

        event.unregister("numba:compile", self.listener)


def test_after_the_bvh_warm_up_no_mesh_build_compiles(monkeypatch):
    """Both builds of every compiled loop of the BVH build (parallel for meshes of PARALLEL_LEVEL triangles or
    more, serial below: the level split, the triangle records, the node and leaf records) get the argument
    types of a mesh's build: building then compiles nothing."""
    monkeypatch.setenv("TOFCORE_TRACER", "auto")
    from tofcore.scene import bvh, bvh_build

    bvh_build.warm_up()          # compiles once per checkout (~9 s on 2 cores), then loads from numba's cache
    rng = np.random.default_rng(0)
    with _Compiles() as compiles:
        for m in (bvh.COMPILED_BUILD_MIN, bvh_build.PARALLEL_LEVEL):
            lo = rng.random((3, m), dtype=np.float32)
            order, *_ = bvh._build_binary(lo, lo + np.float32(0.01), 2, bvh.N_BINS)
            assert sorted(order) == list(range(m))
            vertices = rng.random((3 * m, 3), dtype=np.float32)
            for triangles, leaf_size in ((np.arange(3 * m, dtype=np.int32).reshape(m, 3), 2),
                                         (np.arange(3 * m).reshape(3, m).T, 4)):  # int32; int64 not contiguous
                with warnings.catch_warnings():
                    warnings.simplefilter("error", RuntimeWarning)  # the compiled build, not its NumPy fallback
                    tree = bvh.BVH.build(vertices, triangles, leaf_size=leaf_size)
                assert tree.stats["triangles"] == m
    assert compiles.names == []


_FIRST_RENDERS = """
import sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from tests.tofcore.test_warmup import _Compiles
from tofcore.render import render
from tofcore.scene.bvh import BVH
from tofcore.scene.demo import demo_scene
from tofcore.sensor.presets import load_preset

with _Compiles() as compiles:
    for preset, workers in (("kinect_v2", 1), ("kinect_v2", 2), ("o3d303", 2)):
        sensor = load_preset(preset)
        sensor = sensor.scaled(64 / sensor.camera.width)
        frame = render(demo_scene("room"), sensor, spp=8, workers=workers, target_error_m=0.01)
        assert frame.stats["transport"]["tracer"] == "compiled", frame.stats["transport"]
    vertices = np.random.default_rng(0).random((3 * 5000, 3)).astype(np.float32)
    BVH.build(vertices, np.arange(3 * 5000).reshape(5000, 3))
print("compiled:", compiles.names)
"""


@pytest.mark.slow
def test_after_warmup_a_first_render_compiles_nothing(tmp_path):
    """A fresh numba cache: ``tofcore warmup --device cpu`` in one process (the 40-s compile on 2 cores: slow),
    then Kinect v2 and O3D303 room frames at another size, on 1 and 2 tracer threads, to a target error, and a
    5,000-triangle BVH in another process: no compile there."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), TOFCORE_TRACER="compiled",
               PYTHONPATH=str(REPO_ROOT))
    warm = subprocess.run([sys.executable, "-m", "tofcore", "warmup", "--device", "cpu"], env=env,
                          capture_output=True, text=True, timeout=900)
    assert warm.returncode == 0, warm.stderr
    assert warm.stdout.startswith("compiled tracer on the CPU: ready in "), warm.stdout
    first = subprocess.run([sys.executable, "-c", _FIRST_RENDERS, str(REPO_ROOT)], env=env, capture_output=True,
                           text=True, timeout=600)
    assert first.returncode == 0, first.stderr
    assert first.stdout.strip().splitlines()[-1] == "compiled: []", first.stdout


def test_the_warm_up_compiles_the_bvh_build_in_a_child_beside_the_kernels(monkeypatch, tmp_path):
    """``tofcore warmup`` starts the BVH build's compile in a child process (it then runs beside the kernels'
    compile instead of after it; 8 s of the 35 the warm-up took on 2 cores): the child fills numba's cache — here an empty
    one of its own (about 8 s of compile) —, so the parent's own ``warm_up`` loads. No child where the loops are
    cached or only one CPU is usable."""
    import tofcore.compiled as compiled
    import tofcore.limits as limits
    from tofcore import cli

    monkeypatch.setattr(limits, "usable_cpus", lambda: 1)
    assert cli.bvh_build_aside() is None
    monkeypatch.setattr(limits, "usable_cpus", lambda: 2)
    monkeypatch.setattr(compiled, "bvh_build_cached", lambda: True)
    assert cli.bvh_build_aside() is None
    monkeypatch.setattr(compiled, "bvh_build_cached", lambda: False)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    child = cli.bvh_build_aside()
    assert child is not None and child.wait(timeout=300) == 0
    cached = {p.name.split(".")[1].rsplit("-", 1)[0] for p in tmp_path.rglob("bvh_build.*.nbi")}
    assert {"_split_level_parallel", "_split_level_serial", "_leaf_records_serial"} <= cached, cached
