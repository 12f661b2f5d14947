"""Reading a dataset folder written by ``tofcore-batch run``: :class:`Dataset`, :class:`FrameRef`.

A dataset is read with tofcore alone (NumPy; EXR by :mod:`tofcore.output.exr`); this
module imports neither the ``batch`` package nor bpy nor PyTorch
(:mod:`tofcore.output.torch_dataset` is the optional PyTorch adapter).

Layout read
-----------
::

    DATASET/
      index.jsonl            one JSON record per frame: job_id, status, scene, view, preset, seed, files, …
      set.json               the set of the last run: its set file and its frames' job ids, in set order
      frames/<job_id>/       frame.exr, frame.json, record.json, PNG previews, points.ply

The fields of a record are listed in ``batch/dataset.py``; what the files hold
in :mod:`tofcore.output.writers`. A frame is listed when its index line is a record
(a JSON object with a ``job_id``); other lines (a line cut by a crash, a
stray edit) are skipped with one warning naming the index and the line
numbers. When a job has several lines, the last one wins.

What the reader checks
----------------------
The frame folders are the truth, the index a summary of them. When the
dataset is opened, each indexed frame's ``record.json`` is read (a small file):

* an ok frame whose folder, ``record.json`` or a listed file is a symbolic
  link, whose ``record.json`` is missing, or does not match the size and
  SHA-256 the index keeps for it (``record_file``), is refused: not listed,
  one warning naming it and why (:attr:`Dataset.refused`);
* an index line that differs from its frame's ``record.json`` (an edited
  scene, status or pose) is replaced by ``record.json``, with one warning
  naming the line and the keys;
* frame folders that the index does not list (an emptied or shortened
  index) are not listed, with one warning counting them: running the set
  again (``tofcore-batch run``) repairs the index without rendering them.

When the set changed
--------------------
An edited set file (another spp or seed, a scene removed) gives its frames new
job ids; a rerun renders them and keeps the earlier frames in the index and in
``frames/``, so the index can hold two frames of one view with different
settings, or a removed scene's frames. Each run writes ``set.json``: the set
file and the job ids of the set it ran. Indexed frames that are not in it are
counted in one warning when the dataset is opened (:attr:`Dataset.outside_set`);
``Dataset(root, current_set=True)`` lists only the frames of that set.

When a frame's file is opened (``frame.exr`` by :meth:`FrameRef.load`,
``frame.json`` for metadata), its size is compared with the record every time
and its SHA-256 the first time (``Dataset(root, checksum="size")`` skips the
hash); a mismatch (a file replaced by another frame's) is a
:class:`DatasetError` naming the file. ``tofcore-batch verify`` checks every
file of every frame at once.

Channels
--------
:meth:`FrameRef.load` returns ``{name: NumPy array}`` for the names asked:

=====================  ===========  ==========  ================================================================
name                   shape        unit        content
=====================  ===========  ==========  ================================================================
``depth``              (H, W)       m           the sensor's depth output (radial or z), NaN where invalid
``distance``           (H, W)       m           decoded radial distance, NaN where invalid
``amplitude``          (H, W)       e⁻          modulation amplitude
``intensity``          (H, W)       e⁻          IR image
``offset``             (H, W)       e⁻          offset of the highest frequency
``confidence``         (H, W)       1           decoding confidence in [0, 1]
``valid``              (H, W)       0/1         pixel has a depth
``reason``             (H, W)       code        :class:`~tofcore.output.frame.Reason` code, 0 valid
``gt_distance``        (H, W)       m           noise-free first-hit radial distance, NaN where no surface
``gt_depth``           (H, W)       m           the same in the sensor's depth output
``direct_distance``    (H, W)       m           decoded from the k = 1 bucket only (no multipath, no noise)
``object_id``          (H, W)       index       first-hit object, −1 where none
``render_error``       (H, W)       m           estimated Monte Carlo standard error of depth (when written)
``samples``            (H, W)       spp         samples traced per pixel (when written)
``unwrap_flip``        (H, W)       0/1         the render's replicates unwrap to different intervals (when
                                                written): a whole-wrap error is possible, ``render_error``
                                                does not describe it
``raw``                (R, H, W)    e⁻          the raw images stacked in the order of ``raw_labels``
``raw_labels``         tuple of R   –           e.g. ``("f80MHz_s0", …)``; given whenever ``raw`` is asked
``distance_per_k``     (K, H, W)    m           decoded distance using bounces ≤ k, k = 1..K
``ray_directions``     (H, W, 3)    1           unit pixel-centre ray directions, sensor frame (from the
                                                intrinsics: radial distance × direction = point)
``multipath_error``    (H, W)       m           measured depth − ground-truth depth, NaN where invalid (labels)
``direct_depth``       (H, W)       m           depth decoded from direct light only (labels)
``normal``             (H, W, 3)    1           first-hit normal, sensor frame, facing the camera (labels)
``material_id``        (H, W)       index       first-hit material, −1 none; names: :attr:`FrameRef.materials`
=====================  ===========  ==========  ================================================================

The last four come from ``labels.npz`` (``batch/labels.py``), written when the set's ``[output]`` has
``labels = true``; ``material_id`` is int32 there, the others float32.

Every array is float32 exactly as stored in ``frame.exr`` (:func:`tofcore.read_exr`):
``valid``, ``reason`` and ``object_id`` too, and invalid pixels stay NaN.
:meth:`FrameRef.sample` gives the same data shaped for learning: (C, H, W)
images, a bool ``valid``, the 3×3 camera matrix and the pose.

The EXR is read when :meth:`~FrameRef.load` is called, not before, and not
kept: only the channels asked are converted (every chunk is still
decompressed: each holds all channels of its lines). ``frame.json`` (intrinsics, pose, raw labels)
is read at first use and kept by the :class:`FrameRef`.

Example
-------
>>> from tofcore.output.dataset import Dataset
>>> data = Dataset("out/demo_dataset")
>>> data.frames(scene="room", preset="kinect_v2")[:2]      # doctest: +SKIP
[FrameRef('5d1c…', scene='room', view='pose0', preset='kinect_v2', status='ok'), …]
>>> frame = data.frames()[0]                                # doctest: +SKIP
>>> arrays = frame.load(["depth", "gt_depth", "raw"])      # {name: array}, raw (R, H, W)
>>> frame.intrinsics.matrix, frame.world_from_sensor       # (3, 3), (4, 4) float64
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import stat
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, ExrError

INDEX = "index.jsonl"
FRAMES = "frames"
RECORD = "record.json"
#: The set of the last run (``tofcore-batch run`` writes it): ``{"set_file": path or null, "jobs": [job ids]}``.
CURRENT_SET = "set.json"
FRAME_EXR = "frame.exr"
FRAME_JSON = "frame.json"

#: Channels stored one EXR channel each under the same name.
IMAGE_CHANNELS = ("depth", "distance", "amplitude", "intensity", "offset", "confidence", "valid", "reason",
                  "gt_distance", "gt_depth", "direct_distance", "object_id", "render_error", "samples",
                  "unwrap_flip")
#: Channels built from several EXR channels or from frame.json.
STACKED_CHANNELS = ("raw", "distance_per_k", "ray_directions")
#: Channels of ``labels.npz`` (training labels, when the set asked for them).
LABEL_CHANNELS = ("multipath_error", "direct_depth", "normal", "material_id")
LABELS_FILE = "labels.npz"
#: Every name :meth:`FrameRef.load` accepts (``raw_labels`` comes with ``raw``).
CHANNELS = IMAGE_CHANNELS + STACKED_CHANNELS + LABEL_CHANNELS
#: Values of a record's ``status``.
STATUSES = ("ok", "failed")
#: What a frame's files are checked against when opened: ``"sha256"`` (size always, hash at first open) or ``"size"``.
CHECKSUMS = ("sha256", "size")
_JOB_ID = re.compile(r"[0-9a-f]{16}")


class DatasetError(ConfigError):
    """A folder is not a dataset, or a frame of it cannot be read; the message names the path."""


# --------------------------------------------------------------------------- intrinsics

@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics and OpenCV distortion of a frame, in pixels (as rendered, after ``resolution_scale``).

    =============  ============  ==========================================================
    field          unit          meaning
    =============  ============  ==========================================================
    ``width``      px            image width W
    ``height``     px            image height H
    ``fx, fy``     px            focal lengths
    ``cx, cy``     px            principal point; pixel (u, v) has its centre at (u, v), row 0 on top
    ``distortion`` 1             OpenCV ``(k1, k2, p1, p2, k3)``
    =============  ============  ==========================================================
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def matrix(self) -> np.ndarray:
        """The 3×3 camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def camera(self):
        """A :class:`tofcore.Camera` with these intrinsics (pinhole: no aperture)."""
        from ..scene.camera import Camera

        k1, k2, p1, p2, k3 = self.distortion
        return Camera(width=self.width, height=self.height, fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy,
                      k1=k1, k2=k2, p1=p1, p2=p2, k3=k3)

    @classmethod
    def from_dict(cls, data: dict, where: str) -> Intrinsics:
        """From ``{"width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}`` (distortion optional)."""
        missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if data.get(k) is None]
        if missing:
            raise DatasetError(f"{where}: intrinsics must have width, height, fx, fy, cx, cy, got no {missing}")
        return cls(width=int(data["width"]), height=int(data["height"]),
                   fx=float(data["fx"]), fy=float(data["fy"]), cx=float(data["cx"]), cy=float(data["cy"]),
                   distortion=tuple(float(data.get(k) or 0.0) for k in ("k1", "k2", "p1", "p2", "k3")))


