"""Sensor noise on the CPU: shot + read noise (:func:`tofcore.sensor.noise.add_raw_noise`) on a Kinect v2 frame.

The raw images are those a render of the demo room with the Kinect v2 preset (512 × 424, 9 raw images,
1.95 M charges) hands to the noise model, captured once (``--cache`` keeps them). Timed in one process,
in turn, best and median of ``--repeat`` runs each:

* this tree's counter-based noise (:class:`~tofcore.sensor.noise.NoiseStream`, the same draws on both devices);
* with ``--against REV``, the same function of git revision REV (its ``tofcore`` package extracted to a
  temporary folder and imported as ``tofcore_before``); the two noisy frames must be identical;
* NumPy's own generator (``Generator.poisson`` + ``standard_normal``, other numbers) for scale.

Usage::

    .venv/bin/python bench/bench_noise.py --against c85c71c --repeat 5 --cache /tmp
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import tofcore  # noqa: E402
from tofcore.sensor import noise  # noqa: E402

READ_NOISE_E = 3.0


def kinect_raw(cache: Path | None) -> np.ndarray:
    """The raw images (9, 424, 512), e⁻, that a 1-spp Kinect v2 render of the room passes to the noise model."""
    path = None if cache is None else cache / "kinect_raw.npy"
    if path is not None and path.exists():
        return np.load(path)
    render_module = importlib.import_module("tofcore.render")
    captured = []
    original = render_module.noise_models.add_raw_noise

    def capture(raw, **kwargs):
        captured.append(np.array(raw))
        return original(raw, **kwargs)

    render_module.noise_models.add_raw_noise = capture
    try:
        tofcore.render(tofcore.demo_scene("room"), tofcore.load_preset("kinect_v2"), spp=1, seed=0)
    finally:
        render_module.noise_models.add_raw_noise = original
    if path is not None:
        np.save(path, captured[0])
    return captured[0]


def noise_at(revision: str, folder: Path):
    """``tofcore.sensor.noise`` of git ``revision``, imported as ``tofcore_before.sensor.noise`` (host code only:
    its device-twin marks are left out, so the kernel table of that revision is not needed)."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision, "tofcore"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    (folder / "tofcore").rename(folder / "tofcore_before")
    package = types.ModuleType("tofcore_before")  # the package without its __init__ (which imports everything)
    package.__path__ = [str(folder / "tofcore_before")]
    sys.modules["tofcore_before"] = package
    backend = importlib.import_module("tofcore_before.backend")
    backend.device_twin = lambda on: (lambda function: function)
    return importlib.import_module("tofcore_before.sensor.noise")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="timed runs of each variant, default 5")
    parser.add_argument("--against", default=None, help="git revision to time against (default: none)")
    parser.add_argument("--cache", type=Path, default=None,
                        help="existing folder to keep the captured raw images in (default: none)")
    args = parser.parse_args()
    raw = kinect_raw(args.cache)

    def counter_based(module):
        return lambda: module.add_raw_noise(raw, read_noise_e=READ_NOISE_E, rng=module.NoiseStream.from_seed(0),
                                            check=False)

    def numpy_generator():
        g = np.random.default_rng(0)
        return np.maximum(g.poisson(np.maximum(raw, 0.0)) + READ_NOISE_E * g.standard_normal(raw.shape), 0.0)

    with tempfile.TemporaryDirectory() as folder:
        variants = {"this tree": counter_based(noise)}
        if args.against:
            variants[args.against] = counter_based(noise_at(args.against, Path(folder)))
            same = np.array_equal(variants["this tree"](), variants[args.against]())
            print(f"noisy frame of this tree == that of {args.against}: {same}")
        variants["NumPy Generator"] = numpy_generator
        times: dict[str, list[float]] = {name: [] for name in variants}
        for _ in range(args.repeat):
            for name, run in variants.items():
                start = time.perf_counter()
                run()
                times[name].append(time.perf_counter() - start)
    print(f"add_raw_noise on {raw.shape} raw images ({raw.size:,} charges), {args.repeat} runs each, in turn:")
    for name, values in times.items():
        print(f"  {name:16s} best {min(values) * 1e3:7.0f} ms, median {statistics.median(values) * 1e3:7.0f} ms")
    if args.against:
        ratios = [b / a for a, b in zip(times["this tree"], times[args.against])]
        print(f"  {args.against} / this tree, run by run: {[round(r, 2) for r in ratios]}, "
              f"median {statistics.median(ratios):.2f}")


if __name__ == "__main__":
    main()
