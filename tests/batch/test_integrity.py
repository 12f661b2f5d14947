"""Dataset integrity (issue 12, classes 5 and 6): frames published exactly once, an index that always
describes the files, bad index lines that never stop a run, record.json under checksum, Ctrl-C at any time,
a full disk.

The in-process tests render with one tracer thread (no worker process: the pytest process may have
imported bpy); everything else goes through ``python -m batch`` in a subprocess.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from batch.dataset import JOB_ID, RECORD, Dataset, publish
from batch.jobs import JOB_ID_HEX, expand, group_by_view
from batch.run import InlineExecutor, run_jobs
from batch.setfile import load_set
from batch.worker import run_view
from batch_helpers import REPO, TINY, batch, has_module, read_index, stray_files, write_set

#: Inputs of the publishing tests: (scenes × poses × presets) of different shapes, fixed seeds.
SETS = {
    "corner-2-presets": """
seed = 11
presets = ["kinect_v2", "o3d303"]
""" + TINY + """
[[scenes]]
demo = "corner"
[[scenes.poses]]
suggested = true
""",
    "box-3-poses": """
seed = 5
presets = ["xtion2"]
""" + TINY + """
[[scenes]]
demo = "box_on_wall"
[[scenes.poses]]
suggested = true
[[scenes.poses]]
count = 2
box_min = [-0.5, -2.2, 1.2]
box_max = [0.5, -1.8, 1.8]
target = [0.0, 0.0, 1.5]
""",
}

#: Enough work that a run is still rendering a second after it starts: 8 views of a room.
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


def _quiet():
    return open(os.devnull, "w")


def _start(*args: str) -> subprocess.Popen:
    """``python -m batch ARGS`` started in its own process group (as a terminal would)."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("TOF_BATCH_FAIL", None)
    return subprocess.Popen([sys.executable, "-m", "batch", *args], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True, text=True, preexec_fn=_as_a_shell_does)


