"""Helpers for the batch tests (a unique module name: every test folder has its own conftest)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

#: Top-level key and [quality] table of a tiny render; put it after the other top-level keys.
TINY = """
resolution_scale = 0.0625
[quality]
spp = 2
max_depth = 2
"""


def write_set(folder: Path, body: str, name: str = "set.toml") -> Path:
    path = folder / name
    path.write_text(body)
    return path


def batch(*args: str, env: dict | None = None, timeout: float = 240, cwd: Path = REPO) -> subprocess.CompletedProcess:
    """``python -m batch ARGS`` in a fresh process; its output is captured. ``env``: a value None unsets."""
    full_env = dict(os.environ)
    full_env.pop(_FAIL_ENV, None)
    full_env.pop(_FAKE_GPU_ENV, None)
    full_env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + ([full_env["PYTHONPATH"]] if full_env.get("PYTHONPATH")
                                                            else []))
    for key, value in (env or {}).items():
        if value is None:
            full_env.pop(key, None)
        else:
            full_env[key] = value
    return subprocess.run([sys.executable, "-m", "batch", *args], cwd=cwd, env=full_env, capture_output=True,
                          text=True, timeout=timeout)


_FAIL_ENV = "TOF_BATCH_FAIL"
_FAKE_GPU_ENV = "TOF_BATCH_FAKE_GPU"


def read_index(dataset: Path) -> list[dict]:
    return [json.loads(line) for line in (dataset / "index.jsonl").read_text().splitlines()]


def match_checksums(dataset: Path, job_id: str) -> None:
    """Rewrite a frame's record.json and index line for its files as they are now (sizes, SHA-256): a damaged
    file that only a reader of its content can find."""
    import hashlib

    folder = dataset / "frames" / job_id
    record = json.loads((folder / "record.json").read_bytes())
    for entry in record["files"]:
        data = (folder / entry["name"]).read_bytes()
        entry.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    data = (json.dumps(record, indent=1) + "\n").encode()
    (folder / "record.json").write_bytes(data)
    line = {**record, "record_file": {"kind": "record", "name": "record.json", "bytes": len(data),
                                      "sha256": hashlib.sha256(data).hexdigest()}}
    lines = [line if r["job_id"] == job_id else r for r in read_index(dataset)]
    (dataset / "index.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))


def has_module(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None




def frame_arrays(dataset: Path, record: dict) -> dict:
    """The EXR channels of a dataset frame."""
    import tofcore

    return tofcore.read_exr(dataset / record["dir"] / "frame.exr")


def assert_same_frames(a: Path, b: Path) -> int:
    """Every frame of dataset ``a`` is in ``b`` with bitwise equal EXR channels; the number compared."""
    import numpy as np

    records_a = {r["job_id"]: r for r in read_index(a)}
    records_b = {r["job_id"]: r for r in read_index(b)}
    assert records_a.keys() == records_b.keys()
    for job_id, record in records_a.items():
        assert record["status"] == records_b[job_id]["status"] == "ok", (record.get("error"), records_b[job_id])
        assert record["seed"] == records_b[job_id]["seed"]
        ca, cb = frame_arrays(a, record), frame_arrays(b, records_b[job_id])
        assert ca.keys() == cb.keys()
        for name in ca:
            assert ca[name].dtype == cb[name].dtype
            assert np.array_equal(ca[name], cb[name], equal_nan=True), f"{job_id}: channel {name} differs"
    return len(records_a)


def stray_files(dataset: Path) -> list[Path]:
    """Temporary files or half-written frame folders anywhere in the dataset."""
    return [p for p in dataset.rglob("*") if ".tmp-" in p.name or ".partial-" in p.name]
