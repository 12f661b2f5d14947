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
* :mod:`batch.cli` — ``tofcore-batch run | validate | compare``
* :mod:`batch/blender_entry.py` — ``blender -b file.blend --python batch/blender_entry.py -- …``

Importing this package never imports bpy.
"""

from .jobs import Job, ViewTask, derive_seed, expand, group_by_view
from .setfile import SetFileError, SetSpec, load_set, parse_set, scaled_sensor

__all__ = ["Job", "SetFileError", "SetSpec", "ViewTask", "derive_seed", "expand", "group_by_view", "load_set",
           "parse_set", "scaled_sensor"]
