"""The frame writer (batch/writer.py) and what it must keep: a worker renders the next frame while the last
one is written, the queue is bounded, a write error fails only its frame with one line, and a worker killed
while writing leaves a dataset that verifies and resumes.

Nothing here asserts a duration: the overlap is shown by what the writer held when a render began.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from batch import worker
from batch.dataset import Dataset
from batch.jobs import expand, group_by_view
from batch.setfile import load_set
from batch.writer import FrameWriter
from batch_helpers import TINY, batch, read_index, stray_files, write_set

#: Three views of a small scene with one fast preset: three view tasks, one frame each.
THREE_VIEWS = """
seed = 5
presets = ["xtion2"]
""" + TINY + """
[output]
formats = ["png", "json"]
[[scenes]]
demo = "box_on_wall"
[[scenes.poses]]
suggested = true
[[scenes.poses]]
count = 2
box_min = [-0.5, -2.2, 1.2]
box_max = [0.5, -1.8, 1.8]
target = [0.0, 0.0, 1.5]
"""


def _wait_until(condition, what: str, timeout_s: float = 120.0) -> None:
    """Poll ``condition`` (a deadline only against hanging; nothing is timed)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting until {what}"
        time.sleep(0.01)


# --------------------------------------------------------------------------- the writer alone

def test_the_writer_takes_a_frame_while_it_writes_another_and_blocks_beyond_its_queue():
    writer = FrameWriter(depth=1)
    release, writing = threading.Event(), threading.Event()

    def write(name):
        def run(wait_s):
            writing.set()
            assert release.wait(60)
            return {"job_id": name, "wait_s": wait_s}
        return run

    def fail(exc):
        return {"job_id": "failed", "error": repr(exc)}

    assert writer.submit(write("a"), fail) == 0.0
    _wait_until(writing.is_set, "the writer started on frame a")
    assert writer.submit(write("b"), fail) == 0.0       # queued while a is written: the submitter goes on
    assert writer.in_flight == 2 and writer.take() == []
    third = threading.Thread(target=writer.submit, args=(write("c"), fail))
    third.start()
    _wait_until(lambda: writer.blocked, "the third submit blocks on the full queue")
    assert third.is_alive() and writer.in_flight == 3
    release.set()
    third.join(60)
    records = writer.drain()
    assert [r["job_id"] for r in records] == ["a", "b", "c"] and writer.in_flight == 0
    assert records[0]["wait_s"] == 0.0 and records[2]["wait_s"] > 0.0  # c's wait is handed to its write
    writer.close()
    assert not writer.thread.is_alive()


def test_a_write_that_raises_gives_its_failure_record_and_the_writer_goes_on():
    writer = FrameWriter()

    def broken(_wait_s):
        raise OSError(28, "No space left on device")

    writer.submit(broken, lambda exc: {"job_id": "x", "error": f"{type(exc).__name__}: {exc}"})
    writer.submit(lambda _wait_s: {"job_id": "y", "error": None}, lambda exc: {"job_id": "y", "error": repr(exc)})
    assert writer.drain() == [{"job_id": "x", "error": "OSError: [Errno 28] No space left on device"},
                              {"job_id": "y", "error": None}]
    writer.close()


@pytest.mark.parametrize("depth", [0, -1, 1.5, True])
def test_the_queue_depth_must_be_a_positive_integer(depth):
    with pytest.raises(ValueError, match=rf"FrameWriter: depth must be an integer >= 1, got {depth!r}"):
        FrameWriter(depth=depth)


# --------------------------------------------------------------------------- a worker's views

