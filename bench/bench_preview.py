"""The add-on's live preview after a camera move: time to its first image in a large scene (bpy module).

A Blender scene of subdivided UV spheres (``--triangles``, default 1M) on a floor, the add-on's ToF camera
(Kinect v2 preset, the preview's defaults: quarter resolution, 8 spp, first image after the first pass)
with its live preview on. Three previews are timed from the start of the job to its first image:

* ``first``: the scene exported and its BVH built;
* ``camera moved``: the camera moved by 10 cm — the add-on re-uses the export and the tree;
* ``scene changed``: a sphere moved — exported again; the BVH is built again (new geometry).

Run ``.venv/bin/python bench/bench_preview.py`` (``--triangles 1000000``); needs the ``bpy`` module
(Python 3.11). Blender's user folders go to a temporary folder.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

HOME = tempfile.mkdtemp(prefix="tof-bench-preview-")
for _name in ("BLENDER_USER_RESOURCES", "XDG_CONFIG_HOME", "XDG_CACHE_HOME"):
    os.environ.setdefault(_name, os.path.join(HOME, _name.lower()))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bpy  # noqa: E402

import addon  # noqa: E402
from addon import operators  # noqa: E402


def spheres(n_triangles: int) -> list:
    """UV spheres of 0.3 m in a row 2 m in front of the camera, about ``n_triangles`` triangles in all."""
    count = 4
    segments = max(8, int(math.sqrt(n_triangles / count / 2)))
    objects = []
    for i in range(count):
        bpy.ops.mesh.primitive_uv_sphere_add(segments=2 * segments, ring_count=segments, radius=0.3,
                                             location=(-0.9 + 0.6 * i, 0.0, 0.3))
        objects.append(bpy.context.object)
    bpy.ops.mesh.primitive_plane_add(size=6.0)
    return objects


def first_image(timeout_s: float = 600.0) -> tuple[float, object]:
    """Start the live preview; seconds until its first pass arrives, and the job."""
    t0 = time.perf_counter()
    job = operators.start_live_preview(bpy.context)
    assert job is not None, operators._preview.messages
    while time.perf_counter() - t0 < timeout_s:
        newest, end = job.poll()
        if newest is not None:
            elapsed = time.perf_counter() - t0
            job.cancel()
            job.join(30.0)
            return elapsed, job
        if end is not None:
            raise SystemExit(f"the preview ended without an image: {end}")
        time.sleep(0.005)
    raise SystemExit("no image within the timeout")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=1_000_000, help="triangles of the spheres (default 1M)")
    args = ap.parse_args(argv)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    objects = spheres(args.triangles)
    assert bpy.ops.tof.add_camera(preset="kinect_v2", location=(0.0, -2.0, 1.0),
                                  rotation=(math.radians(70.0), 0.0, 0.0)) == {'FINISHED'}
    camera = bpy.context.scene.camera
    camera.data.tof.live_preview = True
    rows = []
    for step in ("first", "camera moved", "scene changed"):
        if step == "camera moved":
            camera.location.x += 0.1
        elif step == "scene changed":
            objects[0].location.z += 0.05
        bpy.context.view_layer.update()
        seconds, job = first_image()
        rows.append((step, seconds, job.exported.stats["seconds"] if job.exported is not operators else 0.0,
                     job.scene.triangle_count, job.sensor.camera.width, job.sensor.camera.height))
    print("| preview | first image s | export s (when exported) | triangles | resolution |")
    print("|---|---|---|---|---|")
    exported_before = None
    for step, seconds, export_s, tris, w, h in rows:
        print(f"| {step} | {seconds:.2f} | {export_s:.2f} | {tris:,} | {w}×{h} |")
    addon.unregister()


if __name__ == "__main__":
    main()