def _as_a_shell_does() -> None:
    """In the child before exec: SIGINT at its default and unblocked, as a shell starts a foreground job —
    not whatever disposition this test process was left with by other tests (an ignored or blocked SIGINT
    is inherited through exec, and a Ctrl-C before the program's own handler would then be lost)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _tasks(set_file: Path, dataset: Path):
    jobs = expand(load_set(set_file)).jobs
    return jobs, group_by_view(jobs, dataset=str(dataset), render_threads=1)


def _snapshot(dataset: Path) -> dict[str, dict[str, tuple[int, bytes]]]:
    """(mtime ns, bytes) of every file of every published frame folder."""
    return {d.name: {f.name: (f.stat().st_mtime_ns, f.read_bytes()) for f in d.iterdir()}
            for d in (dataset / "frames").iterdir() if JOB_ID.fullmatch(d.name)}


def _assert_true_index(dataset: Path, n: int) -> list[dict]:
    """``n`` ok frames, one index line each, every checksum (record.json too) right, nothing stray."""
    records = read_index(dataset)
    assert len(records) == n and len({r["job_id"] for r in records}) == n
    assert all(r["status"] == "ok" for r in records), [r.get("error") for r in records]
    assert all("record_file" in r for r in records)
    report = Dataset(dataset).check("sha256")
    assert report["problems"] == []
    assert stray_files(dataset) == []
    return records


# --------------------------------------------------------------------------- exactly once

@pytest.mark.parametrize("name", sorted(SETS))
def test_a_second_execution_of_a_view_leaves_its_published_folders_alone(tmp_path, name):
    """Dask may run a view twice (a worker lost, a duplicate task): the second execution must not replace
    what the first published, and must report the published records, not the ones it wrote."""
    set_file = write_set(tmp_path, SETS[name])
    dataset = tmp_path / "dataset"
    Dataset(dataset).create()
    _, tasks = _tasks(set_file, dataset)
    first = [run_view(task) for task in tasks]
    before = _snapshot(dataset)
    time.sleep(0.01)  # a replaced file would have a later mtime
    second = [run_view(task) for task in tasks]
    assert _snapshot(dataset) == before
    assert second == first  # the published records, record_file (size, SHA-256 of record.json) included
    assert all(r["status"] == "ok" and "record_file" in r for rs in first for r in rs)
    assert stray_files(dataset) == []  # the second execution's staging folders are gone


def test_publish_refuses_a_published_folder_and_keeps_its_bytes(tmp_path):
    frames = tmp_path / "frames"
    final = frames / "0123456789abcdef"
    for i, content in enumerate([b"first", b"second", b"third"]):
        partial = frames / f".0123456789abcdef.partial-{i:08x}"
        partial.mkdir(parents=True)
        (partial / RECORD).write_bytes(content)
        assert publish(partial, final) is (i == 0)
        if i:
            shutil.rmtree(partial)
        assert (final / RECORD).read_bytes() == b"first"


class _RunsViewsTwice(InlineExecutor):
    """What Dask does after a worker holding finished results dies: it runs those views again.

    ``silent``: the second execution's result never reaches the parent (Dask recomputing a lost result),
    else it is reported too, before the first one (a duplicate task finishing first).
    """

    def __init__(self, silent: bool):
        self.silent = silent
        self.name = "views-twice executor"

    def results(self, tasks):
        for task in tasks:
            first = run_view(task)
            time.sleep(0.01)
            second = run_view(task)
            if not self.silent:
                yield task, second
            yield task, first


@pytest.mark.parametrize("silent", [True, False], ids=["rerun-unreported", "duplicate-reported-first"])
@pytest.mark.parametrize("name", sorted(SETS))
def test_views_run_twice_leave_an_index_that_describes_the_files(tmp_path, name, silent):
    set_file = write_set(tmp_path, SETS[name])
    dataset = tmp_path / "dataset"
    jobs = expand(load_set(set_file)).jobs
    result = run_jobs(jobs, dataset, executor=_RunsViewsTwice(silent), threads_per_worker=1, quiet=True,
                      stream=_quiet())
    assert result.exit_code == 0 and result.rendered == len(jobs)
    assert result.duplicates == (0 if silent else len(jobs))
    _assert_true_index(dataset, len(jobs))
    assert batch("verify", str(dataset)).returncode == 0


def test_the_index_writer_appends_a_frame_once(tmp_path):
    data = Dataset(tmp_path / "dataset")
    data.create()
    ok = {"job_id": "0123456789abcdef", "status": "ok", "n": 1}
    failed = {"job_id": "fedcba9876543210", "status": "failed", "n": 1}
    assert data.append(ok) and not data.append(ok) and not data.append(dict(ok, n=2))
    assert not data.append(dict(ok, status="failed"))  # a published frame's line never changes
    assert data.append(failed) and not data.append(dict(failed, n=2))
    assert data.append(dict(failed, status="ok"))  # failed, then its folder appeared: the ok line follows
    data.close_index()
    lines = [json.loads(line) for line in data.index_path.read_text().splitlines()]
    assert [(r["job_id"], r["status"], r["n"]) for r in lines] == [
        ("0123456789abcdef", "ok", 1), ("fedcba9876543210", "failed", 1), ("fedcba9876543210", "ok", 1)]


def test_a_killed_pool_worker_leaves_an_index_that_describes_the_files(tmp_path):
    """kill -9 of a local pool worker: its view in flight is recorded failed, except frames it had published
    (indexed as published); --retry-failed then completes the set."""
    set_file = write_set(tmp_path, SLOW)
    dataset = tmp_path / "dataset"
    proc = _start("run", str(set_file), "--out", str(dataset), "--quiet", "--workers", "2")
    index = dataset / "index.jsonl"
    deadline = time.monotonic() + 120
    while not (index.exists() and index.read_text().strip()):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.02)
    os.kill(json.loads(index.read_text().splitlines()[0])["pid"], signal.SIGKILL)
    _, stderr = proc.communicate(timeout=180)
    assert proc.returncode in (0, 1) and "Traceback" not in stderr, stderr
    records = read_index(dataset)
    assert len(records) == 8 and Dataset(dataset).check("sha256")["problems"] == []
    assert stray_files(dataset) == []
    failed = [r for r in records if r["status"] == "failed"]
    assert all("WorkerDied: the worker process" in r["error"] and not (dataset / "frames" / r["job_id"]).exists()
               for r in failed)
    retry = batch("run", str(set_file), "--out", str(dataset), "--quiet", "--retry-failed")
    assert retry.returncode == 0, retry.stderr
    _assert_true_index(dataset, 8)


_DRIVER = """
import json, os, signal, sys, time
from pathlib import Path
from batch.jobs import expand
from batch.run import DaskExecutor, run_jobs
from batch.setfile import load_set

