"""A .blend scene through ``python -m batch run`` and through the emulated ``blender -b … --python
batch/blender_entry.py -- …``: the same job ids and bitwise the same frames.

The .blend is made in a child process with bpy (a wall, a cube, a ToF camera and a second camera, both
moving between frames 1 and 3). This process never imports bpy.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from batch_helpers import REPO, assert_same_frames, batch, has_module, read_index, stray_files, write_set

pytestmark = [pytest.mark.bpy, pytest.mark.skipif(not has_module("bpy"), reason="needs the bpy module")]

MAKE_BLEND = r"""
import sys
import bpy

out = sys.argv[-1]
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene


def mesh_object(name, vertices, faces):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices, [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    scene.collection.objects.link(obj)
    return obj


mesh_object("Wall", [(-2, 0, 0), (2, 0, 0), (2, 0, 3), (-2, 0, 3)], [(0, 3, 2, 1)])
(x0, y0, z0), (x1, y1, z1) = (-0.3, -1.0, 1.2), (0.3, -0.4, 1.8)
mesh_object("Cube", [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0), (x0, y0, z1), (x1, y0, z1),
                     (x1, y1, z1), (x0, y1, z1)],
            [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)])
for name, x in (("TofCam", 0.0), ("Other", 0.5)):
    cam = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    scene.collection.objects.link(cam)
    cam.rotation_euler = (1.5708, 0.0, 0.0)
    cam.location = (x, -2.5, 1.5)
    cam.keyframe_insert("location", frame=1)
    cam.location = (x + 0.3, -2.5, 1.6)
    cam.keyframe_insert("location", frame=3)
addon = False
try:  # mark TofCam as a ToF camera when the add-on in this checkout registers
    sys.path.insert(0, sys.argv[-2])
    import addon as tof_addon
    tof_addon.register()
    bpy.data.objects["TofCam"].data.tof.enabled = True
    addon = True
except Exception as exc:
    print("add-on not registered:", exc)
scene.frame_set(1)
bpy.ops.wm.save_as_mainfile(filepath=out)
print("ADDON", addon)
"""

EMULATE_BLENDER = r"""
import runpy
import sys

import bpy

blend, script, *rest = sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=blend, load_ui=False)
sys.argv = ["blender", "-b", blend, "--python", script, "--", *rest]   # what Blender's sys.argv holds
try:
    runpy.run_path(script, run_name="__main__")
except SystemExit as exc:
    sys.exit(exc.code)
"""


@pytest.fixture(scope="module")
def blend_file(tmp_path_factory) -> tuple[Path, bool]:
    folder = tmp_path_factory.mktemp("blend")
    path = folder / "scene.blend"
    proc = subprocess.run([sys.executable, "-c", MAKE_BLEND, str(REPO), str(path)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0 and path.is_file(), proc.stderr
    return path, "ADDON True" in proc.stdout


def test_plain_python_and_blender_entry_give_the_same_frames(tmp_path, blend_file):
    blend, _ = blend_file
    set_file = write_set(tmp_path, f"""
seed = 4
presets = ["kinect_v2", "xtion2"]
resolution_scale = 0.0625
[quality]
spp = 2
max_depth = 2
[[scenes]]
blend = "{blend}"
cameras = ["TofCam"]
frames = "1-2"
""")
    plain = batch("run", str(set_file), "--out", str(tmp_path / "plain"), "--quiet")
    assert plain.returncode == 0, plain.stderr
    records = read_index(tmp_path / "plain")
    assert [r["view"]["label"] + "/" + r["preset"] for r in records] == [
        "TofCam@1/kinect_v2", "TofCam@1/xtion2", "TofCam@2/kinect_v2", "TofCam@2/xtion2"]
    assert records[0]["source"]["kind"] == "blend" and len(records[0]["source"]["sha256"]) == 64
    # The camera moved between frames 1 and 2: the pose comes from the exporter, per frame.
    assert records[0]["world_from_sensor"] != records[2]["world_from_sensor"]
    assert abs(records[0]["world_from_sensor"][0][3]) < 1e-6

    env = dict(os.environ, PYTHONPATH=str(REPO))
    entry = subprocess.run(
        [sys.executable, "-c", EMULATE_BLENDER, str(blend), str(REPO / "batch" / "blender_entry.py"),
         "--preset", "kinect_v2,xtion2", "--out", str(tmp_path / "blender"), "--cameras", "TofCam",
         "--frames", "1-2", "--spp", "2", "--max-depth", "2", "--seed", "4", "--resolution-scale", "0.0625",
         "--quiet"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)
    assert entry.returncode == 0, entry.stderr
    assert "in-process executor (no worker processes)" in entry.stderr
    assert assert_same_frames(tmp_path / "plain", tmp_path / "blender") == 4
    assert stray_files(tmp_path / "blender") == []

    # Rerunning the Blender way on the dataset made the plain way renders nothing: the same jobs.
    again = subprocess.run(
        [sys.executable, "-c", EMULATE_BLENDER, str(blend), str(REPO / "batch" / "blender_entry.py"),
         "--preset", "kinect_v2,xtion2", "--out", str(tmp_path / "plain"), "--cameras", "TofCam",
         "--frames", "1-2", "--spp", "2", "--max-depth", "2", "--seed", "4", "--resolution-scale", "0.0625"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)
    assert again.returncode == 0 and "nothing to render" in again.stderr, again.stderr


def test_default_cameras_and_bad_camera_names(tmp_path, blend_file):
    blend, addon = blend_file
    set_file = write_set(tmp_path, f'[[scenes]]\nblend = "{blend}"\n')
    proc = batch("validate", str(set_file), "--list")
    assert proc.returncode == 0, proc.stderr
    cameras = {line.split()[1].split("/")[1] for line in proc.stdout.splitlines() if line[:1].isalnum()
               and "/" in line}
    assert cameras == ({"TofCam@1"} if addon else {"Other@1", "TofCam@1"})
    bad = write_set(tmp_path, f'[[scenes]]\nblend = "{blend}"\ncameras = ["TofCam", "Nope"]\n', "bad.toml")
    proc = batch("validate", str(bad))
    assert proc.returncode == 2
    assert "scenes[0].cameras[1]: camera 'Nope' is not a camera object" in proc.stderr
    assert "['Other', 'TofCam']" in proc.stderr


@pytest.mark.dask
@pytest.mark.skipif(not has_module("distributed"), reason="needs dask[distributed]")
def test_dask_workers_export_blend_views_in_a_child_process(tmp_path, blend_file):
    """bpy works only on a process's main thread; Dask runs tasks on other threads."""
    blend, _ = blend_file
    set_file = write_set(tmp_path, f"""
presets = ["kinect_v2"]
resolution_scale = 0.0625
[quality]
spp = 2
max_depth = 2
[[scenes]]
blend = "{blend}"
cameras = ["Other"]
""")
    local = batch("run", str(set_file), "--out", str(tmp_path / "local"), "--quiet")
    assert local.returncode == 0, local.stderr
    dask = batch("run", str(set_file), "--out", str(tmp_path / "dask"), "--dask", "local", "--quiet")
    assert dask.returncode == 0, dask.stderr
    assert assert_same_frames(tmp_path / "local", tmp_path / "dask") == 1


