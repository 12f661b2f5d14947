"""BVH against the brute-force reference: closest hit, any hit, ignore_prim, edge cases."""

import numpy as np
import pytest

from tofcore.scene.bvh import BVH, RAY_CHUNK, Hits, intersect_brute


def unit(x):
    x = np.asarray(x, np.float64)
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def soup(rng, m, size=0.08):
    """``m`` random triangles of edge ~``size`` in the unit cube, no shared vertices."""
    centre = rng.random((m, 1, 3))
    v = (centre + size * rng.standard_normal((m, 3, 3))).reshape(-1, 3).astype(np.float32)
    return v, np.arange(3 * m, dtype=np.int32).reshape(m, 3)


def terrain(rng, n):
    """Height field over [0, 1]^2 with n x n quads: every inner edge and vertex is shared."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    z = 0.1 * rng.random((n + 1, n + 1))
    v = np.stack([i / n, j / n, z], -1).reshape(-1, 3).astype(np.float32)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    tri = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, tri.astype(np.int32)


def rays_at(rng, targets, spread=2.0):
    """Rays from random points around the unit cube aimed exactly at ``targets``."""
    o = (0.5 + spread * rng.standard_normal(targets.shape)).astype(np.float32)
    return o, unit(targets - o)


def mixed_rays(rng, v, tri, n_each):
    """Random rays from inside the scene, and rays aimed at vertices and edge midpoints."""
    o_in = rng.random((n_each, 3)).astype(np.float32)
    d_in = unit(rng.standard_normal((n_each, 3)))
    pick = rng.integers(0, len(tri), n_each)
    corner = rng.integers(0, 3, n_each)
    vert = v[tri[pick, corner]]
    mid = 0.5 * (v[tri[pick, corner]] + v[tri[pick, (corner + 1) % 3]])
    o_v, d_v = rays_at(rng, vert)
    o_m, d_m = rays_at(rng, mid)
    return np.concatenate([o_in, o_v, o_m]), np.concatenate([d_in, d_v, d_m])


def assert_same_hits(got: Hits, ref: Hits):
    """Same triangle (or a tie within 1e-6 relative t) and t within 1e-5 relative."""
    assert got.t.dtype == np.float32 and got.prim.dtype == np.int32
    np.testing.assert_array_equal(got.prim >= 0, ref.prim >= 0)
    hit = ref.prim >= 0
    np.testing.assert_allclose(got.t[hit], ref.t[hit], rtol=1e-5)
    assert np.all(np.isinf(got.t[~hit]))
    differ = hit & (got.prim != ref.prim)
    assert np.all(np.abs(got.t[differ] - ref.t[differ]) <= 1e-6 * ref.t[differ])
    same = hit & (got.prim == ref.prim)
    np.testing.assert_allclose(got.u[same], ref.u[same], atol=1e-6)
    np.testing.assert_allclose(got.v[same], ref.v[same], atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_closest_hit_soup_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    v, tri = soup(rng, 1500)
    o, d = mixed_rays(rng, v, tri, 1500)
    bvh = BVH.build(v, tri)
    assert_same_hits(bvh.intersect(o, d), intersect_brute(v, tri, o, d))


def test_closest_hit_shared_edges_matches_brute_force_and_has_no_cracks():
    rng = np.random.default_rng(2)
    n = 24
    v, tri = terrain(rng, n)
    o, d = mixed_rays(rng, v, tri, 1200)
    bvh = BVH.build(v, tri)
    assert_same_hits(bvh.intersect(o, d), intersect_brute(v, tri, o, d))
    # from above, aimed at interior vertices and at the midpoints of edges between two triangles
    grid = v.reshape(n + 1, n + 1, 3)
    inner = grid[1:-1, 1:-1].reshape(-1, 3)
    edges = np.concatenate([0.5 * (grid[1:, 1:-1] + grid[:-1, 1:-1]).reshape(-1, 3),  # along x
                            0.5 * (grid[1:-1, 1:] + grid[1:-1, :-1]).reshape(-1, 3),  # along y
                            0.5 * (grid[1:, 1:] + grid[:-1, :-1]).reshape(-1, 3)])  # diagonals
    target = np.concatenate([inner, edges])
    o_top = np.concatenate([target[:, :2] + 0.3 * rng.standard_normal((len(target), 2)),
                            np.full((len(target), 1), 1.5)], 1).astype(np.float32)
    d_top = unit(target - o_top)
    got = bvh.intersect(o_top, d_top)
    assert_same_hits(got, intersect_brute(v, tri, o_top, d_top))
    assert np.all(got.prim >= 0), "a ray aimed at a shared vertex or edge slipped through"


@pytest.mark.parametrize("leaf_size", [1, 2, 7])
def test_leaf_sizes_match_brute_force(leaf_size):
    rng = np.random.default_rng(3)
    v, tri = soup(rng, 700)
    o, d = mixed_rays(rng, v, tri, 400)
    bvh = BVH.build(v, tri, leaf_size=leaf_size)
    assert bvh.stats["leaf_size_max"] <= leaf_size
    assert_same_hits(bvh.intersect(o, d), intersect_brute(v, tri, o, d))


def test_axis_aligned_rays_on_axis_aligned_grid():
    v, tri = terrain(np.random.default_rng(4), 8)
    v[:, 2] = 0.25  # flat: every box has zero thickness before padding
    g = np.linspace(-0.05, 1.05, 23, dtype=np.float32)  # includes grid lines (multiples of 1/8)
    x, y = np.meshgrid(g, g)
    o = np.stack([x.ravel(), y.ravel(), np.full(x.size, 1.0, np.float32)], -1)
    d = np.tile(np.float32([0, 0, -1]), (len(o), 1))
    o_side = np.stack([np.full(x.size, -1.0, np.float32), y.ravel(), np.full(x.size, 0.25, np.float32)], -1)
    d_side = np.tile(np.float32([1, 0, 0]), (len(o), 1))  # in the plane of the mesh
    d_neg_zero = np.tile(np.float32([-0.0, -0.0, -1]), (len(o), 1))  # signed zeros: octant of +0
    o, d = np.concatenate([o, o_side, o]), np.concatenate([d, d_side, d_neg_zero])
    assert_same_hits(BVH.build(v, tri).intersect(o, d), intersect_brute(v, tri, o, d))


def test_occluded_matches_brute_force():
    rng = np.random.default_rng(5)
    v, tri = soup(rng, 1500)
    o, d = mixed_rays(rng, v, tri, 1000)
    t_max = (2.5 * rng.random(len(o))).astype(np.float32)
    ignore = np.where(rng.random(len(o)) < 0.5, rng.integers(0, len(tri), len(o)), -1).astype(np.int32)
    ref = intersect_brute(v, tri, o, d, ignore_prim=ignore)
    bvh = BVH.build(v, tri)
    np.testing.assert_array_equal(bvh.occluded(o, d, t_max, ignore_prim=ignore), ref.t < t_max)
    assert_same_hits(bvh.intersect(o, d, t_max=t_max, ignore_prim=ignore),
                     intersect_brute(v, tri, o, d, t_max=t_max, ignore_prim=ignore))


def test_ignore_prim_skips_the_named_triangle_only():
    rng = np.random.default_rng(6)
    v, tri = soup(rng, 800)
    o, d = mixed_rays(rng, v, tri, 500)
    bvh = BVH.build(v, tri)
    first = bvh.intersect(o, d)
    hit = first.prim >= 0
    o, d, ignore = o[hit], d[hit], first.prim[hit]
    second = bvh.intersect(o, d, ignore_prim=ignore)
    assert not np.any(second.prim == ignore)
    assert np.all(second.t >= first.t[hit])
    assert_same_hits(second, intersect_brute(v, tri, o, d, ignore_prim=ignore))
    assert not bvh.occluded(o, d, first.t[hit] * 0.999).any()  # nothing before the closest hit
    # rays leaving a triangle's surface never hit that triangle
    w = rng.dirichlet([1, 1, 1], len(tri)).astype(np.float32)
    o2 = np.einsum("mk,mka->ma", w, v[tri])
    d2 = unit(rng.standard_normal((len(tri), 3)))
    own = np.arange(len(tri), dtype=np.int32)
    leave = bvh.intersect(o2, d2, ignore_prim=own)
    assert not np.any(leave.prim == own)
    assert_same_hits(leave, intersect_brute(v, tri, o2, d2, ignore_prim=own))


@pytest.mark.parametrize("offset", [1e-3, 1e-4, 1e-5, 1e-6])
def test_corner_has_no_gap(offset):
    """Two perpendicular unit quads meeting along the edge x = 2, z = 1."""
    v = np.float32([[2, 2, 1], [2, 3, 1], [2, 3, 2], [2, 2, 2],  # wall x = 2
                    [3, 2, 1], [3, 3, 1]])  # floor z = 1 (with the wall's lower edge)
    tri = np.int32([[0, 1, 2], [0, 2, 3], [0, 4, 5], [0, 5, 1]])
    bvh = BVH.build(v, tri, leaf_size=1)
    ys = np.linspace(2.1, 2.9, 9, dtype=np.float32)
    o_wall = np.stack([np.full(9, 2), ys, np.full(9, 1 + offset)], -1).astype(np.float32)
    o_floor = np.stack([np.full(9, 2 + offset), ys, np.full(9, 1)], -1).astype(np.float32)
    d_wall, d_floor = unit(np.tile([1, 0, -1], (9, 1))), unit(np.tile([-1, 0, 1], (9, 1)))
    own_wall = np.where(ys - 2 >= o_wall[:, 2] - 1, 0, 1).astype(np.int32)  # triangle under the origin
    own_floor = np.where(o_floor[:, 0] - 2 <= ys - 2, 3, 2).astype(np.int32)
    for o, d, own, other, height in [(o_wall, d_wall, own_wall, (2, 3), o_wall[:, 2] - 1),
                                     (o_floor, d_floor, own_floor, (0, 1), o_floor[:, 0] - 2)]:
        hits = bvh.intersect(o, d, ignore_prim=own)
        assert np.all(np.isin(hits.prim, other)), hits.prim
        np.testing.assert_allclose(hits.t, height.astype(np.float64) * np.sqrt(2), rtol=1e-3)
        assert bvh.occluded(o, d, np.full(9, 1.0, np.float32), ignore_prim=own).all()


def test_empty_rays():
    rng = np.random.default_rng(7)
    v, tri = soup(rng, 50)
    bvh = BVH.build(v, tri)
    empty = np.zeros((0, 3), np.float32)
    hits = bvh.intersect(empty, empty)
    assert hits.t.shape == hits.prim.shape == hits.u.shape == hits.v.shape == (0,)
    assert hits.t.dtype == np.float32 and hits.prim.dtype == np.int32
    occ = bvh.occluded(empty, empty, np.zeros(0, np.float32))
    assert occ.shape == (0,) and occ.dtype == bool
    assert intersect_brute(v, tri, empty, empty).t.shape == (0,)


def test_single_triangle():
    v = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    tri = np.int32([[0, 1, 2]])
    bvh = BVH.build(v, tri)
    assert bvh.stats["nodes"] == 1 and bvh.stats["leaves"] == 1
    o = np.float32([[0.25, 0.25, 1], [0.25, 0.25, -2], [0.8, 0.8, 1], [0.25, 0.25, 1]])
    d = np.float32([[0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, 1]])
    hits = bvh.intersect(o, d)
    np.testing.assert_array_equal(hits.prim, [0, 0, -1, -1])
    np.testing.assert_allclose(hits.t[:2], [1, 2])
    np.testing.assert_allclose([hits.u[0], hits.v[0]], [0.25, 0.25])
    np.testing.assert_array_equal(bvh.occluded(o, d, np.float32([1.5, 1.5, 9, 9])), [True, False, False, False])
    np.testing.assert_array_equal(bvh.intersect(o, d, ignore_prim=np.zeros(4, np.int32)).prim, [-1] * 4)


def test_threads_and_chunks_do_not_change_results():
    rng = np.random.default_rng(8)
    v, tri = soup(rng, 400)
    n = 2 * RAY_CHUNK + 123
    o = rng.random((n, 3)).astype(np.float32)
    d = unit(rng.standard_normal((n, 3)))
    bvh = BVH.build(v, tri)
    one, two = bvh.intersect(o, d, workers=1), bvh.intersect(o, d, workers=2)
    for a, b in zip((one.t, one.prim, one.u, one.v), (two.t, two.prim, two.u, two.v)):
        np.testing.assert_array_equal(a, b)
    part = bvh.intersect(o[:777], d[:777])  # other chunks and octant groups
    np.testing.assert_array_equal(part.prim, one.prim[:777])
    np.testing.assert_array_equal(part.t, one.t[:777])
    t_max = np.full(n, 0.5, np.float32)
    np.testing.assert_array_equal(bvh.occluded(o, d, t_max, workers=1), bvh.occluded(o, d, t_max, workers=2))


def test_stats_and_counters():
    rng = np.random.default_rng(9)
    v, tri = soup(rng, 300)
    bvh = BVH.build(v, tri, leaf_size=4)
    st = bvh.stats
    assert st["triangles"] == 300 and st["depth"] >= 2 and st["build_time_s"] > 0
    assert sum(k * c for k, c in enumerate(st["leaf_size_hist"], start=1)) == 300
    counts = {}
    bvh.intersect(rng.random((100, 3)).astype(np.float32), unit(rng.standard_normal((100, 3))), counters=counts)
    assert counts["rays"] == 100 and counts["box_tests"] >= 400 and counts["tri_tests"] >= 0


# ----------------------------------------------------------------- the compiled build (tofcore.scene.bvh_build)
def _meshes_for_the_build():
    """Meshes that exercise every branch of the level split: irregular soup (binned and small-node cuts),
    a height field (shared vertices), a flat plane (zero centroid extent on one axis), stacked copies of
    a few triangles (equal centroids: no finite cut, split at the middle) and a mix of tiny and huge
    triangles (boxes much wider than their centroids' bins)."""
    rng = np.random.default_rng(11)
    v_soup, t_soup = soup(rng, 3000)
    v_ter, t_ter = terrain(rng, 30)
    v_flat = v_ter.copy()
    v_flat[:, 2] = 0.25
    few = rng.random((9, 3)).astype(np.float32)
    v_stack, t_stack = few, np.tile(np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]], np.int32), (700, 1))
    big = np.array([[-5, -5, 0], [5, -5, 0], [0, 5, 0.5]], np.float32)
    v_mix = np.concatenate([v_soup[:900], big])
    t_mix = np.concatenate([t_soup[:300], np.full((40, 3), 900, np.int32) + [0, 1, 2]])
    return {"soup": (v_soup, t_soup), "terrain": (v_ter, t_ter), "flat": (v_flat, t_ter),
            "stacked": (v_stack, t_stack), "mixed": (v_mix, t_mix)}


