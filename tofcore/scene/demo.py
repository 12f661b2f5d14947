"""Demo scenes: small, known geometry for tests, examples and the thesis experiments.

====================  =================================================================================
name                  what it is
====================  =================================================================================
``"plane"``           a 4 × 3 m wall 2 m in front of the sensor, facing it (radiometry checks)
``"corner"``          two perpendicular 3 × 2.5 m walls meeting on a vertical edge 1.5 m away,
                      σ = 0.5, η = 1.52 as in the thesis's corner experiment (§6.3)
``"box_on_wall"``     a 0.3 m box 0.5 m in front of a bright wall 2 m away (§6.1, §6.2, LED shadows)
``"room"``            a closed 5 × 4 × 2.7 m room with a table, a cabinet and a box
``"textured_room"``   the room without its ceiling, every material textured (checkered walls, tiled
                      floor, wood grain, a bumped table top, brushed metal) under a small sky map
                      (:func:`demo_ambient`): what an artist's Blender scene with an HDRI world exports
====================  =================================================================================

Textures and the sky are generated in code (no files); UVs are metres along each quad's edges, so
every texture repeats once a metre.

Each scene stores a suggested sensor pose in ``scene.metadata["world_from_sensor"]``
(see :func:`suggested_pose`). ``detail`` subdivides every quad into
detail × detail cells (2·detail² triangles), which scales the triangle count
for benchmarks without changing the geometry.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .ambient import Ambient
from .material import Material, Texture
from .pose import framed_view, look_at
from .scene import Scene

NAMES = ("plane", "corner", "box_on_wall", "room", "textured_room")


class _Builder:
    """Collects quads and boxes into flat arrays."""

    def __init__(self, detail: int):
        self.detail = detail
        self.vertices: list[np.ndarray] = []
        self.triangles: list[np.ndarray] = []
        self.materials: list[np.ndarray] = []
        self.objects: list[np.ndarray] = []
        self.uvs: list[np.ndarray] = []
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
        self.uvs.append(np.stack([uu.reshape(-1) * np.linalg.norm(edge_u), vv.reshape(-1) * np.linalg.norm(edge_v)], 1))
        self.triangles.append(tris + self.n)
        self.materials.append(np.full(len(tris), material))
        self.objects.append(np.full(len(tris), obj))
        self.n += len(pts)

    def box(self, lo, hi, material: int, name: str, inward: bool = False, open_top: bool = False) -> None:
        """An axis-aligned box; normals point outwards (inwards for a room's walls); ``open_top``: no +z face."""
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
        for corner, eu, ev in faces[:1] + faces[2:] if open_top else faces:
            if inward:
                eu, ev = ev, eu
            self.quad(corner, eu, ev, material, obj)

    def named_quad(self, corner, edge_u, edge_v, material: int, name: str) -> None:
        obj = len(self.object_names)
        self.object_names.append(name)
        self.quad(corner, edge_u, edge_v, material, obj)

    def scene(self, materials, name: str, pose: np.ndarray) -> Scene:
        textured = any(m.textures for m in materials)
        return Scene.from_arrays(
            np.concatenate(self.vertices), np.concatenate(self.triangles), np.concatenate(self.materials),
            materials, object_ids=np.concatenate(self.objects), object_names=self.object_names, name=name,
            uvs=np.concatenate(self.uvs) if textured else None, metadata={"world_from_sensor": pose.tolist()})


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
    if name == "textured_room":
        return _room(b, name, _textured_materials(), open_top=True)
    walls = Material(name="walls", reflectance=0.7, roughness=0.6)
    floor = Material(name="floor", reflectance=0.3, roughness=0.3)
    wood = Material(name="wood", reflectance=0.5, roughness=0.2)
    metal = Material(name="metal", metallic=1.0, ior=1.35, extinction=9.6, roughness=0.15)
    return _room(b, name, [walls, floor, wood, metal])


def _room(b: _Builder, name: str, materials: list, open_top: bool = False) -> Scene:
    """The room's geometry with ``materials`` (walls, floor, wood, metal)."""
    b.box((-2.5, -2.0, 0.0), (2.5, 2.0, 2.7), 0, "room", inward=True, open_top=open_top)
    # The floor is a separate quad just above the room's bottom face so it can carry its own material.
    b.named_quad((-2.5, -2.0, 0.001), (5.0, 0.0, 0.0), (0.0, 4.0, 0.0), 1, "floor")
    b.box((-0.8, 0.2, 0.70), (0.8, 1.0, 0.75), 2, "table top")
    for x in (-0.75, 0.7):
        for y in (0.25, 0.9):
            b.box((x, y, 0.0), (x + 0.05, y + 0.05, 0.70), 2, "table leg")
    b.box((1.6, 1.4, 0.0), (2.4, 1.95, 1.9), 2, "cabinet")
    b.box((-2.0, 1.2, 0.0), (-1.4, 1.8, 0.5), 3, "metal box")
    return b.scene(materials, name, look_at((0.0, -1.8, 1.6), (0.0, 1.0, 0.8)))


def _textured_materials() -> list:
    """The textured room's walls, floor, wood and metal: images made here, 64 texels a metre."""
    n = 64
    s = (np.arange(n) + 0.5) / n
    u, v = np.meshgrid(s, s)
    checker = np.where((np.floor(8 * u) + np.floor(8 * v)) % 2 == 0, 0.8, 0.35)  # 12.5 cm checks
    grout = (np.minimum(4 * u % 1.0, 4 * v % 1.0) < 0.06)  # 25 cm tiles, 1.5 cm grout
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (12 * v + 0.8 * np.sin(2 * np.pi * 2 * u)))
    bumps = 2 * np.pi * 6 * np.stack([u, v])  # a normal map of gentle bumps, 6 a metre
    slope = 0.25 * np.stack([np.cos(bumps[0]) * np.sin(bumps[1]), np.sin(bumps[0]) * np.cos(bumps[1])])
    normal = np.stack([slope[0], slope[1], np.ones_like(u)], axis=-1)
    normal = 0.5 + 0.5 * normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    brushed = 0.1 + 0.1 * np.abs(np.sin(2 * np.pi * 40 * v + 3 * u))
    return [Material(name="walls", reflectance=0.7, roughness=0.6, reflectance_texture=Texture(checker, "checker")),
            Material(name="floor", reflectance=0.3, roughness=0.3, reflectance_texture=Texture(
                np.where(grout, 0.15, 0.45), "tiles"), roughness_texture=Texture(np.where(grout, 0.6, 0.25), "grout")),
            Material(name="wood", reflectance=0.5, roughness=0.2, reflectance_texture=Texture(
                0.35 + 0.25 * grain, "wood grain"), roughness_texture=Texture(0.15 + 0.2 * grain, "wood gloss"),
                normal_texture=Texture(normal, "bumps")),
            Material(name="metal", metallic=1.0, ior=1.35, extinction=9.6, roughness=0.15,
                     roughness_texture=Texture(brushed, "brushed"), metallic_texture=Texture(
                         np.where(grout, 0.0, 1.0), "painted seams"))]


