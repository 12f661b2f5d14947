"""numba's cache of the compiled kernels is never stale: a changed constant compiles anew.

numba reuses cached machine code while kernels.py's own stamp is unchanged, but the kernels freeze
constants read from other modules (rng, qmc, bsdf, surface, sampler, layout). The cache folder is named
after a hash of those constants (tofcore.compiled._target.constants_fingerprint); the end-to-end test
changes rng's SplitMix multiplier in a fresh process and checks that the compiled ``uniform`` follows it
(a cache miss), while the unchanged constants load the cached code (a hit) and give the same number.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tofcore import compiled
from tofcore.compiled import _target

needs_numba = pytest.mark.skipif(compiled.numba_version() is None, reason="numba is not installed")

ROOT = Path(__file__).resolve().parents[2]

PROBE = """
import json, sys
import numpy as np
if sys.argv[1] == "changed":
    from tofcore import rng
    rng._M1 = np.uint64(0x9E3779B97F4A7C15)
from tofcore import compiled
from tofcore.compiled import kernels as k
value = k.uniform(np.uint64(1), 2, 3, 4)
from tofcore import rng
print(json.dumps({"value": float(value), "numpy": float(rng.uniform(np.uint64(1), np.array([2]), np.array([3]), 4)[0]),
                  "hits": sum(k.uniform.stats.cache_hits.values()), "folder": k.uniform.stats.cache_path,
                  "location": compiled.cache_location()}))
"""


def test_fingerprint_changes_with_any_constant_and_ignores_functions():
    base = {"__name__": "m", "A": 1, "B": 2.5, "T": np.arange(4, dtype=np.uint64), "P": (1, np.float32(2.0)),
            "f": len, "np": np}
    fingerprint = _target.constants_fingerprint(base)
    changed = [{"A": 2}, {"B": 2.5000000000000004}, {"T": np.array([0, 1, 2, 5], np.uint64)},
               {"T": np.arange(4, dtype=np.int64)}, {"P": (1, np.float32(2.5))}, {"C": 0}]
    for change in changed:
        assert _target.constants_fingerprint({**base, **change}) != fingerprint, change
    assert _target.constants_fingerprint({**base, "f": abs, "__doc__": "x"}) == fingerprint
    assert _target.constants_fingerprint(base, {"fastmath": True}) != fingerprint


def test_cache_folder_is_named_after_the_fingerprint_and_writable(tmp_path, monkeypatch):
    numba = pytest.importorskip("numba")
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path))
    folder = _target.cache_folder(__file__, "0123456789abcdef")
    assert folder == str(tmp_path / "tofcore-0123456789abcdef") and os.path.isdir(folder)
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "file"))
    (tmp_path / "file").write_text("not a folder")
    assert _target.cache_folder(__file__, "0123456789abcdef") is None


@needs_numba
def test_a_changed_constant_is_compiled_anew_not_loaded_stale(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "PYTHONPATH": str(ROOT)}

    def probe(which: str) -> dict:
        out = subprocess.run([sys.executable, "-c", PROBE, which], env=env, capture_output=True, text=True,
                             check=True, cwd=ROOT)
        return json.loads(out.stdout.strip().splitlines()[-1])

    first, again, changed, back = probe("same"), probe("same"), probe("changed"), probe("same")
    assert first["hits"] == 0 and again["hits"] == 1 and back["hits"] == 1
    assert first["value"] == again["value"] == back["value"] == first["numpy"]
    assert changed["hits"] == 0, "stale machine code loaded for a changed constant"
    assert changed["value"] == changed["numpy"] != first["value"]
    assert changed["folder"] != first["folder"] == back["folder"]
    assert first["folder"].startswith(first["location"] + os.sep), "tofcore render --verbose names another folder"


COLD_PROBE = "from tofcore import compiled; print(compiled.cpu_kernels_cached(), compiled.cache_location())"


@needs_numba
def test_a_cold_cache_is_recognised_before_the_render_so_the_command_can_say_it_compiles(tmp_path):
    """An empty cache folder: False (tofcore render then says it compiles for ~40 s); TOFCORE_TRACER=numpy: None."""
    def probe(**extra) -> tuple[str, str]:
        env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(tmp_path))
        env.pop("TOFCORE_TRACER", None)
        env.update(extra)
        out = subprocess.run([sys.executable, "-c", COLD_PROBE], env=env, capture_output=True, text=True,
                             timeout=120, check=True).stdout.split()
        return out[0], out[1]

    cached, folder = probe()
    assert cached == "False"
    assert probe(TOFCORE_TRACER="numpy")[0] == "None"
    index = Path(folder) / "compiled_1" / "kernels.trace_pixels-1093.py311.nbi"  # numba's index of the driver
    index.parent.mkdir(parents=True)
    index.write_bytes(b"")
    assert probe()[0] == "True"
