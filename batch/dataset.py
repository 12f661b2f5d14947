"""The dataset folder: frame folders, the index, records, verification, the lock.

Layout
------
::

    DATASET/
      index.jsonl            one JSON record per frame (job), in set order after a run
      set.json               the set of the last run: its set file and job ids (in set order)
      README.md              the dataset card (counts, presets, settings, how to load)
      frames/<job_id>/       tofcore.write_frame outputs + record.json (the frame's done record)
      frames/.<job_id>.partial-XXXXXXXX/   a frame being written (removed by the next run)
      frames/.<job_id>.stale-XXXXXXXX/     a frame folder being deleted (it failed verification)
      index.jsonl.rejected   lines of the index that were not records, as they were (if any)
      .lock                  held (flock) while a run writes to the dataset

A run writes nothing outside the dataset folder: each of these paths, when it
exists, must be a real folder or file, never a symbolic link
(:meth:`Dataset.check_paths`, :func:`_open_lock_file`); frame folders are made fresh (``mkdir``), files
are written to temp names (``O_EXCL``) and renamed over, appended files are
opened with ``O_NOFOLLOW``.

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
when failed (a GPU failure: one line, no traceback), ``host``, ``pid``,
``finished`` (UTC). In the index only, an ok record also has ``record_file``
(kind ``"record"``, name ``record.json``, bytes, sha256).

Resuming
--------
A frame is done when its folder exists, its ``record.json`` says ``ok``, the
index line's ``record_file`` (size and SHA-256 of ``record.json``, kept only in
the index: a file cannot hold its own checksum) matches, and every file
matches the size and SHA-256 in the record. The index is appended one line per
finished job (one ``write``, then fsync) and rewritten atomically at the start
and the end of a run, so after a run it holds exactly one record per job.

Exactly once
------------
A frame folder is published once: the worker renames its staging folder to
``frames/<job_id>/`` with ``rename(2)``, which refuses a non-empty target
(:func:`publish`), so a second execution of the same job (Dask running a view
again after a worker died, a duplicate task, a zombie task of an earlier run)
never replaces a published folder: it deletes its staging folder and reports
the published record instead. The parent, the index's only writer, indexes
for a job the ``record.json`` of its published folder when there is one
(:meth:`Dataset.settle`) and appends a job's line once per run
(:meth:`Dataset.append` skips a line it has already written). A folder that
must be rendered again (it failed verification) is moved aside and deleted by
the parent before any worker starts (:meth:`Dataset.discard`).

Index lines that are not records
--------------------------------
The index can be rebuilt from the frame folders, so a bad line never stops a
run (:meth:`Dataset.read_index`): an incomplete last line (a run stopped while
writing it) is dropped with a note; any other line that is not a record
(:func:`record_problem`: not JSON, not an object, a record with keys missing
or of the wrong type) is reported as ``index.jsonl:LINE: ignored (why)``,
copied verbatim to ``index.jsonl.rejected`` and left out of the rewritten
index. The frame it would describe is then taken from its folder's
``record.json`` when every file verifies, else rendered again.
``tofcore-batch verify DATASET`` checks all of this without changing anything.

When the set changed
--------------------
A run keeps the records of frames that are not in its set (an earlier version
of the set file, another set run into the same folder): they stay in the index
and in ``frames/``, after the set's own. Each run writes ``set.json``
(:meth:`Dataset.write_current_set`) before it renders; the run warns how many
indexed frames are not in its set, ``verify`` lists them
(:meth:`Dataset.outside_set`), and the reader opens only the set's frames with
``Dataset(root, current_set=True)`` (:mod:`tofcore.output.dataset`).
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import math
import os
import re
import secrets
import shutil
import stat
from collections.abc import Iterable
from contextlib import contextmanager
from pathlib import Path

from tofcore.output.dataset import CURRENT_SET, FRAMES, INDEX, RECORD, STATUSES, read_current_set, read_regular
from tofcore.output.dataset import differing_keys as reader_differing_keys

CARD = "README.md"
LOCK = ".lock"
REJECTED = INDEX + ".rejected"
#: A job id (``batch.jobs.JOB_ID_HEX`` hex digits); also what makes ``frames/<job_id>`` a safe path.
JOB_ID = re.compile(r"[0-9a-f]{16}")
_SHA256 = re.compile(r"[0-9a-f]{64}")
# What a run leaves behind when it is killed: a frame being written or deleted, a temp file of
# write_bytes_atomic (the index, the card) in the dataset folder.
_STRAY_FRAME = re.compile(r"\.[0-9a-f]{16}\.(partial|stale)-[0-9a-f]{8}")
_STRAY_TEMP = re.compile(r"\..+\.tmp-[0-9a-f]{8}")


class DatasetLocked(RuntimeError):
    """Another run holds the dataset's lock."""


