"""Bad input to ``python -m batch run | validate | compare`` and ``batch/blender_entry.py`` (issue 12,
classes 1–3): one line on stderr, exit code 2, nothing rendered, no dataset or report folder.

Every case runs the real entry point in a child process. argparse's usage lines are allowed before
its one error line.

1. malformed scene files (.npz) named in a set file or by ``compare --scene``;
2. resource limits (:mod:`tofcore.limits`) in set files and flags, checked before expanding or rendering;
3. flags (``--scheduler``, ``--workers``, quality flags) and physics values that would overflow.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

import tofcore
from batch_helpers import REPO, TINY, batch, has_module, write_set

KINECT = (REPO / "presets" / "kinect_v2.toml").read_text()


# --------------------------------------------------------------------------- helpers

def error_line(proc: subprocess.CompletedProcess) -> str:
    """The one error line, after checking exit code 2, no traceback and nothing else on stderr."""
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip() and not line.startswith(("usage:", " "))]
    assert len(lines) == 1, proc.stderr
    return lines[0]


def assert_refused(proc: subprocess.CompletedProcess, *needles: str, out: Path | None = None) -> str:
    line = error_line(proc)
    for needle in needles:
        assert needle in line, (needle, line)
    if out is not None:
        assert not out.exists(), sorted(p.name for p in out.iterdir())
    return line


def one_scene_set(folder: Path, scene: str, *, top: str = "", quality: str = "", name: str = "set.toml") -> Path:
    """A tiny set (1/16 resolution, 2 spp, png + json) with one ``[[scenes]]`` body."""
    return write_set(folder, f"seed = 3\n{top}\n{TINY}{quality}\n[output]\nformats = [\"png\", \"json\"]\n"
                             f"[[scenes]]\n{scene}\n", name=name)


LOOK = "[[scenes.poses]]\neye = [0.0, -2.0, 1.0]\ntarget = [0.0, 0.0, 1.0]\n"


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


def good_arrays(folder: Path, textured: bool = False) -> dict[str, np.ndarray]:
    scene = tofcore.demo_scene("plane")
    if textured:
        material = tofcore.Material(name="tex", roughness_texture=tofcore.Texture(np.full((2, 2), 0.3), name="r.png"))
        uvs = np.zeros((len(scene.vertices), 2), np.float32)
        scene = tofcore.Scene.from_arrays(scene.vertices, scene.triangles, None, [material], uvs=uvs, name="plane")
    with np.load(scene.save(folder / "good_source.npz")) as data:
        return {key: data[key] for key in data.files}


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for key, value in arrays.items():
            archive.writestr(f"{key}.npy", _npy(value))
    return path


def _header_without_materials(a: dict) -> dict:
    header = json.loads(str(a["header"]))
    del header["materials"]
    return dict(a, header=np.array(json.dumps(header)))


def _bytes(data: bytes):
    return lambda folder, path: path.write_bytes(data)


def _arrays(change, textured: bool = False):
    return lambda folder, path: write_npz(path, change(good_arrays(folder, textured)))


def _truncated(folder: Path, path: Path) -> None:
    data = write_npz(folder / "full.npz", good_arrays(folder)).read_bytes()
    path.write_bytes(data[: len(data) // 2])


BAD_SCENES = {
    "header_not_json": (_arrays(lambda a: dict(a, header=np.array("{not json"))), "header must be a JSON object"),
    "header_without_materials": (_arrays(_header_without_materials), "header must have the key 'materials'"),
    "missing_vertices": (_arrays(lambda a: {k: v for k, v in a.items() if k != "vertices"}),
                         "must hold the array 'vertices'"),
    "truncated_zip": (_truncated, "a damaged or truncated zip archive"),
    "renamed_npy": (_bytes(_npy(np.zeros((4, 3), np.float32))), "a single .npy array (numpy.save)"),
    "texture_without_name": (_arrays(lambda a: {k: v for k, v in a.items() if not k.startswith("texture_name/")},
                                     textured=True), "array 'texture_name/0/roughness_texture' must be present"),
    "vertices_wrong_dtype": (_arrays(lambda a: dict(a, vertices=np.array(["a", "b", "c"]))),
                             "vertices: must be a numeric array, got dtype <U1"),
    "random_bytes": (_bytes(np.random.default_rng(21).bytes(2048)), "a file that is not a zip archive"),
    "empty_file": (_bytes(b""), "got an empty file"),
    "pose_scaled": (_arrays(lambda a: dict(a, header=np.array(json.dumps(
        {**json.loads(str(a["header"])), "metadata": {"world_from_sensor": (2 * np.eye(4)).tolist()}})))),
        "header metadata.world_from_sensor must be a rigid transform"),
}


def bad_scene(folder: Path, case: str) -> Path:
    make, _ = BAD_SCENES[case]
    path = folder / f"{case}.npz"
    make(folder, path)
    return path


# --------------------------------------------------------------------------- class 1: scene files

@pytest.mark.parametrize("case", sorted(BAD_SCENES))
def test_validate_names_the_bad_scene_file(tmp_path, case):
    path = bad_scene(tmp_path, case)
    set_file = one_scene_set(tmp_path, f'npz = "{path.name}"\n{LOOK}')
    proc = batch("validate", str(set_file))
    line = assert_refused(proc, f"{set_file}:", "scenes[0].npz:", str(path), BAD_SCENES[case][1])
    assert line.startswith("error: ")


@pytest.mark.parametrize("case", ["header_not_json", "truncated_zip", "empty_file", "pose_scaled"])
def test_run_refuses_the_bad_scene_file_before_writing_anything(tmp_path, case):
    """Before: the set was accepted and every frame failed in the workers (exit 1, a dataset of failures)."""
    path = bad_scene(tmp_path, case)
    set_file = one_scene_set(tmp_path, f'npz = "{path.name}"\n{LOOK}')
    proc = batch("run", str(set_file), "--out", str(tmp_path / "dataset"), "--quiet")
    assert_refused(proc, "scenes[0].npz:", str(path), BAD_SCENES[case][1], out=tmp_path / "dataset")


@pytest.mark.parametrize("case", ["header_without_materials", "renamed_npy", "random_bytes"])
def test_compare_names_the_bad_scene_file(tmp_path, case):
    path = bad_scene(tmp_path, case)
    proc = batch("compare", "--scene", str(path), "--presets", "kinect_v2", "--eye", "0,-2,1", "--target", "0,0,1",
                 "--resolution-scale", "0.0625", "--spp", "1", "--out", str(tmp_path / "report"))
    assert_refused(proc, f"error: --scene: {path}: ", BAD_SCENES[case][1], out=tmp_path / "report")


def test_zip_bomb_in_a_set_is_refused_unread(tmp_path):
    arrays = good_arrays(tmp_path)
    arrays["vertices"] = np.zeros((2_000_000, 3), np.float32)   # 24 MB that deflate to ~24 kB
    path = write_npz(tmp_path / "bomb.npz", arrays)
    set_file = one_scene_set(tmp_path, f'npz = "{path.name}"\n{LOOK}')
    proc = batch("validate", str(set_file), env={"TOFCORE_MAX_SCENE_BYTES": "1000000"})
    assert_refused(proc, str(path), "array 'vertices' (uncompressed size from the zip directory) must be at most "
                   "1,000,000 bytes", "TOFCORE_MAX_SCENE_BYTES=N", "got 24,000,128 bytes")


# --------------------------------------------------------------------------- class 2: resource limits

def test_resolution_scale_200_is_refused_while_parsing(tmp_path):
    set_file = write_set(tmp_path, 'resolution_scale = 200\n[[scenes]]\ndemo = "plane"\n')
    for command in (["validate"], ["run", "--out", str(tmp_path / "dataset")]):
        proc = batch(*command[:1], str(set_file), *command[1:])
        assert_refused(proc, f"{set_file}:1: resolution_scale: cannot scale the sensor 'kinect_v2' by 200.0: "
                             "width x height must be at most 16,777,216 pixels", "TOFCORE_MAX_PIXELS=N",
                       "got 1.024e+05 x 8.48e+04", out=tmp_path / "dataset")


def test_a_hundred_million_random_poses_are_refused(tmp_path):
    set_file = one_scene_set(tmp_path, 'demo = "plane"\n[[scenes.poses]]\ncount = 100000000\nbox_min = [0, -3, 1]\n'
                                       'box_max = [1, -2, 2]\ntarget = [0, 0, 1]\n')
    proc = batch("validate", str(set_file))
    assert_refused(proc, "scenes[0].poses[0].count: must be at most 100,000 frames (limit max_set_frames",
                   "TOFCORE_MAX_SET_FRAMES=N", "got 100000000 poses")


def test_a_billion_frame_range_is_refused_before_it_is_built(tmp_path):
    (tmp_path / "shot.blend").write_bytes(b"")  # parsing only checks that the file is there
    set_file = one_scene_set(tmp_path, 'blend = "shot.blend"\ncameras = ["Cam"]\nframes = "1-1000000000"\n')
    proc = batch("validate", str(set_file))
    assert_refused(proc, "scenes[0].frames: the frame ranges must be at most 100,000 frames",
                   "TOFCORE_MAX_SET_FRAMES=N", "got '1-1000000000' (1,000,000,000 frames)")


def test_frames_of_the_whole_set_are_counted_before_expanding(tmp_path):
    set_file = write_set(tmp_path, 'presets = ["kinect_v2", "o3d303"]\n' + TINY
                         + '[[scenes]]\ndemo = "plane"\n[[scenes.poses]]\ncount = 3\nbox_min = [0, -3, 1]\n'
                           'box_max = [1, -2, 2]\ntarget = [0, 0, 1]\n')
    proc = batch("validate", str(set_file), env={"TOFCORE_MAX_SET_FRAMES": "5"})
    assert_refused(proc, "scenes: must be at most 5 frames", "got 6 frames (views x frames x presets, all scenes)")


@pytest.mark.parametrize("quality, needle", [
    ("spp = 1000000000", "quality.spp: must be at most 1,048,576 samples per pixel (limit max_spp"),
    ("max_depth = 1000", "quality.max_depth: must be at most 64 surface vertices (limit max_depth"),
])
def test_quality_limits_in_a_set_file(tmp_path, quality, needle):
    set_file = write_set(tmp_path, f'[quality]\n{quality}\n[[scenes]]\ndemo = "plane"\n')
    proc = batch("validate", str(set_file))
    assert_refused(proc, f"{set_file}:2: ", needle, quality.split(" = ")[1])


def test_huge_camera_override_is_refused_while_parsing(tmp_path):
    set_file = write_set(tmp_path, 'presets = [{ preset = "kinect_v2", overrides = { "camera.width" = 100000, '
                                   '"camera.height" = 100000 } }]\n[[scenes]]\ndemo = "plane"\n')
    proc = batch("validate", str(set_file))
    assert_refused(proc, "presets[0].overrides: invalid override: Sensor.replace [camera]: width x height must be at "
                   "most 16,777,216 pixels", "got 100000 x 100000 = 10,000,000,000")


def test_render_memory_is_checked_per_preset(tmp_path):
    set_file = write_set(tmp_path, '[quality]\nmax_depth = 8\n[[scenes]]\ndemo = "plane"\n')
    proc = batch("validate", str(set_file), env={"TOFCORE_MAX_RENDER_BYTES": "1000000"})
    assert_refused(proc, "presets: preset 'kinect_v2': the estimated render memory (512 x 424 pixels, 9 raw images, "
                   "max_depth 8) must be at most 1,000,000 bytes", "TOFCORE_MAX_RENDER_BYTES=N")


@pytest.mark.parametrize("flag, value, needle", [
    ("--workers", "100000", "argument --workers: must be at most {MAX_WORKERS} processes (limit max_workers; raise it with "
                            "the environment variable TOFCORE_MAX_WORKERS=N), got '100000'"),
    ("--threads-per-worker", "100000", "argument --threads-per-worker: must be at most {MAX_WORKERS} processes"),
])
def test_worker_counts_are_checked(tmp_path, flag, value, needle):
    from tofcore.limits import MAX_WORKERS  # 4 × the usable CPUs here, at least 8
    needle = needle.replace("{MAX_WORKERS}", f"{MAX_WORKERS.value:,}")
    set_file = one_scene_set(tmp_path, 'demo = "plane"')
    proc = batch("run", str(set_file), "--out", str(tmp_path / "dataset"), flag, value)
    assert_refused(proc, needle, out=tmp_path / "dataset")


# --------------------------------------------------------------------------- class 3: flags and physics

@pytest.mark.parametrize("address", ["not a url", "notaurl", "tcp://scheduler", "tcp://host:99999"])
def test_scheduler_address_is_checked_before_anything(tmp_path, address):
    set_file = one_scene_set(tmp_path, 'demo = "plane"')
    proc = batch("run", str(set_file), "--out", str(tmp_path / "dataset"), "--scheduler", address)
    assert_refused(proc, "argument --scheduler: must be a Dask scheduler address tcp://HOST:PORT", repr(address),
                   out=tmp_path / "dataset")


@pytest.mark.parametrize("flags, needle", [
    (["--max-depth", "1000"], "argument --max-depth: must be at most 64 surface vertices"),
    (["--spp", "1000000000"], "argument --spp: must be at most 1,048,576 samples per pixel"),
    (["--resolution-scale", "300"], "error: --resolution-scale: cannot scale the sensor 'kinect_v2' by 300.0: "
                                    "width x height must be at most 16,777,216 pixels"),
    (["--time-budget", "-5"], "argument --time-budget: must be a finite number > 0 (seconds), got '-5'"),
    (["--ambient", "-1"], "argument --ambient: must be a finite number >= 0, at most 1e+30"),
    (["--eye", "nan,0,0", "--target", "0,0,1"], "argument --eye: must be three comma-separated numbers"),
    (["--presets", "preset.toml"], "error: --presets: invalid preset: "),
])
def test_compare_flags_are_checked_before_rendering(tmp_path, flags, needle):
    preset = tmp_path / "preset.toml"
    preset.write_text(KINECT.replace("responsivity = 7e7", "responsivity = 1e300"))
    proc = batch("compare", "--scene", "plane", "--out", str(tmp_path / "report"), "--resolution-scale", "0.0625",
                 "--spp", "1", *flags, cwd=tmp_path)
    assert_refused(proc, needle, out=tmp_path / "report")


@pytest.mark.parametrize("edit, needle", [
    (("responsivity = 7e7", "responsivity = 1e300"),
     "[readout]: responsivity must be at most 1e+30 (e-/s per W m^-2 sr^-1), got 1e+300"),
    (("intensity_w_sr = 1.0 ", "intensity_w_sr = 1e308 "),
     "[[leds]] #1: intensity_w_sr must be at most 1e+30 (W/sr), got 1e+308"),
])
def test_overflowing_physics_in_a_preset_names_the_key(tmp_path, edit, needle):
    preset = tmp_path / "hot.toml"
    preset.write_text(KINECT.replace(*edit))
    assert preset.read_text() != KINECT
    set_file = write_set(tmp_path, 'presets = ["hot.toml"]\n[[scenes]]\ndemo = "plane"\n')
    proc = batch("validate", str(set_file))
    assert_refused(proc, f"{set_file}:1: presets[0]: invalid preset: {preset} ", needle)


def test_overflowing_physics_in_an_override_names_the_key(tmp_path):
    set_file = write_set(tmp_path, 'presets = [{ preset = "kinect_v2", overrides = { "readout.responsivity" = 1e300 '
                                   '} }]\n[[scenes]]\ndemo = "plane"\nambient_w_m2_sr = 1.0\n')
    proc = batch("validate", str(set_file))
    assert_refused(proc, "presets[0].overrides: invalid override: Sensor.replace [readout]: responsivity must be at "
                   "most 1e+30", "got 1e+300")


def test_ambient_that_would_overflow_in_a_set_file(tmp_path):
    set_file = one_scene_set(tmp_path, 'demo = "plane"\nambient_w_m2_sr = 1e308')
    proc = batch("validate", str(set_file))
    assert_refused(proc, "scenes[0].ambient_w_m2_sr: must be at most 1e+30 (W m^-2 sr^-1), got 1e+308")


# --------------------------------------------------------------------------- the Blender entry script

EMULATE_BLENDER = r"""
import runpy
import sys