@pytest.mark.parametrize("leaf_size, threads", [(1, "one"), (2, "one"), (4, "one"), (2, "all")])
def test_compiled_build_gives_the_numpy_tree_bit_for_bit(leaf_size, threads, monkeypatch):
    """The compiled level split (numba; on one thread, and on all of numba's threads as for meshes of
    PARALLEL_LEVEL triangles or more) and the NumPy levels make the same tree: every array equal."""
    pytest.importorskip("numba")
    from tofcore.scene import bvh as bvh_module, bvh_build

    monkeypatch.setattr(bvh_build, "PARALLEL_LEVEL", 0 if threads == "all" else 1 << 62)

    for name, (v, t) in _meshes_for_the_build().items():
        corners = v[t.astype(np.int64)]
        lo = np.ascontiguousarray(corners.min(axis=1).T)
        hi = np.ascontiguousarray(corners.max(axis=1).T)
        numpy_tree = bvh_module._build_binary(lo, hi, leaf_size, bvh_module.N_BINS, compiled=False)
        compiled_tree = bvh_module._build_binary(lo, hi, leaf_size, bvh_module.N_BINS, compiled=True)
        for what, a, b in zip(("order", "lo", "hi", "left", "right", "start", "count"), numpy_tree, compiled_tree):
            assert np.array_equal(a, b), f"{name}, leaf size {leaf_size}: {what} differs"
        assert len(numpy_tree[3]) > 1, name