class UnsafeDataset(RuntimeError):
    """A folder or file that a run writes is a symbolic link (or not a folder/file): nothing is written."""


#: What a run creates or writes in the dataset folder; each must be what it seems, never a symbolic link
#: (the lock file has its own check: :func:`_open_lock_file`).
WRITTEN = {FRAMES: "folder", INDEX: "file", CARD: "file", REJECTED: "file"}


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


def exr_defect(path: Path) -> str | None:
    """Why tofcore's EXR codec cannot read ``path`` (header, declared sizes, offset table, chunk headers:
    :func:`tofcore.output.exr.check`, no pixels inflated), or None. A file whose checksum was made to
    match the record is still found."""
    from tofcore.errors import ExrError
    from tofcore.output import exr

    try:
        exr.check(path)
    except ExrError as exc:
        return str(exc).removeprefix(f"{path}: ")
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    return None


def file_entry(kind: str, path: Path) -> dict:
    """``{kind, name, bytes, sha256}`` of a written file."""
    path = Path(path)
    return {"kind": kind, "name": path.name, "bytes": path.stat().st_size, "sha256": sha256_of(path)}


def record_bytes(record: dict) -> bytes:
    """The bytes of a ``record.json``: indented JSON, NaN/inf as null, a final newline."""
    return (json.dumps(jsonable(record), indent=1, allow_nan=False) + "\n").encode()


