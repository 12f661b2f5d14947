"""The dataset folder: frame folders, the index, records, verification, the lock.

Layout
------
::

    DATASET/
      index.jsonl            one JSON record per frame (job), in set order after a run
      README.md              the dataset card (counts, presets, settings, how to load)
      frames/<job_id>/       tofcore.write_frame outputs + record.json (the frame's done record)
      frames/.<job_id>.partial-XXXXXXXX/   a frame being written (removed by the next run)
      .lock                  held (flock) while a run writes to the dataset

Records
-------
A record is a flat JSON object: ``job_id``, ``status`` (``"ok"`` or
``"failed"``), ``scene``, ``source`` (kind, demo name or path, SHA-256),
``view`` (label, camera, frame, pose kind and index), ``world_from_sensor``,
``preset``, ``sensor_name``, ``seed`` (the render seed), ``set_seed``,
``settings`` (spp, max_depth, time_budget_s, target_error_m, resolution_scale,
ambient_w_m2_sr, formats, width, height), ``dir`` and ``files`` (kind, name,
bytes, sha256), ``render_seconds``, ``spp`` reached, ``passes``,
``est_depth_error_m`` and ``convergence`` (per pass: seconds, spp, estimated
RMS depth error), ``rms_depth_error_m``, ``median_abs_depth_error_m``,
``multipath_rms_m``, ``valid_fraction``, ``device`` (where the frame rendered:
``name`` ``"cpu"``/``"gpu"``, ``description`` e.g. ``"GPU 0 (CUDA_VISIBLE_DEVICES=1):
NVIDIA H100 … (CuPy 14.0)"``, ``requested`` ``"cpu"``/``"gpu"``/``"auto"``,
``fallback_reason`` why ``auto`` used the CPU; a failed frame has only what was
requested), ``cuda_visible_devices`` (the worker's ``CUDA_VISIBLE_DEVICES`` for
GPU and auto renders: the GPU it was pinned to), ``error`` and ``traceback``
when failed (a GPU failure: one line, no traceback), ``host``, ``finished``
(UTC).

Resuming
--------
A frame is done when its folder exists, its ``record.json`` says ``ok`` and
every file matches the size and SHA-256 in the record. The index is appended
one line per finished job (flush + fsync) and rewritten atomically at the
start and the end of a run, so after a run it holds exactly one record per
job; a line cut by a crash is ignored, and a frame whose folder is complete
but whose index line was lost is taken from its ``record.json``.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import math
import os
import secrets
import shutil
import stat
from collections.abc import Iterable
from contextlib import contextmanager
from pathlib import Path

FRAMES = "frames"
INDEX = "index.jsonl"
CARD = "README.md"
RECORD = "record.json"
LOCK = ".lock"


class DatasetLocked(RuntimeError):
    """Another run holds the dataset's lock."""


