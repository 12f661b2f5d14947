"""batch.devices: GPU discovery without CUDA in the parent, one pinned worker per GPU, the CPU fall-back.

This machine may have no GPU and no CuPy. The GPU runs use the test stand-in ``TOF_BATCH_FAKE_GPU=1``:
GPU discovery (``CUDA_VISIBLE_DEVICES``), the clamping of ``--workers`` and the pinning of each
worker process run as on a GPU machine, and the workers render on the CPU. ``TOF_BATCH_FAIL=gpu:…``
makes a frame fail as an out-of-memory GPU would.
"""

from __future__ import annotations

import importlib.util
import json
import os

import pytest

import tofcore
from batch import devices, worker
from batch.card import device_rows
from batch.devices import DevicePlan, parse_visible_devices, plan_devices, visible_gpus
from batch.jobs import expand, group_by_view
from batch.setfile import load_set
from batch_helpers import REPO, TINY, assert_same_frames, batch, has_module, read_index, write_set
from tofcore.backend import Device, GpuUnavailable

HAS_CUPY = importlib.util.find_spec("cupy") is not None
no_cupy = pytest.mark.skipif(HAS_CUPY, reason="CuPy is installed here: the no-CuPy message cannot be checked")

ONE_VIEW = """
seed = 3
presets = ["kinect_v2"]
""" + TINY + """
[[scenes]]
demo = "corner"
[[scenes.poses]]
suggested = true
"""

# 6 views of one preset, big enough (64 x 53 px, 4 spp) that a second worker starts before the first
# has rendered them all.
SIX_VIEWS = """
seed = 5
presets = ["kinect_v2"]
resolution_scale = 0.125
[quality]
spp = 4
max_depth = 2
[[scenes]]
demo = "box_on_wall"
[[scenes.poses]]
count = 6
box_min = [-0.5, -2.2, 1.2]
box_max = [0.5, -1.8, 1.8]
target = [0.0, 0.0, 1.5]
"""


# --------------------------------------------------------------------------- discovery (pure)

@pytest.mark.parametrize("value, ids", [
    ("0", ["0"]),
    ("0,1,2,3", ["0", "1", "2", "3"]),
    (" 2 , 0 ", ["2", "0"]),                          # spaces ignored, order kept
    ("", []),                                         # empty: no GPU
    ("   ", []),
    ("-1", []),                                       # the usual way to hide every GPU
    ("0,-1,2", ["0"]),                                # CUDA stops at the first invalid entry
    ("1,none", ["1"]),
    ("0,1,", ["0", "1"]),
    ("0,0,1", ["0", "1"]),                            # one worker per GPU
    ("GPU-8a1b2c3d-1111-2222-3333-444455556666,1", ["GPU-8a1b2c3d-1111-2222-3333-444455556666", "1"]),
    ("MIG-4f3e2d1c-aaaa-bbbb-cccc-ddddeeeeffff", ["MIG-4f3e2d1c-aaaa-bbbb-cccc-ddddeeeeffff"]),
])
def test_parse_visible_devices(value, ids):
    assert parse_visible_devices(value) == ids


def test_visible_gpus_reads_the_variable_without_cuda():
    empty = visible_gpus({"CUDA_VISIBLE_DEVICES": ""})
    assert empty.ids == () and empty.reason == "CUDA_VISIBLE_DEVICES is empty"
    hidden = visible_gpus({"CUDA_VISIBLE_DEVICES": "-1"})
    assert hidden.ids == () and hidden.reason == "CUDA_VISIBLE_DEVICES='-1' names no GPU"
    fake = visible_gpus({"CUDA_VISIBLE_DEVICES": "3,GPU-abc", "TOF_BATCH_FAKE_GPU": "1"})
    assert fake.ids == ("3", "GPU-abc") and fake.source == "CUDA_VISIBLE_DEVICES" and fake.reason is None


