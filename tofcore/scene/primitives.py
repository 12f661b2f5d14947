"""Closed primitive meshes made in code: box, cylinder, sphere, cone — objects for randomized scenes.

Each primitive is a :class:`~tofcore.scene.Scene` of one object whose bounding box is the unit cube
centred on the origin ([−½, ½]³, metres, Z up), outward-facing triangles (counter-clockwise seen from
outside), one material named ``name``. :mod:`tofcore.scene.placement` scales and turns them.

==============  ===========================================================================
name            geometry (``segments`` around the axis, ``rings`` from pole to pole)
==============  ===========================================================================
``"box"``       the unit cube, 12 triangles
``"cylinder"``  radius ½, height 1, axis Z, capped: 4·segments triangles
``"sphere"``    radius ½, a UV sphere: 2·segments·(rings − 1) triangles
``"cone"``      base radius ½ at z = −½, apex at z = ½: 2·segments triangles
==============  ===========================================================================
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .material import Material
from .scene import Scene

NAMES = ("box", "cylinder", "sphere", "cone")


def _box() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, y, z] for z in (-0.5, 0.5) for y in (-0.5, 0.5) for x in (-0.5, 0.5)], dtype=np.float64)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    return v, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def _ring(segments: int, radius: float, z: float) -> np.ndarray:
    phi = 2 * np.pi * np.arange(segments) / segments
    return np.stack([radius * np.cos(phi), radius * np.sin(phi), np.full(segments, z)], axis=1)


def _cylinder(segments: int, cone: bool = False) -> tuple[np.ndarray, np.ndarray]:
    n = segments
    bottom = _ring(n, 0.5, -0.5)
    top = np.array([[0.0, 0.0, 0.5]]) if cone else _ring(n, 0.5, 0.5)
    v = np.concatenate([bottom, top, [[0.0, 0.0, -0.5]], [[0.0, 0.0, 0.5]]])
    i = np.arange(n)
    j = (i + 1) % n
    c_bottom, c_top = len(v) - 2, len(v) - 1
    base = np.stack([i, np.full(n, c_bottom), j], axis=1)  # seen from below: counter-clockwise
    if cone:
        apex = n
        return v, np.concatenate([base, np.stack([i, j, np.full(n, apex)], axis=1)])
    side = np.concatenate([np.stack([i, j, j + n], axis=1), np.stack([i, j + n, i + n], axis=1)])
    cap = np.stack([i + n, j + n, np.full(n, c_top)], axis=1)
    return v, np.concatenate([base, side, cap])


def _sphere(segments: int, rings: int) -> tuple[np.ndarray, np.ndarray]:
    theta = np.pi * np.arange(1, rings) / rings  # polar angles of the inner rings
    phi = 2 * np.pi * np.arange(segments) / segments
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = 0.5 * np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    v = np.concatenate([ring, [[0.0, 0.0, 0.5]], [[0.0, 0.0, -0.5]]])
    north, south = len(v) - 2, len(v) - 1
    n = segments
    i = np.arange(n)
    j = (i + 1) % n
    tris = [np.stack([np.full(n, north), i, j], axis=1)]
    for r in range(rings - 2):
        a, b = r * n + i, r * n + j
        tris += [np.stack([a, a + n, b + n], axis=1), np.stack([a, b + n, b], axis=1)]
    last = (rings - 2) * n
    tris.append(np.stack([last + i, np.full(n, south), last + j], axis=1))
    return v, np.concatenate(tris)


def primitive(name: str, material: Material | None = None, *, segments: int = 24, rings: int = 12) -> Scene:
    """The primitive ``name`` (one of :data:`NAMES`) as a one-object scene; see the module docstring."""
    if name not in NAMES:
        raise ConfigError(f"primitive: name must be one of {list(NAMES)}, got {name!r}")
    if segments < 3 or rings < 2:
        raise ConfigError(f"primitive: segments must be >= 3 and rings >= 2, got {segments}, {rings}")
    if name == "box":
        v, t = _box()
    elif name == "sphere":
        v, t = _sphere(segments, rings)
    else:
        v, t = _cylinder(segments, cone=name == "cone")
    return Scene.from_arrays(v, t, materials=[material or Material(name=name)], object_names=[name], name=name)
