"""tofcore.scene.placement and tofcore.scene.viewpoint: objects on surfaces without interpenetration,
camera views that see their target. Checked against brute-force ray tests (not the BVH the code uses)."""

import numpy as np
import pytest

import tofcore
from tofcore.scene.bvh import intersect_brute
from tofcore.scene.placement import compose, interpenetrates, place_objects, rotation
from tofcore.scene.primitives import NAMES, primitive
from tofcore.scene.viewpoint import orbit_eye, sees

ROOM = tofcore.demo_scene("room")
MESHES = [(name, primitive(name, segments=12, rings=6)) for name in NAMES]
GAP_M = 0.002


def _edges_cross(vertices, triangles, edge_vertices, edge_triangles) -> bool:
    """Whether an edge of mesh B crosses a triangle of mesh A: Möller–Trumbore in float64 over every pair
    (edges parallel to a triangle's plane are left out: a coplanar overlap shows as overlapping boxes)."""
    e = np.unique(np.sort(np.concatenate([edge_triangles[:, [0, 1]], edge_triangles[:, [1, 2]],
                                          edge_triangles[:, [2, 0]]]), axis=1), axis=0)
    p0, p1 = edge_vertices[e[:, 0]][:, None], edge_vertices[e[:, 1]][:, None]
    a, b, c = (vertices[triangles[:, k]][None] for k in range(3))
    d = p1 - p0
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ijk,ijk->ij", e1, h)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = p0 - a
        u = np.einsum("ijk,ijk->ij", s, h) / det
        q = np.cross(s, e1)
        v = np.einsum("ijk,ijk->ij", d, q) / det
        t = np.einsum("ijk,ijk->ij", e2, q) / det
        hit = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < 1 - 1e-9)
        return bool(hit.any())


def _inside(point, vertices, triangles) -> bool:
    """Point in a closed mesh: an odd number of crossings along a ray (a skewed direction avoids edges)."""
    d = np.array([0.5731, 0.6142, 0.5425])
    d /= np.linalg.norm(d)
    count, origin = 0, np.asarray(point, np.float64)
    for _ in range(64):
        hit = intersect_brute(vertices, triangles, origin[None], d[None])
        if hit.prim[0] < 0:
            return count % 2 == 1
        count += 1
        origin = origin + d * (float(hit.t[0]) + 1e-5)
    raise AssertionError("too many crossings")


def _object_meshes(scene, first_object):
    """(vertices, triangles) of each placed object of a composed scene."""
    v = scene.vertices.astype(np.float64)
    out = []
    for obj in range(first_object, int(scene.object_ids.max()) + 1):
        t = scene.triangles[scene.object_ids == obj]
        used, local = np.unique(t, return_inverse=True)
        out.append((v[used], local.reshape(-1, 3)))
    return out


@pytest.mark.parametrize("seed", range(4))
def test_placed_objects_never_interpenetrate_the_room_or_each_other(seed):
    rng = np.random.default_rng(seed)
    placed = place_objects(ROOM, MESHES, 12, rng, draw_size=lambda r: r.uniform(0.15, 0.6),
                           draw_yaw=lambda r: r.uniform(0, 2 * np.pi),
                           draw_tilt=lambda r: r.choice([0.0, np.pi / 2, 0.3]), gap_m=GAP_M)
    assert len(placed.placements) >= 8  # the room has space: most objects find a place
    scene = compose(ROOM, dict(MESHES), placed.placements)
    first = int(ROOM.object_ids.max()) + 1
    objects = _object_meshes(scene, first)
    assert len(objects) == len(placed.placements)
    base_v, base_t = ROOM.vertices.astype(np.float64), ROOM.triangles
    closed_base = [i for i, name in enumerate(ROOM.object_names) if name not in ("room", "floor")]
    for i, (v, t) in enumerate(objects):
        # Surfaces never cross: no edge of one crosses a triangle of the other, both ways.
        assert not _edges_cross(base_v, base_t, v, t) and not _edges_cross(v, t, base_v, base_t)
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        for obj in closed_base:  # not inside the table top, a leg, the cabinet or the metal box
            assert not _inside(centre, base_v, base_t[ROOM.object_ids == obj])
        assert _inside(centre, base_v, base_t[ROOM.object_ids == 0])  # inside the room
        for w, _ in objects[i + 1:]:  # placed objects keep apart: their bounding boxes do not overlap
            assert np.any(v.max(axis=0) < w.min(axis=0)) or np.any(w.max(axis=0) < v.min(axis=0))
        # It rests on its support point: its lowest vertex is the gap above it.
        p = placed.placements[i]
        assert v[:, 2].min() == pytest.approx(p.support_m[2] + GAP_M, abs=1e-5)
        lo, hi = np.asarray(p.bounds_m)
        assert np.allclose(v.min(axis=0), lo, atol=1e-5) and np.allclose(v.max(axis=0), hi, atol=1e-5)