dataset = Path(sys.argv[2])
snapshot = {}

class KillTheFirstWorker(DaskExecutor):
    def results(self, tasks):
        killed = False
        for item in super().results(tasks):
            yield item  # the parent has indexed it when this generator resumes
            if item is None or killed or isinstance(item[1], BaseException):
                continue
            killed = True
            for record in item[1]:
                folder = dataset / "frames" / record["job_id"]
                snapshot[record["job_id"]] = {f.name: f.stat().st_mtime_ns for f in folder.iterdir()}
            os.kill(item[1][0]["pid"], signal.SIGKILL)  # the worker that holds the view's result
        # Let Dask finish whatever it runs again (a lost result still wanted is computed again).
        busy = lambda dask_scheduler: sum(ts.state not in ("memory", "released", "forgotten", "erred")
                                          for ts in dask_scheduler.tasks.values())
        deadline = time.monotonic() + 90
        while self.client.run_on_scheduler(busy) and time.monotonic() < deadline:
            time.sleep(0.2)

jobs = expand(load_set(sys.argv[1])).jobs
result = run_jobs(jobs, dataset, executor=KillTheFirstWorker(workers=2), threads_per_worker=1, quiet=True)
after = {job_id: {f.name: f.stat().st_mtime_ns for f in (dataset / "frames" / job_id).iterdir()}
         for job_id in snapshot}
print(json.dumps({"exit_code": result.exit_code, "jobs": len(jobs), "same": after == snapshot,
                  "killed": sorted(snapshot)}))
