"""A progressive render with a frame after every pass (the Blender add-on's Render ToF and live preview):
where the time goes besides tracing, with and without preview frames.

Renders the demo room with the Kinect v2 preset (sensor noise off) by ``tofcore.render_progressive(...,
every_pass=True)`` and prints the whole render's wall time and, summed over the passes, the time of the
per-pass error estimates (``render.depth_standard_error``), of building the frames (``render._frame``) and,
inside those, of the per-path-length decodes (``render._decode_clean_per_k``, K decodes per frame) that
``preview_frames=True`` leaves to the final frame.

Usage (one process per setting; pair them with a timer over several runs)::

    .venv/bin/python bench/bench_pass_frames.py --spp 16                      # 512 × 424: the add-on's render
    .venv/bin/python bench/bench_pass_frames.py --spp 16 --preview-frames
    .venv/bin/python bench/bench_pass_frames.py --spp 8 --scale 0.25 [--preview-frames]   # the live preview
"""

from __future__ import annotations

import argparse
import importlib
import time

import tofcore

render_module = importlib.import_module("tofcore.render")


def timed(spent: dict, name: str, function):
    """``function`` wrapped to add its wall seconds to ``spent[name]``."""
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            spent[name] += time.perf_counter() - start
    return wrapper


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--scale", type=float, default=1.0, help="resolution scale of the Kinect v2 preset")
    parser.add_argument("--preview-frames", action="store_true", help="render_progressive(preview_frames=True)")
    args = parser.parse_args()
    spent = {"estimates": 0.0, "frames": 0.0, "per-k decodes": 0.0}
    for name, attribute in (("estimates", "depth_standard_error"), ("frames", "_frame"),
                            ("per-k decodes", "_decode_clean_per_k")):
        setattr(render_module, attribute, timed(spent, name, getattr(render_module, attribute)))
    scene = tofcore.demo_scene("room")
    sensor = tofcore.load_preset("kinect_v2").replace(**{"noise.model": "none"}).scaled(args.scale)
    start = time.perf_counter()
    passes = 0
    for frame in tofcore.render_progressive(scene, sensor, spp=args.spp, every_pass=True,
                                            preview_frames=args.preview_frames):
        passes += 1
    total = time.perf_counter() - start
    print(f"{sensor.camera.width} x {sensor.camera.height}, {passes} passes to {args.spp} spp, preview_frames="
          f"{args.preview_frames}, {frame.stats['transport']['tracer']} tracer: {total:.1f} s; "
          + ", ".join(f"{name} {seconds:.1f} s" for name, seconds in spent.items()))


if __name__ == "__main__":
    main()
