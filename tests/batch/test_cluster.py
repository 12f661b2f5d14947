"""batch.cluster: ``python -m batch run --scheduler`` on a scheduler and workers started apart (``dask scheduler``,
``dask worker``) from the venv, with no `batch` on their path, as a user starts them; a worker without tofcore is
one line."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from batch_helpers import REPO, TINY, batch, has_module, read_index, write_set

pytestmark = [pytest.mark.dask,
              pytest.mark.skipif(not has_module("distributed"), reason="needs dask[distributed]")]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _dask(*args: str, cwd: Path, env: dict) -> subprocess.Popen:
    """``dask ARGS`` of this venv in its own process group, output to a log file in ``cwd``."""
    script = Path(sys.executable).with_name("dask")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "dask"]
    log = open(cwd / f"{args[0]}-{time.monotonic_ns()}.log", "w")
    return subprocess.Popen([*command, *args], cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)


def _wait_for_workers(address: str, n: int) -> None:
    from distributed import Client

    with Client(address, timeout="20s") as client:
        client.wait_for_workers(n, timeout=20)


@pytest.fixture
def cluster(tmp_path):
    """A scheduler on a free loopback port and a function that starts workers; all stopped afterwards."""
    folder = tmp_path / "cluster"
    folder.mkdir()  # not the checkout: `batch` is not importable from the processes' folder
    # The venv's tofcore, but this checkout's: a folder holding only a link to it (the venv's editable install
    # may point at another checkout, a worktree's main); `batch` stays out of the processes' reach.
    (folder / "path").mkdir()
    (folder / "path" / "tofcore").symlink_to(REPO / "tofcore", target_is_directory=True)
    env = dict(os.environ, PYTHONPATH=str(folder / "path"), TOFCORE_TRACER="numpy",  # no kernel compile here
               NUMBA_NUM_THREADS="1")
    address = f"tcp://127.0.0.1:{_free_port()}"
    started = [_dask("scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1], "--no-dashboard",
                     cwd=folder, env=env)]

    def add_worker(extra_env: dict | None = None) -> None:
        started.append(_dask("worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                             "--local-directory", str(folder / f"worker{len(started)}"),
                             cwd=folder, env=dict(env, **(extra_env or {}))))
        _wait_for_workers(address, len(started) - 1)

    try:
        yield address, add_worker
    finally:
        for process in reversed(started):
            os.killpg(process.pid, signal.SIGTERM)
        for process in reversed(started):
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()


def test_a_cluster_started_apart_renders_from_the_checkout_and_names_a_worker_without_tofcore(tmp_path, cluster):
    address, add_worker = cluster
    set_file = write_set(tmp_path, 'seed = 3\npresets = ["kinect_v2"]\n' + TINY
                         + '[[scenes]]\ndemo = "corner"\n[[scenes.poses]]\nsuggested = true\n')
    add_worker()
    proc = batch("run", str(set_file), "--out", str(tmp_path / "d"), "--scheduler", address, "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert "1 frames: 1 ok" in proc.stderr
    assert [r["status"] for r in read_index(tmp_path / "d")] == ["ok"]

    # A worker whose environment cannot import tofcore: a package of that name that raises, first on its path.
    broken = tmp_path / "broken"
    (broken / "tofcore").mkdir(parents=True)
    (broken / "tofcore" / "__init__.py").write_text("raise ImportError('tofcore is not installed here')\n")
    add_worker({"PYTHONPATH": str(broken)})  # instead of the checkout's
    proc = batch("run", str(set_file), "--out", str(tmp_path / "e"), "--scheduler", address, "--quiet")
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "cannot import tofcore (ImportError: tofcore is not installed here)" in lines[0]
    assert lines[0].startswith("error: --scheduler: Dask worker tcp://127.0.0.1:")
