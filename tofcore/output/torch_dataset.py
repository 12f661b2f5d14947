"""PyTorch adapter of a dataset folder: :class:`TorchDataset`.

Optional: ``import tofcore`` never imports this module nor PyTorch; importing
this module without PyTorch installed raises one ``ImportError`` line saying
so. The reading is :class:`tofcore.output.dataset.Dataset`'s; a sample is
:meth:`tofcore.output.dataset.FrameRef.sample` with every array made a tensor
(``torch.from_numpy``, no copy) and the strings left as they are.

Sample
------
=====================  =============  ==========  ==================================================
key                    shape          dtype       content
=====================  =============  ==========  ==================================================
``depth`` (and any     (1, H, W)      float32     as stored, NaN where invalid (mask your loss with
image channel asked)                              ``valid``); metres, electrons … (see tofcore.output.dataset)
``valid``              (1, H, W)      bool        pixel has a depth
``reason``             (1, H, W)      uint8       :class:`~tofcore.output.frame.Reason` code
``object_id``          (1, H, W)      int32       first-hit object, −1 none
``raw``                (R, H, W)      float32     raw images (e⁻), in the order of the frame's ``raw_labels``
``distance_per_k``     (K, H, W)      float32     decoded distance using bounces ≤ k (m)
``ray_directions``     (3, H, W)      float32     unit pixel-centre ray directions, sensor frame
``intrinsics``         (3, 3)         float32     [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (px)
``distortion``         (5,)           float32     OpenCV k1, k2, p1, p2, k3
``world_from_sensor``  (4, 4)         float32     sensor (OpenCV axes) → world pose, metres
``id``                 –              str         job id (the frame's folder name)
``scene``, ``view``,   –              str         from the index record
``preset``
=====================  =============  ==========  ==================================================

Only the channels asked are in a sample; the last seven keys always are.
The default collate batches samples of one size and one raw count, so frames of
several presets or image sizes are refused when the dataset is made, with one
line listing the groups: choose one with ``preset=``, or pass
``allow_mixed=True`` (batch size 1, or a ``transform``/collate that makes them
alike).

Parameters
----------
root : str or os.PathLike
    The dataset folder.
channels : iterable of str, default ``("depth", "gt_depth", "valid")``
    Channel names of :data:`tofcore.output.dataset.CHANNELS`.
scene, preset, view : str or iterable of str, optional
    Filters of :meth:`tofcore.output.dataset.Dataset.frames` (default: every frame with status ``"ok"``).
transform : callable, optional
    Applied to each sample dict; its return value is the sample.
allow_mixed : bool, default False
    Accept frames of several presets or image sizes.
current_set : bool, default False
    Only the frames of the set the last run rendered (``Dataset(root, current_set=True)``).

Example
-------
>>> from torch.utils.data import DataLoader                         # doctest: +SKIP
>>> from tofcore.output.torch_dataset import TorchDataset
>>> data = TorchDataset("out/demo_dataset", channels=["depth", "gt_depth", "valid", "raw"],
...                     preset="kinect_v2")
>>> batch = next(iter(DataLoader(data, batch_size=4, shuffle=True)))
>>> batch["depth"].shape, batch["raw"].shape                        # (4, 1, H, W), (4, 9, H, W)
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable

try:
    import torch
    from torch.utils.data import Dataset as _TorchBase
except ImportError:
    raise ImportError("tofcore.output.torch_dataset: needs PyTorch, which is not installed: pip install torch "
                      "(tofcore.output.dataset.Dataset reads the same data as NumPy arrays without it)") from None

import numpy as np

from .dataset import Dataset, FrameRef, _check_channels, check_one_kind

DEFAULT_CHANNELS = ("depth", "gt_depth", "valid")


class TorchDataset(_TorchBase):
    """A dataset folder as a map-style ``torch.utils.data.Dataset``; see the module docstring."""

    def __init__(self, root: str | os.PathLike, channels: Iterable[str] = DEFAULT_CHANNELS, *,
                 scene=None, preset=None, view=None,
                 transform: Callable[[dict], dict] | None = None, allow_mixed: bool = False,
                 current_set: bool = False):
        self.dataset = Dataset(root, current_set=current_set)
        where = f"TorchDataset({str(self.dataset.root)!r})"
        self.channels = tuple(_check_channels(channels, where))
        self.refs: list[FrameRef] = self.dataset.frames(scene=scene, preset=preset, view=view)
        self.transform = transform
        if not allow_mixed:
            check_one_kind(self.refs, where)

    def __len__(self) -> int:
        return len(self.refs)

    def __getitem__(self, index: int) -> dict:
        sample = self.refs[index].sample(self.channels)
        sample = {k: torch.from_numpy(np.ascontiguousarray(v)) if isinstance(v, np.ndarray) else v
                  for k, v in sample.items()}
        return self.transform(sample) if self.transform is not None else sample

