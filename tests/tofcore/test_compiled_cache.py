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
import numba
value = numba.njit(lambda: k.uniform(np.uint64(1), np.int64(2), np.int64(3), np.int64(4)))()  # jitted callers only
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
    with pytest.warns(_target.CompiledWarning, match="cannot be used .*compiled again in every process"):
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


# --------------------------------------------------------------------------- a cache that cannot brick an install

#: The drivers' caches as numba writes them, made by hand (nothing compiled): a whole index naming one data file;
#: then the same with the index emptied and with the data file truncated (issue 35: True was said for both).
CRAFTED_PROBE = """
import os, pickle, sys
from tofcore import compiled
from tofcore.compiled import kernels
def craft(driver):
    cache = driver._cache
    index = cache._cache_file._index_path
    data = os.path.join(cache.cache_path, os.path.basename(index)[:-len(".nbi")] + ".1.nbc")
    cache._cache_file._save_index({("sig", "target"): os.path.basename(data)})   # numba's own index writer
    with open(data, "wb") as fh:
        fh.write(pickle.dumps(("a compiled library", b"x" * 4096), protocol=4))
    return index, data
craft(kernels.first_hits)  # the ground truth's driver, whole throughout
index, data = craft(kernels.trace_pixels)
whole = compiled.cpu_kernels_cached()
size = os.path.getsize(data)
os.truncate(data, 11)
truncated = compiled.cpu_kernels_cached()
os.truncate(data, 0)
with open(data, "wb") as fh:
    fh.write(pickle.dumps(("a compiled library", b"x" * 4096), protocol=4))
open(index, "wb").close()
emptied = compiled.cpu_kernels_cached()
print(whole, truncated, emptied)
"""


@needs_numba
def test_cpu_kernels_cached_is_true_only_for_a_whole_index_and_whole_data_files(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(tmp_path))
    env.pop("TOFCORE_TRACER", None)
    out = subprocess.run([sys.executable, "-c", CRAFTED_PROBE], env=env, capture_output=True, text=True,
                         timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True", "False", "False"]


@pytest.fixture(scope="module")
def filled_cache(tmp_path_factory) -> Path:
    """A numba cache holding the compiled ``uniform`` (and the functions it calls): a second or so to compile."""
    folder = tmp_path_factory.mktemp("numba-cache")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(folder), "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-c", PROBE, "same"], env=env, capture_output=True, text=True, check=True,
                   cwd=ROOT)
    return folder


def _probe_in(folder: Path) -> tuple[dict, str]:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(folder), "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", PROBE, "same"], env=env, capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1]), out.stderr


@needs_numba
@pytest.mark.parametrize("damage", ["truncated nbc", "emptied nbi"])
def test_a_damaged_cache_file_is_set_aside_and_compiled_anew_once(filled_cache, tmp_path, damage):
    """An 11-byte .nbc or an empty .nbi: an UnpicklingError/EOFError traceback in every later process before."""
    import shutil

    folder = Path(shutil.copytree(filled_cache, tmp_path / "cache"))
    [index] = folder.glob("*/*/kernels.uniform-*.nbi")
    [data] = index.parent.glob("kernels.uniform-*.nbc")
    if damage == "truncated nbc":
        os.truncate(data, 11)
    else:
        index.write_bytes(b"")
    first, stderr = _probe_in(folder)
    assert first["value"] == first["numpy"] and first["hits"] == 0
    notes = [line for line in stderr.splitlines() if "CompiledWarning: " in line]
    assert len(notes) == 1 and f"kernels.uniform-" in notes[0] and "set aside as *.damaged" in notes[0], stderr
    assert sorted(p.name for p in index.parent.glob("kernels.uniform-*.damaged")) == sorted(
        [index.name + ".damaged", data.name + ".damaged"])
    again, stderr = _probe_in(folder)
    assert again["hits"] == 1 and again["value"] == first["value"] and "damaged" not in stderr