# --------------------------------------------------------------------------- one frame

class FrameRef:
    """One frame of a :class:`Dataset`: its index record, paths, and loaders. Reads nothing when made.

    Attributes
    ----------
    id : str
        The job id, also the name of the frame's folder.
    scene : str
        The scene's name in the set.
    view : str
        The view's label (``"pose0"``, ``"TofCam@12"`` …).
    preset : str
        The preset label (a preset name, or a set file's ``label``).
    seed : int
        The render seed.
    status : str
        ``"ok"`` or ``"failed"`` (then ``record["error"]`` says why).
    record : dict
        The whole index record (see ``batch/dataset.py``): settings, metrics, timings, files.
    folder : pathlib.Path or None
        ``DATASET/frames/<id>``; None unless the status is ``"ok"``.
    """

    __slots__ = ("id", "scene", "view", "preset", "seed", "status", "record", "folder", "checksum", "_document",
                 "_checked")

    def __init__(self, record: dict, root: Path, checksum: str = "sha256"):
        self.record = record
        self.id = str(record["job_id"])
        self.scene = record.get("scene")
        view = record.get("view")
        self.view = view.get("label") if isinstance(view, dict) else view
        self.preset = record.get("preset")
        self.seed = record.get("seed")
        self.status = record.get("status")
        self.folder = root / FRAMES / self.id if self.status == "ok" else None
        self.checksum = checksum
        self._document: dict | None = None
        self._checked: set[str] = set()  # files whose SHA-256 matched the record

    def __repr__(self) -> str:
        return (f"FrameRef({self.id!r}, scene={self.scene!r}, view={self.view!r}, preset={self.preset!r}, "
                f"status={self.status!r})")

    # ---------------------------------------------------------------- files
    @property
    def paths(self) -> dict[str, Path]:
        """The frame's files by kind (``exr``, ``json``, ``depth_mm``, ``ply``, …), from the record; {} if failed."""
        if self.folder is None:
            return {}
        return {entry["kind"]: self.folder / entry["name"] for entry in self.record.get("files") or []}

    def _file(self, name: str) -> Path:
        """The path of ``name`` in the frame's folder, or DatasetError naming it and why."""
        if self.status != "ok" or self.folder is None:
            raise DatasetError(f"frame {self.id}: status {self.status!r}, no files "
                               f"(error: {self.record.get('error')})")
        path = self.folder / name
        if self.folder.is_symlink() or path.is_symlink():
            raise DatasetError(f"{path}: a symbolic link, not a frame file (a run never writes one); refused")
        if not path.is_file():
            formats = (self.record.get("settings") or {}).get("formats")
            hint = f" (the set's formats were {formats})" if name == FRAME_EXR and formats else ""
            raise DatasetError(f"{path}: frame file not found{hint}")
        entry = next((e for e in self.record.get("files") or [] if isinstance(e, dict) and e.get("name") == name),
                     None)
        if entry is None:
            raise DatasetError(f"{path}: not among the files of the frame's record")
        size = path.stat().st_size
        if size != entry.get("bytes"):
            raise DatasetError(f"{path}: {size} bytes, the frame's record says {entry.get('bytes')} (replaced or "
                               f"damaged; tofcore-batch verify checks the dataset)")
        if self.checksum == "sha256" and name not in self._checked:
            if _sha256_of(path) != entry.get("sha256"):
                raise DatasetError(f"{path}: SHA-256 differs from the frame's record (replaced or damaged; "
                                   f"tofcore-batch verify checks the dataset)")
            self._checked.add(name)
        return path

    @property
    def document(self) -> dict:
        """``frame.json`` (sensor, intrinsics, pose, raw labels, stats), read once and kept."""
        if self._document is None:
            path = self._file(FRAME_JSON)
            try:
                self._document = json.loads(path.read_text())
            except ValueError as exc:
                raise DatasetError(f"{path}: not valid JSON ({exc})") from None
        return self._document

    # ---------------------------------------------------------------- metadata
    @property
    def intrinsics(self) -> Intrinsics:
        """The frame's :class:`Intrinsics`, from ``frame.json`` (metadata ``intrinsics``, else the sensor's camera)."""
        metadata = self.document.get("metadata") or {}
        data = metadata.get("intrinsics") or (metadata.get("sensor") or {}).get("camera")
        if not data:
            raise DatasetError(f"{self.folder / FRAME_JSON}: metadata holds no intrinsics")
        return Intrinsics.from_dict(data, str(self.folder / FRAME_JSON))

    @property
    def world_from_sensor(self) -> np.ndarray:
        """(4, 4) float64 pose: sensor frame (OpenCV: x right, y down, z forward) → world, metres."""
        pose = self.document.get("world_from_sensor")
        if pose is None:
            pose = self.record.get("world_from_sensor")
        return np.asarray(pose, dtype=np.float64).reshape(4, 4)

    @property
    def raw_labels(self) -> tuple[str, ...]:
        """Names of the raw images, in the order of the ``raw`` stack."""
        return tuple(self.document.get("raw_labels") or ())

    @property
    def objects(self) -> dict[int, dict]:
        """What the ``object_id`` values mean: ``{id: {"name": …, "materials": [...]}}`` (−1 is no surface);
        from the index record, else ``frame.json`` (empty for frames rendered before the table existed)."""
        table = self.record.get("objects") or (self.document.get("metadata") or {}).get("objects") or []
        return {int(entry["id"]): {"name": entry["name"], "materials": list(entry.get("materials", []))}
                for entry in table}

    @property
    def materials(self) -> dict[int, str]:
        """What the ``material_id`` label's values mean: ``{id: material name}`` (−1 is no surface); empty
        for frames written without labels."""
        return {int(entry["id"]): entry["name"] for entry in self.record.get("materials") or []}

    @property
    def randomization(self) -> dict:
        """What a randomized view drew (objects, materials, ambient, camera, sensor unit; ``batch/randomize.py``),
        from the index record; empty for frames of fixed views."""
        return dict(self.record.get("randomization") or {})

    @property
    def transient(self) -> tuple[np.ndarray, float]:
        """The transient histogram ``(H, W, B)`` float32 and its bin width in metres (``transient.npy``;
        bin b centred at (b + ½)·width). DatasetError when the frame has none."""
        entry = (self.document.get("previews") or {}).get("transient")
        if not entry:
            raise DatasetError(f"{self.folder / FRAME_JSON}: the frame has no transient histogram (set "
                               f"[output] transient_bin_m and transient_max_m)")
        return np.load(self._file(entry["file"]), allow_pickle=False), float(entry["bin_width_m"])

    @property
    def sensor(self) -> dict:
        """The sensor as rendered (``Sensor.to_dict()``), from ``frame.json``."""
        return dict((self.document.get("metadata") or {}).get("sensor") or {})

    @property
    def ray_directions(self) -> np.ndarray:
        """(H, W, 3) float32 unit pixel-centre ray directions in the sensor frame (read-only)."""
        return self.intrinsics.camera().pixel_center_directions()

    # ---------------------------------------------------------------- pixels
    def load(self, channels: Iterable[str] | str | None = None) -> dict[str, Any]:
        """Read the frame's EXR and return the channels asked as NumPy arrays.

        Parameters
        ----------
        channels : iterable of str, str or None
            Names from the module docstring's table (:data:`CHANNELS`). None:
            every channel the file holds — the images, ``raw`` (+ ``raw_labels``)
            and ``distance_per_k`` — but not ``ray_directions``.

        Returns
        -------
        dict
            ``{name: array}`` as in the table: (H, W) float32 images exactly as
            stored (NaN where invalid), ``raw`` (R, H, W) with ``raw_labels``,
            ``distance_per_k`` (K, H, W), ``ray_directions`` (H, W, 3).

        Raises
        ------
        DatasetError
            Unknown channel name (the valid names listed), a channel this file
            does not hold (``render_error`` of an old frame), a failed frame,
            or a missing ``frame.exr``/``frame.json`` (the path named).

        Example
        -------
        >>> arrays = frame.load(["depth", "gt_depth", "valid"])    # doctest: +SKIP
        >>> error_m = (arrays["depth"] - arrays["gt_depth"])[arrays["valid"] > 0.5]
        """
        names = _check_channels(channels, f"frame {self.id}")
        has_labels = any(e.get("name") == LABELS_FILE for e in self.record.get("files") or [] if isinstance(e, dict))
        stored: dict[str, np.ndarray] = {}
        if names is None or any(n not in LABEL_CHANNELS for n in names):
            exr = self._file(FRAME_EXR)
            from .writers import read_exr

            try:
                stored = read_exr(exr)
            except ExrError as exc:  # tofcore.output.exr: "{path}: {defect}", one line
                raise DatasetError(f"{exr}: cannot be read as EXR: {str(exc).removeprefix(f'{exr}: ')}") from None
            except OSError as exc:
                raise DatasetError(f"{exr}: cannot be read as EXR ({exc.strerror or exc})") from None
        if names is None:
            names = [n for n in IMAGE_CHANNELS if n in stored] + ["raw", "distance_per_k"] + (
                list(LABEL_CHANNELS) if has_labels else [])
        labels = self._labels(has_labels) if any(n in LABEL_CHANNELS for n in names) else {}
        out: dict[str, Any] = {}
        for name in names:
            if name in LABEL_CHANNELS:
                out[name] = labels[name]
            elif name == "raw":
                labels = self.raw_labels or tuple(sorted(k[4:] for k in stored if k.startswith("raw.")))
                out["raw"] = _stack(stored, [f"raw.{label}" for label in labels], exr)
                out["raw_labels"] = labels
            elif name == "distance_per_k":
                k_max = self.document.get("distance_per_k")
                if k_max is None:
                    k_max = sum(1 for k in stored if k.startswith("distance_k"))
                out["distance_per_k"] = _stack(stored, [f"distance_k{k}" for k in range(1, int(k_max) + 1)], exr)
            elif name == "ray_directions":
                out["ray_directions"] = self.ray_directions
            else:
                out[name] = _channel(stored, name, exr)
        return out

    def _labels(self, has_labels: bool) -> dict[str, np.ndarray]:
        """The arrays of ``labels.npz``; DatasetError when the frame was written without labels."""
        if not has_labels:
            raise DatasetError(f"frame {self.id}: no {LABELS_FILE} (the set's [output] did not ask for labels = true)")
        path = self._file(LABELS_FILE)
        try:
            with np.load(path, allow_pickle=False) as data:
                return {name: data[name] for name in data.files}
        except (OSError, ValueError, KeyError) as exc:
            raise DatasetError(f"{path}: cannot be read ({type(exc).__name__}: {exc})") from None

    def sample(self, channels: Iterable[str] | str = ("depth", "gt_depth", "valid")) -> dict[str, Any]:
        """The frame as a training sample of NumPy arrays (what :class:`tofcore.output.torch_dataset.TorchDataset` gives).

        Parameters
        ----------
        channels : iterable of str or str
            Channel names (:data:`CHANNELS`).

        Returns
        -------
        dict
            =====================  =============  ========  ==================================================
            key                    shape          dtype     content
            =====================  =============  ========  ==================================================
            an image channel       (1, H, W)      float32   as stored, NaN where invalid (mask your loss)
            ``valid``              (1, H, W)      bool      pixel has a depth
            ``reason``             (1, H, W)      uint8     :class:`~tofcore.output.frame.Reason` code
            ``object_id``          (1, H, W)      int32     first-hit object, −1 none
            ``raw``                (R, H, W)      float32   raw images (e⁻), order of ``raw_labels``
            ``distance_per_k``     (K, H, W)      float32   per-bounce distances (m)
            ``ray_directions``     (3, H, W)      float32   unit ray directions, sensor frame
            ``normal``             (3, H, W)      float32   first-hit normal, sensor frame (labels)
            ``material_id``        (1, H, W)      int32     first-hit material, −1 none (labels)
            ``multipath_error``,   (1, H, W)      float32   labels: depth − gt_depth, direct-light depth (m)
            ``direct_depth``
            ``intrinsics``         (3, 3)         float32   camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
            ``distortion``         (5,)           float32   OpenCV k1, k2, p1, p2, k3
            ``world_from_sensor``  (4, 4)         float32   pose, metres
            ``id``                 –              str       job id (frame folder name)
            ``scene``, ``view``,   –              str       from the index record
            ``preset``
            =====================  =============  ========  ==================================================
        """
        arrays = self.load(channels)
        intrinsics = self.intrinsics
        sample: dict[str, Any] = {}
        for name, value in arrays.items():
            if name == "raw_labels":
                continue
            if name in ("raw", "distance_per_k"):
                sample[name] = np.ascontiguousarray(value, dtype=np.float32)
            elif name in ("ray_directions", "normal"):
                sample[name] = np.ascontiguousarray(np.moveaxis(value, -1, 0), dtype=np.float32)
            elif name == "valid":
                sample[name] = (value > 0.5)[None]
            elif name == "reason":
                sample[name] = value.astype(np.uint8)[None]
            elif name in ("object_id", "material_id"):
                sample[name] = value.astype(np.int32)[None]
            else:
                sample[name] = value[None]
        sample["intrinsics"] = intrinsics.matrix.astype(np.float32)
        sample["distortion"] = np.asarray(intrinsics.distortion, dtype=np.float32)
        sample["world_from_sensor"] = self.world_from_sensor.astype(np.float32)
        sample.update(id=self.id, scene=self.scene, view=self.view, preset=self.preset)
        return sample


