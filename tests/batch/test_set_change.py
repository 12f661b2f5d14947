"""A set file edited between runs (issue 35): the rerun warns how many indexed frames are not in the set,
``verify`` lists them, and the reader can open only the frames of the set the last run rendered."""

from __future__ import annotations

import json
import warnings

import pytest

from batch_helpers import TINY, batch, read_index, write_set
from tofcore.output.dataset import Dataset, DatasetError

BEFORE = """
seed = 3
presets = ["kinect_v2"]
""" + TINY + """
[[scenes]]
demo = "corner"
[[scenes.poses]]
suggested = true
[[scenes]]
demo = "box_on_wall"
[[scenes.poses]]
suggested = true
"""


def test_an_edited_set_says_which_indexed_frames_are_not_in_it(tmp_path):
    """spp changed and a scene removed: 1 frame of the new set, 2 indexed frames outside it (the corner at the
    old spp, the removed box) — the rerun said "ok", verify "ok" and the reader listed all 3 before."""
    out = tmp_path / "ds"
    set_file = write_set(tmp_path, BEFORE)
    assert batch("run", str(set_file), "--out", str(out), "--quiet").returncode == 0
    before = {r["job_id"] for r in read_index(out)}
    edited = BEFORE.replace("spp = 2", "spp = 3")
    write_set(tmp_path, edited[:edited.index('[[scenes]]\ndemo = "box_on_wall"')])
    proc = batch("run", str(set_file), "--out", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr
    warned = [line for line in proc.stderr.splitlines() if "not in" in line and "indexed frame(s)" in line]
    assert len(warned) == 1 and warned[0].startswith(f"warning: 2 indexed frame(s) are not in {set_file} "), \
        proc.stderr
    assert "the index also holds 2 frame(s) not in this set" in proc.stderr
    records = read_index(out)
    [current] = [r["job_id"] for r in records if r["job_id"] not in before]
    assert json.loads((out / "set.json").read_text())["jobs"] == [current]

    proc = batch("validate", str(set_file), "--out", str(out))
    assert proc.returncode == 0 and f"{out}: 1 done, 0 failed, 0 to render; 2 indexed frame(s) not in this set" \
        in proc.stdout, proc.stdout + proc.stderr

    proc = batch("verify", str(out))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    notes = [line for line in proc.stdout.splitlines() if "not in the set of the last run" in line]
    assert len(notes) == 1 and notes[0].startswith(f"  note: 2 indexed frame(s) are not in the set of the last run "
                                                   f"({set_file}): "), proc.stdout
    assert all(job_id in notes[0] for job_id in before)
    assert "(2 frame(s) not in the last run's set: see the note)" in proc.stdout

    with pytest.warns(UserWarning, match=r"2 indexed frame\(s\) are not in the set of the last run"):
        everything = Dataset(out)
    assert len(everything) == 3 and sorted(everything.outside_set) == sorted(before)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        current_only = Dataset(out, current_set=True)
    assert [f.id for f in current_only.frames()] == [current]
    assert current_only.frames()[0].record["settings"]["spp"] == 3


def test_current_set_needs_the_set_json_of_a_run(tmp_path):
    out = tmp_path / "ds"
    (out / "frames").mkdir(parents=True)
    (out / "index.jsonl").write_text("")
    assert len(Dataset(out)) == 0  # an older dataset: no set.json, no warning
    with pytest.raises(DatasetError, match=r"set\.json: not found or not readable"):
        Dataset(out, current_set=True)