def record_file_entry(data: bytes) -> dict:
    """The index's ``record_file`` entry for a ``record.json`` holding ``data``."""
    return {"kind": "record", "name": RECORD, "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def write_record(folder: Path, record: dict) -> dict:
    """Write ``folder/record.json`` atomically; ``record`` with its ``record_file`` entry (for the index)."""
    data = record_bytes(record)
    write_bytes_atomic(Path(folder) / RECORD, data)
    return {**record, "record_file": record_file_entry(data)}


def differing_keys(line: dict, stored) -> list[str]:
    """The top-level keys in which an index line and its frame's ``record.json`` differ (``record_file``,
    the index's own entry, left out); ``["record.json"]`` when ``stored`` is not a JSON object.

    The line is compared as JSON (NaN and inf as null, :func:`dumps`), so a line that is ``record.json``
    plus ``record_file`` differs in nothing (:func:`tofcore.output.dataset.differing_keys`, the reader's).
    """
    if not isinstance(stored, dict):
        return [RECORD]
    return reader_differing_keys(json.loads(dumps(line)), stored)


def publish(partial: Path, final: Path) -> bool:
    """Rename a finished frame folder into place unless one is there; True when this call published it.

    ``rename(2)`` replaces an empty folder but refuses a non-empty one (``ENOTEMPTY``, ``EEXIST`` on
    some systems), in one atomic step: of several executions of the same job exactly one publishes,
    and a published folder (never empty: it holds ``record.json``) is never replaced. A folder that
    must be rendered again is removed by the parent first (:meth:`Dataset.discard`).
    """
    try:
        os.rename(partial, final)
    except OSError as exc:
        if exc.errno in (errno.ENOTEMPTY, errno.EEXIST):
            return False
        raise
    _fsync_dir(final.parent)
    return True


# --------------------------------------------------------------------------- records

def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _json_kind(value) -> str:
    return {list: "list", str: "string", bool: "boolean", int: "number", float: "number",
            type(None): "null"}.get(type(value), type(value).__name__)


def _entry_problem(entry, where: str) -> str | None:
    """None when ``entry`` is a ``{kind, name, bytes, sha256}`` file entry naming a plain file name."""
    if not isinstance(entry, dict):
        return f"{where} must be an object, got {_short(entry)}"
    name = entry.get("name")
    if not isinstance(name, str) or name in ("", ".", "..") or any(c in name for c in "/\\\0"):
        return f"{where}.name must be a file name, got {_short(name)}"
    size = entry.get("bytes")
    if not isinstance(size, int) or isinstance(size, bool) or size < 0:
        return f"{where}.bytes must be an integer >= 0, got {_short(size)}"
    digest = entry.get("sha256")
    if not isinstance(digest, str) or not _SHA256.fullmatch(digest):
        return f"{where}.sha256 must be 64 hex digits, got {_short(digest)}"
    return None


def record_problem(record) -> str | None:
    """None when ``record`` is a frame record that every reader can use, else what is wrong (one line).

    Checked: ``job_id`` (16 hex digits), ``status`` (``"ok"``/``"failed"``), ``scene`` and ``preset``
    (strings), ``view`` (an object with a ``label``), ``settings`` (an object with integer ``width`` and
    ``height``); for an ok record also ``dir`` (``frames/<job_id>``), ``files`` (a non-empty list of
    ``{kind, name, bytes, sha256}`` with plain file names) and, when present, ``record_file``.
    """
    if not isinstance(record, dict):
        return f"a JSON {_json_kind(record)}, not a record"
    job_id = record.get("job_id")
    if not isinstance(job_id, str) or not JOB_ID.fullmatch(job_id):
        return f"job_id must be 16 hex digits, got {_short(job_id)}"
    if record.get("status") not in STATUSES:
        return f"status must be 'ok' or 'failed', got {_short(record.get('status'))}"
    for key in ("scene", "preset"):
        if not isinstance(record.get(key), str):
            return f"{key} must be a string, got {_short(record.get(key))}"
    view = record.get("view")
    if not isinstance(view, dict) or not isinstance(view.get("label"), str):
        return f"view must be an object with a label, got {_short(view)}"
    settings = record.get("settings")
    if not isinstance(settings, dict) or not all(isinstance(settings.get(k), int) for k in ("width", "height")):
        return f"settings must be an object with integer width and height, got {_short(settings)}"
    if record["status"] == "failed":
        return None
    if record.get("dir") != f"{FRAMES}/{job_id}":
        return f"dir must be {FRAMES}/{job_id!s}, got {_short(record.get('dir'))}"
    files = record.get("files")
    if not isinstance(files, list) or not files:
        return f"files must be a non-empty list, got {_short(files)}"
    for i, entry in enumerate(files):
        problem = _entry_problem(entry, f"files[{i}]")
        if problem is not None:
            return problem
    if "record_file" in record:
        return _entry_problem(record["record_file"], "record_file")
    return None


# --------------------------------------------------------------------------- the dataset

class Dataset:
    """A dataset folder (see the module docstring). Nothing is created until :meth:`create`."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).resolve()
        self.frames = self.root / FRAMES
        self.index_path = self.root / INDEX
        self._index_fd: int | None = None
        self._appended: dict[str, str] = {}  # job id -> status of the line this object appended

    def create(self) -> None:
        """Make the dataset and ``frames/`` folders, after :meth:`check_paths`."""
        self.check_paths()
        self.frames.mkdir(parents=True, exist_ok=True)

    def check_paths(self) -> None:
        """:class:`UnsafeDataset` when a path of :data:`WRITTEN` exists as a symbolic link or as the wrong kind.

        A run writes only inside the dataset folder: a ``frames`` link to a folder elsewhere would get
        complete frame folders written there, so links are refused, not followed (the lock file's
        own check, :func:`_open_lock_file`, also refuses FIFOs and devices).
        """
        for name, kind in WRITTEN.items():
            path = self.root / name
            if path.is_symlink():
                raise UnsafeDataset(f"{path}: a symbolic link; a run writes only inside the dataset folder and "
                                    f"never through links: remove it")
            if path.exists() and (path.is_dir() != (kind == "folder")):
                raise UnsafeDataset(f"{path}: must be a {kind}; remove it or choose another --out")

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

    @contextmanager
    def reading(self):
        """Hold a shared lock for a reader that must not see a run half-way (``verify``); creates nothing.

        Raises :class:`DatasetLocked` while a run holds the dataset.
        """
        try:
            fd = os.open(self.root / LOCK, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
        except FileNotFoundError:
            yield self  # no run has ever written here
            return
        except OSError as exc:
            raise DatasetLocked(f"{self.root / LOCK}: cannot open the lock file ({exc.strerror})") from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                raise DatasetLocked(f"{self.root}: a run is writing to this dataset; check it when the run has "
                                    f"finished") from None
            yield self
        finally:
            os.close(fd)

    # ---------------------------------------------------------------- index
    def read_index(self) -> tuple[dict[str, dict], dict]:
        """Records by job id (the last line of a job wins) and what the other lines were; never raises
        for the content.

        The second value: ``lines`` (read), ``duplicates`` (records superseded by a later line of the
        same job), ``problems`` (``(line number, why, the line's bytes)`` of every line that is not a
        record, :func:`record_problem`), ``truncated`` (the number of an incomplete last line: no
        newline and not JSON, what a run stopped mid-write leaves; else None) and ``bad_lines`` (both
        counted). Blank lines are skipped.
        """
        records: dict[str, dict] = {}
        info = {"lines": 0, "bad_lines": 0, "duplicates": 0, "problems": [], "truncated": None}
        try:
            fh = open(self.index_path, "rb")
        except FileNotFoundError:
            return records, info
        with fh:
            for number, raw in enumerate(fh, start=1):
                info["lines"] = number
                if not raw.strip():
                    continue
                try:
                    record = json.loads(raw)
                except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
                    if not raw.endswith(b"\n"):
                        info["truncated"] = number
                    else:
                        why = f"not JSON: {exc.msg}" if isinstance(exc, json.JSONDecodeError) else "not JSON"
                        info["problems"].append((number, why, raw))
                    continue
                problem = record_problem(record)
                if problem is not None:
                    info["problems"].append((number, problem, raw))
                    continue
                job_id = record["job_id"]
                if job_id in records:
                    info["duplicates"] += 1
                    del records[job_id]  # keep file order = order of the last record
                records[job_id] = record
        info["bad_lines"] = len(info["problems"]) + (info["truncated"] is not None)
        return records, info

    def reject(self, problems: list[tuple[int, str, bytes]]) -> Path:
        """Append the lines of ``problems`` (from :meth:`read_index`) to ``index.jsonl.rejected``, as they
        were, and make them durable: the rewritten index leaves them out, nothing a person wrote is lost."""
        path = self.root / REJECTED
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        try:
            _write_all(fd, b"".join(raw if raw.endswith(b"\n") else raw + b"\n" for _, _, raw in problems))
            os.fsync(fd)
        finally:
            os.close(fd)
        return path

    def rewrite_index(self, records: Iterable[dict]) -> None:
        """Replace the index atomically with ``records`` (one line each)."""
        self.close_index()
        text = "".join(dumps(r) + "\n" for r in records)
        write_bytes_atomic(self.index_path, text.encode())

    def append(self, record: dict) -> bool:
        """Append one record line and make it durable (one ``write``, then fsync) before returning.

        Idempotent per frame: False, and nothing written, when this object has already appended a line
        for the job, unless that line said failed and this one ok (the folder appeared). A published
        frame's line never changes, so a duplicate result of a job adds nothing to the index.
        """
        job_id = record["job_id"]
        before = self._appended.get(job_id)
        if before is not None and not (before == "failed" and record.get("status") == "ok"):
            return False
        if self._index_fd is None:
            self._index_fd = os.open(self.index_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW
                                     | os.O_CLOEXEC, 0o644)
        _write_all(self._index_fd, (dumps(record) + "\n").encode())
        os.fsync(self._index_fd)
        self._appended[job_id] = record.get("status")
        return True

    def close_index(self) -> None:
        if self._index_fd is not None:
            os.close(self._index_fd)
            self._index_fd = None

    # ---------------------------------------------------------------- frames
    def published_record(self, job_id: str) -> dict | None:
        """The record of the published folder ``frames/<job_id>/`` with its ``record_file`` entry, or None.

        None when there is no such folder (or it is a symbolic link), or its ``record.json`` is unreadable,
        not a regular file, not an ok record (:func:`record_problem`), or names another job.
        """
        if not JOB_ID.fullmatch(job_id) or (self.frames / job_id).is_symlink():
            return None
        try:
            data = read_regular(self.frames / job_id / RECORD)
            record = json.loads(data)
        except (OSError, ValueError, RecursionError):
            return None
        if record_problem(record) is not None or record["job_id"] != job_id or record["status"] != "ok":
            return None
        record["record_file"] = record_file_entry(data)
        return record

    def settle(self, record: dict) -> dict:
        """The record to index for a job a worker reported: its published folder's record when there is one.

        The published folder is the truth: a second execution of a job that lost the race to publish,
        or a view failed because its worker died after publishing some of its frames, is indexed as
        what was published. When no folder is visible (none was published, or a shared file system
        does not show it yet) the worker's record is kept; the next run verifies it.
        """
        published = self.published_record(record["job_id"])
        return record if published is None else published

    def verify(self, record: dict, mode: str = "sha256") -> str | None:
        """None when the record's frame is complete on disk, else why not.

        ``mode``: ``"sha256"`` checks sizes and checksums of ``record.json`` and of every file,
        ``"size"`` only sizes (fast); with ``"sha256"`` an EXR file must also be one the codec can read
        (:func:`exr_defect`). A record without ``record_file`` (an index line written before
        ``record.json`` was checksummed) must equal the folder's ``record.json``.
        """
        if record.get("status") != "ok":
            return f"status {record.get('status')!r}"
        folder = self.frames / record["job_id"]
        if folder.is_symlink():
            return "the frame folder is a symbolic link (a run never publishes one)"
        try:
            data = read_regular(folder / RECORD)
        except OSError as exc:
            return f"no {RECORD} in the frame folder" if isinstance(exc, FileNotFoundError) else \
                f"{RECORD}: {exc.strerror}"
        expected = record.get("record_file")
        if expected is not None:
            if len(data) != expected["bytes"]:
                return f"{RECORD} has {len(data)} bytes, the index says {expected['bytes']}"
            if mode == "sha256" and hashlib.sha256(data).hexdigest() != expected["sha256"]:
                return f"{RECORD} checksum differs from the index"
        try:
            stored = json.loads(data)
        except (ValueError, RecursionError):
            stored = None
        changed = differing_keys(record, stored)
        if changed:
            return f"the index line differs from {RECORD} in {', '.join(changed)}"
        for entry in record.get("files", []):
            path = folder / entry["name"]
            if path.is_symlink():
                return f"{entry['name']} is a symbolic link (a run never writes one)"
            try:
                size = path.stat().st_size
            except OSError:
                return f"{entry['name']} missing"
            if size != entry["bytes"]:
                return f"{entry['name']} has {size} bytes, the record says {entry['bytes']}"
            if mode == "sha256" and sha256_of(path) != entry["sha256"]:
                return f"{entry['name']} checksum differs from the record"
            if mode == "sha256" and path.suffix == ".exr":
                defect = exr_defect(path)
                if defect is not None:
                    return f"{entry['name']}: {defect}"
        return None

    def discard(self, job_id: str) -> bool:
        """Delete ``frames/<job_id>/`` before the job is rendered again; True when there was one.

        The folder is first renamed to ``.<job_id>.stale-XXXXXXXX`` (atomic), so a run killed while
        deleting leaves no half-deleted folder under the job's name; the next run removes the rest.
        """
        folder = self.frames / job_id
        if not (folder.exists() or folder.is_symlink()):
            return False
        stale = self.frames / f".{job_id}.stale-{secrets.token_hex(4)}"
        os.rename(folder, stale)
        _fsync_dir(self.frames)
        _remove(stale)
        return True

    def clean_partials(self) -> int:
        """Remove what a killed run left: frame folders half-written or half-deleted, temp files of the
        index and the card; the number removed. Only while no worker writes (under the lock)."""
        removed = 0
        for folder, pattern in ((self.frames, _STRAY_FRAME), (self.root, _STRAY_TEMP)):
            if not folder.is_dir():
                continue
            for path in folder.iterdir():
                if pattern.fullmatch(path.name):
                    _remove(path)
                    removed += 1
        return removed

    def check(self, mode: str = "sha256") -> dict:
        """Everything :meth:`read_index`, :meth:`verify` and the frames folder say, without changing anything.

        Returns ``{"problems": [one line each], "notes": [...], "counts": {records, ok, failed,
        record_files, files, outside_set}}``. Problems: index lines that are not records, ok frames that do not
        verify (``mode``), published folders missing from the index, leftovers of a killed run. Frames not in the
        last run's set (``set.json``) are a note: kept on purpose, not damage.
        """
        records, info = self.read_index()
        problems = [f"{INDEX}:{number}: not a frame record ({why})" for number, why, _ in info["problems"]]
        if info["truncated"] is not None:
            problems.append(f"{INDEX}:{info['truncated']}: incomplete last line (a run stopped while writing it)")
        counts = {"records": len(records), "ok": 0, "failed": 0, "record_files": 0, "files": 0}
        legacy = 0
        for job_id, record in records.items():
            if record["status"] != "ok":
                counts["failed"] += 1
                if (self.frames / job_id).exists() or (self.frames / job_id).is_symlink():
                    problems.append(f"{FRAMES}/{job_id}: the index line says {record['status']!r} but the frame "
                                    f"folder exists")
                continue
            counts["ok"] += 1
            counts["record_files"] += 1
            counts["files"] += len(record["files"])
            legacy += "record_file" not in record
            why = self.verify(record, mode)
            if why is not None:
                problems.append(f"{FRAMES}/{job_id}: {why}")
        if self.frames.is_dir():
            for path in sorted(self.frames.iterdir()):
                if _STRAY_FRAME.fullmatch(path.name):
                    problems.append(f"{FRAMES}/{path.name}: left by an interrupted run")
                elif JOB_ID.fullmatch(path.name) and path.name not in records:
                    problems.append(f"{FRAMES}/{path.name}: published but not in the index")
        for path in sorted(self.root.iterdir()) if self.root.is_dir() else []:
            if _STRAY_TEMP.fullmatch(path.name):
                problems.append(f"{path.name}: temporary file left by an interrupted run")
        notes = []
        current, outside = self.outside_set(records)
        if outside:
            shown = ", ".join(f"{r['job_id']} ({r['scene']}/{r['view']['label']}/{r['preset']})" for r in outside[:3])
            notes.append(f"{len(outside)} indexed frame(s) are not in the set of the last run "
                         f"({current.get('set_file') or 'its set'}): {shown}{' …' if len(outside) > 3 else ''}; an "
                         f"earlier version of the set file or another set (kept; the reader's "
                         f"Dataset(root, current_set=True) opens only that set's frames)")
        counts["outside_set"] = len(outside)
        if info["duplicates"]:
            notes.append(f"{info['duplicates']} index line(s) superseded by a later line of the same frame")
        if legacy:
            notes.append(f"{legacy} index line(s) without the checksum of record.json (written by an older "
                         f"version; compared by content; the next run adds it)")
        return {"problems": problems, "notes": notes, "counts": counts}

    def write_current_set(self, set_file: str | None, job_ids: Iterable[str]) -> None:
        """Write ``set.json``: the set file and the job ids, in set order, of the set this run renders."""
        from datetime import datetime, timezone

        write_json_atomic(self.root / CURRENT_SET, {
            "set_file": set_file, "written": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "jobs": list(job_ids)})

    def outside_set(self, records: dict[str, dict]) -> tuple[dict | None, list[dict]]:
        """``set.json`` (None where there is none) and the records (any status) of ``records`` whose job is not in
        it, in index order."""
        current = read_current_set(self.root)
        if current is None:
            return None, []
        in_set = set(current["jobs"])
        return current, [r for job_id, r in records.items() if job_id not in in_set]

    def write_card(self, text: str) -> None:
        write_bytes_atomic(self.root / CARD, utf8_text(text))


def utf8_text(text: str) -> bytes:
    """``text`` as UTF-8 for a Markdown file; bytes of a path that were not UTF-8 (kept by Python as lone
    surrogates, PEP 383) are spelled ``\\xNN``, so the file stays valid UTF-8 and shows them."""
    return re.sub("[\udc80-\udcff]", lambda m: f"\\x{ord(m.group()) - 0xDC00:02x}", text).encode()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