@pytest.mark.parametrize("leaf_size, threads", [(1, "one"), (2, "one"), (4, "one"), (1, "all"), (2, "all"),
                                                (4, "all")])
def test_compiled_build_gives_the_numpy_records_bit_for_bit(leaf_size, threads, monkeypatch):
    """`BVH.build` in compiled loops (bvh_build: the triangle records, the levels, the padding, the collapse
    to 4-wide nodes, the node and leaf records) gives the NumPy build's records and stats: every bit, on the
    meshes of the level test, a single triangle (the root a leaf) and a mesh with zeros of both signs."""
    pytest.importorskip("numba")
    from tofcore.scene import bvh as bvh_module, bvh_build

    monkeypatch.setattr(bvh_build, "PARALLEL_LEVEL", 0 if threads == "all" else 1 << 62)
    monkeypatch.setattr(bvh_module, "COMPILED_BUILD_MIN", 1)
    monkeypatch.setattr(bvh_module, "COMPILE_PAYS_MIN", 1)  # compiled even before numba's cache holds it
    meshes = _meshes_for_the_build()
    meshes["one"] = (np.eye(3, dtype=np.float32), np.array([[0, 1, 2]], np.int32))
    v_zero, t_zero = meshes["terrain"]
    v_zero = v_zero - np.float32(0.5)  # a vertex row at x = 0 and y = 0
    v_zero[::2][v_zero[::2] == 0] = np.float32(-0.0)
    meshes["signed zeros"] = (v_zero, t_zero)
    calls = []
    tree_records = bvh_build.tree_records
    monkeypatch.setattr(bvh_build, "tree_records", lambda *a, **k: calls.append(1) or tree_records(*a, **k))
    for name, (v, t) in meshes.items():
        monkeypatch.setenv("TOFCORE_TRACER", "numpy")
        reference = BVH.build(v, t, leaf_size=leaf_size)
        monkeypatch.setenv("TOFCORE_TRACER", "auto")
        calls.clear()
        compiled = BVH.build(v, t, leaf_size=leaf_size)
        assert calls, name
        for what in ("_nodes", "_leaves"):
            a, b = getattr(reference, what), getattr(compiled, what)
            assert a.dtype == b.dtype and a.shape == b.shape, f"{name}, leaf size {leaf_size}: {what}"
            assert np.array_equal(a, b), f"{name}, leaf size {leaf_size}: {what} differs"
        stats = [{k: x for k, x in tree.stats.items() if k != "build_time_s"} for tree in (reference, compiled)]
        assert stats[0] == stats[1], name


