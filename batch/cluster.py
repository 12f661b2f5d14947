"""What a Dask cluster started elsewhere needs to run this package's tasks: its code, shipped; tofcore, checked.

Dask pickles a task by reference: :func:`batch.worker.run_view` and :class:`batch.jobs.ViewTask`
travel as module and class names, which the scheduler (it unpickles the task graph) and every
worker must import. A checkout runs this package as ``batch`` (``python -m batch``), an install as
``tofcore_batch``; a scheduler and workers started from the checkout's venv (``dask scheduler``,
``dask worker``) import ``tofcore_batch`` (the editable install) but not ``batch``, and every frame
failed with Dask's "Error during deserialization of the task graph".

:func:`ship` zips this package's modules under the name this process imported them as and hands the
zip to the cluster with Dask's own upload plugins (``SchedulerUploadFile`` on the scheduler,
``UploadFile`` on every worker, also on those that join later): each puts the zip first on its
``sys.path``. The workers then run this process's code whatever copy of the package they have (a
worker that imported an older copy before keeps it until it restarts). tofcore is not shipped: it
must be installed where the workers run (it holds the compiled kernels' cache and optional
dependencies); :func:`import_problem` runs on the scheduler and every worker and
:func:`check_imports` turns a missing tofcore into one line naming the process and the cause.

This module imports the standard library only: a worker imports it (from the zip) to run
:func:`import_problem` even where tofcore cannot be imported.
"""

from __future__ import annotations

import hashlib
import io
import os
import tempfile
import zipfile
from pathlib import Path

#: The plugins' name: a later run's upload replaces an earlier one's instead of piling up.
PLUGIN_NAME = "tofcore-batch-code"


def package_zip(package_dir: Path, package: str) -> bytes:
    """The ``*.py`` files under ``package_dir`` as a zip whose top-level folder is ``package``.

    Entries are sorted and dated 1980-01-01, so equal sources give equal bytes.
    """
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(package_dir.rglob("*.py")):
            relative = path.relative_to(package_dir)
            if "__pycache__" in relative.parts:
                continue
            info = zipfile.ZipInfo(f"{package}/{relative.as_posix()}", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, path.read_bytes())
    return buffer.getvalue()


def ship(client) -> str:
    """Upload this package to the scheduler and the workers of ``client``'s cluster; the zip's file name."""
    from distributed.diagnostics.plugin import SchedulerUploadFile, UploadFile

    package = __package__ or "batch"
    data = package_zip(Path(__file__).resolve().parent, package)
    # The file name is what the workers store it as (their local folder): one per content.
    name = f"{package}-{hashlib.sha256(data).hexdigest()[:12]}.zip"
    with tempfile.TemporaryDirectory(prefix="tofcore-batch-") as folder:
        path = os.path.join(folder, name)
        with open(path, "wb") as file:
            file.write(data)
        client.register_plugin(SchedulerUploadFile(path, load=True), name=PLUGIN_NAME)
        client.register_plugin(UploadFile(path, load=True), name=PLUGIN_NAME)
    return name


def import_problem() -> str | None:
    """None where ``import tofcore`` works in this process, else the exception in one line."""
    try:
        import tofcore  # noqa: F401
    except Exception as exc:  # ImportError, or an error raised while tofcore's own imports run
        return f"{type(exc).__name__}: {exc}"
    return None


def check_imports(client, address: str) -> None:
    """Raise :class:`RuntimeError` (one line) when the scheduler or a worker cannot import tofcore."""
    problems = {f"scheduler {address}": client.run_on_scheduler(import_problem)}
    problems.update((f"worker {worker}", problem) for worker, problem in client.run(import_problem).items())
    for who, problem in problems.items():
        if problem is not None:
            raise RuntimeError(f"--scheduler: Dask {who} cannot import tofcore ({problem}); start the scheduler and "
                               f"workers from an environment where tofcore is installed (pip install tofcore, "
                               f"or the checkout's .venv after make venv)")