@needs_numba
def test_an_unusable_cache_folder_is_named_once_with_its_cost(tmp_path):
    """NUMBA_CACHE_DIR under a regular file (or read-only): every process compiles; tofcore says so, and
    cpu_kernels_cached() is False (it said True, or "compiling once", before)."""
    (tmp_path / "file").write_text("not a folder")
    env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(tmp_path / "file" / "cache"))
    env.pop("TOFCORE_TRACER", None)
    code = "from tofcore import compiled; print(compiled.cpu_kernels_cached()); print(compiled.cache_problem())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    cached, problem = out.stdout.splitlines()
    assert cached == "False"
    assert problem.startswith(f"the compiled tracer's kernel cache NUMBA_CACHE_DIR={tmp_path / 'file' / 'cache'} "
                              f"cannot be used (Not a directory): the kernels are compiled again in every process")
    notes = [line for line in out.stderr.splitlines() if "CompiledWarning: " in line]
    assert len(notes) == 1 and notes[0].endswith(f"CompiledWarning: {problem}"), out.stderr


@needs_numba
def test_a_cache_on_a_full_disk_never_stops_the_compile(filled_cache, tmp_path):
    """A cache folder on a full file system: the function is compiled and runs, one note names the folder (an
    OSError naming no path before)."""
    import shutil

    disk = tmp_path / "disk"
    disk.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0 or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)], capture_output=True).returncode != 0:
        pytest.skip("needs root to mount a small tmpfs")
    try:
        code = ("import os\nfrom tofcore.compiled import kernels\n"  # the cache folder is made, then the disk fills
                "fd = os.open(os.path.join(os.environ['NUMBA_CACHE_DIR'], 'filler'), os.O_WRONLY | os.O_CREAT)\n"
                "try:\n    while True: os.write(fd, bytes(4096))\nexcept OSError: os.close(fd)\n" + PROBE)
        env = {**os.environ, "NUMBA_CACHE_DIR": str(disk), "PYTHONPATH": str(ROOT)}
        out = subprocess.run([sys.executable, "-c", code, "same"], env=env, capture_output=True, text=True, cwd=ROOT)
        assert out.returncode == 0, out.stderr
        result = json.loads(out.stdout.strip().splitlines()[-1])
        assert result["value"] == result["numpy"]
        notes = [line for line in out.stderr.splitlines() if "CompiledWarning: " in line]
        assert len(notes) == 1 and f"{disk}/tofcore-" in notes[0] and "No space left on device" in notes[0], out.stderr
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_the_cache_folder_is_in_the_users_cache_and_named_after_the_source_too(tmp_path, monkeypatch):
    numba = pytest.importorskip("numba")
    monkeypatch.setattr(numba.config, "CACHE_DIR", "")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert _target.cache_folder(__file__, "0123456789abcdef") == str(tmp_path / "cache" / "tofcore"
                                                                      / "numba-0123456789abcdef")
    source = tmp_path / "m.py"
    source.write_text("A = 1\n")
    namespace = {"__file__": str(source), "A": 1}
    fingerprint = _target.content_fingerprint(namespace)
    source.write_text("A = 1  # edited\n")
    assert _target.content_fingerprint(namespace) != fingerprint, "another source shares the cached code"


REINSTALL_PROBE = """
import json
import numpy as np
from tofcore.compiled import kernels as k
import numba
numba.njit(lambda: k.uniform(np.uint64(1), np.int64(2), np.int64(3), np.int64(4)))()  # jitted callers only
print(json.dumps({"hits": sum(k.uniform.stats.cache_hits.values()), "file": k.__file__}))
"""


@needs_numba
def test_compiled_kernels_outlive_a_reinstall_of_the_same_version(tmp_path):
    """A Blender extension's zip installed again replaces tofcore's folder (new files, new times): the kernels
    compiled before are loaded from the user's cache, not compiled again."""
    import shutil

    site = tmp_path / "site-packages"
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "PYTHONPATH")}
    env.update(PYTHONPATH=str(site), XDG_CACHE_HOME=str(tmp_path / "cache"))

    def install_and_probe() -> dict:
        shutil.rmtree(site, ignore_errors=True)
        shutil.copytree(ROOT / "tofcore", site / "tofcore", ignore=shutil.ignore_patterns("__pycache__"))
        out = subprocess.run([sys.executable, "-c", REINSTALL_PROBE], env=env, capture_output=True, text=True,
                             check=True, cwd=tmp_path, timeout=300)
        return json.loads(out.stdout.strip().splitlines()[-1])

    first, again = install_and_probe(), install_and_probe()
    assert first["file"].startswith(str(site)) and first["hits"] == 0
    assert again["hits"] == 1, "the reinstall compiled the kernels again"
