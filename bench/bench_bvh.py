"""Benchmark of `tofcore.scene.bvh`: build time, rays/s and tests per ray on room scenes.

The scene is a closed 6 x 6 x 3 m room (floor, ceiling, four walls) with a
1 m box and a UV sphere, every surface subdivided so the whole mesh has about
the requested number of triangles.  Three ray sets, 512 x 424 rays each:

* ``primary``: from a pinhole at (0, 0.2, 1.2) m looking along +y, 70° wide;
* ``secondary``: from random surface points (area-uniform), cosine-distributed
  about the normal facing the camera side, leaving triangle ignored;
* ``shadow``: `occluded` from the primary hit points to a point light 5 cm
  beside the pinhole, ``t_max`` = distance to the light.

Run ``python bench/bench_bvh.py`` (``--sizes 10000 500000 1000000``,
``--repeat 5``, ``--workers 1 2``, ``--leaf-size`` = the `BVH.build`
default).  ``--build-only`` times `BVH.build` alone, the compiled levels
(:mod:`tofcore.scene.bvh_build`, numba's threads: ``NUMBA_NUM_THREADS``)
against the NumPy levels, interleaved, wall and CPU seconds, and checks
that both give the same tree.  Times are the best of ``--repeat`` interleaved runs (the host's
load varies); box tests count every
child box of every visited node, triangle tests every (padded) leaf slot.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tofcore.scene.bvh import BVH  # noqa: E402

WIDTH_PX, HEIGHT_PX = 512, 424


def grid(corner, edge_u, edge_v, n_u, n_v):
    """Quad grid ``corner + i/n_u * edge_u + j/n_v * edge_v`` as (vertices, triangles)."""
    i, j = np.meshgrid(np.arange(n_u + 1), np.arange(n_v + 1), indexing="ij")
    pts = (np.asarray(corner) + (i[..., None] / n_u) * np.asarray(edge_u)
           + (j[..., None] / n_v) * np.asarray(edge_v))
    idx = np.arange((n_u + 1) * (n_v + 1)).reshape(n_u + 1, n_v + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    tri = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return pts.reshape(-1, 3), tri


def uv_sphere(center, radius, n_lat, n_lon):
    """UV sphere as (vertices, triangles); the pole rows are degenerate-free fans."""
    verts, tris = grid((0, 0, 0), (np.pi, 0, 0), (0, 2 * np.pi, 0), n_lat, n_lon)
    theta, phi = verts[:, 0], verts[:, 1]
    pts = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    pts = np.asarray(center) + radius * pts
    # merge the duplicated poles and seam, then drop triangles that became degenerate
    key = np.round(pts, 9)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    tris = inverse.reshape(-1)[tris]
    tris = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])]
    return pts[first], tris


def room_scene(n_triangles):
    """Closed room with a box and a sphere, about ``n_triangles`` triangles (metres, z up)."""
    n = max(2, int(round(np.sqrt(n_triangles / 16))))
    h = max(1, n // 2)
    parts = [
        grid((-3, 0, 0), (6, 0, 0), (0, 6, 0), n, n),  # floor
        grid((-3, 0, 3), (6, 0, 0), (0, 6, 0), n, n),  # ceiling
        grid((-3, 0, 0), (6, 0, 0), (0, 0, 3), n, n),  # front wall (behind the camera)
        grid((-3, 6, 0), (6, 0, 0), (0, 0, 3), n, n),  # back wall
        grid((-3, 0, 0), (0, 6, 0), (0, 0, 3), n, n),  # left wall
        grid((3, 0, 0), (0, 6, 0), (0, 0, 3), n, n),  # right wall
        uv_sphere((1.2, 2.5, 0.5), 0.5, h, n),
    ]
    c, e = np.array([-0.9, 3.0, 0.0]), np.eye(3)  # 1 m box, faces as grids
    for axis in range(3):
        u, v = e[(axis + 1) % 3], e[(axis + 2) % 3]
        parts.append(grid(c, u, v, h, h))
        parts.append(grid(c + e[axis], u, v, h, h))
    verts, tris, base = [], [], 0
    for p, t in parts:
        verts.append(p)
        tris.append(t + base)
        base += len(p)
    return np.concatenate(verts).astype(np.float32), np.concatenate(tris).astype(np.int32)


def primary_rays(rng):
    """Pinhole rays, one per pixel with a random offset, looking along +y."""
    eye = np.array([0.0, 0.2, 1.2], np.float32)
    tan_half = np.tan(np.radians(70) / 2)
    x = (np.arange(WIDTH_PX) + rng.random(WIDTH_PX)) / WIDTH_PX * 2 - 1
    y = (np.arange(HEIGHT_PX) + rng.random(HEIGHT_PX)) / HEIGHT_PX * 2 - 1
    xx, yy = np.meshgrid(x * tan_half, -y * tan_half * HEIGHT_PX / WIDTH_PX)
    d = np.stack([xx.ravel(), np.ones(xx.size), yy.ravel()], -1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(eye, d.shape).astype(np.float32), d.astype(np.float32)


def secondary_rays(verts, tris, rng, n_rays):
    """Rays leaving area-uniform surface points, cosine-distributed about a normal."""
    p = verts[tris].astype(np.float64)
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = np.linalg.norm(normal, axis=1)
    prim = rng.choice(len(tris), n_rays, p=area / area.sum())
    a, b = rng.random(n_rays), rng.random(n_rays)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    origin = p[prim, 0] + a[:, None] * (p[prim, 1] - p[prim, 0]) + b[:, None] * (p[prim, 2] - p[prim, 0])
    nrm = normal[prim] / area[prim, None]
    nrm *= np.where(((np.array([0, 0.2, 1.2]) - origin) * nrm).sum(1) < 0, -1, 1)[:, None]
    d = rng.standard_normal((n_rays, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d += nrm  # cosine-distributed about nrm
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return origin.astype(np.float32), d.astype(np.float32), prim.astype(np.int32)


def timed(fn):
    """Wall time of one call, and its result."""
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def _boxes(verts, tris):
    """(3, M) float32 triangle box minima and maxima."""
    corners = verts[tris.astype(np.int64)]
    return np.ascontiguousarray(corners.min(axis=1).T), np.ascontiguousarray(corners.max(axis=1).T)


def build_only(sizes, repeat):
    """`BVH.build` with the compiled levels and with the NumPy levels (TOFCORE_TRACER=numpy), interleaved."""
    import os

    from tofcore.scene import bvh as bvh_module

    print("| triangles | levels | wall s (best of %d) | CPU s | of which the levels, wall s |" % repeat)
    print("|---|---|---|---|---|")
    for size in sizes:
        verts, tris = room_scene(size)
        warm = room_scene(2 * bvh_module.COMPILED_BUILD_MIN)  # numba's compile (or cache load) is not timed
        bvh_module._build_binary(*_boxes(*warm), 2, bvh_module.N_BINS, compiled=True)
        results = {}
        for _ in range(repeat):
            for kind in ("compiled", "numpy"):
                os.environ["TOFCORE_TRACER"] = "auto" if kind == "compiled" else "numpy"
                levels_s = []
                levels = bvh_module._levels

                def timed_levels(*a, **k):
                    t = time.perf_counter()
                    out = levels(*a, **k)
                    levels_s.append(time.perf_counter() - t)
                    return out

                bvh_module._levels = timed_levels
                c0, t0 = time.process_time(), time.perf_counter()
                tree = BVH.build(verts, tris)
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                bvh_module._levels = levels
                best = results.get(kind)
                if best is None or wall < best[0]:
                    results[kind] = (wall, cpu, levels_s[-1], tree)
        same = all(np.array_equal(getattr(results["compiled"][3], a), getattr(results["numpy"][3], a))
                   for a in ("_nodes", "_leaves"))
        for kind, (wall, cpu, lv, _) in results.items():
            print(f"| {len(tris):,} | {kind} | {wall:.3f} | {cpu:.3f} | {lv:.3f} |", flush=True)
        print(f"| | same tree: {same} | {results['numpy'][0] / results['compiled'][0]:.1f}× | | |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 500_000, 1_000_000],
                    help="approximate triangle counts (default: 10000 500000 1000000)")
    ap.add_argument("--repeat", type=int, default=5, help="runs per timing, best kept (default: 5)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="thread counts (default: 1 2)")
    ap.add_argument("--leaf-size", type=int, default=None, help="BVH leaf size (default: BVH.build's)")
    ap.add_argument("--build-only", action="store_true", help="time the build alone: compiled against NumPy levels")
    args = ap.parse_args(argv)
    if args.build_only:
        return build_only(args.sizes, args.repeat)
    leaf = {} if args.leaf_size is None else {"leaf_size": args.leaf_size}
    rng = np.random.default_rng(7)
    print(f"numpy {np.__version__}; {WIDTH_PX}x{HEIGHT_PX} = {WIDTH_PX * HEIGHT_PX} rays per set")
    print("| triangles | build s | nodes | depth | MB | rays | workers | Mrays/s | box tests/ray | tri tests/ray |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for size in args.sizes:
        verts, tris = room_scene(size)
        build_s, bvh = timed(lambda: BVH.build(verts, tris, **leaf))
        st = bvh.stats
        o, d = primary_rays(rng)
        first = bvh.intersect(o, d)
        hit = first.prim >= 0
        p = o[hit] + first.t[hit, None] * d[hit]
        light = np.array([0.05, 0.2, 1.2], np.float32)
        to_light = light - p
        dist = np.linalg.norm(to_light, axis=1)
        shadow = (p, to_light / dist[:, None], dist.astype(np.float32), first.prim[hit])
        so, sd, sprim = secondary_rays(verts, tris, rng, WIDTH_PX * HEIGHT_PX)
        sets = {
            "primary": lambda w, c=None: bvh.intersect(o, d, workers=w, counters=c),
            "secondary": lambda w, c=None: bvh.intersect(so, sd, ignore_prim=sprim, workers=w, counters=c),
            "shadow": lambda w, c=None: bvh.occluded(*shadow[:3], ignore_prim=shadow[3], workers=w, counters=c),
        }
        for name, run in sets.items():
            counts = {}
            run(1, counts)
            best = dict.fromkeys(args.workers, np.inf)
            for _ in range(args.repeat):  # interleaved, so a busy host slows every variant alike
                for w in args.workers:
                    best[w] = min(best[w], timed(lambda: run(w))[0])
            for w, sec in best.items():
                print(f"| {st['triangles']} | {build_s:.2f} | {st['nodes']} | {st['depth']} | "
                      f"{st['memory_bytes'] / 1e6:.1f} | {name} | {w} | "
                      f"{counts['rays'] / sec / 1e6:.2f} | {counts['box_tests'] / counts['rays']:.1f} | "
                      f"{counts['tri_tests'] / counts['rays']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
