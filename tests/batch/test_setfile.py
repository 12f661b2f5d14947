"""batch.setfile: the schema, its error messages (file, line, key path, value), scaled sensors."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import tofcore
from batch.setfile import SetFileError, load_set, parse_frames
from batch_helpers import TINY, batch, write_set

GOOD = """
description = "two scenes"
seed = 3
presets = ["kinect_v2", { preset = "o3d303", label = "o3d_clean", overrides = { "noise.model" = "none" } }]
""" + TINY + """
[output]
formats = ["exr", "png"]

[[scenes]]
demo = "corner"
[[scenes.poses]]
suggested = true
[[scenes.poses]]
world_from_sensor = [[1, 0, 0, 0], [0, 0, 1, -2], [0, -1, 0, 1.5], [0, 0, 0, 1]]

[[scenes]]
name = "room_random"
demo = "room"
presets = ["xtion2"]
[scenes.quality]
spp = 4
[[scenes.poses]]
count = 3
box_min = [-1.0, -1.5, 1.0]
box_max = [1.0, -1.0, 2.0]
target = [0.0, 1.0, 0.8]
seed = 5
"""


def test_a_good_set_is_parsed_with_its_defaults_and_overrides(tmp_path):
    spec = load_set(write_set(tmp_path, GOOD))
    assert spec.seed == 3 and spec.description == "two scenes"
    assert spec.formats == ("exr", "png", "json")  # json (the done record) is always written
    corner, room = spec.scenes
    assert [p.label for p in corner.presets] == ["kinect_v2", "o3d_clean"]
    assert corner.presets[1].sensor.noise.model == "none"
    assert corner.presets[0].sensor.camera.width == 32  # 512 / 16
    assert [p.kind for p in corner.poses] == ["suggested", "matrix"]
    assert corner.quality.spp == 2 and room.quality.spp == 4 and room.quality.max_depth == 2
    assert room.name == "room_random" and [p.label for p in room.presets] == ["xtion2"]
    assert room.poses[0].count == 3 and room.poses[0].seed == 5


def _error(tmp_path: Path, body: str) -> str:
    with pytest.raises(SetFileError) as info:
        load_set(write_set(tmp_path, body))
    return str(info.value)


def test_unknown_key_names_file_line_path_and_the_valid_keys(tmp_path):
    message = _error(tmp_path, """seed = 1
[[scenes]]
demo = "corner"
[[scenes]]
demo = "plane"
pose = 3
""")
    assert message.startswith(f"{tmp_path / 'set.toml'}:6: scenes[1].pose: unknown key 'pose'")
    assert "did you mean 'poses'?" in message and "'cameras'" in message


def test_unknown_key_in_a_nested_table_has_its_line(tmp_path):
    message = _error(tmp_path, """[[scenes]]
demo = "corner"
[[scenes.poses]]
eye = [0, -2, 1]
target = [0, 0, 1]
upp = [0, 0, 1]
""")
    assert re.search(r"set\.toml:6: scenes\[0\]\.poses\[0\]\.upp: unknown key 'upp'", message), message


def test_wrong_type_names_the_rule_and_value(tmp_path):
    message = _error(tmp_path, """[quality]
spp = "many"
[[scenes]]
demo = "corner"
""")
    assert message.endswith("set.toml:2: quality.spp: must be an integer >= 1, got 'many'")
    message = _error(tmp_path, """[[scenes]]
demo = "corner"
[[scenes.poses]]
eye = [0, -2]
target = [0, 0, 1]
""")
    assert "set.toml:4: scenes[0].poses[0].eye: must be a list of 3 finite numbers" in message
    assert "[0, -2]" in message


def test_missing_file_names_the_key_and_the_absolute_path(tmp_path):
    message = _error(tmp_path, """[[scenes]]
npz = "scenes/missing.npz"
""")
    assert message == f"{tmp_path / 'set.toml'}:2: scenes[0].npz: file not found: {tmp_path / 'scenes/missing.npz'}"


def test_unknown_preset_lists_the_presets(tmp_path):
    message = _error(tmp_path, """presets = ["kinect_v2", "kinect_v3"]
[[scenes]]
demo = "corner"
""")
    assert "set.toml:1: presets[1]: unknown preset 'kinect_v3' (did you mean 'kinect_v2'?)" in message
    assert str(tofcore.list_presets()) in message


def test_invalid_override_is_caught_before_rendering(tmp_path):
    message = _error(tmp_path, """presets = [{ preset = "kinect_v2", overrides = { "noise.model" = "loud" } }]
