"""batch.warmup: the workers' kernels compiled once, by one child process, before any worker starts.

The real warm-up compiles for ~15 s on 2 cores; here its command is a stand-in (a Python line that notes when it
ran) and the cache state is given, in a wrapper process that patches :mod:`batch.warmup` and runs
``python -m batch run`` (the tests' workers render with the NumPy tracer, tests/conftest.py).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from batch import warmup
from batch.devices import DevicePlan
from batch_helpers import REPO, TINY, read_index, write_set

# Patches batch.warmup, then runs the batch CLI: argv = log file, cache state (cold/warm), exit status of the
# stand-in warm-up, then the batch arguments.
_WRAPPER = r"""
import sys
import batch.warmup as warmup

log, state, status = sys.argv[1], sys.argv[2], int(sys.argv[3])
warmup.cpu_warmup_needed = lambda env: (state == "cold", "")

def command(python, device):
    note = (f"import time; open({log!r}, 'a').write('{device} ' + repr(time.time())); time.sleep(0.3); "
            f"open({log!r}, 'a').write(' ' + repr(time.time()) + chr(10)); "
            f"print('stand-in tracer on the {device.upper()}: ready'); raise SystemExit({status})")
    return [python, "-c", note]

warmup.warmup_command = command
from batch.cli import main
sys.exit(main(sys.argv[4:]))
"""


@pytest.fixture
def four_views(tmp_path: Path) -> Path:
    return write_set(tmp_path, 'seed = 3\npresets = ["kinect_v2"]\n' + TINY + """