def test_the_parallel_and_serial_level_splits_have_their_own_cache_entries():
    """numba keys its cache by a function's module, name and line, not its compile options: the two builds
    of the level split are copies under their own names, so neither loads the other's code from the cache
    (the parallel split ran on one thread when both shared ``_split_level``'s entry)."""
    pytest.importorskip("numba")
    from tofcore.scene import bvh_build

    parallel, serial = bvh_build._split_level_parallel, bvh_build._split_level_serial
    assert parallel.targetoptions.get("parallel") and not serial.targetoptions.get("parallel")
    assert parallel._cache._cache_file._index_path != serial._cache._cache_file._index_path


def test_build_uses_the_compiled_levels_above_the_size_rule(monkeypatch):
    """`BVH.build` takes the compiled levels for a mesh of COMPILED_BUILD_MIN triangles or more, and the
    records equal the NumPy build's; TOFCORE_TRACER=numpy keeps the build in NumPy."""
    pytest.importorskip("numba")
    from tofcore.scene import bvh as bvh_module, bvh_build

    monkeypatch.setenv("TOFCORE_TRACER", "auto")  # the suite's default is the NumPy reference (tests/conftest.py)
    v, t = soup(np.random.default_rng(5), bvh_module.COMPILED_BUILD_MIN)
    calls = []
    split = bvh_build.split_level
    monkeypatch.setattr(bvh_build, "split_level", lambda *a, **k: calls.append(1) or split(*a, **k))
    compiled = BVH.build(v, t)
    assert calls
    monkeypatch.setenv("TOFCORE_TRACER", "numpy")
    calls.clear()
    reference = BVH.build(v, t)
    assert not calls
    assert np.array_equal(compiled._nodes, reference._nodes) and np.array_equal(compiled._leaves, reference._leaves)


