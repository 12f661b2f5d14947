"""SHA-256 of the input files a set names (scenes, textures, meshes), cached per file state in this process.

Job ids and the worker's check that a scene file is still the one the set was expanded against both hash
the file; a randomized set hashes whole folders of textures and meshes. Each file is read once per
(path, size, mtime) in a process.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

_HASHES: dict[tuple[str, int, int], str] = {}


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's content, cached per (path, size, mtime) for this process."""
    st = os.stat(path)
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _HASHES:
        with open(path, "rb") as fh:
            _HASHES[key] = hashlib.file_digest(fh, "sha256").hexdigest()
    return _HASHES[key]