[[scenes]]
demo = "corner"
[[scenes.poses]]
count = 4
box_min = [-0.5, -2.2, 1.2]
box_max = [0.5, -1.8, 1.8]
target = [0.0, 0.0, 1.2]
""")


def _run(tmp_path: Path, set_file: Path, name: str, state: str, *extra: str, status: int = 0,
         env: dict | None = None) -> tuple[subprocess.CompletedProcess, list[list[str]]]:
    log = tmp_path / f"{name}.log"
    child_env = dict(os.environ, PYTHONPATH=str(REPO), **(env or {}))
    proc = subprocess.run([sys.executable, "-c", _WRAPPER, str(log), state, str(status), "run", str(set_file),
                           "--out", str(tmp_path / name), "--quiet", *extra],
                          cwd=REPO, env=child_env, capture_output=True, text=True, timeout=240)
    return proc, [line.split() for line in log.read_text().splitlines()] if log.exists() else []


def test_a_cold_cache_is_warmed_once_before_the_workers_start(tmp_path, four_views):
    proc, warm_ups = _run(tmp_path, four_views, "cold", "cold", "--workers", "2")
    assert proc.returncode == 0, proc.stderr
    (device, started, ended), = warm_ups                       # once, not per worker
    assert device == "cpu"
    records = read_index(tmp_path / "cold")
    assert len(records) == 4 and all(r["status"] == "ok" for r in records)
    assert min(r["timing"]["worker_started"] for r in records) >= float(ended)   # before any worker
    assert ("kernel warm-up: compiling the CPU kernels (numba) once for the 2 workers (`python -m tofcore warmup "
            "--device cpu`); the workers then load them …") in proc.stderr
    assert "kernel warm-up done in " in proc.stderr and ": stand-in tracer on the CPU: ready" in proc.stderr
    assert proc.stderr.index("kernel warm-up done") < proc.stderr.index("rendering 4 (4 views)")


def test_a_warm_cache_one_worker_or_in_process_skip_it(tmp_path, four_views):
    for name, state, extra in (("warm", "warm", ("--workers", "2")), ("one", "cold", ("--workers", "1"))):
        proc, warm_ups = _run(tmp_path, four_views, name, state, *extra)
        assert proc.returncode == 0, proc.stderr
        assert warm_ups == [] and "kernel warm-up" not in proc.stderr, name


def test_a_failed_warm_up_leaves_the_workers_to_compile(tmp_path, four_views):
    proc, warm_ups = _run(tmp_path, four_views, "failed", "cold", "--workers", "2", status=3)
    assert proc.returncode == 0, proc.stderr
    assert len(warm_ups) == 1
    assert [r["status"] for r in read_index(tmp_path / "failed")] == ["ok"] * 4
    (line,) = [ln for ln in proc.stderr.splitlines() if ln.startswith("kernel warm-up failed")]
    assert line.endswith("(exit status 3): each worker compiles the kernels itself"), line


def test_two_stand_in_gpus_warm_the_cpu_their_workers_render_on(tmp_path, four_views):
    proc, warm_ups = _run(tmp_path, four_views, "fake-gpu", "cold", "--device", "gpu",
                          env={"TOF_BATCH_FAKE_GPU": "1", "CUDA_VISIBLE_DEVICES": "3,5"})
    assert proc.returncode == 0, proc.stderr
    assert [w[0] for w in warm_ups] == ["cpu"]
    assert {r["cuda_visible_devices"] for r in read_index(tmp_path / "fake-gpu")} == {"3", "5"}


# --------------------------------------------------------------------------- the plan (no process started)

GPUS = DevicePlan("gpu", "gpu", gpus=("3", "5"), workers=2)


def test_a_gpu_set_warms_up_on_its_first_gpu_whatever_the_cache():
    warm, why_not = warmup.plan_warmup(GPUS, executor="local", workers=2, env={"PATH": "/bin"})
    assert why_not == "" and warm is not None
    assert warm.device == "gpu" and warm.gpu == "3" and warm.workers == 2
    assert warm.command == (sys.executable, "-m", "tofcore", "warmup", "--device", "gpu")
    assert warm.env["CUDA_VISIBLE_DEVICES"] == "3" and warm.env["PATH"] == "/bin"
    assert warm.env["PYTHONPATH"].split(os.pathsep)[0] == str(REPO)          # this checkout's tofcore
    assert "on GPU 3" in warm.start_line()
    # The NumPy tracer on a GPU still compiles CuPy's kernels; a LocalCluster's workers are on this machine too.
    assert warmup.plan_warmup(GPUS, executor="dask-local", workers=2, env={"TOFCORE_TRACER": "numpy"})[0].gpu == "3"


@pytest.mark.parametrize("executor, workers", [("cluster", 2), ("inline", 2), ("local", 1)])
def test_no_warm_up_where_it_cannot_help(executor, workers):
    assert warmup.plan_warmup(GPUS, executor=executor, workers=workers, env={}) == (None, "")


def test_the_cpu_plan_follows_the_cache(monkeypatch):
    cpu = DevicePlan("cpu", "cpu", workers=2)
    assert warmup.plan_warmup(cpu, executor="local", workers=2, env={"TOFCORE_TRACER": "numpy"}) == (None, "")
    monkeypatch.setattr(warmup, "cpu_warmup_needed", lambda env: (False, "kernel warm-up skipped: read-only"))
    assert warmup.plan_warmup(cpu, executor="local", workers=2, env={}) == (None, "kernel warm-up skipped: read-only")
    monkeypatch.setattr(warmup, "cpu_warmup_needed", lambda env: (True, ""))
    warm, _ = warmup.plan_warmup(cpu, executor="local", workers=2, env={"CUDA_VISIBLE_DEVICES": "0"})
    assert warm.device == "cpu" and warm.gpu is None and warm.command[-1] == "cpu"


def test_cpu_warmup_needed_reads_the_cache(monkeypatch):
    from tofcore import compiled

    assert warmup.cpu_warmup_needed({"TOFCORE_TRACER": "numpy"}) == (False, "")
    for warm, expected in ((None, False), (True, False), (False, True)):
        monkeypatch.setattr(compiled, "cpu_warm", lambda warm=warm: warm)
        monkeypatch.setattr(compiled, "cache_problem", lambda: "")
        assert warmup.cpu_warmup_needed({}) == (expected, "")
    monkeypatch.setattr(compiled, "cache_problem", lambda: "NUMBA_CACHE_DIR=/ro cannot be used")
    assert warmup.cpu_warmup_needed({}) == (False, "kernel warm-up skipped: NUMBA_CACHE_DIR=/ro cannot be used")


def test_a_warm_up_that_cannot_start_or_times_out_is_one_line(tmp_path):
    lines: list[str] = []
    missing = warmup.WarmUp("cpu", (str(tmp_path / "no-python"), "-c", "pass"), dict(os.environ), 2)
    assert warmup.warm_up(missing, lines.append) is False
    assert lines[-1].startswith("kernel warm-up failed after ") and "could not be started" in lines[-1]
    slow = warmup.WarmUp("cpu", (sys.executable, "-c", "import time; time.sleep(30)"), dict(os.environ), 2)
    assert warmup.warm_up(slow, lines.append, timeout_s=0.5) is False
    assert "s and was stopped): each worker compiles the kernels itself" in lines[-1], lines[-1]