def test_a_seed_places_the_same_objects():
    def run(seed):
        return place_objects(ROOM, MESHES, 6, np.random.default_rng(seed), draw_size=lambda r: r.uniform(0.1, 0.4),
                             draw_yaw=lambda r: r.uniform(0, 6.28), draw_tilt=lambda r: 0.0).placements

    a, b, c = run(3), run(3), run(4)
    assert [(p.mesh, p.world_from_object.tolist()) for p in a] == [(p.mesh, p.world_from_object.tolist()) for p in b]
    assert [p.world_from_object.tolist() for p in a] != [p.world_from_object.tolist() for p in c]


def _box_at(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    box = primitive("box")
    v = box.vertices.astype(np.float64) * (hi - lo) + 0.5 * (lo + hi)
    return v, box.triangles


@pytest.mark.parametrize("lo, hi, expected", [
    ((-0.1, 0.5, 0.6), (0.1, 0.7, 0.9), True),      # through the table top (z 0.70–0.75)
    ((1.9, 1.6, 0.5), (2.1, 1.8, 0.7), True),       # inside the cabinet: no surface crossed
    ((-0.1, 0.5, 0.752), (0.1, 0.7, 0.95), False),  # on the table top
    ((-2.3, -1.5, 0.3), (-2.1, -1.3, 0.6), False),  # in free air
    ((-0.3, -0.3, 0.0005), (0.3, 0.3, 0.3), True),  # swallows floor-grid vertices (z 0.001) of the base
])
def test_the_interpenetration_test_finds_crossings_and_containment(lo, hi, expected):
    v, t = _box_at(lo, hi)
    assert interpenetrates(ROOM, ROOM.bvh, v - np.asarray(ROOM.origin_m), t) is expected
    base_v = ROOM.vertices.astype(np.float64)  # the brute-force checker above agrees where surfaces cross
    crossing = _edges_cross(base_v, ROOM.triangles, v, t) or _edges_cross(v, t, base_v, ROOM.triangles)
    assert crossing if lo[2] == 0.6 else (expected or not crossing)


def test_rotation_turns_about_z_after_tilting_about_x():
    r = rotation(np.pi / 2, np.pi / 2)
    assert np.allclose(r @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # up → tilted to −y → turned to +x
    assert np.allclose(r @ r.T, np.eye(3))


def test_an_orbit_view_sees_its_target_unless_something_is_in_the_way():
    target = np.array([0.0, 0.6, 0.9])  # above the table
    eye = orbit_eye(target, 1.5, -np.pi / 2, np.radians(20))
    assert np.allclose(np.linalg.norm(eye - target), 1.5)
    assert eye[2] == pytest.approx(0.9 + 1.5 * np.sin(np.radians(20)))
    assert sees(ROOM, eye, target)
    assert not sees(ROOM, [0.0, 0.6, 0.4], target)          # under the table: the top is in the way
    assert not sees(ROOM, [0.0, -3.0, 1.0], target)         # outside the room: its wall seen from behind
    assert not sees(ROOM, [2.0, 1.7, 1.0], target)          # inside the cabinet


def test_an_eye_near_a_wall_is_not_clear():
    from tofcore.scene.viewpoint import clear

    assert clear(ROOM, [0.0, 0.0, 1.5], 0.1)
    assert not clear(ROOM, [2.45, 0.0, 1.5], 0.1)           # 5 cm from the wall x = 2.5
    assert not clear(ROOM, [0.0, 0.0, 2.62], 0.1)           # 8 cm below the ceiling
    # A plane 0.8 × clearance away at the worst angle between the test directions is still found.
    n = np.array([0.591, 0.0, 0.807])
    n /= np.linalg.norm(n)
    u = np.cross(n, [0.0, 1.0, 0.0])
    plane = tofcore.Scene.from_arrays(np.array([0.079 * n + 5 * (a * u + b * np.array([0, 1, 0]))
                                                for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]),
                                      [[0, 1, 2], [0, 2, 3]])
    assert not clear(plane, [0.0, 0.0, 0.0], 0.1)
