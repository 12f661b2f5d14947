"""Demo scenes: small, known geometry for tests, examples and the thesis experiments.

====================  =================================================================================
name                  what it is
====================  =================================================================================
``"plane"``           a 4 × 3 m wall 2 m in front of the sensor, facing it (radiometry checks)
``"corner"``          two perpendicular 3 × 2.5 m walls meeting on a vertical edge 1.5 m away,
                      σ = 0.5, η = 1.52 as in the thesis's corner experiment (§6.3)
``"box_on_wall"``     a 0.3 m box 0.5 m in front of a bright wall 2 m away (§6.1, §6.2, LED shadows)
``"room"``            a closed 5 × 4 × 2.7 m room with a table, a cabinet and a box
====================  =================================================================================

Each scene stores a suggested sensor pose in ``scene.metadata["world_from_sensor"]``
(see :func:`suggested_pose`). ``detail`` subdivides every quad into
detail × detail cells (2·detail² triangles), which scales the triangle count
for benchmarks without changing the geometry.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .material import Material
from .pose import look_at
from .scene import Scene

NAMES = ("plane", "corner", "box_on_wall", "room")


class _Builder:
    """Collects quads and boxes into flat arrays."""

    def __init__(self, detail: int):
        self.detail = detail
        self.vertices: list[np.ndarray] = []
        self.triangles: list[np.ndarray] = []
        self.materials: list[np.ndarray] = []
        self.objects: list[np.ndarray] = []
        self.object_names: list[str] = []
        self.n = 0

    def quad(self, corner, edge_u, edge_v, material: int, obj: int) -> None:
        """A planar grid; its front (normal = edge_u × edge_v) faces where the normal points."""
        n = self.detail
        s = np.linspace(0.0, 1.0, n + 1)
        uu, vv = np.meshgrid(s, s, indexing="xy")
        pts = (np.asarray(corner, float) + uu.reshape(-1, 1) * np.asarray(edge_u, float)
               + vv.reshape(-1, 1) * np.asarray(edge_v, float))
        i = np.arange(n)[None, :] + (n + 1) * np.arange(n)[:, None]
        i = i.reshape(-1)
        tris = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
        self.vertices.append(pts)
        self.triangles.append(tris + self.n)
        self.materials.append(np.full(len(tris), material))
        self.objects.append(np.full(len(tris), obj))
        self.n += len(pts)

    def box(self, lo, hi, material: int, name: str, inward: bool = False) -> None:
        """An axis-aligned box; normals point outwards (inwards for a room's walls)."""
        obj = len(self.object_names)
        self.object_names.append(name)
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        size = hi - lo
        ex, ey, ez = np.diag(size)
        faces = [  # (corner, edge_u, edge_v) with edge_u × edge_v pointing outwards
            (lo, ey, ex), (lo + ez, ex, ey),          # bottom (−z), top (+z)
            (lo, ex, ez), (lo + ey, ez, ex),          # front (−y), back (+y)
            (lo, ez, ey), (lo + ex, ey, ez),          # left (−x), right (+x)
        ]
        for corner, eu, ev in faces:
            if inward:
                eu, ev = ev, eu
            self.quad(corner, eu, ev, material, obj)

    def named_quad(self, corner, edge_u, edge_v, material: int, name: str) -> None:
        obj = len(self.object_names)
        self.object_names.append(name)
        self.quad(corner, edge_u, edge_v, material, obj)

    def scene(self, materials, name: str, pose: np.ndarray) -> Scene:
        return Scene.from_arrays(
            np.concatenate(self.vertices), np.concatenate(self.triangles), np.concatenate(self.materials),
            materials, object_ids=np.concatenate(self.objects), object_names=self.object_names, name=name,
            metadata={"world_from_sensor": pose.tolist()})


def demo_scene(name: str, detail: int = 4) -> Scene:
    """Build the demo scene ``name`` (one of :data:`NAMES`); see the module docstring."""
    if name not in NAMES:
        raise ConfigError(f"demo_scene: name must be one of {list(NAMES)}, got {name!r}")
    if not isinstance(detail, (int, np.integer)) or detail < 1:
        raise ConfigError(f"demo_scene: detail must be an integer >= 1, got {detail!r}")
    b = _Builder(int(detail))
    if name == "plane":
        wall = Material(name="wall", reflectance=0.8, roughness=0.0)
        b.named_quad((-2.0, 0.0, 0.0), (4.0, 0.0, 0.0), (0.0, 0.0, 3.0), 0, "wall")  # y = 0, normal −y
        return b.scene([wall], name, look_at((0.0, -2.0, 1.5), (0.0, 0.0, 1.5)))
    if name == "corner":
        wall = Material(name="wall", reflectance=0.8, roughness=0.5, ior=1.52)
        b.named_quad((0.0, 0.0, 0.0), (0.0, 3.0, 0.0), (0.0, 0.0, 2.5), 0, "wall x=0")   # normal +x
        b.named_quad((0.0, 0.0, 0.0), (0.0, 0.0, 2.5), (3.0, 0.0, 0.0), 0, "wall y=0")   # normal +y
        d = 1.5 / np.sqrt(2.0)
        return b.scene([wall], name, look_at((d, d, 1.25), (0.0, 0.0, 1.25)))
    if name == "box_on_wall":
        wall = Material(name="wall", reflectance=0.9, roughness=0.5)
        box = Material(name="box", reflectance=0.5, roughness=0.5)
        b.named_quad((-2.0, 0.0, 0.0), (4.0, 0.0, 0.0), (0.0, 0.0, 3.0), 0, "wall")     # y = 0, normal −y
        b.box((-0.15, -0.8, 1.35), (0.15, -0.5, 1.65), 1, "box")
        return b.scene([wall, box], name, look_at((0.0, -2.0, 1.5), (0.0, 0.0, 1.5)))
    # room
    walls = Material(name="walls", reflectance=0.7, roughness=0.6)
    floor = Material(name="floor", reflectance=0.3, roughness=0.3)
    wood = Material(name="wood", reflectance=0.5, roughness=0.2)
    metal = Material(name="metal", metallic=1.0, ior=1.35, extinction=9.6, roughness=0.15)
    b.box((-2.5, -2.0, 0.0), (2.5, 2.0, 2.7), 0, "room", inward=True)
    # The floor is a separate quad just above the room's bottom face so it can carry its own material.
    b.named_quad((-2.5, -2.0, 0.001), (5.0, 0.0, 0.0), (0.0, 4.0, 0.0), 1, "floor")
    b.box((-0.8, 0.2, 0.70), (0.8, 1.0, 0.75), 2, "table top")
    for x in (-0.75, 0.7):
        for y in (0.25, 0.9):
            b.box((x, y, 0.0), (x + 0.05, y + 0.05, 0.70), 2, "table leg")
    b.box((1.6, 1.4, 0.0), (2.4, 1.95, 1.9), 2, "cabinet")
    b.box((-2.0, 1.2, 0.0), (-1.4, 1.8, 0.5), 3, "metal box")
    return b.scene([walls, floor, wood, metal], name, look_at((0.0, -1.8, 1.6), (0.0, 1.0, 0.8)))


def suggested_pose(scene: Scene) -> np.ndarray:
    """The sensor pose stored with a demo scene (identity when there is none)."""
    pose = scene.metadata.get("world_from_sensor")
    return np.eye(4) if pose is None else np.asarray(pose, dtype=np.float64)