"""


@pytest.mark.dask
@pytest.mark.skipif(not has_module("distributed"), reason="needs dask[distributed]")
@pytest.mark.parametrize("name", sorted(SETS))
def test_a_dask_worker_killed_after_a_view_does_not_get_it_published_again(tmp_path, name):
    """kill -9 of the Dask worker holding a finished view's result: Dask used to run the view again, whose
    folders replaced the published ones while the index kept the first checksums."""
    set_file = write_set(tmp_path, SETS[name])
    dataset = tmp_path / "dataset"
    proc = subprocess.run([sys.executable, "-c", _DRIVER, str(set_file), str(dataset)], cwd=REPO,
                          env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["exit_code"] == 0 and out["killed"], out
    assert out["same"], "a finished frame folder was published again"
    _assert_true_index(dataset, out["jobs"])


# --------------------------------------------------------------------------- bad index lines

def _dataset(tmp_path: Path, name: str = "corner-2-presets") -> tuple[Path, Path]:
    set_file = write_set(tmp_path, SETS[name])
    dataset = tmp_path / "dataset"
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert proc.returncode == 0, proc.stderr
    return set_file, dataset


@pytest.mark.parametrize("bad, why", [
    (b'{"job_id":"abc"}', "job_id must be 16 hex digits, got 'abc'"),
    (b"[1, 2]", "a JSON list, not a record"),
    (b'{"job_id":[1]}', "job_id must be 16 hex digits, got [1]"),
    (b'"x"', "a JSON string, not a record"),
    (b'{"job_id":"@ID","status":"ok"}', "scene must be a string, got None"),
    (b"\xff\xfe\x00garbage", "not JSON"),
    (b'{"job_id":"@ID","status":"ok","scene":"corner","preset":"kinect_v2","view":{"label":"pose0"},'
     b'"settings":{"width":32,"height":27},"dir":"frames/@ID","files":[{"kind":"x","name":"../../../etc/passwd",'
     b'"bytes":1,"sha256":"' + b"0" * 64 + b'"}]}', "files[0].name must be a file name"),
])
def test_an_index_line_that_is_not_a_record_is_reported_kept_aside_and_never_stops_a_run(tmp_path, bad, why):
    assert JOB_ID.pattern == f"[0-9a-f]{{{JOB_ID_HEX}}}"  # the ids batch.jobs makes are the ids accepted
    set_file, dataset = _dataset(tmp_path)
    first = read_index(dataset)
    bad = bad.replace(b"@ID", first[0]["job_id"].encode())
    lines = (dataset / "index.jsonl").read_bytes().splitlines(keepends=True)
    # The bad line after the frame's good line (it would supersede it) and again as the last line.
    (dataset / "index.jsonl").write_bytes(lines[0] + bad + b"\n" + b"".join(lines[1:]) + bad + b"\n")
    check = batch("verify", str(dataset))
    assert check.returncode == 1 and f"index.jsonl:2: not a frame record ({why}" in check.stdout
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    index = dataset / "index.jsonl"
    assert f"warning: {index}:2: ignored ({why}" in proc.stderr
    assert f"warning: {index}:{len(lines) + 2}: ignored ({why}" in proc.stderr
    assert "nothing to render" in proc.stderr  # the frames' good lines and folders still verify
    assert (dataset / "index.jsonl.rejected").read_bytes() == (bad + b"\n") * 2
    assert [r["job_id"] for r in _assert_true_index(dataset, len(first))] == [r["job_id"] for r in first]
    assert batch("verify", str(dataset)).returncode == 0


@pytest.mark.parametrize("keep", [1, 40, -1], ids=["one-byte", "forty-bytes", "all-but-newline"])
def test_a_cut_last_index_line_is_dropped_with_a_note_and_its_frame_recovered(tmp_path, keep):
    set_file, dataset = _dataset(tmp_path, "box-3-poses")
    lines = (dataset / "index.jsonl").read_bytes().splitlines(keepends=True)
    last = lines[-1].rstrip(b"\n")
    (dataset / "index.jsonl").write_bytes(b"".join(lines[:-1]) + last[:keep])
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert f"{dataset / 'index.jsonl'}:{len(lines)}: incomplete last line" in proc.stderr
    assert "1 finished frame(s) taken from their record.json" in proc.stderr and "nothing to render" in proc.stderr
    assert not (dataset / "index.jsonl.rejected").exists()
    _assert_true_index(dataset, len(lines))


def test_a_bad_line_for_a_damaged_frame_gets_the_frame_rendered_again(tmp_path):
    set_file, dataset = _dataset(tmp_path, "box-3-poses")
    records = read_index(dataset)
    victim = records[1]
    png = dataset / victim["dir"] / "depth_mm.png"
    png.write_bytes(png.read_bytes()[:-1] + b"\0")
    text = (dataset / "index.jsonl").read_text().replace(json.dumps(victim, separators=(",", ":")),
                                                         '{"job_id":"' + victim["job_id"] + '"}')
    (dataset / "index.jsonl").write_text(text)
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert f"index.jsonl:2: ignored (status must be 'ok' or 'failed', got None)" in proc.stderr
    assert f"redo {victim['job_id']}" in proc.stderr and "rendering 1 (1 view)" in proc.stderr
    _assert_true_index(dataset, len(records))


# --------------------------------------------------------------------------- record.json under checksum

def _damage_same_size(data: bytes) -> bytes:
    """A digit of a metric changed: still valid JSON, same size."""
    key = b'"valid_fraction": '
    at = data.index(key) + len(key) + 2  # past "0." (or "1.")
    digit = data[at:at + 1]
    return data[:at] + (b"7" if digit != b"7" else b"3") + data[at + 1:]


@pytest.mark.parametrize("damage, size_sees_it", [
    (_damage_same_size, True),  # size: record.json is also compared with the index line, key by key
    (lambda data: data + b" ", True),
    (lambda data: data[: len(data) // 2], True),
], ids=["digit-changed", "byte-added", "cut-in-half"])
def test_a_damaged_record_json_is_detected_and_the_frame_rendered_again(tmp_path, damage, size_sees_it):
    set_file, dataset = _dataset(tmp_path, "box-3-poses")
    records = read_index(dataset)
    victim = records[2]
    path = dataset / victim["dir"] / RECORD
    path.write_bytes(damage(path.read_bytes()))
    by_size = batch("verify", str(dataset), "--checksum", "size")
    assert by_size.returncode == (1 if size_sees_it else 0), by_size.stdout
    check = batch("verify", str(dataset))
    assert check.returncode == 1 and f"frames/{victim['job_id']}: {RECORD}" in check.stdout
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet", "--verify", "sha256")
    assert proc.returncode == 0, proc.stderr
    assert f"redo {victim['job_id']}" in proc.stderr and RECORD in proc.stderr
    assert "rendering 1 (1 view)" in proc.stderr
    after = _assert_true_index(dataset, len(records))
    assert after[2]["record_file"]["sha256"] != victim["record_file"]["sha256"]  # rendered again


def test_index_lines_without_the_record_checksum_are_compared_by_content_and_upgraded(tmp_path):
    """An index written before record.json had a checksum: accepted when record.json says the same."""
    set_file, dataset = _dataset(tmp_path, "box-3-poses")
    records = read_index(dataset)
    old = [{k: v for k, v in r.items() if k != "record_file"} for r in records]
    other = dataset / old[0]["dir"] / RECORD
    other.write_text(other.read_text().replace('"preset": "xtion2"', '"preset": "xtion2 "'))
    (dataset / "index.jsonl").write_text("".join(json.dumps(r) + "\n" for r in old))
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert f"redo {old[0]['job_id']}" in proc.stderr and "the index line differs from record.json in preset" in proc.stderr
    assert "rendering 1 (1 view)" in proc.stderr
    _assert_true_index(dataset, len(records))


# --------------------------------------------------------------------------- Ctrl-C at any time

def _interpreter_start_up(returncode: int, stderr: str) -> bool:
    """A Ctrl-C that came while the Python interpreter itself was starting, before any line of batch ran:
    killed before Python handled SIGINT at all, or Python's own report (site, runpy, import machinery)."""
    if returncode == -signal.SIGINT and not stderr:
        return True
    if "Fatal Python error: init_import_site" in stderr:  # the site module, importing the standard library
        return True
    frames = [line for line in stderr.splitlines() if line.startswith('  File "')]
    return returncode != 0 and "KeyboardInterrupt" in stderr and all("<frozen" in f or "site-packages" in f
                                                                      for f in frames)