def _open_lock_file(path: Path):
    """The lock file, opened without following a symbolic link and only if it is a regular file.

    ``open(path, "a+")`` would follow a link planted at DATASET/.lock and the run would then truncate the
    link's target; O_NOFOLLOW refuses it (ELOOP), and the mode check refuses a FIFO or a device.
    """
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK, 0o644)
    except OSError as exc:
        if path.is_symlink():
            raise DatasetLocked(f"{path}: the lock file is a symbolic link; remove it (a run never "
                                f"writes through links)") from None
        raise DatasetLocked(f"{path}: cannot open the lock file ({exc.strerror})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise DatasetLocked(f"{path}: the lock file is not a regular file; remove it")
    return os.fdopen(fd, "r+")


# --------------------------------------------------------------------------- atomic files

def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_bytes_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to a temp file beside ``path``, fsync, rename over ``path``."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{secrets.token_hex(4)}")
    try:
        with open(tmp, "xb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def jsonable(value):
    """``value`` with NaN and ±inf floats replaced by None (JSON has neither), recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    return value


def dumps(record) -> str:
    """One index line (no newline): compact JSON, NaN/inf as null."""
    return json.dumps(jsonable(record), allow_nan=False, separators=(",", ":"))


def write_json_atomic(path: Path, data) -> Path:
    return write_bytes_atomic(path, (json.dumps(jsonable(data), indent=1, allow_nan=False) + "\n").encode())


def sha256_of(path: Path) -> str:
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def file_entry(kind: str, path: Path) -> dict:
    """``{kind, name, bytes, sha256}`` of a written file."""
    path = Path(path)
    return {"kind": kind, "name": path.name, "bytes": path.stat().st_size, "sha256": sha256_of(path)}


def publish(partial: Path, final: Path) -> None:
    """Rename a finished frame folder into place (replacing a stale one), then sync the parent folder."""
    if final.exists():
        shutil.rmtree(final)
    os.rename(partial, final)
    _fsync_dir(final.parent)


# --------------------------------------------------------------------------- the dataset

class Dataset:
    """A dataset folder (see the module docstring). Nothing is created until :meth:`create`."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).resolve()
        self.frames = self.root / FRAMES
        self.index_path = self.root / INDEX
        self._index_fh = None

    def create(self) -> None:
        self.frames.mkdir(parents=True, exist_ok=True)

    @contextmanager
    def locked(self):
        """Hold an exclusive lock on the dataset for the duration (released by the kernel if killed)."""
        self.create()
        fh = _open_lock_file(self.root / LOCK)
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            fh.close()
            raise DatasetLocked(f"{self.root}: another run is writing to this dataset ({holder}); "
                                f"wait for it or stop it") from None
        try:
            fh.seek(0)
            fh.truncate()
            fh.write(f"pid {os.getpid()}\n")
            fh.flush()
            yield self
        finally:
            self.close_index()
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
            fh.close()

    # ---------------------------------------------------------------- index
    def read_index(self) -> tuple[dict[str, dict], dict]:
        """Records by job id (the last line of a job wins) and ``{"lines", "bad_lines", "duplicates"}``."""
        records: dict[str, dict] = {}
        info = {"lines": 0, "bad_lines": 0, "duplicates": 0}
        if not self.index_path.exists():
            return records, info
        with open(self.index_path, "rb") as fh:
            for raw in fh:
                info["lines"] += 1
                try:
                    record = json.loads(raw)
                    job_id = record["job_id"]
                except (ValueError, KeyError, TypeError):
                    info["bad_lines"] += 1  # a line cut by a crash
                    continue
                if job_id in records:
                    info["duplicates"] += 1
                    del records[job_id]  # keep file order = order of the last record
                records[job_id] = record
        return records, info

    def rewrite_index(self, records: Iterable[dict]) -> None:
        """Replace the index atomically with ``records`` (one line each)."""
        self.close_index()
        text = "".join(dumps(r) + "\n" for r in records)
        write_bytes_atomic(self.index_path, text.encode())

    def append(self, record: dict) -> None:
        """Append one record line and make it durable (flush + fsync) before returning."""
        if self._index_fh is None:
            self._index_fh = open(self.index_path, "ab")
        self._index_fh.write((dumps(record) + "\n").encode())
        self._index_fh.flush()
        os.fsync(self._index_fh.fileno())

    def close_index(self) -> None:
        if self._index_fh is not None:
            self._index_fh.close()
            self._index_fh = None

    # ---------------------------------------------------------------- frames
    def folder_record(self, job_id: str) -> dict | None:
        """The ``record.json`` of a published frame folder, or None."""
        try:
            return json.loads((self.frames / job_id / RECORD).read_text())
        except (OSError, ValueError):
            return None

    def verify(self, record: dict, mode: str = "sha256") -> str | None:
        """None when the record's frame is complete on disk, else why not.

        ``mode``: ``"sha256"`` checks sizes and checksums, ``"size"`` only sizes (fast).
        """
        if record.get("status") != "ok":
            return f"status {record.get('status')!r}"
        folder = self.frames / record["job_id"]
        if not (folder / RECORD).is_file():
            return "no record.json in the frame folder"
        for entry in record.get("files", []):
            path = folder / entry["name"]
            try:
                size = path.stat().st_size
            except OSError:
                return f"{entry['name']} missing"
            if size != entry["bytes"]:
                return f"{entry['name']} has {size} bytes, the record says {entry['bytes']}"
            if mode == "sha256" and sha256_of(path) != entry["sha256"]:
                return f"{entry['name']} checksum differs from the record"
        return None

    def clean_partials(self) -> int:
        """Remove frame folders left half-written by a killed run; the number removed."""
        removed = 0
        if self.frames.is_dir():
            for path in self.frames.glob(".*.partial-*"):
                shutil.rmtree(path, ignore_errors=True)
                removed += 1
        return removed

    def write_card(self, text: str) -> None:
        write_bytes_atomic(self.root / CARD, text.encode())