@no_cupy
def test_visible_gpus_without_cupy_says_so():
    named = visible_gpus({**os.environ, "CUDA_VISIBLE_DEVICES": "0,1"})  # checked by a child process
    assert named.ids == () and named.reason.startswith("CUDA_VISIBLE_DEVICES='0,1': GPU: CuPy is not installed")
    env = {k: v for k, v in os.environ.items() if k not in ("CUDA_VISIBLE_DEVICES", "TOF_BATCH_FAKE_GPU")}
    probed = visible_gpus(env)  # no CUDA_VISIBLE_DEVICES: a child process asks tofcore.backend.gpu_count()
    assert probed.ids == () and "CuPy is not installed" in probed.reason and "probe" in probed.source


def test_ids_cuda_cannot_find_are_dropped_before_any_worker_starts(monkeypatch):
    """CUDA stops at the first entry it cannot find: the child process's count keeps the first ones."""
    answers = {"0,7": (1, None), "7": (0, "GPU: CuPy 14.2.0 found no usable CUDA device (cudaErrorNoDevice)")}
    monkeypatch.setattr(devices, "_probe", lambda env, timeout_s: answers[env["CUDA_VISIBLE_DEVICES"]])
    some = visible_gpus({"CUDA_VISIBLE_DEVICES": "0,7"})
    assert some.ids == ("0",) and some.note.startswith("CUDA_VISIBLE_DEVICES='0,7': CUDA uses 1 of its 2 entries")
    with pytest.raises(GpuUnavailable, match=r"^--device gpu: no usable GPU: CUDA_VISIBLE_DEVICES='7': GPU: CuPy "
                                             r"14.2.0 found no usable CUDA device \(cudaErrorNoDevice\); use"):
        plan_devices("gpu", executor="local", env={"CUDA_VISIBLE_DEVICES": "7"})


def test_plans_one_worker_per_gpu_and_clamps_workers():
    env = {"CUDA_VISIBLE_DEVICES": "0,1,2", "TOF_BATCH_FAKE_GPU": "1"}
    assert plan_devices("cpu", executor="local", workers=None) == DevicePlan("cpu", "cpu", workers=1)
    plan = plan_devices("gpu", executor="local", workers=None, env=env)
    assert plan.gpus == ("0", "1", "2") and plan.workers == 3 and plan.render == "gpu"
    more = plan_devices("gpu", executor="local", workers=8, env=env)
    assert more.gpus == ("0", "1", "2") and more.workers == 3
    assert "--workers 8 clamped to 3: one worker per GPU" in more.notes
    fewer = plan_devices("auto", executor="dask-local", workers=2, env=env)
    assert fewer.gpus == ("0", "1") and fewer.workers == 2 and fewer.render == "auto"
    assert "--workers 2: using the first 2 of 3 GPU(s)" in fewer.notes
    # An existing Dask cluster: nothing is discovered here, the device is passed through.
    cluster = plan_devices("gpu", executor="cluster", workers=None, env={"CUDA_VISIBLE_DEVICES": ""})
    assert cluster.gpus == () and cluster.render == "gpu" and "dask worker" in cluster.notes[0]


def test_no_gpu_is_one_line_for_gpu_and_a_reported_fall_back_for_auto():
    with pytest.raises(GpuUnavailable) as err:
        plan_devices("gpu", executor="local", env={"CUDA_VISIBLE_DEVICES": ""})
    assert str(err.value) == "--device gpu: no usable GPU: CUDA_VISIBLE_DEVICES is empty; use --device cpu or auto"
    auto = plan_devices("auto", executor="local", workers=2, env={"CUDA_VISIBLE_DEVICES": ""})
    assert auto.gpus == () and auto.workers == 2 and auto.fallback_reason == "CUDA_VISIBLE_DEVICES is empty"
    assert auto.notes == ("device auto: no usable GPU (CUDA_VISIBLE_DEVICES is empty); rendering on the CPU",)


