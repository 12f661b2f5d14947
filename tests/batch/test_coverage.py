"""A frame with few valid pixels: ok (its files are whole) but its record says why, and so does the run."""

from __future__ import annotations

from batch_helpers import TINY, batch, read_index, write_set


def test_a_frame_that_sees_nothing_is_recorded_with_a_warning(tmp_path):
    set_file = write_set(tmp_path, 'seed = 1\npresets = ["kinect_v2"]\n' + TINY + """
[[scenes]]
demo = "corner"
[[scenes.poses]]
suggested = true
[[scenes.poses]]
eye = [0.0, -3.0, 1.0]
target = [0.0, -6.0, 1.0]
""")
    proc = batch("run", str(set_file), "--out", str(tmp_path / "d"), "--quiet")
    assert proc.returncode == 0, proc.stderr
    records = {r["view"]["label"]: r for r in read_index(tmp_path / "d")}
    assert records["pose0"]["status"] == "ok" and records["pose0"]["warning"] is None
    away = records["pose1"]
    assert away["status"] == "ok" and away["valid_fraction"] == 0.0
    assert away["warning"].startswith("only 0.0 % of the pixels are valid (fewer than 10 %): 100 % see no surface")
    assert f"    warning: {away['warning']}" in proc.stderr
    assert "1 frame(s) ok but with few valid pixels ('warning' in index.jsonl), e.g. corner/pose1/kinect_v2: " \
        in proc.stderr


def test_a_mesh_scenes_suggested_view_is_framed_for_every_preset_of_the_scene(tmp_path):
    """One view for the scene's presets: their narrowest field of view, the range all of them measure."""
    import numpy as np
    import pytest

    trimesh = pytest.importorskip("trimesh")
    import tofcore
    from batch.jobs import expand
    from batch.setfile import load_set

    trimesh.creation.box(extents=[6.0, 0.1, 3.0]).export(str(tmp_path / "wall.stl"))  # Z up: a wall facing −Y
    set_file = write_set(tmp_path, 'presets = ["kinect_v2", "o3d303"]\n' + TINY
                         + '[[scenes]]\nmesh = "wall.stl"\n[[scenes.poses]]\nsuggested = true\n')
    jobs = expand(load_set(set_file)).jobs
    scene = tofcore.load_mesh(tmp_path / "wall.stl")
    framed = tofcore.suggested_pose(scene, [tofcore.load_preset("kinect_v2"), tofcore.load_preset("o3d303")])
    assert len(jobs) == 2 and all(np.allclose(job.world_from_sensor, framed) for job in jobs)
    assert not np.allclose(framed, scene.metadata["world_from_sensor"])