def test_a_failing_compiled_build_falls_back_to_numpy_with_a_warning(monkeypatch):
    """A level split that raises (numba unable to load a damaged cache file) costs a warning, not the
    render: the NumPy levels build the same tree."""
    pytest.importorskip("numba")
    import pickle

    from tofcore.scene import bvh as bvh_module, bvh_build

    def broken(*args, **kwargs):
        raise pickle.UnpicklingError("pickle data was truncated")

    v, t = soup(np.random.default_rng(6), 500)
    reference = BVH.build(v, t)
    monkeypatch.setenv("TOFCORE_TRACER", "auto")
    monkeypatch.setattr(bvh_module, "COMPILED_BUILD_MIN", 1)
    monkeypatch.setattr(bvh_module, "COMPILE_PAYS_MIN", 1)  # compiled even before numba's cache holds it
    monkeypatch.setattr(bvh_build, "split_level", broken)
    with pytest.warns(RuntimeWarning, match="compiled BVH build failed.*UnpicklingError"):
        tree = BVH.build(v, t)
    assert np.array_equal(tree._nodes, reference._nodes)


def test_cached_tree_is_shared_by_equal_geometry_only():
    """`BVH.cached` returns the tree built for the same triangles (another array object, another Scene), and
    a new tree when one vertex moved."""
    from tofcore.scene import bvh as bvh_module

    v, t = soup(np.random.default_rng(7), 200)
    first = BVH.cached(v, t)
    assert BVH.cached(v.copy(), t.astype(np.int64)) is first
    moved = v.copy()
    moved[0, 0] += np.float32(1e-3)
    other = BVH.cached(moved, t)
    assert other is not first
    assert bvh_module.geometry_key(v, t, 2) != bvh_module.geometry_key(moved, t, 2)
    assert bvh_module.geometry_key(v, t, 2) != bvh_module.geometry_key(v, t, 4)
    for seed in range(bvh_module.CACHED_TREES + 1):  # the oldest tree is dropped
        BVH.cached(*soup(np.random.default_rng(100 + seed), 50))
    assert BVH.cached(v, t) is not first