def test_a_worker_renders_the_next_view_while_the_last_frame_is_written(tmp_path, monkeypatch):
    """The local pool's worker (start_view / finish_writes, in this process): a view is reported once rendered,
    the next one renders while the writer still holds the last frame, and the render waits once the queue is
    full. The writer is held by a gate, so what it holds when each render begins is known exactly."""
    dataset = tmp_path / "dataset"
    Dataset(dataset).create()
    jobs = expand(load_set(write_set(tmp_path, THREE_VIEWS))).jobs
    tasks = group_by_view(jobs, dataset=str(dataset), render_threads=1)
    assert len(tasks) == 3
    monkeypatch.setattr(worker, "_WRITER", None)
    gate = threading.Event()
    write, render = worker.write_frame, worker._render

    def gated_write(*args, **kwargs):
        assert gate.wait(120)
        return write(*args, **kwargs)

    held_at_render: list[int] = []

    def render_counting(*args, **kwargs):
        held_at_render.append(worker._WRITER.in_flight)
        return render(*args, **kwargs)

    monkeypatch.setattr(worker, "write_frame", gated_write)
    monkeypatch.setattr(worker, "_render", render_counting)
    try:
        assert worker.start_view(tasks[0]) == []       # rendered and handed over; not written yet
        assert worker.start_view(tasks[1]) == []       # rendered while frame 1 is being written
        third: list = []
        runner = threading.Thread(target=lambda: third.extend(worker.start_view(tasks[2])))
        runner.start()
        _wait_until(lambda: worker._WRITER.blocked, "the third view's frame waits for room in the queue")
        assert held_at_render == [0, 1, 2]
        assert not any(p.name == job.job_id for job in jobs for p in (dataset / "frames").iterdir())
        gate.set()
        runner.join(120)
        records = third + worker.finish_writes()
    finally:
        gate.set()
        if worker._WRITER is not None:
            worker._WRITER.close()
    assert sorted(r["job_id"] for r in records) == sorted(job.job_id for job in jobs)
    assert all(r["status"] == "ok" for r in records), [r.get("error") for r in records]
    timing = {r["job_id"]: r["timing"] for r in records}
    assert timing[tasks[2].jobs[0].job_id]["handoff_wait_s"] > 0.0   # the render thread waited for the writer
    for t in timing.values():
        assert t["write_started"] >= t["render_started"] + t["render_s"] and t["write_s"] > 0.0
    assert all(Dataset(dataset).verify(r) is None for r in records)  # published, every file as recorded
    assert stray_files(dataset) == []


# --------------------------------------------------------------------------- runs

def test_a_write_error_fails_only_its_frame_with_one_line_and_retry_failed_writes_it(tmp_path):
    set_file = write_set(tmp_path, THREE_VIEWS)
    dataset = tmp_path / "dataset"
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet",
                 env={"TOF_BATCH_FAIL": "write:box_on_wall/pose1/*"})
    assert proc.returncode == 1, proc.stderr
    records = read_index(dataset)
    failed = [r for r in records if r["status"] == "failed"]
    assert len(records) == 3 and len(failed) == 1
    (record,) = failed
    assert record["view"]["label"] == "pose1" and record["traceback"] is None and record["files"] == []
    assert record["error"] == ("OSError: [Errno 28] No space left on device (fault injected by "
                               "TOF_BATCH_FAIL='write:box_on_wall/pose1/*')")
    assert record["timing"]["write_s"] >= 0.0
    assert not (dataset / "frames" / record["job_id"]).exists() and stray_files(dataset) == []
    assert f"failed {record['job_id']} box_on_wall/pose1/xtion2: {record['error']}" in proc.stderr
    verify = batch("verify", str(dataset))
    assert verify.returncode == 0, verify.stdout
    retry = batch("run", str(set_file), "--out", str(dataset), "--quiet", "--retry-failed")
    assert retry.returncode == 0, retry.stderr
    assert [r["status"] for r in read_index(dataset)] == ["ok"] * 3


def test_a_worker_killed_while_writing_leaves_a_dataset_that_verifies_and_resumes(tmp_path):
    """SIGKILL in the middle of a frame's writing (its files written, no record.json, not published): nothing
    half-written is indexed or left, the frames the worker held are failed, the rest of the set renders on a
    new worker, and --retry-failed completes the set."""
    set_file = write_set(tmp_path, THREE_VIEWS)
    dataset = tmp_path / "dataset"
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet",
                 env={"TOF_BATCH_FAIL": "kill-write:box_on_wall/pose1/*"})
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    records = {r["view"]["label"]: r for r in read_index(dataset)}
    assert len(records) == 3
    killed = records["pose1"]
    assert killed["status"] == "failed"
    assert killed["error"].startswith("WorkerDied: the worker process (pid ") and "killed by SIGKILL" in killed["error"]
    for record in records.values():
        folder = dataset / "frames" / record["job_id"]
        assert folder.is_dir() == (record["status"] == "ok")
    assert stray_files(dataset) == []
    verify = batch("verify", str(dataset))
    assert verify.returncode == 0, verify.stdout
    retry = batch("run", str(set_file), "--out", str(dataset), "--quiet", "--retry-failed")
    assert retry.returncode == 0, retry.stderr
    assert [r["status"] for r in read_index(dataset)] == ["ok"] * 3
    verify = batch("verify", str(dataset))
    assert verify.returncode == 0, verify.stdout


def test_a_run_reports_how_much_writing_overlapped_rendering(tmp_path):
    set_file = write_set(tmp_path, THREE_VIEWS)
    dataset = tmp_path / "dataset"
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert proc.returncode == 0, proc.stderr
    for record in read_index(dataset):
        timing = record["timing"]
        assert {"handoff_wait_s", "write_started", "write_s", "finished"} <= timing.keys()
        assert timing["write_started"] >= timing["render_started"] + timing["render_s"]
    (line,) = [line for line in proc.stderr.splitlines() if line.startswith("worker ")]
    assert "3 frame(s)" in line and "s of it while rendering; rendering waited " in line
