"""The installed commands: build the wheel, install it into a fresh venv, run ``tofcore`` and ``tofcore-batch``.

The wheel is built from a copy of the files a build reads (pyproject.toml, setup.py, MANIFEST.in,
README.md, tofcore/, batch/, presets/), so a stale ``build/`` folder in the checkout cannot leak into
it and the checkout is left untouched. The venv is clean (no ``--system-site-packages``: the project
venv holds an editable tofcore that would shadow the wheel); pip installs the wheel and NumPy, pinned to
the version this interpreter runs so that pip's cache or the machine's index serves it. Every command
runs with that venv's ``bin`` first on PATH, no PYTHONPATH, from a folder outside the repository.

Building needs setuptools >= 68 (pip's isolated build environment fetches it) and installing needs a
NumPy wheel: where pip can reach neither (offline, empty cache) the tests skip and say so. Any other
build or install failure is a packaging error and fails. About 20-30 s in all, most of it pip.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]

#: What the build reads: metadata files and the three source folders (batch/ installs as tofcore_batch).
BUILD_FILES = ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md")
BUILD_DIRS = ("tofcore", "batch", "presets")

#: pip output meaning "could not fetch a package" (offline, no cache): skip rather than fail.
_UNREACHABLE = re.compile(r"No matching distribution found|Could not find a version that satisfies|"
                          r"NewConnectionError|Failed to establish a new connection|Temporary failure in name "
                          r"resolution|Network is unreachable|Max retries exceeded|ConnectTimeout|ReadTimeout")


def _pip_or_skip(cmd: list[str], what: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        pytest.skip(f"{what}: pip took over {timeout:.0f} s (slow or no network)")
    if proc.returncode != 0:
        out = proc.stdout + proc.stderr
        if _UNREACHABLE.search(out):
            pytest.skip(f"{what}: pip cannot fetch what it needs (offline, no cache): {out.strip()[-400:]}")
        pytest.fail(f"{what} failed (exit {proc.returncode}):\n{out[-4000:]}")
    return proc


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    src = tmp_path_factory.mktemp("src")
    for name in BUILD_FILES:
        shutil.copy2(REPO / name, src / name)
    for name in BUILD_DIRS:
        shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    dist = tmp_path_factory.mktemp("dist")
    _pip_or_skip([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(dist), str(src)],
                 "building the wheel")
    wheels = sorted(dist.glob("tofcore-*.whl"))
    assert len(wheels) == 1, f"expected one tofcore wheel in {dist}, got {[w.name for w in wheels]}"
    return wheels[0]


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory) -> Path:
    """A fresh venv with the wheel and NumPy installed; returns its ``bin`` folder."""
    root = tmp_path_factory.mktemp("venv") / "venv"
    proc = subprocess.run([sys.executable, "-m", "venv", str(root)], capture_output=True, text=True, timeout=120)
    if proc.returncode != 0:
        pytest.skip(f"cannot create a venv (python -m venv: {proc.stderr.strip()[-300:]})")
    bin_dir = root / "bin"
    _pip_or_skip([str(bin_dir / "python"), "-m", "pip", "install", "--quiet", str(wheel), f"numpy=={np.__version__}"],
                 "installing the wheel")
    return bin_dir


@pytest.fixture
def run(venv, tmp_path):
    """``run("tofcore", "presets")``: a command of the venv, found on PATH, run in a folder outside the repo."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    env["PATH"] = os.pathsep.join([str(venv), env.get("PATH", "")])
    cwd = tmp_path / "cwd"
    cwd.mkdir()

    def call(command: str, *args: str, timeout: float = 240) -> subprocess.CompletedProcess:
        exe = shutil.which(command, path=env["PATH"])
        assert exe is not None and Path(exe).parent == venv, f"{command!r} is not a command of the venv: {exe}"
        return subprocess.run([exe, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)

    call.cwd = cwd
    return call


def _ok(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 0, f"exit {proc.returncode}\nstdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
    return proc.stdout


def test_wheel_holds_every_module_the_presets_and_the_commands(wheel):
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        info = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        entry_points = archive.read(info).decode()
    expected = {p.relative_to(REPO).as_posix() for p in (REPO / "tofcore").rglob("*.py")}
    expected |= {"tofcore_batch/" + p.relative_to(REPO / "batch").as_posix() for p in (REPO / "batch").rglob("*.py")}
    expected |= {f"tofcore/_presets/{p.name}" for p in (REPO / "presets").glob("*.toml")}
    expected |= {f"tofcore/gpu/{p.name}" for p in (REPO / "tofcore" / "gpu").glob("*.cu")}
    expected |= {f"tofcore_batch/examples/{p.name}" for p in (REPO / "batch" / "examples").glob("*.toml")}
    assert not expected - names, f"missing from {wheel.name}: {sorted(expected - names)}"
    assert not any(n.startswith("batch/") for n in names), "a bare top-level 'batch' package is in the wheel"
    # Through a module whose package imports nothing, so Ctrl-C is taken over before NumPy loads.
    assert "tofcore = tofcore_batch.entry:tofcore" in entry_points
    assert "tofcore-batch = tofcore_batch.entry:tofcore_batch" in entry_points


def test_tofcore_help_and_presets(run, venv):
    out = _ok(run("tofcore", "--help"))
    assert out.startswith("usage: tofcore ") and "{render,presets,warmup}" in out and "example:" in out
    assert "tofcore render --scene" in _ok(run("tofcore", "render", "--help"))
    names = [line.split()[0] for line in _ok(run("tofcore", "presets")).splitlines() if line.strip()]
    assert names == sorted(p.stem for p in (REPO / "presets").glob("*.toml"))
    # The import is the installed copy, not the checkout.
    where = _ok(run("python", "-c", "import tofcore, tofcore.sensor.presets as p; print(tofcore.__file__); print(p.PRESETS_DIR)"))
    module, presets_dir = where.split()
    assert Path(module).is_relative_to(venv.parent) and Path(presets_dir).name == "_presets"


def test_tofcore_render(run):
    # EXR too: the wheel's only dependencies are NumPy and tqdm (tofcore writes EXR with its own codec).
    proc = run("tofcore", "render", "--scene", "corner", "--preset", "kinect_v2", "--spp", "1", "--max-depth", "1",
               "--device", "cpu", "--formats", "exr,png,json", "--out", "out", "--quiet")
    _ok(proc)
    frame = json.loads((run.cwd / "out" / "frame.json").read_text())
    assert frame["metadata"]["sensor"]["name"] == "kinect_v2" and (frame["width"], frame["height"]) == (512, 424)
    for entry in frame["files"]:
        assert (run.cwd / "out" / entry["name"]).stat().st_size == entry["bytes"]
    assert {"depth_mm.png", "frame.exr"} <= {entry["name"] for entry in frame["files"]}
    bad = run("tofcore", "render", "--scene", "corner", "--preset", "kinect_v3", "--out", "out2", "--quiet")
    assert bad.returncode == 2 and "kinect_v2" in bad.stderr


def test_tofcore_batch_help_validate_run(run):
    out = _ok(run("tofcore-batch", "--help"))
    assert out.startswith("usage: tofcore-batch ") and "{run,validate,verify,compare,examples}" in out
    for command in ("run", "validate", "verify", "compare", "examples"):
        assert f"example:\n  tofcore-batch {command} " in _ok(run("tofcore-batch", command, "--help"))
    set_file = run.cwd / "tiny.toml"
    set_file.write_text("""
seed = 3
presets = ["kinect_v2"]
resolution_scale = 0.0625
[quality]
spp = 1
max_depth = 1
[output]
formats = ["png", "json"]
[[scenes]]
demo = "corner"
[[scenes.poses]]
suggested = true
""")
    out = _ok(run("tofcore-batch", "validate", str(set_file)))
    assert "ok — 1 scene(s), 1 view(s), 1 frame(s)" in out
    # A worker process of the local pool (spawn) under the console script.
    proc = run("tofcore-batch", "run", str(set_file), "--out", "dataset", "--workers", "1", "--quiet")
    _ok(proc)
    records = [json.loads(line) for line in (run.cwd / "dataset" / "index.jsonl").read_text().splitlines()]
    assert [r["status"] for r in records] == ["ok"], proc.stderr[-2000:]
    assert "ok: the index describes every frame folder" in _ok(run("tofcore-batch", "verify", "dataset"))
    bad = run("tofcore-batch", "validate", "missing.toml")
    assert bad.returncode == 2 and "missing.toml" in bad.stderr


def test_tofcore_batch_is_importable_and_ships_its_examples(run):
    code = ("import importlib.util, pathlib, tofcore_batch; "
            "print(sorted(p.name for p in pathlib.Path(tofcore_batch.__path__[0], 'examples').glob('*.toml'))); "
            "print(importlib.util.find_spec('batch'))")
    examples, bare = _ok(run("python", "-c", code)).splitlines()
    assert examples == repr(sorted(p.name for p in (REPO / "batch" / "examples").glob("*.toml")))
    assert bare == "None", "the wheel must not install a top-level 'batch'"


def test_installed_progress_and_blend_child_commands(run):
    """tqdm comes with the wheel; in a log (stderr a pipe) the commands print plain lines; the .blend child
    processes name tofcore_batch.blend (batch.blend does not exist in an installed copy)."""
    _ok(run("python", "-c", "import tqdm"))
    proc = run("tofcore", "render", "--scene", "corner", "--preset", "kinect_v2", "--spp", "2", "--max-depth", "1",
               "--device", "cpu", "--formats", "json", "--out", "out")
    _ok(proc)
    assert "\r" not in proc.stderr and proc.stderr.startswith("pass 1: 2/2 spp"), proc.stderr
    assert "wrote 4 files to out/" in proc.stdout  # frame.json and the three camera files
    spec = importlib.util.spec_from_file_location("child_commands", REPO / "tests" / "batch" / "test_child_commands.py")
    child = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(child)
    lines = _ok(run("python", "-c", child.CHILD_COMMANDS, "tofcore_batch")).splitlines()
    assert lines == ["tofcore_batch.blend inspect", "tofcore_batch.blend export"]


def test_installed_first_command_and_help_for_a_user_without_the_repository(run):
    """The README's first command after a plain ``pip install`` (no OpenEXR in the venv): the default formats,
    EXR included, are written by tofcore's own codec; with png/json it renders at the size asked. Help and the
    example sets need no checkout."""
    proc = run("tofcore", "render", "--scene", "corner", "--preset", "Kinect_V2", "--spp", "1", "--max-depth", "1",
               "--device", "cpu", "--out", "out_default", "--quiet")
    _ok(proc)
    assert (run.cwd / "out_default" / "frame.exr").is_file() and (run.cwd / "out_default" / "depth.exr").is_file()
    assert _ok(run("python", "-c", "import importlib.util as u; print(u.find_spec('OpenEXR'))")).strip() == "None"
    _ok(run("tofcore", "render", "--scene", "corner", "--resolution", "64x53", "--spp", "1", "--max-depth", "1",
            "--target-error", "5mm", "--device", "cpu", "--formats", "png,json", "--out", "out", "--quiet"))
    frame = json.loads((run.cwd / "out" / "frame.json").read_text())
    assert (frame["width"], frame["height"]) == (64, 53) and frame["stats"]["target_error_m"] == 0.005
    assert {"ir.png", "camera.json", "camera_opencv.yml", "camera_info.yaml"} <= {f["name"] for f in frame["files"]}
    for command in (("tofcore", "render", "--help"), ("tofcore-batch", "--help"), ("tofcore-batch", "run", "--help")):
        text = _ok(run(*command))
        assert "batch/" not in text and "``" not in text, command
    assert "wrote" in _ok(run("tofcore-batch", "examples", "--copy", "sets"))
    validate = run("tofcore-batch", "validate", "sets/demo_set.toml")    # the copied set names exr in its formats
    assert validate.returncode == 0 and "ok —" in validate.stdout, validate.stdout + validate.stderr
    bad = run("tofcore", "render", "--scene", "chair.glb", "--out", "o", "--formats", "json")
    assert bad.returncode == 2 and "chair.glb" in bad.stderr