def test_a_mesh_below_a_million_triangles_waits_for_no_compile_of_the_build(monkeypatch):
    """The compiled build costs 4–6 s of compile the first time, more than the NumPy build of a mesh below
    `COMPILE_PAYS_MIN` triangles: such a mesh uses it only where it is compiled or cached already; a bigger mesh
    compiles it."""
    pytest.importorskip("numba")
    from tofcore.scene import bvh as bvh_module, bvh_build

    monkeypatch.setenv("TOFCORE_TRACER", "auto")
    m = bvh_module.COMPILED_BUILD_MIN
    monkeypatch.setattr(bvh_build, "cached", lambda parallel: False)
    assert not bvh_module._compiled_build_pays(m) and not bvh_module._compiled_build_pays(m - 1)
    assert bvh_module._compiled_build_pays(bvh_module.COMPILE_PAYS_MIN)
    monkeypatch.setattr(bvh_build, "cached", lambda parallel: parallel is (m >= bvh_build.PARALLEL_LEVEL))
    assert bvh_module._compiled_build_pays(m) and not bvh_module._compiled_build_pays(m - 1)
    monkeypatch.setenv("TOFCORE_TRACER", "numpy")
    assert not bvh_module._compiled_build_pays(bvh_module.COMPILE_PAYS_MIN)


def test_the_build_counts_as_cached_once_compiled(monkeypatch):
    """``bvh_build.cached`` is True for a build whose loops this process compiled (the warm-up), whatever the
    cache folder holds."""
    pytest.importorskip("numba")
    from tofcore.scene import bvh_build

    monkeypatch.setenv("TOFCORE_TRACER", "auto")
    bvh_build.warm_up()
    assert bvh_build.cached(True) and bvh_build.cached(False)
