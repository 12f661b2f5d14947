"""batch.run: executors give identical frames; runs resume after a kill; failures are recorded and retried."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from batch.dataset import Dataset
from batch.jobs import expand
from batch.run import run_jobs
from batch.setfile import load_set
from batch_helpers import REPO, assert_same_frames, batch, has_module, read_index, stray_files, write_set


def _check_complete(dataset: Path, n: int) -> list[dict]:
    """One ok record per frame, every file present with its checksum, nothing half-written."""
    records = read_index(dataset)
    assert len(records) == n
    assert len({r["job_id"] for r in records}) == n
    data = Dataset(dataset)
    for record in records:
        assert record["status"] == "ok", record.get("error")
        assert data.verify(record, "sha256") is None
        assert json.loads((dataset / record["dir"] / "record.json").read_text())["job_id"] == record["job_id"]
    assert stray_files(dataset) == []
    assert sorted(p.name for p in (dataset / "frames").iterdir()) == sorted(r["job_id"] for r in records)
    return records


def test_local_pool_and_in_process_give_identical_frames(tmp_path, small_set):
    proc = batch("run", str(small_set), "--out", str(tmp_path / "pool"), "--workers", "2", "--quiet")
    assert proc.returncode == 0, proc.stderr
    records = _check_complete(tmp_path / "pool", 8)
    assert "with the local pool, 2 worker processes" in proc.stderr
    assert "8 frames: 8 ok (8 rendered now" in proc.stderr
    first = records[0]
    assert first["scene"] == "corner" and first["preset"] == "kinect_v2" and first["settings"]["width"] == 32
    assert first["rms_depth_error_m"] > 0 and 0 < first["valid_fraction"] <= 1 and first["convergence"]
    assert {f["kind"] for f in first["files"]} >= {"exr", "depth_mm", "convergence", "ply", "json"}
    assert first["est_depth_error_m"] == first["convergence"][-1]["est_depth_error_m"]
    card = (tmp_path / "pool" / "README.md").read_text()
    assert "frames: **8** (8 ok, 0 failed)" in card and "tofcore.read_exr" in card
    example = card.split("![convergence of one frame](", 1)[1].split(")", 1)[0]
    assert "## Convergence" in card and (tmp_path / "pool" / example).is_file()
    # The same jobs in this process, one after another, with another thread count.
    jobs = expand(load_set(small_set)).jobs
    result = run_jobs(jobs, tmp_path / "inline", inline=True, threads_per_worker=1, quiet=True,
                      stream=open(os.devnull, "w"))
    assert result.exit_code == 0
    assert assert_same_frames(tmp_path / "pool", tmp_path / "inline") == 8


@pytest.mark.dask
@pytest.mark.skipif(not has_module("distributed"), reason="needs dask[distributed]")
def test_dask_local_cluster_gives_the_same_frames_as_the_local_pool(tmp_path, small_set):
    local = batch("run", str(small_set), "--out", str(tmp_path / "local"), "--workers", "1", "--quiet")
    assert local.returncode == 0, local.stderr
    dask = batch("run", str(small_set), "--out", str(tmp_path / "dask"), "--dask", "local", "--workers", "2",
                 "--quiet")
    assert dask.returncode == 0, dask.stderr
    assert "Dask LocalCluster, 2 worker processes" in dask.stderr
    _check_complete(tmp_path / "dask", 8)
    assert assert_same_frames(tmp_path / "local", tmp_path / "dask") == 8
    # Same order in both indexes (set order), whatever order the frames finished in.
    assert [r["job_id"] for r in read_index(tmp_path / "local")] == [r["job_id"] for r in read_index(tmp_path / "dask")]


SLOW = """
seed = 2
presets = ["kinect_v2"]
resolution_scale = 0.25
[quality]
spp = 8
max_depth = 2
[[scenes]]
demo = "room"
[[scenes.poses]]
count = 8
box_min = [-1.5, -1.7, 1.0]
box_max = [1.5, -1.0, 2.0]
target = [0.0, 1.0, 0.8]
"""


def _start(set_file: Path, dataset: Path, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("TOF_BATCH_FAIL", None)
    return subprocess.Popen([sys.executable, "-m", "batch", "run", str(set_file), "--out", str(dataset), "--quiet",
                             *extra], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, text=True)


def _wait_for_records(dataset: Path, proc: subprocess.Popen, count: int = 1, timeout: float = 120) -> None:
    index = dataset / "index.jsonl"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if index.exists() and len([line for line in index.read_text().splitlines() if line.strip()]) >= count:
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.02)
    raise AssertionError("no record appeared")


def _finished(dataset: Path) -> dict[str, dict[str, int]]:
    """mtime (ns) of every file of every published frame folder."""
    frames = dataset / "frames"
    return {d.name: {f.name: f.stat().st_mtime_ns for f in d.iterdir()}
            for d in frames.iterdir() if not d.name.startswith(".")}


def test_a_killed_run_resumes_without_duplicates_or_partial_files(tmp_path):
    set_file = write_set(tmp_path, SLOW)
    dataset = tmp_path / "dataset"
    proc = _start(set_file, dataset, "--workers", "1")
    _wait_for_records(dataset, proc)
    os.killpg(proc.pid, signal.SIGKILL)  # the whole run at once, like a crash: no clean-up code runs
    proc.wait(timeout=30)
    before = _finished(dataset)
    assert 1 <= len(before) < 8, "the run should have been killed part-way"
    for job_id in before:  # every published folder is complete
        record = json.loads((dataset / "frames" / job_id / "record.json").read_text())
        assert Dataset(dataset).verify(record) is None

    rerun = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert rerun.returncode == 0, rerun.stderr
    records = _check_complete(dataset, 8)
    done_before = int(rerun.stderr.split(" already done")[0].rsplit("; ", 1)[1])
    assert done_before == len(before)
    after = _finished(dataset)
    for job_id, files in before.items():  # finished frames were not rendered again
        assert after[job_id] == files
    assert [r["job_id"] for r in records] == [j.job_id for j in expand(load_set(set_file)).jobs]

    again = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert again.returncode == 0 and "nothing to render" in again.stderr
    assert _finished(dataset) == after


def test_sigterm_stops_cleanly(tmp_path):
    set_file = write_set(tmp_path, SLOW)
    dataset = tmp_path / "dataset"
    proc = _start(set_file, dataset, "--workers", "1")
    _wait_for_records(dataset, proc)
    proc.send_signal(signal.SIGTERM)  # the parent only: it stops its workers itself
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 143, stderr
    assert "interrupted (SIGTERM)" in stderr
    assert stray_files(dataset) == []  # the worker cancelled its render and removed its folder
    records = read_index(dataset)
    assert records and all(r["status"] == "ok" for r in records)
    finished = _finished(dataset)  # a frame being published when the signal came may have no index line yet
    assert {r["job_id"] for r in records} <= finished.keys() and len(finished) < 8
    for job_id in finished:
        assert Dataset(dataset).verify(json.loads((dataset / "frames" / job_id / "record.json").read_text())) is None
    rerun = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert rerun.returncode == 0, rerun.stderr
    _check_complete(dataset, 8)


def test_a_failing_frame_is_recorded_and_retried(tmp_path, small_set):
    dataset = tmp_path / "dataset"
    proc = batch("run", str(small_set), "--out", str(dataset), "--quiet", env={"TOF_BATCH_FAIL": "corner/pose1/o3d303"})
    assert proc.returncode == 1, proc.stderr
    assert "8 frames: 7 ok" in proc.stderr and "1 failed" in proc.stderr and "--retry-failed" in proc.stderr
    records = {r["preset"] + "@" + r["scene"] + "/" + r["view"]["label"]: r for r in read_index(dataset)}
    failed = records["o3d303@corner/pose1"]
    assert failed["status"] == "failed" and "fault injected by TOF_BATCH_FAIL" in failed["error"]
    assert failed["files"] == [] and not (dataset / "frames" / failed["job_id"]).exists()
    assert sum(r["status"] == "ok" for r in records.values()) == 7
    assert "## Failed frames" in (dataset / "README.md").read_text()
    ok_before = _finished(dataset)

    # A plain rerun does not retry the failure (it would fail again), and still reports it.
    rerun = batch("run", str(small_set), "--out", str(dataset), "--quiet")
    assert rerun.returncode == 1 and "nothing to render" in rerun.stderr

    retry = batch("run", str(small_set), "--out", str(dataset), "--retry-failed", "--quiet")
    assert retry.returncode == 0, retry.stderr
    assert "rendering 1 (1 view)" in retry.stderr
    _check_complete(dataset, 8)
    after = _finished(dataset)
    assert all(after[job_id] == files for job_id, files in ok_before.items())


def test_a_damaged_frame_and_a_cut_index_line_are_repaired(tmp_path, small_set):
    dataset = tmp_path / "dataset"
    assert batch("run", str(small_set), "--out", str(dataset), "--quiet").returncode == 0
    records = read_index(dataset)
    damaged, lost = records[2], records[5]
    png = dataset / damaged["dir"] / "depth_mm.png"
    png.write_bytes(png.read_bytes()[:-1] + b"\0")
    # An index whose line for one frame is missing and whose last line was cut by a crash.
    lines = (dataset / "index.jsonl").read_text().splitlines(keepends=True)
    (dataset / "index.jsonl").write_text("".join(l for l in lines if lost["job_id"] not in l) + lines[0][:40])
    rerun = batch("run", str(small_set), "--out", str(dataset), "--quiet")
    assert rerun.returncode == 0, rerun.stderr
    assert f"redo {damaged['job_id']}" in rerun.stderr and "checksum" in rerun.stderr
    assert "1 finished frame(s) taken from their record.json" in rerun.stderr
    assert "rendering 1 (1 view)" in rerun.stderr
    _check_complete(dataset, 8)


def test_a_second_run_on_the_same_dataset_is_refused(tmp_path, small_set):
    dataset = tmp_path / "dataset"
    with Dataset(dataset).locked():
        proc = batch("run", str(small_set), "--out", str(dataset), "--quiet")
    assert proc.returncode == 2 and "another run is writing to this dataset" in proc.stderr


def test_a_lock_file_planted_as_a_symlink_is_refused_and_its_target_untouched(tmp_path, small_set):
    """DATASET/.lock pointing at a user's file: one-line refusal, exit code 2, the file keeps its bytes."""
    dataset = tmp_path / "dataset"
    (dataset / "frames").mkdir(parents=True)
    precious = tmp_path / "precious.txt"
    precious.write_text("do not truncate me\n")
    (dataset / ".lock").symlink_to(precious)
    proc = batch("run", str(small_set), "--out", str(dataset), "--quiet")
    assert proc.returncode == 2, proc.stderr
    assert "the lock file is a symbolic link" in proc.stderr and "Traceback" not in proc.stderr
    assert precious.read_text() == "do not truncate me\n"


