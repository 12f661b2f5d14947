"""Multi-GPU runs (issue 26): a GPU worker killed mid-run, and mixed work under ``--device auto``.

Each test runs on two fake GPUs (``TOF_BATCH_FAKE_GPU``: two pinned worker processes rendering on the
CPU; what CI runs) and, marked ``gpu``, on the first two real GPUs of a machine that has at least two
(skipped elsewhere). On a real GPU the set is the benchmark's frame (Kinect v2 room, 512 × 424, 64 spp,
the tracer chosen as a user's run chooses it): point ``CUPY_CACHE_DIR`` and ``NUMBA_CACHE_DIR`` at warm
kernel caches to keep the first frame short.
"""

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
from batch_helpers import REPO, batch, read_index, stray_files, write_set

FAKE_SET = """
seed = 5
presets = ["kinect_v2"]
resolution_scale = 0.25
[quality]
spp = 8
max_depth = 2
[output]
formats = ["png", "json"]
[[scenes]]
demo = "room"
[[scenes.poses]]
count = 8
box_min = [-1.5, -1.8, 1.2]
box_max = [1.5, -1.2, 1.9]
target = [0.0, 1.0, 0.8]
seed = 1
"""
GPU_SET = FAKE_SET.replace("resolution_scale = 0.25", "resolution_scale = 1.0").replace("spp = 8", "spp = 64") \
    .replace("max_depth = 2", "max_depth = 5")


def _two_real_gpus() -> list[str]:
    from batch.devices import visible_gpus

    return list(visible_gpus().ids[:2])


@pytest.fixture(params=["fake", pytest.param("cuda", marks=pytest.mark.gpu)])
def two_gpus(request) -> tuple[dict, str]:
    """(environment for ``python -m batch``, set file body) for two fake or two real GPUs."""
    if request.param == "fake":
        return {"CUDA_VISIBLE_DEVICES": "0,1", "TOF_BATCH_FAKE_GPU": "1"}, FAKE_SET
    gpus = _two_real_gpus()
    if len(gpus) < 2:
        pytest.skip(f"needs 2 CUDA GPUs and CuPy; {len(gpus)} usable")
    # The product's tracer choice (the suite's conftest pins the NumPy reference): on a GPU, the compiled one.
    return {"CUDA_VISIBLE_DEVICES": ",".join(gpus), "TOFCORE_TRACER": "auto"}, GPU_SET


def _start(env: dict, *args: str) -> subprocess.Popen:
    full = dict(os.environ, PYTHONPATH=str(REPO), **env)
    full.pop("TOF_BATCH_FAIL", None)
    return subprocess.Popen([sys.executable, "-m", "batch", *args], cwd=REPO, env=full, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True, text=True)


def _first_ok_record(index: Path, proc: subprocess.Popen, timeout_s: float) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        lines = index.read_text().splitlines() if index.exists() else []
        ok = [r for r in map(json.loads, lines[:-1] if lines and not lines[-1].endswith("}") else lines)
              if r["status"] == "ok"]
        if ok:
            return ok[0]
        time.sleep(0.02)


def test_a_killed_gpu_worker_fails_only_its_view_and_retry_failed_completes_the_set(tmp_path, two_gpus):
    env, body = two_gpus
    set_file = write_set(tmp_path, body)
    dataset = tmp_path / "dataset"
    proc = _start(env, "run", str(set_file), "--out", str(dataset), "--device", "gpu", "--quiet")
    first = _first_ok_record(dataset / "index.jsonl", proc, timeout_s=300)
    victim, victim_gpu = first["pid"], first["cuda_visible_devices"]
    killed_at = time.time()
    os.kill(victim, signal.SIGKILL)  # it is rendering its next view (the parent hands one over at once)
    _, stderr = proc.communicate(timeout=600)
    print(stderr)
    assert proc.returncode in (0, 1) and "Traceback" not in stderr, stderr

    records = read_index(dataset)
    assert len(records) == 8 and len({r["job_id"] for r in records}) == 8  # each frame indexed once
    assert Dataset(dataset).check("sha256")["problems"] == [] and stray_files(dataset) == []
    failed = [r for r in records if r["status"] == "failed"]
    # what the dead worker held: the view it rendered and the frame its writer wrote (batch.writer); a frame it
    # had published is indexed ok
    assert len(failed) <= 2
    for record in failed:
        assert record["error"].startswith(f"WorkerDied: the worker process for GPU {victim_gpu} (pid {victim}) "
                                          f"died while rendering or writing this frame (killed by SIGKILL)")
        assert record["pid"] == victim and record["cuda_visible_devices"] == victim_gpu
        assert not (dataset / "frames" / record["job_id"]).exists()
    # The other GPU's worker kept working: the same process rendered frames after the kill.
    others = [r for r in records if r["status"] == "ok" and r["cuda_visible_devices"] != victim_gpu]
    assert len({r["pid"] for r in others}) == 1
    assert any(r["timing"]["render_started"] > killed_at for r in others)
    assert len(list((dataset / "frames").iterdir())) == 8 - len(failed)

    retry = batch("run", str(set_file), "--out", str(dataset), "--device", "gpu", "--quiet", "--retry-failed",
                  env=env, timeout=600)
    assert retry.returncode == 0, retry.stderr
    assert all(r["status"] == "ok" for r in read_index(dataset)) and len(read_index(dataset)) == 8
    verify = batch("verify", str(dataset))
    assert verify.returncode == 0, verify.stdout + verify.stderr


def test_auto_with_gpus_renders_every_frame_on_them_and_falls_back_per_frame(tmp_path):
    """``--device auto`` with GPUs: one worker per GPU and no CPU workers beside them (a CPU frame takes ~30×
    a GPU frame: the set would wait for it); a frame the GPU cannot render is rendered on the CPU by its GPU
    worker, the reason recorded; the others stay on their GPUs."""
    set_file = write_set(tmp_path, FAKE_SET.replace("spp = 8", "spp = 2").replace("0.25", "0.0625"))
    env = {"CUDA_VISIBLE_DEVICES": "0,1", "TOF_BATCH_FAKE_GPU": "1", "TOF_BATCH_FAIL": "gpu:room/pose3/*"}
    proc = batch("run", str(set_file), "--out", str(tmp_path / "auto"), "--device", "auto", "--workers", "4",
                 "--quiet", env=env)
    assert proc.returncode == 0, proc.stderr
    assert "--workers 4 clamped to 2: one worker per GPU" in proc.stderr
    assert "local pool, 2 worker processes (one per GPU: CUDA_VISIBLE_DEVICES 0, 1)" in proc.stderr
    records = read_index(tmp_path / "auto")
    assert len(records) == 8 and {r["cuda_visible_devices"] for r in records} <= {"0", "1"}
    reasons = {r["view"]["label"]: r["device"]["fallback_reason"] for r in records}
    assert reasons.pop("pose3") == "GPU: fault injected by TOF_BATCH_FAIL='gpu:room/pose3/*'"
    assert all("TOF_BATCH_FAKE_GPU" in reason for reason in reasons.values())  # the stand-in for "on the GPU"