[[scenes]]
demo = "corner"
""")
    assert "presets[0].overrides: invalid override" in message and "'loud'" in message


def test_syntax_error_carries_the_line(tmp_path):
    message = _error(tmp_path, "seed = 1\n[[scenes]\ndemo = 'x'\n")
    assert "invalid TOML" in message and "line 2" in message


@pytest.mark.parametrize("body, fragment", [
    ("[[scenes]]\ndemo = 'corner'\nnpz = 'a.npz'\n", "scenes[0]: needs exactly one of 'demo', 'npz', 'mesh', 'blend'"),
    ("[[scenes]]\ndemo = 'kitchen'\n", "scenes[0].demo: must be one of ['plane', 'corner', 'box_on_wall', 'room']"),
    ("seed = -1\n[[scenes]]\ndemo = 'corner'\n", "seed: must be an integer >= 0, got -1"),
    ("[[scenes]]\ndemo = 'corner'\ncameras = ['Cam']\n", "scenes[0].cameras: only a blend scene has cameras"),
    ("[[scenes]]\ndemo = 'corner'\n[[scenes.poses]]\nworld_from_sensor = [[1, 0, 0, 0], [0, 1, 0, 0], "
     "[0, 0, 1, 0], [1, 2, 3, 1]]\n", "scenes[0].poses[0].world_from_sensor: must be a 4x4 rigid transform"),
    ("[[scenes]]\ndemo = 'corner'\n[[scenes]]\ndemo = 'corner'\n", "scene name 'corner' is used twice"),
    ("seed = 1\n", "scenes: missing"),
    ("[output]\nformats = ['tiff']\n[[scenes]]\ndemo = 'corner'\n", "output.formats: must be a non-empty list"),
])
def test_other_schema_errors(tmp_path, body, fragment):
    assert fragment in _error(tmp_path, body)


def test_relative_paths_are_relative_to_the_set_file(tmp_path):
    folder = tmp_path / "sets"
    folder.mkdir()
    tofcore.demo_scene("plane").save(tmp_path / "plane.npz")
    spec = load_set(write_set(folder, "[[scenes]]\nnpz = '../plane.npz'\n"))
    assert spec.scenes[0].source == str((tmp_path / "plane.npz").resolve())


def test_validate_and_run_report_a_bad_file_and_render_nothing(tmp_path):
    bad = write_set(tmp_path, "[[scenes]]\ndemo = 'corner'\nspp = 3\n")
    for args in (("validate", str(bad)), ("run", str(bad), "--out", str(tmp_path / "dataset"))):
        proc = batch(*args)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.strip().splitlines()[-1].startswith(f"error: {bad}:3: scenes[0].spp: unknown key 'spp'")
    assert not (tmp_path / "dataset").exists()


def test_validate_lists_the_frames(tmp_path, small_set):
    proc = batch("validate", str(small_set), "--list")
    assert proc.returncode == 0, proc.stderr
    assert "2 scene(s), 4 view(s), 8 frame(s)" in proc.stdout
    assert len(re.findall(r"^[0-9a-f]{16}  \S+/pose\d/\S+  seed \d+$", proc.stdout, re.M)) == 8


def test_parse_frames():
    assert parse_frames("1-3,7, 9-10") == (1, 2, 3, 7, 9, 10)
    assert parse_frames("5") == (5,)
    for bad in ("3-1", "a", "1-", ""):
        with pytest.raises(ValueError):
            parse_frames(bad)


@pytest.mark.parametrize("pose, line, key, needle", [
    ("eye = [1.0, 1.0, 1.0]\ntarget = [1.0, 1.0, 1.0]", 6, "eye", "target must differ from eye"),
    ("eye = [1.0, 1.0, 1.0]\ntarget = [1.0, 1.0, 0.0]\nup = [0.0, 0.0, 1.0]", 8, "up", "must not be parallel"),
])
def test_a_look_at_pose_error_names_the_pose_and_its_line_not_the_presets(tmp_path, pose, line, key, needle):
    message = _error(tmp_path, f"""seed = 1
presets = ["kinect_v2"]
[[scenes]]
demo = "corner"
[[scenes.poses]]
{pose}
""")
    assert message.startswith(f"{tmp_path / 'set.toml'}:{line}: scenes[0].poses[0].{key}: look_at: "), message
    assert needle in message
