"""What a dataset hands to the user's tools: mesh scenes, [output] options, camera files, object names,
the transient histogram, and the example sets that ship with the package."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from batch.setfile import SetFileError, load_set
from batch_helpers import batch, read_index, write_set

trimesh = pytest.importorskip("trimesh")
OpenEXR = pytest.importorskip("OpenEXR")

SET = """
seed = 2
presets = ["kinect_v2"]
resolution_scale = 0.0625
[quality]
spp = 1
max_depth = 2
[output]
formats = ["exr", "json"]
exr_half = true
exr_channels = ["depth", "valid", "object_id"]
transient_bin_m = 0.05
transient_max_m = 12.0
[[scenes]]
mesh = "crate.glb"
[[scenes.poses]]
suggested = true
"""


def _crate(folder):
    box = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    box.visual = trimesh.visual.TextureVisuals(
        material=trimesh.visual.material.PBRMaterial(name="cardboard", baseColorFactor=[0.6, 0.5, 0.4, 1.0]))
    scene = trimesh.Scene()
    scene.add_geometry(box, node_name="crate")
    scene.export(str(folder / "crate.glb"))


def test_a_mesh_scene_with_output_options_writes_what_the_tools_read(tmp_path):
    _crate(tmp_path)
    set_file = write_set(tmp_path, SET)
    proc = batch("run", str(set_file), "--out", str(tmp_path / "ds"), "--workers", "1", "--quiet")
    assert proc.returncode == 0, proc.stderr
    (record,) = read_index(tmp_path / "ds")
    assert record["status"] == "ok" and record["source"]["kind"] == "mesh"
    assert record["objects"] == [{"id": 0, "name": "crate", "materials": ["cardboard"]}]
    assert record["settings"]["exr_half"] is True and record["settings"]["transient_bin_m"] == 0.05
    folder = tmp_path / "ds" / record["dir"]
    names = {entry["name"] for entry in record["files"]}
    assert {"frame.exr", "depth.exr", "transient.npy", "camera.json", "camera_opencv.yml", "camera_info.yaml",
            "frame.json"} <= names
    channels = OpenEXR.File(str(folder / "frame.exr"), separate_channels=True).channels()
    assert set(channels) == {"depth", "valid", "object_id"}
    assert all(c.pixels.dtype == np.float16 for c in channels.values())
    hist = np.load(folder / "transient.npy")
    assert hist.shape == (27, 32, 240) and hist.dtype == np.float32
    bop = json.loads((folder / "camera.json").read_text())
    assert (bop["width"], bop["height"], bop["depth_scale"]) == (32, 27, 1.0)
    import tofcore.output.dataset

    ref = tofcore.output.dataset.Dataset(tmp_path / "ds").frames()[0]
    assert ref.objects == {0: {"name": "crate", "materials": ["cardboard"]}}
    histogram, bin_m = ref.transient
    assert bin_m == 0.05 and np.array_equal(histogram, hist)
    # a dataset's depth is never the preview denoiser's (tofcore.sensor.denoise): only a render that asks
    assert json.loads((folder / "frame.json").read_text())["stats"]["preview_denoise"] is None
    assert "ok:" in batch("verify", str(tmp_path / "ds")).stdout


@pytest.mark.parametrize("change, message", [
    ('exr_channels = ["depth", "valid", "object_id"]', None),
    ('exr_channels = ["depth", "dpeth"]', r"output\.exr_channels: must be channels of frame\.exr for preset "
                                          r"'kinect_v2' \(unknown: \['dpeth'\]"),
    ("transient_max_m = 12.0", None),
    ("transient_max_m = 0.01", r"output\.transient_max_m: must be longer than transient_bin_m \(0\.05 m\)"),
    ("exr_half = true", None),
    ('exr_half = "yes"', r"output\.exr_half: must be true or false"),
])
def test_output_options_are_checked_when_the_set_is_read(tmp_path, change, message):
    _crate(tmp_path)
    key = change.split(" = ")[0]
    body = "\n".join(change if line.startswith(key + " =") else line for line in SET.splitlines())
    if message is None:
        assert load_set(write_set(tmp_path, body)).output[key] is not None
    else:
        with pytest.raises(SetFileError, match=message):
            load_set(write_set(tmp_path, body))


def test_sets_without_output_options_keep_their_job_ids(tmp_path):
    """Datasets made before these options resume: the options enter a job's id only when given."""
    from batch.jobs import expand

    _crate(tmp_path)
    plain = "\n".join(line for line in SET.splitlines()
                      if not line.startswith(("exr_half", "exr_channels", "transient")))
    spec = load_set(write_set(tmp_path, plain))
    assert spec.output == {}
    (job,) = expand(spec).jobs
    assert job.output == {}
    with_options = expand(load_set(write_set(tmp_path, SET, "with.toml"))).jobs[0]
    assert with_options.job_id != job.job_id


def test_the_example_sets_are_listed_printed_and_copied(tmp_path):
    listing = batch("examples")
    assert listing.returncode == 0 and listing.stdout.startswith("demo_set ") and "kinect_room " in listing.stdout
    shown = batch("examples", "--show", "demo_set")
    assert shown.returncode == 0 and 'description = "Demo scenes' in shown.stdout
    proc = batch("examples", "--copy", str(tmp_path / "sets"))
    assert proc.returncode == 0, proc.stderr
    assert sorted(os.listdir(tmp_path / "sets")) == ["demo_set.toml", "kinect_room.toml", "randomized_room.toml"]
    assert "ok —" in batch("validate", str(tmp_path / "sets" / "demo_set.toml")).stdout
    assert "1000 frame(s)" in batch("validate", str(tmp_path / "sets" / "randomized_room.toml")).stdout
    schema = batch("examples", "--schema").stdout
    assert "[output]" in schema and "``" not in schema and ".. code-block" not in schema
    bad = batch("examples", "--show", "nope")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "demo_set" in bad.stderr