import bpy

blend, script, *rest = sys.argv[1:]
if blend == "NEW":
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.save_as_mainfile(filepath=rest[0])
    sys.exit(0)
bpy.ops.wm.open_mainfile(filepath=blend, load_ui=False)
sys.argv = ["blender", "-b", blend, "--python", script, "--", *rest]   # what Blender's sys.argv holds
try:
    runpy.run_path(script, run_name="__main__")
except SystemExit as exc:
    sys.exit(exc.code)
"""


@pytest.mark.bpy
@pytest.mark.skipif(not has_module("bpy"), reason="needs the bpy module")
def test_blender_entry_checks_its_flags(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    blend = tmp_path / "empty.blend"
    made = subprocess.run([sys.executable, "-c", EMULATE_BLENDER, "NEW", "-", str(blend)], env=env,
                          capture_output=True, text=True, timeout=120)
    assert made.returncode == 0 and blend.is_file(), made.stderr
    script = str(REPO / "batch" / "blender_entry.py")
    for flags, needle in (
            (["--frames", "1-1000000000"], "error: --frames: the frame ranges must be at most 100,000 frames"),
            (["--seed", "-1"], "argument --seed: must be an integer >= 0, got '-1'"),
            (["--formats", "exr,gif"], "argument --formats: must be a comma list of one or more of exr, png, ply, "
                                       "json, got 'exr,gif' (unknown: 'gif')")):
        proc = subprocess.run([sys.executable, "-c", EMULATE_BLENDER, str(blend), script, "--out",
                               str(tmp_path / "dataset"), *flags], cwd=tmp_path, env=env, capture_output=True,
                              text=True, timeout=240)
        assert_refused(proc, needle, out=tmp_path / "dataset")

