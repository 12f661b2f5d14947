"""Write and read time of one Kinect v2 ``frame.exr``: tofcore's own codec against the OpenEXR package.

    .venv/bin/python bench/bench_exr.py [--repeats 7]

Renders the demo room once (Kinect v2, 512 × 424, 4 spp, max_depth 5: 26 float32 channels), then times,
in this one process, ``tofcore.exr.encode`` + write and ``tofcore.exr.read`` against ``OpenEXR.File(...)
.write`` and ``OpenEXR.File(path, separate_channels=True).channels()`` on the same channels (ZIP, 16-line
chunks, both), and prints the median of ``--repeats`` runs and the file sizes. Both files are checked to
hold the same pixels.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import tofcore
from tofcore.output import exr, writers


def median_s(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    sensor = tofcore.load_preset("kinect_v2")
    scene = tofcore.demo_scene("room")
    frame = tofcore.render(scene, sensor, tofcore.suggested_pose(scene), spp=4, max_depth=5, seed=0)
    channels = writers._exr_channels(frame)
    print(f"frame: {frame.width} x {frame.height}, {len(channels)} float32 channels")
    with tempfile.TemporaryDirectory() as tmp:
        ours, theirs = Path(tmp) / "ours.exr", Path(tmp) / "theirs.exr"
        rows = [("tofcore.exr", median_s(lambda: exr.write(ours, channels), args.repeats),
                 median_s(lambda: exr.read(ours), args.repeats), ours)]
        try:
            import OpenEXR
        except ImportError:
            OpenEXR = None
        if OpenEXR is not None:
            header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
            write = lambda: OpenEXR.File(header, dict(channels)).write(str(theirs))  # noqa: E731
            read = lambda: OpenEXR.File(str(theirs), separate_channels=True).channels()  # noqa: E731
            rows.append((f"OpenEXR {OpenEXR.__version__}", median_s(write, args.repeats),
                         median_s(read, args.repeats), theirs))
            a, b = exr.read(ours), {k: c.pixels for k, c in read().items()}
            assert all(np.array_equal(a[k], b[k], equal_nan=True) for k in channels)
        print(f"{'codec':<16} {'write ms':>9} {'read ms':>9} {'MB':>7}   (median of {args.repeats})")
        for name, write_s, read_s, path in rows:
            print(f"{name:<16} {write_s * 1e3:9.1f} {read_s * 1e3:9.1f} {path.stat().st_size / 1e6:7.2f}")


if __name__ == "__main__":
    main()
