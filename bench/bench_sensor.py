"""Time of the sensor's per-frame array code on a Kinect v2 frame (512 × 424): decoding and lens scattering.

    .venv/bin/python bench/bench_sensor.py [--repeats 5]

* decoding: :func:`tofcore.sensor.decode.decode` of the 9 ideal raw images (3 frequencies × 3 phase steps,
  float32) of a ramp of distances 0.5–18 m;
* scattering: :func:`tofcore.sensor.optics.apply_scattering` of 9 random raw images with the Kinect preset's
  kind of kernel (airy, radius 2 px, negative lobe) and with the largest kernel (257 × 257, radius 100 px).

Prints the best and the median of ``--repeats`` runs each (after one warm-up). These timings were assertions
in tests/tofcore/test_decode.py and test_optics.py; speed is measured here, never asserted in a test.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tofcore.sensor.decode import decode  # noqa: E402
from tofcore.sensor.modulation import Modulation, ideal_raw  # noqa: E402
from tofcore.sensor.optics import apply_scattering, psf_kernel  # noqa: E402

KINECT = dict(frequencies_hz=(80e6, 16e6, 120e6), phase_steps=(3, 3, 3), exposure_s=(8e-3, 4e-3, 8e-3))


def timed(label: str, function, repeats: int) -> None:
    function()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    print(f"{label:70s} best {min(times) * 1e3:7.1f} ms, median {statistics.median(times) * 1e3:7.1f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of each case (default 5)")
    args = parser.parse_args()
    modulation = Modulation(kind="cw_square", **KINECT)
    distances = np.linspace(0.5, 18.0, 424 * 512).reshape(424, 512)
    raw = ideal_raw(modulation, distances, 800.0, 200.0).astype(np.float32)
    timed("decode, 512 × 424, 3 frequencies × 3 steps", lambda: decode(raw, modulation), args.repeats)
    images = np.random.default_rng(0).random((9, 424, 512)) * 1e3
    for label, kernel in (("airy, radius 2 px, negative lobe 0.03",
                           psf_kernel("airy", strength=0.05, radius_px=2.0, negative_lobe=0.03)),
                          ("airy, radius 100 px", psf_kernel("airy", strength=0.05, radius_px=100.0))):
        timed(f"scatter 9 raw images, {label} ({kernel.shape[0]} × {kernel.shape[1]})",
              lambda kernel=kernel: apply_scattering(images, kernel), args.repeats)


if __name__ == "__main__":
    main()