#: What may differ between two runs of the same set: timings, the process, and the files that record timings.
_RUN_DEPENDENT = {"render_seconds", "trace_seconds", "seconds", "rays_per_second", "finished", "pid", "host",
                  "files", "record_file", "timing"}


def test_one_or_two_workers_give_identical_index_lines_apart_from_timings(tmp_path):
    """The README promises bit-identical datasets whatever the worker count: frames and every index value
    that is not a timing (est_depth_error_m, convergence spp and errors, metrics) are equal (issue 23)."""
    set_file = write_set(tmp_path, """
seed = 3
presets = ["kinect_v2"]
resolution_scale = 0.0625
[quality]
spp = 40
max_depth = 3
[[scenes]]
demo = "room"
[[scenes.poses]]
suggested = true
[[scenes.poses]]
eye = [1.0, -1.5, 1.4]
target = [0.0, 1.0, 0.8]
""")
    for workers in ("1", "2"):
        proc = batch("run", str(set_file), "--out", str(tmp_path / workers), "--workers", workers, "--quiet")
        assert proc.returncode == 0, proc.stderr
    assert assert_same_frames(tmp_path / "1", tmp_path / "2") == 2
    for one, two in zip(read_index(tmp_path / "1"), read_index(tmp_path / "2")):
        assert one["passes"] > 1  # adaptive passes ran
        for key in sorted(one.keys() - _RUN_DEPENDENT):
            value_1, value_2 = one[key], two[key]
            if key == "convergence":
                value_1, value_2 = ([{k: v for k, v in row.items() if k != "seconds"} for row in rows]
                                    for rows in (value_1, value_2))
            assert value_1 == value_2, (key, value_1, value_2)