@pytest.mark.parametrize("extra", [(), ("--dask", "local", "--workers", "2")], ids=["local-pool", "dask-local"])
def test_ctrl_c_at_any_moment_is_one_line_exit_130_and_the_rerun_completes(tmp_path, extra):
    if extra and not has_module("distributed"):
        pytest.skip("needs dask[distributed]")
    set_file = write_set(tmp_path, SLOW)
    delays = [0.0, 0.05, 0.1, 0.3, 1.0] + ([3.0] if extra else [2.0])
    for delay in delays:
        dataset = tmp_path / f"after-{delay}"
        proc = _start("run", str(set_file), "--out", str(dataset), "--quiet", *extra)
        time.sleep(delay)
        os.killpg(proc.pid, signal.SIGINT)  # what the terminal does: every process of the group
        _, stderr = proc.communicate(timeout=120)
        where = f"Ctrl-C after {delay} s: exit {proc.returncode}\n{stderr}"
        if _interpreter_start_up(proc.returncode, stderr):
            assert not dataset.exists(), where
            continue
        assert proc.returncode == 130 and "Traceback" not in stderr and "Warning" not in stderr, where
        last = stderr.strip().splitlines()[-1] if not dataset.exists() else \
            [line for line in stderr.splitlines() if line.startswith("interrupted")][-1]
        assert last.startswith("interrupted (SIGINT)"), where
        if dataset.exists():
            assert "published by this run; rerun the same command to resume" in last \
                or "before any frame was rendered" in last or last.endswith("nothing was written"), where
            with Dataset(dataset).locked():  # released
                pass
            assert stray_files(dataset) == [], where  # no half-written frame
            report = Dataset(dataset).check("sha256")
            assert report["problems"] == [], (where, report)
            rerun = batch("run", str(set_file), "--out", str(dataset), "--quiet")
            assert rerun.returncode == 0, rerun.stderr
            _assert_true_index(dataset, 8)
            assert batch("verify", str(dataset)).returncode == 0