def demo_ambient(name: str) -> Ambient | None:
    """The ambient light a demo scene is meant to be seen under: the textured room's small sky map (a
    32 × 64 equirectangular radiance map, W m⁻² sr⁻¹: a horizon-to-zenith gradient of 0.01–0.04 and a
    sun of 3 at 50° elevation), None for the others."""
    if name not in NAMES:
        raise ConfigError(f"demo_ambient: name must be one of {list(NAMES)}, got {name!r}")
    if name != "textured_room":
        return None
    h, w = 32, 64
    elevation = np.pi * (0.5 - (np.arange(h) + 0.5) / h)  # row 0 is the zenith
    azimuth = 2 * np.pi * ((np.arange(w) + 0.5) / w - 0.5)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    sky = 0.01 + 0.03 * np.clip(np.sin(el), 0.0, 1.0)
    sun = np.cos(el) * np.cos(np.radians(50.0)) * np.cos(az - 0.6) + np.sin(el) * np.sin(np.radians(50.0))
    sky = np.where(sun > np.cos(np.radians(6.0)), 3.0, sky)
    return Ambient(environment=Texture(sky, "demo sky"))


def suggested_pose(scene: Scene, sensors=None) -> np.ndarray:
    """The sensor pose suggested for a scene: for a scene that stores the box to frame
    (``metadata["framing"]``: mesh files, :func:`tofcore.load_mesh`) and given ``sensors`` (one
    :class:`~tofcore.sensor.Sensor` or several), :func:`~tofcore.scene.pose.framed_view` of that box for
    their narrowest field of view and the range all of them measure; else the pose stored with the scene
    (``metadata["world_from_sensor"]``; identity when there is none)."""
    framing = scene.metadata.get("framing")
    if framing is not None and sensors is not None:
        sensors = [sensors] if hasattr(sensors, "camera") else list(sensors)
        if sensors:
            return framed_view(framing["lo"], framing["hi"], tan_half_fov=_tan_half_fov(sensors),
                               range_m=(max(s.range_m[0] for s in sensors), min(s.range_m[1] for s in sensors)))
    pose = scene.metadata.get("world_from_sensor")
    return np.eye(4) if pose is None else np.asarray(pose, dtype=np.float64)


def _tan_half_fov(sensors) -> tuple[float, float]:
    """(t_x, t_y): the narrowest half field of view of the sensors' cameras (principal point off-centre: its
    nearer image edge)."""
    return (min(min(s.camera.cx, s.camera.width - s.camera.cx) / s.camera.fx for s in sensors),
            min(min(s.camera.cy, s.camera.height - s.camera.cy) / s.camera.fy for s in sensors))