def _sha256_of(path: Path) -> str:
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def read_regular(path: Path) -> bytes:
    """The bytes of ``path``: a regular file, its last component not a symbolic link (else OSError)."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    with os.fdopen(fd, "rb") as fh:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(errno.EINVAL, "not a regular file", str(path))
        return fh.read()


def read_current_set(root: Path) -> dict | None:
    """``set.json`` of a dataset folder: ``{"set_file": str or None, "jobs": [job ids], …}``, or None where it is
    missing or not of that form (a dataset written before it existed, or a damaged file)."""
    try:
        data = json.loads(read_regular(root / CURRENT_SET))
    except (OSError, ValueError, RecursionError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("jobs"), list) \
            or not all(isinstance(i, str) for i in data["jobs"]):
        return None
    return data


def differing_keys(line: dict, stored: dict) -> list[str]:
    """Top-level keys in which an index line and its ``record.json`` differ (the index's ``record_file`` left out)."""
    missing = object()
    keys = (line.keys() | stored.keys()) - {"record_file"}
    return sorted(k for k in keys if line.get(k, missing) != stored.get(k, missing))


def _check_channels(channels, where: str) -> list[str] | None:
    """``channels`` as a list of known names (duplicates dropped), None for all; DatasetError listing valid names."""
    if channels is None:
        return None
    names = [channels] if isinstance(channels, str) else list(channels)
    unknown = [n for n in names if n not in CHANNELS]
    if unknown:
        raise DatasetError(f"{where}: channels must be among {list(CHANNELS)}, got unknown {unknown!r}")
    return list(dict.fromkeys(names))


def _channel(stored: dict[str, np.ndarray], name: str, exr: Path) -> np.ndarray:
    """The EXR channel ``name`` as read; DatasetError naming the file and what it holds if it is missing."""
    try:
        return stored[name]
    except KeyError:
        raise DatasetError(f"{exr}: channel {name!r} not in the file; it holds {sorted(stored)}") from None


def _stack(stored: dict[str, np.ndarray], names: Sequence[str], exr: Path) -> np.ndarray:
    """(len(names), H, W) float32 stack of EXR channels (an empty stack for no names)."""
    if not names:
        first = next(iter(stored.values()))
        return np.empty((0, *first.shape), dtype=np.float32)
    return np.stack([_channel(stored, n, exr) for n in names])


# --------------------------------------------------------------------------- the dataset

class Dataset:
    """A dataset folder written by ``tofcore-batch run``, opened for reading.

    Parameters
    ----------
    root : str or os.PathLike
        The dataset folder (holding ``index.jsonl`` and ``frames/``).
    checksum : {"sha256", "size"}
        How a frame's files are checked when opened: size every time and
        SHA-256 the first time (default), or size only.
    current_set : bool
        List only the frames of the set the last run rendered (``set.json``);
        False (default): every indexed frame, with a warning counting those
        not in that set (an earlier version of the set file, another set).

    Raises
    ------
    DatasetError
        ``root`` is missing, not a folder, or has no ``index.jsonl``/``frames/``
        (one line naming the path); ``current_set=True`` where there is no
        readable ``set.json`` (a dataset of an older run).

    Warns
    -----
    UserWarning
        Index lines that are not records, lines that differ from their
        frame's ``record.json`` (which is used), frames refused (see the
        module docstring), frame folders the index does not list, and frames
        not in the last run's set (unless ``current_set``).

    Notes
    -----
    The index is read once, when the dataset is opened; open it again to see
    frames rendered since. ``len(data)`` and ``iter(data)`` cover the frames
    with status ``"ok"``; ``data[i]`` is the i-th of those, ``data["<id>"]`` a
    frame by id (any status).

    Example
    -------
    >>> data = Dataset("out/demo_dataset")                  # doctest: +SKIP
    >>> for frame in data.frames(preset="kinect_v2"):       # doctest: +SKIP
    ...     depth = frame.load("depth")["depth"]
    """

    def __init__(self, root: str | os.PathLike, checksum: str = "sha256", current_set: bool = False):
        if checksum not in CHECKSUMS:
            raise DatasetError(f"Dataset: checksum must be one of {list(CHECKSUMS)}, got {checksum!r}")
        self.checksum = checksum
        self.root = Path(root).expanduser().resolve()
        if not self.root.exists():
            raise DatasetError(f"{self.root}: dataset folder not found")
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: must be a dataset folder, got a file")
        self.index_path = self.root / INDEX
        if not self.index_path.is_file():
            raise DatasetError(f"{self.root}: not a dataset folder (no {INDEX}; "
                               f"`tofcore-batch run SET.toml --out FOLDER` writes one)")
        if (self.root / FRAMES).is_symlink() or not (self.root / FRAMES).is_dir():
            raise DatasetError(f"{self.root}: not a dataset folder (no {FRAMES}/ beside {INDEX}, or a symbolic "
                               f"link)")
        self._refs: dict[str, FrameRef] = {}
        self.skipped_lines: list[int] = []
        #: Frames of the index that were not listed, by id: why (see the module docstring).
        self.refused: dict[str, str] = {}
        #: Frame folders that the index does not list.
        self.unindexed: list[str] = []
        #: The set of the last run (``set.json``): ``{"set_file": …, "jobs": [ids]}``, or None (an older dataset).
        self.current_set: dict | None = read_current_set(self.root)
        #: Indexed frames (any status) that are not in :attr:`current_set`, by id, in index order.
        self.outside_set: list[str] = []
        self._read_index()
        self._check_against_folders()
        self._check_against_set(current_set)

    def _read_index(self) -> None:
        """Fill ``_refs`` in index order (a job's last line wins); skip and warn about lines that are not records."""
        with open(self.index_path, "rb") as fh:
            for number, line in enumerate(fh, start=1):
                if not line.strip():
                    continue
                try:
                    record = json.loads(line)
                    job_id = record["job_id"]
                    if not isinstance(record, dict) or not isinstance(job_id, str) or not job_id:
                        raise TypeError
                except (ValueError, KeyError, TypeError):
                    self.skipped_lines.append(number)
                    continue
                self._refs.pop(job_id, None)
                self._refs[job_id] = FrameRef({**record, "_line": number}, self.root, self.checksum)
        if self.skipped_lines:
            shown = ", ".join(map(str, self.skipped_lines[:10])) + (" …" if len(self.skipped_lines) > 10 else "")
            warnings.warn(f"{self.index_path}: skipped {len(self.skipped_lines)} line(s) that are not frame "
                          f"records (line {shown})", stacklevel=3)

    def _check_against_folders(self) -> None:
        """Each indexed frame against its ``record.json``, and the frame folders against the index (module
        docstring): replace edited lines, refuse what cannot be trusted, count unindexed folders; one warning each."""
        corrected: list[str] = []
        for job_id, ref in list(self._refs.items()):
            line = ref.record.pop("_line")
            folder = self.root / FRAMES / job_id
            if not (folder.exists() or folder.is_symlink()):
                if ref.status == "ok":
                    self._refuse(job_id, f"{folder}: frame folder not found")
                continue
            if folder.is_symlink():
                self._refuse(job_id, f"{folder}: a symbolic link, not a frame folder (a run never publishes one)")
                continue
            try:
                data = read_regular(folder / RECORD)
                stored = json.loads(data)
            except (OSError, ValueError, RecursionError) as exc:
                if ref.status == "ok":
                    self._refuse(job_id, f"{folder / RECORD}: cannot be read ({getattr(exc, 'strerror', None) or exc})")
                continue
            expected = ref.record.get("record_file")
            if isinstance(expected, dict) and (len(data) != expected.get("bytes")
                                               or hashlib.sha256(data).hexdigest() != expected.get("sha256")):
                self._refuse(job_id, f"{folder / RECORD}: does not match the size and SHA-256 the index keeps for it")
                continue
            if not isinstance(stored, dict) or stored.get("job_id") != job_id or stored.get("status") not in STATUSES:
                self._refuse(job_id, f"{folder / RECORD}: not the record of frame {job_id}")
                continue
            changed = differing_keys(ref.record, stored)
            if changed:
                corrected.append(f"line {line} ({', '.join(changed)})")
                self._refs[job_id] = FrameRef({**stored, **({"record_file": expected} if expected else {})},
                                              self.root, self.checksum)
        if corrected:
            shown = "; ".join(corrected[:5]) + (" …" if len(corrected) > 5 else "")
            warnings.warn(f"{self.index_path}: {len(corrected)} line(s) differ from their frame's {RECORD}, "
                          f"which is used: {shown}; tofcore-batch run repairs the index", stacklevel=3)
        if self.refused:
            shown = "; ".join(self.refused.values()) if len(self.refused) <= 3 else \
                "; ".join(list(self.refused.values())[:3]) + " …"
            warnings.warn(f"{self.root}: {len(self.refused)} frame(s) refused: {shown}", stacklevel=3)
        known = self._refs.keys() | self.refused.keys()
        self.unindexed = sorted(p.name for p in (self.root / FRAMES).iterdir()
                                if _JOB_ID.fullmatch(p.name) and p.name not in known)
        if self.unindexed:
            warnings.warn(f"{self.root}: {len(self.unindexed)} frame folder(s) in {FRAMES}/ are not in {INDEX} and "
                          f"not listed (e.g. {self.unindexed[0]}); running the set again (tofcore-batch run) "
                          f"repairs the index", stacklevel=3)

    def _check_against_set(self, only: bool) -> None:
        """Set aside the frames not in the last run's set (``only``), else warn about them."""
        if self.current_set is None:
            if only:
                raise DatasetError(f"{self.root / CURRENT_SET}: not found or not readable, so the frames of the "
                                   f"current set are not known (a dataset of an older run: run the set again)")
            return
        in_set = set(self.current_set["jobs"])
        self.outside_set = [i for i in self._refs if i not in in_set]
        if only:
            for job_id in self.outside_set:
                del self._refs[job_id]
        elif self.outside_set:
            example = self._refs[self.outside_set[0]]
            warnings.warn(f"{self.root}: {len(self.outside_set)} indexed frame(s) are not in the set of the last run "
                          f"({self.current_set.get('set_file') or 'its set'}), e.g. {example.id} "
                          f"({example.scene}/{example.view}/{example.preset}): an earlier version of the set file or "
                          f"another set; Dataset(root, current_set=True) lists only that set's frames", stacklevel=3)

    def _refuse(self, job_id: str, why: str) -> None:
        self._refs.pop(job_id)
        self.refused[job_id] = why

    def __repr__(self) -> str:
        return f"Dataset({str(self.root)!r}: {len(self)} ok of {len(self._refs)} frames)"

    # ---------------------------------------------------------------- listing
    @property
    def scenes(self) -> list[str]:
        """Scene names in index order (all statuses)."""
        return list(dict.fromkeys(r.scene for r in self._refs.values()))

    @property
    def presets(self) -> list[str]:
        """Preset labels in index order (all statuses)."""
        return list(dict.fromkeys(r.preset for r in self._refs.values()))

    @property
    def views(self) -> list[str]:
        """View labels in index order (all statuses)."""
        return list(dict.fromkeys(r.view for r in self._refs.values()))

    def frames(self, scene: str | Iterable[str] | None = None, preset: str | Iterable[str] | None = None,
               status: str | Iterable[str] | None = "ok", view: str | Iterable[str] | None = None) -> list[FrameRef]:
        """The frames that match every filter given, in index order.

        Parameters
        ----------
        scene : str, iterable of str or None
            Scene name(s); None: any.
        preset : str, iterable of str or None
            Preset label(s); None: any.
        status : str, iterable of str or None
            ``"ok"`` (default), ``"failed"``, both, or None for any.
        view : str, iterable of str or None
            View label(s); None: any.

        Raises
        ------
        DatasetError
            A scene, preset or view not in the dataset at all, or an unknown
            status: the valid values are listed (an empty list from a typo
            would pass silently).
        """
        wanted = {
            "scene": _wanted(scene, self.scenes, "scene", self.root),
            "preset": _wanted(preset, self.presets, "preset", self.root),
            "status": _wanted(status, STATUSES, "status", self.root),
            "view": _wanted(view, self.views, "view", self.root),
        }
        return [ref for ref in self._refs.values()
                if all(values is None or getattr(ref, field) in values for field, values in wanted.items())]

    def frame(self, frame_id: str) -> FrameRef:
        """The frame with job id ``frame_id`` (any status); DatasetError if the index has none."""
        if frame_id in self.refused:
            raise DatasetError(f"frame {frame_id}: refused ({self.refused[frame_id]})")
        try:
            return self._refs[frame_id]
        except KeyError:
            raise DatasetError(f"{self.index_path}: no frame with id {frame_id!r} "
                               f"({len(self._refs)} frames)") from None

    def __len__(self) -> int:
        return sum(1 for ref in self._refs.values() if ref.status == "ok")

    def __iter__(self) -> Iterator[FrameRef]:
        return iter(self.frames())

    def __getitem__(self, key: int | str) -> FrameRef:
        if isinstance(key, str):
            return self.frame(key)
        return self.frames()[key]


def _wanted(value, valid: Sequence[str], field: str, root: Path) -> set[str] | None:
    """The set of accepted values of a filter, None for any; DatasetError for a value not in ``valid``."""
    if value is None:
        return None
    values = [value] if isinstance(value, str) else list(value)
    unknown = [v for v in values if v not in valid]
    if unknown:
        raise DatasetError(f"{root}: frames({field}=…): {field} must be among {list(valid)}, got {unknown[0]!r}")
    return set(values)


def check_one_kind(refs: list[FrameRef], where: str) -> None:
    """ValueError (one line) when the frames differ in preset or image size: torch's default collate cannot
    stack them (``stack expects each tensor to be equal size``)."""
    groups: dict[tuple, int] = {}
    for ref in refs:
        settings = ref.record.get("settings") or {}
        key = (ref.preset, settings.get("width"), settings.get("height"))
        groups[key] = groups.get(key, 0) + 1
    if len(groups) > 1:
        listed = "; ".join(f"{p} {w}x{h} ({n} frames)" for (p, w, h), n in sorted(groups.items(), key=str))
        first = sorted(groups, key=str)[0][0]
        raise ValueError(f"{where}: frames of {len(groups)} presets or sizes cannot be stacked into batches: "
                         f"{listed}; choose one with preset={first!r}, or pass allow_mixed=True")
