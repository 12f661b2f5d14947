"""batch — the headless ToF dataset generator: scene sets → frames → a resumable dataset folder.

Modules, one concept each:

* :mod:`batch.setfile` — the scene-set TOML schema, parsed and checked (:func:`load_set`)
* :mod:`batch.jobs` — expansion into frames with content-hash ids and derived seeds, grouped by view
* :mod:`batch.worker` — what a worker does with a view: load/export once, render every preset, write
* :mod:`batch.blend` — the bpy side (open, list cameras, export a view); only workers import it
* :mod:`batch.dataset` — the dataset folder: atomic files, index, records, verification, lock
* :mod:`batch.card` — the generated dataset card (README.md)
* :mod:`batch.devices` — ``--device cpu|gpu|auto``: visible GPUs, one pinned worker per GPU, CPU fall-back
* :mod:`batch.run` — executors (local spawn pool, Dask, in-process), resume logic, progress, summary
* :mod:`batch.compare` — the sensor comparison report
* :mod:`batch.cli` — ``tofcore-batch run | validate | verify | compare``
* :mod:`batch.entry`, :mod:`batch.interrupt` — the installed commands' entry points (``tofcore``,
  ``tofcore-batch``): Ctrl-C is one line from their first line, before NumPy loads
* :mod:`batch/blender_entry.py` — ``blender -b file.blend --python batch/blender_entry.py -- …``

Importing this package never imports bpy, and imports nothing else until a name below is used
(``python -m batch`` imports the package first: its Ctrl-C handling must start before NumPy loads).
"""

import importlib

_EXPORTS = {"Job": "jobs", "ViewTask": "jobs", "derive_seed": "jobs", "expand": "jobs", "group_by_view": "jobs",
            "SetFileError": "setfile", "SetSpec": "setfile", "load_set": "setfile", "parse_set": "setfile"}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