# --------------------------------------------------------------------------- a full disk

def _mount_tmpfs(where: Path, size: str) -> bool:
    where.mkdir(parents=True, exist_ok=True)
    if shutil.which("mount") is None or os.geteuid() != 0:
        return False
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                          capture_output=True).returncode == 0


@pytest.mark.parametrize("size", ["8k", "40k", "450k"])  # index full at once, after a few lines, frames only
def test_a_full_disk_fails_frames_or_stops_the_run_cleanly_and_the_rerun_completes(tmp_path, size):
    """A real full file system (a small tmpfs; needs root): one-line errors, and once there is room, the
    reruns complete a dataset that verifies."""
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, size):
        pytest.skip("needs to mount a tmpfs (root)")
    try:
        set_file = write_set(tmp_path, SETS["box-3-poses"].replace("count = 2", "count = 5"))
        dataset = disk / "dataset"
        proc = batch("run", str(set_file), "--out", str(dataset), "--quiet")
        assert proc.returncode in (1, 2) and "Traceback" not in proc.stderr, proc.stderr
        assert "No space left on device" in proc.stderr
        if proc.returncode == 2:
            assert proc.stderr.strip().splitlines()[-1].startswith("error: ")
        subprocess.run(["mount", "-o", "remount,size=20m", str(disk)], check=True)
        rerun = batch("run", str(set_file), "--out", str(dataset), "--quiet", "--retry-failed")
        assert rerun.returncode in (0, 1), rerun.stderr
        rerun = batch("run", str(set_file), "--out", str(dataset), "--quiet")
        assert rerun.returncode == 0, rerun.stderr
        _assert_true_index(dataset, 6)
        assert batch("verify", str(dataset)).returncode == 0
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


# --------------------------------------------------------------------------- the verify command

def test_verify_reports_unindexed_folders_and_leftovers_and_refuses_while_a_run_writes(tmp_path):
    set_file, dataset = _dataset(tmp_path)
    records = read_index(dataset)
    (dataset / "index.jsonl").write_text(json.dumps(records[0]) + "\n")
    (dataset / "frames" / ".0123456789abcdef.partial-0badf00d").mkdir()
    (dataset / ".index.jsonl.tmp-0badf00d").write_text("{")
    proc = batch("verify", str(dataset))
    assert proc.returncode == 1, proc.stdout
    assert f"frames/{records[1]['job_id']}: published but not in the index" in proc.stdout
    assert "frames/.0123456789abcdef.partial-0badf00d: left by an interrupted run" in proc.stdout
    assert ".index.jsonl.tmp-0badf00d: temporary file left by an interrupted run" in proc.stdout
    with Dataset(dataset).locked():
        busy = batch("verify", str(dataset))
    assert busy.returncode == 2 and "a run is writing to this dataset" in busy.stderr
    assert batch("verify", str(tmp_path)).returncode == 2
    # What verify found, the next run repairs: leftovers removed, the folder indexed again.
    rerun = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert rerun.returncode == 0 and "nothing to render" in rerun.stderr, rerun.stderr
    _assert_true_index(dataset, len(records))
    assert batch("verify", str(dataset)).returncode == 0