def test_blender_entry_device(tmp_path, blend_file):
    """The Blender entry renders in its own process: --device gpu needs a GPU there, auto falls back."""
    blend, _ = blend_file
    env = dict(os.environ, PYTHONPATH=str(REPO), CUDA_VISIBLE_DEVICES="")
    env.pop("TOF_BATCH_FAKE_GPU", None)

    def entry(device: str, out: Path) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-c", EMULATE_BLENDER, str(blend), str(REPO / "batch" / "blender_entry.py"),
             "--preset", "kinect_v2", "--out", str(out), "--cameras", "TofCam", "--spp", "2", "--max-depth", "2",
             "--resolution-scale", "0.0625", "--device", device, "--quiet"],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)

    gpu = entry("gpu", tmp_path / "gpu")
    assert gpu.returncode == 2, gpu.stderr
    errors = [line for line in gpu.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and errors[0].startswith("error: --device gpu: no usable GPU: GPU: ")
    assert "Traceback" not in gpu.stderr and not (tmp_path / "gpu").exists()
    auto = entry("auto", tmp_path / "auto")
    assert auto.returncode == 0, auto.stderr
    (record,) = read_index(tmp_path / "auto")
    assert record["device"]["name"] == "cpu" and record["device"]["requested"] == "auto"
    assert record["device"]["fallback_reason"].startswith("GPU: ")


EMBEDDED_SCRIPT = r"""
import sys
import bpy

blend, marker = sys.argv[-2], sys.argv[-1]
bpy.ops.wm.read_factory_settings(use_empty=True)
text = bpy.data.texts.new("evil.py")
text.write(f"open({marker!r}, 'w').write('ran')\n")
text.use_module = True   # a registered text block: Blender runs it when the file is opened with scripts
bpy.ops.wm.save_as_mainfile(filepath=blend)
"""

OPEN_IT = r"""
import sys
import bpy
sys.path.insert(0, sys.argv[-2])
bpy.context.preferences.filepaths.use_scripts_auto_execute = True   # the most permissive process
from batch import blend
blend.open_file(sys.argv[-1])
print("opened", len(bpy.data.texts))
"""


def test_scene_files_never_run_their_scripts(tmp_path):
    """A .blend with a registered text block, opened by the batch with auto-run enabled: the script does not
    run (issue 12, class 6)."""
    blend_path, marker = tmp_path / "evil.blend", tmp_path / "ran.txt"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    made = subprocess.run([sys.executable, "-c", EMBEDDED_SCRIPT, str(blend_path), str(marker)],
                          capture_output=True, text=True, env=env, timeout=300)
    assert made.returncode == 0, made.stderr[-2000:]
    assert not marker.exists()
    opened = subprocess.run([sys.executable, "-c", OPEN_IT, str(REPO), str(blend_path)],
                            capture_output=True, text=True, env=env, timeout=300)
    assert opened.returncode == 0, opened.stderr[-2000:]
    assert "opened 1" in opened.stdout
    assert not marker.exists(), "the scene file's script ran"


def test_tofcore_render_takes_a_blend_file(tmp_path, blend_file):
    """``tofcore render --scene FILE.blend``: exported by the add-on's exporter in a child process (this one never
    imports bpy); the file has no active camera, so it asks for one or for --eye/--target."""
    blend, _ = blend_file
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    base = [sys.executable, "-m", "tofcore", "render", "--scene", str(blend), "--resolution-scale", "0.0625",
            "--spp", "1", "--max-depth", "1", "--formats", "json", "--quiet"]
    no_camera = subprocess.run([*base, "--out", str(tmp_path / "a")], capture_output=True, text=True, env=env,
                               timeout=300)
    assert no_camera.returncode == 2 and "has no active camera" in no_camera.stderr, no_camera.stderr
    proc = subprocess.run([*base, "--out", str(tmp_path / "b"), "--eye", "0,-2.5,1.5", "--target", "0,0,1.5"],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    import json

    document = json.loads((tmp_path / "b" / "frame.json").read_text())
    assert {o["name"] for o in document["metadata"]["objects"]} == {"Wall", "Cube"}