@pytest.mark.parametrize("formats", ['formats = ["png", "json"]', ""], ids=["previews", "every-format"])
def test_a_set_file_and_a_dataset_in_folders_whose_names_are_not_utf8(tmp_path, formats):
    """Bytes that are not UTF-8 in the set file's folder and in --out (issue 23, class 3): written, verified,
    and the card names the paths with those bytes spelled \\xNN (before: UnicodeEncodeError writing README.md)."""
    folder = Path(os.fsdecode(os.fsencode(tmp_path) + b"/sets\xff"))
    folder.mkdir()
    set_file = write_set(folder, f"""
seed = 1
presets = ["kinect_v2"]
resolution_scale = 0.0625
[quality]
spp = 2
max_depth = 1
[output]
{formats}
[[scenes]]
demo = "plane"
[[scenes.poses]]
suggested = true
""".replace("[output]\n\n", ""))
    dataset = Path(os.fsdecode(os.fsencode(tmp_path) + b"/out\xff\xfe"))
    env = dict(os.environ, PYTHONPATH=str(REPO))
    for argv in (["run", str(set_file), "--out", str(dataset), "--quiet"], ["verify", str(dataset)]):
        proc = subprocess.run([sys.executable, "-m", "batch", *argv], cwd=REPO, env=env, capture_output=True,
                              timeout=240)  # bytes: the paths are printed as the bytes they are
        assert proc.returncode == 0 and b"Traceback" not in proc.stderr, proc.stderr
    assert os.fsencode(dataset) in proc.stdout
    card = (dataset / "README.md").read_bytes().decode("utf-8")  # valid UTF-8
    assert "sets\\xff" in card
    assert all(r["status"] == "ok" and r["error"] is None for r in read_index(dataset))


def test_a_dead_workers_exit_status_is_waited_for_when_another_thread_reaps_it():
    """The pool's manager thread reaps a broken worker too: while it holds the status, this thread's look sees
    None (waitpid's ECHILD). ``_exit_code`` polls until the status appears (it was 'ended' in 1 of 10 kills)."""
    from batch.run import _exit_code

    class Reaped:  # the status shows on the third look, as after the other thread's waitpid returns
        looks = 0

        def join(self, timeout=None):
            pass

        @property
        def exitcode(self):
            self.looks += 1
            return -9 if self.looks >= 3 else None

    assert _exit_code(Reaped(), timeout_s=2.0) == -9