def test_a_worker_pins_itself_to_its_gpu(monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1")
    monkeypatch.setattr(worker.signal, "signal", lambda *_args: None)  # leave pytest's handlers alone
    worker.init_worker(None, "1", launched=123.0)
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "1" and worker._WORKER_STARTED == 123.0


# --------------------------------------------------------------------------- the worker (in this process)

def _one_task(tmp_path, device: str, fallback_reason: str | None = None):
    jobs = expand(load_set(write_set(tmp_path, ONE_VIEW))).jobs
    (task,) = group_by_view(jobs, dataset=str(tmp_path / "dataset"), render_threads=1, device=device,
                            fallback_reason=fallback_reason)
    scene, pose, ambient, warnings = worker._load_scene(task)
    return task, (task.jobs[0], task, scene, pose, ambient, warnings)


class OutOfMemoryError(Exception):
    """Looks like CuPy's (its module is what the batch checks)."""


OutOfMemoryError.__module__ = "cupy.cuda.memory"


def test_gpu_failures_fail_the_frame_with_one_line(tmp_path, monkeypatch):
    monkeypatch.delenv("TOF_BATCH_FAKE_GPU", raising=False)
    task, args = _one_task(tmp_path, "gpu")

    def out_of_memory(*_args, **_kwargs):
        raise OutOfMemoryError("Out of memory allocating 1,073,741,824 bytes (allocated so far: 0 bytes).\nmore")

    monkeypatch.setattr(tofcore, "render", out_of_memory)
    record = worker.render_job(*args)
    assert record["status"] == "failed" and record["traceback"] is None and record["files"] == []
    assert record["error"].startswith("GpuUnavailable: GPU: out of device memory (Out of memory allocating")
    assert "\n" not in record["error"]
    assert record["device"] == {"name": None, "description": None, "requested": "gpu", "fallback_reason": None}
    frames = tmp_path / "dataset" / "frames"
    assert not frames.exists() or not any(frames.iterdir())  # no frame, not even a partial one


@no_cupy
def test_gpu_without_cupy_in_a_worker_is_one_line(tmp_path, monkeypatch):
    monkeypatch.delenv("TOF_BATCH_FAKE_GPU", raising=False)
    _, args = _one_task(tmp_path, "gpu")
    record = worker.render_job(*args)
    assert record["status"] == "failed" and record["traceback"] is None
    assert record["error"].startswith("GpuUnavailable: GPU: CuPy is not installed") and "\n" not in record["error"]


def test_auto_renders_again_on_the_cpu_when_the_gpu_fails(tmp_path, monkeypatch):
    monkeypatch.delenv("TOF_BATCH_FAKE_GPU", raising=False)
    _, args = _one_task(tmp_path, "auto")
    render = tofcore.render

    def gpu_breaks(*a, device="cpu", **kw):
        if not isinstance(device, Device):
            raise GpuUnavailable("GPU: CUDA error (CUDARuntimeError: cudaErrorIllegalAddress)")
        return render(*a, device=device, **kw)

    monkeypatch.setattr(tofcore, "render", gpu_breaks)
    record = worker.render_job(*args)
    assert record["status"] == "ok", record["error"]
    assert record["device"]["name"] == "cpu" and record["device"]["requested"] == "auto"
    assert record["device"]["fallback_reason"] == "GPU: CUDA error (CUDARuntimeError: cudaErrorIllegalAddress)"


# --------------------------------------------------------------------------- the command line

def test_gpu_without_a_gpu_exits_2_with_one_line(tmp_path):
    set_file = write_set(tmp_path, ONE_VIEW)
    proc = batch("run", str(set_file), "--out", str(tmp_path / "dataset"), "--device", "gpu",
                 env={"CUDA_VISIBLE_DEVICES": ""})
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [
        "error: --device gpu: no usable GPU: CUDA_VISIBLE_DEVICES is empty; use --device cpu or auto"]
    assert not (tmp_path / "dataset").exists()  # nothing created


@no_cupy
def test_gpu_without_cupy_exits_2_with_one_line(tmp_path):
    set_file = write_set(tmp_path, ONE_VIEW)
    env = {"CUDA_VISIBLE_DEVICES": None}  # unset: the discovery asks a child process
    proc = batch("run", str(set_file), "--out", str(tmp_path / "dataset"), "--device", "gpu", env=env)
    assert proc.returncode == 2, proc.stderr
    (line,) = proc.stderr.splitlines()
    assert line.startswith("error: --device gpu: no usable GPU: GPU: CuPy is not installed")
    assert "Traceback" not in proc.stderr and not (tmp_path / "dataset").exists()


def test_auto_without_a_gpu_renders_on_the_cpu_and_records_why(tmp_path):
    set_file = write_set(tmp_path, ONE_VIEW)
    auto = batch("run", str(set_file), "--out", str(tmp_path / "auto"), "--device", "auto", "--quiet",
                 env={"CUDA_VISIBLE_DEVICES": ""})
    assert auto.returncode == 0, auto.stderr
    assert "device auto: no usable GPU (CUDA_VISIBLE_DEVICES is empty); rendering on the CPU" in auto.stderr
    assert "1 worker process" in auto.stderr and "CPU (auto fall-back)" in auto.stderr
    (record,) = read_index(tmp_path / "auto")
    assert record["status"] == "ok"
    expected = {"name": "cpu", "description": f"CPU (NumPy {__import__('numpy').__version__})",
                "requested": "auto", "fallback_reason": "CUDA_VISIBLE_DEVICES is empty"}
    assert record["device"] == expected
    assert json.loads((tmp_path / "auto" / record["dir"] / "record.json").read_text())["device"] == expected
    assert json.loads((tmp_path / "auto" / record["dir"] / "frame.json").read_text())["stats"]["device"] == expected
    card = (tmp_path / "auto" / "README.md").read_text()
    assert "* rendered on: CPU (NumPy" in card and "asked for auto, fell back: CUDA_VISIBLE_DEVICES is empty" in card
    cpu = batch("run", str(set_file), "--out", str(tmp_path / "cpu"), "--quiet")
    assert cpu.returncode == 0, cpu.stderr
    assert read_index(tmp_path / "cpu")[0]["device"]["requested"] == "cpu"
    assert assert_same_frames(tmp_path / "auto", tmp_path / "cpu") == 1  # same job ids, same frame


def test_two_gpus_two_pinned_workers_the_same_frames(tmp_path):
    set_file = write_set(tmp_path, SIX_VIEWS)
    env = {"CUDA_VISIBLE_DEVICES": "0,1", "TOF_BATCH_FAKE_GPU": "1"}
    gpu = batch("run", str(set_file), "--out", str(tmp_path / "gpu"), "--device", "gpu", "--workers", "3",
                "--quiet", env=env)
    assert gpu.returncode == 0, gpu.stderr
    assert "device gpu: 2 GPU(s) visible (CUDA_VISIBLE_DEVICES 0, 1; from CUDA_VISIBLE_DEVICES)" in gpu.stderr
    assert "--workers 3 clamped to 2: one worker per GPU" in gpu.stderr
    assert "local pool, 2 worker processes (one per GPU: CUDA_VISIBLE_DEVICES 0, 1)" in gpu.stderr
    records = read_index(tmp_path / "gpu")
    assert len(records) == 6 and all(r["status"] == "ok" for r in records)
    pinned = {r["pid"]: r["cuda_visible_devices"] for r in records}
    assert sorted(pinned.values()) == ["0", "1"]  # two processes, each saw only its own GPU
    assert all(pinned[r["pid"]] == r["cuda_visible_devices"] for r in records)
    assert all(r["device"]["requested"] == "gpu" and "TOF_BATCH_FAKE_GPU" in r["device"]["fallback_reason"]
               for r in records)
    one = batch("run", str(set_file), "--out", str(tmp_path / "one"), "--workers", "1", "--quiet")
    assert one.returncode == 0, one.stderr
    assert assert_same_frames(tmp_path / "gpu", tmp_path / "one") == 6


def test_a_failing_gpu_fails_the_frame_and_retry_failed_renders_it(tmp_path, small_set):
    env = {"CUDA_VISIBLE_DEVICES": "0,1", "TOF_BATCH_FAKE_GPU": "1", "TOF_BATCH_FAIL": "gpu:corner/pose1/o3d303"}
    dataset = tmp_path / "dataset"
    first = batch("run", str(small_set), "--out", str(dataset), "--device", "gpu", "--quiet", env=env)
    assert first.returncode == 1, first.stderr
    assert "8 frames: 7 ok" in first.stderr and "Traceback" not in first.stderr
    (failed,) = [r for r in read_index(dataset) if r["status"] == "failed"]
    assert failed["error"] == "GpuUnavailable: GPU: fault injected by TOF_BATCH_FAIL='gpu:corner/pose1/o3d303'"
    assert failed["traceback"] is None and failed["device"]["requested"] == "gpu"
    assert failed["cuda_visible_devices"] in ("0", "1")
    # auto: the same GPU failure is rendered again on the CPU, the reason recorded.
    auto = batch("run", str(small_set), "--out", str(dataset), "--device", "auto", "--retry-failed", "--quiet",
                 env=env)
    assert auto.returncode == 0, auto.stderr
    assert "rendering 1 (1 view)" in auto.stderr
    (retried,) = [r for r in read_index(dataset) if r["job_id"] == failed["job_id"]]
    assert retried["status"] == "ok" and retried["device"]["requested"] == "auto"
    assert retried["device"]["fallback_reason"] == "GPU: fault injected by TOF_BATCH_FAIL='gpu:corner/pose1/o3d303'"


def test_compare_takes_the_device(tmp_path):
    out = tmp_path / "report"
    proc = batch("compare", "--scene", "corner", "--presets", "kinect_v2,o3d303", "--out", str(out), "--spp", "2",
                 "--max-depth", "2", "--resolution-scale", "0.0625", "--device", "gpu", "--quiet",
                 env={"CUDA_VISIBLE_DEVICES": "0,1", "TOF_BATCH_FAKE_GPU": "1"})
    assert proc.returncode == 0, proc.stderr
    assert "2 worker processes (one per GPU" in proc.stderr
    assert {r["cuda_visible_devices"] for r in read_index(out)} <= {"0", "1"}


@pytest.mark.dask
@pytest.mark.skipif(not has_module("distributed"), reason="needs dask[distributed]")
def test_dask_local_cluster_pins_one_worker_per_gpu(tmp_path, small_set):
    proc = batch("run", str(small_set), "--out", str(tmp_path / "dask"), "--dask", "local", "--device", "gpu",
                 "--quiet", env={"CUDA_VISIBLE_DEVICES": "0,1", "TOF_BATCH_FAKE_GPU": "1"})
    assert proc.returncode == 0, proc.stderr
    assert "Dask LocalCluster, 2 worker processes (one per GPU: CUDA_VISIBLE_DEVICES 0, 1)" in proc.stderr
    records = read_index(tmp_path / "dask")
    pinned = {r["pid"]: r["cuda_visible_devices"] for r in records}
    assert len(records) == 8 and set(pinned.values()) <= {"0", "1"} and len(pinned) <= 2
    assert all(pinned[r["pid"]] == r["cuda_visible_devices"] for r in records)


def test_the_card_says_which_devices_rendered():
    def record(status="ok", **device):
        return {"status": status, "device": device, "cuda_visible_devices": None}

    gpu = {"name": "gpu", "description": "GPU 0 (CUDA_VISIBLE_DEVICES=1): NVIDIA H100 (CuPy 14.0)",
           "requested": "gpu", "fallback_reason": None}
    fallback = {"name": "cpu", "description": "CPU (NumPy 1.26.4)", "requested": "auto",
                "fallback_reason": "GPU: out of device memory"}
    rows = device_rows([record(**gpu), record(**gpu), record(**fallback), {"status": "ok"},
                        record("failed", name=None, description=None, requested="gpu")])
    assert rows == [("GPU 0 (CUDA_VISIBLE_DEVICES=1): NVIDIA H100 (CuPy 14.0)", 2),
                    ("CPU (NumPy 1.26.4); asked for auto, fell back: GPU: out of device memory", 1),
                    ("not recorded (rendered before records held the device)", 1)]


STAND_IN_CUPY = """
import os

visible = os.environ.get("CUDA_VISIBLE_DEVICES")
with open(LOG, "a") as fh:
    fh.write(f"{os.getpid()} {visible}\\n")
if visible is None or "," not in visible:  # a pinned worker: fail as a CuPy without CUDA does
    raise ImportError("stand-in CuPy: no CUDA here")


class ndarray:  # the discovery's child process: CUDA sees every entry of the list
    pass


class cuda:
    class runtime:
        @staticmethod
        def getDeviceCount():
            return len(visible.split(","))
"""


def test_only_the_pinned_workers_touch_cupy(tmp_path, small_set):
    """A stand-in ``cupy`` package logs who imports it and with which CUDA_VISIBLE_DEVICES: the discovery's
    child process (which it answers with 2 GPUs), the kernels' warm-up child on the first GPU (batch.warmup:
    it fails, one line) and each worker, pinned to its GPU (where it fails as a CuPy without CUDA does: every
    frame fails with one line), never the batch process itself."""
    fake = tmp_path / "site" / "cupy"
    fake.mkdir(parents=True)
    log = tmp_path / "imports.log"
    (fake / "__init__.py").write_text(f"LOG = {str(log)!r}\n" + STAND_IN_CUPY)
    env = {"CUDA_VISIBLE_DEVICES": "0,1", "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), str(REPO)])}
    proc = batch("run", str(small_set), "--out", str(tmp_path / "dataset"), "--device", "gpu", "--quiet", env=env)
    assert proc.returncode == 1, proc.stderr
    assert "local pool, 2 worker processes (one per GPU: CUDA_VISIBLE_DEVICES 0, 1)" in proc.stderr
    assert "Traceback" not in proc.stderr
    records = read_index(tmp_path / "dataset")
    assert len(records) == 8 and all(r["status"] == "failed" and r["traceback"] is None for r in records)
    assert all(r["error"].startswith("GpuUnavailable: GPU: CuPy is not installed (stand-in CuPy: no CUDA here)")
               for r in records)
    imports = [(int(pid), visible) for pid, visible in (line.split() for line in log.read_text().splitlines())]
    worker_pids = {r["pid"]: r["cuda_visible_devices"] for r in records}
    (probe,) = [(pid, visible) for pid, visible in imports if visible == "0,1"]  # the parent would be a 2nd
    assert probe[0] not in worker_pids
    warm_up = [(pid, visible) for pid, visible in imports if pid != probe[0] and pid not in worker_pids]
    assert [visible for _, visible in warm_up] == ["0"]  # the warm-up child, before the workers, on GPU 0
    assert imports.index(warm_up[0]) < min(i for i, (pid, _) in enumerate(imports) if pid in worker_pids)
    assert "kernel warm-up failed after " in proc.stderr and "each worker compiles the kernels itself" in proc.stderr
    in_workers = [(pid, visible) for pid, visible in imports if pid in worker_pids]
    assert len(in_workers) == 8  # once per frame (a failed import is not cached)
    assert all(worker_pids.get(pid) == visible and visible in ("0", "1") for pid, visible in in_workers)


def test_cpu_batch_chooses_frames_and_threads_for_the_cores():
    """Without --workers a CPU batch renders cpus // CPU_THREADS_PER_FRAME frames at once, never more than
    it has frames, and gives each the remaining threads: every core busy, none oversubscribed."""
    from batch.devices import CPU_THREADS_PER_FRAME, cpu_frames_and_threads

    assert CPU_THREADS_PER_FRAME == 4
    assert cpu_frames_and_threads(2, 100) == (1, 2)
    assert cpu_frames_and_threads(16, 100) == (4, 4)
    assert cpu_frames_and_threads(16, 2) == (2, 8)
    assert cpu_frames_and_threads(128, 100) == (32, 4)
    assert cpu_frames_and_threads(1, 0) == (1, 1)
    for cpus in range(1, 65):
        for frames in (1, 3, 50):
            workers, threads = cpu_frames_and_threads(cpus, frames)
            assert 1 <= workers <= max(1, frames) and workers * threads <= max(cpus, 1)