# --------------------------------------------------------------------------- issue 23: verified end to end, no links

def _edit_line(dataset: Path, index: int, **changes) -> dict:
    """Change keys of the ``index``-th index line (a person editing it); the edited record."""
    records = read_index(dataset)
    records[index] = {**records[index], **changes}
    (dataset / "index.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    return records[index]


@pytest.mark.parametrize("changes, key", [
    ({"scene": "room"}, "scene"),
    ({"status": "failed"}, None),
    ({"world_from_sensor": [[1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "world_from_sensor"),
])
def test_verify_names_an_index_line_that_contradicts_its_record_and_a_run_takes_the_record(tmp_path, changes, key):
    set_file, dataset = _dataset(tmp_path)
    before = read_index(dataset)
    edited = _edit_line(dataset, 0, **changes)
    proc = batch("verify", str(dataset))
    assert proc.returncode == 1, proc.stdout
    job = edited["job_id"]
    if key is None:
        assert f"frames/{job}: the index line says 'failed' but the frame folder exists" in proc.stdout
    else:
        assert f"frames/{job}: the index line differs from record.json in {key}" in proc.stdout
    rerun = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert rerun.returncode == 0 and "nothing to render" in rerun.stderr, rerun.stderr
    assert read_index(dataset) == before  # the line taken from record.json, nothing rendered again
    assert batch("verify", str(dataset)).returncode == 0


def test_verify_names_a_frame_exr_replaced_by_another_frames_and_a_symlinked_frame_folder(tmp_path):
    _, dataset = _dataset(tmp_path)
    first, second = read_index(dataset)[:2]
    frames = dataset / "frames"
    shutil.copyfile(frames / second["job_id"] / "frame.exr", frames / first["job_id"] / "frame.exr")
    proc = batch("verify", str(dataset))
    assert proc.returncode == 1 and f"frames/{first['job_id']}: frame.exr" in proc.stdout, proc.stdout
    shutil.rmtree(frames / first["job_id"])
    (frames / first["job_id"]).symlink_to(frames / second["job_id"])
    proc = batch("verify", str(dataset))
    assert proc.returncode == 1
    assert f"frames/{first['job_id']}: the frame folder is a symbolic link" in proc.stdout, proc.stdout


@pytest.mark.parametrize("name", ["frames", "index.jsonl", "README.md", "index.jsonl.rejected", "card"])
def test_a_path_of_the_dataset_planted_as_a_symlink_is_refused_and_nothing_written_through_it(tmp_path, name):
    """DATASET/frames (or the index, the card) pointing elsewhere: one line, exit 2, the elsewhere untouched."""
    set_file = write_set(tmp_path, SETS["corner-2-presets"])
    dataset = tmp_path / "dataset"
    dataset.mkdir()
    elsewhere = tmp_path / "elsewhere"
    if name in ("frames", "card"):
        elsewhere.mkdir()
    else:
        elsewhere.write_text("precious\n")
    (dataset / name).symlink_to(elsewhere)
    proc = batch("run", str(set_file), "--out", str(dataset), "--quiet")
    assert proc.returncode == 2, proc.stderr
    assert f"{dataset.resolve() / name}: a symbolic link; a run writes only inside the dataset folder" in proc.stderr
    assert "Traceback" not in proc.stderr
    if name in ("frames", "card"):
        assert list(elsewhere.iterdir()) == []
    else:
        assert elsewhere.read_text() == "precious\n"
