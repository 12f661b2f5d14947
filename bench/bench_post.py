"""The per-frame pipeline after the trace, on the Kinect v2 room (512 × 424, 5 vertices): time and device work.

After the trace a render turns the :class:`~tofcore.tracer.transport.Transport` into a frame: the
render-error estimate (every pass), the convergence row, raw images, lens scattering, sensor noise,
decoding with unwrapping and the bilateral phasor filter, and the ground truth per path length
(``tofcore.render``). This bench traces the frame once, then runs :func:`tofcore.render.render` with the
trace replaced by that stored transport, so everything it times and counts is after the trace:

* **CPU**: the post-trace pipeline on NumPy, median of ``--repeat`` runs (``seconds`` of the frame);
* **device work** on the CuPy stand-in (``tests/fakecupy.py``, NumPy behind CuPy's rules): device arrays
  allocated and host synchronisations per frame — what a real GPU pays per launch and per read-back.

Two cases: the 16-spp frame (one pass of 16 samples, ``render(spp=16)``) and one 1-spp pass with its
frame (``render(spp=1)``, the live preview); they differ only in the stored transport.

Usage::

    .venv/bin/python bench/bench_post.py            # both cases, CPU time and counts
    .venv/bin/python bench/bench_post.py --repeat 5 --cases 16 --cache /tmp   # trace once, keep it

On a real GPU ``bench/gpu_profile.py --post`` times the same pipeline on CuPy.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import pickle
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import tofcore  # noqa: E402
from tofcore.tracer.trace import trace_progressive  # noqa: E402

render_module = importlib.import_module("tofcore.render")


def stored_transport(scene, sensor, spp: int, cache: Path | None):
    """The Kinect room's transport after one pass of ``spp`` samples (traced once on the CPU; kept in
    ``cache``/post_transport_<spp>.pkl when a cache folder is given)."""
    path = None if cache is None else cache / f"post_transport_{spp}.pkl"
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    passes = trace_progressive(scene, sensor.camera, sensor.leds, world_from_sensor=tofcore.suggested_pose(scene),
                               correlations=sensor.modulation.correlation_bank(), spp=spp, max_depth=5, seed=0,
                               progressive=False)
    transport = next(passes)
    passes.close()
    if path is not None:
        path.write_bytes(pickle.dumps(transport))
    return transport


def on_device(transport, xp):
    """``transport`` with its accumulators on ``xp`` (``first_hit`` stays NumPy, as the GPU tracer leaves it)."""
    import dataclasses

    arrays = {name: xp.asarray(getattr(transport, name))
              for name in ("sample_count", "signal_sum", "correlation_sum", "ambient_sum", "replicate_sum")}
    return dataclasses.replace(transport, **arrays)


@contextlib.contextmanager
def traced(transport):
    """``render`` with its trace replaced by ``transport`` (one pass)."""
    class Stored:  # the passes of tofcore.tracer.trace.trace_progressive: one, already traced
        def __iter__(self):
            yield transport

        def report(self, report):
            return True  # no pass follows

        def close(self):
            pass

    original = render_module.trace_progressive
    render_module.trace_progressive = lambda *args, **kwargs: Stored()
    try:
        yield
    finally:
        render_module.trace_progressive = original


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="timed CPU runs per case (median), default 3")
    parser.add_argument("--cases", default="16,1", help="spp of the stored transports, comma-separated (16,1)")
    parser.add_argument("--cache", type=Path, default=None,
                        help="existing folder to keep the traced transports in between runs (default: none)")
    args = parser.parse_args()
    scene = tofcore.demo_scene("room")
    sensor = tofcore.load_preset("kinect_v2")
    from tests import fakecupy
    import pytest

    patches = pytest.MonkeyPatch()
    fakecupy.install(patches)  # the CUDA kernels' NumPy twins, each counted as one kernel
    fake_device = tofcore.backend.select_device("gpu")
    for spp in (int(s) for s in args.cases.split(",")):
        transport = stored_transport(scene, sensor, spp, args.cache)
        times = []
        with traced(transport):
            for _ in range(args.repeat):
                start = time.perf_counter()
                frame = render_module.render(scene, sensor, spp=spp, max_depth=5, seed=0)
                times.append(time.perf_counter() - start)
        device_transport = on_device(transport, fakecupy)
        with traced(device_transport), fakecupy.counting() as counts:
            fake = render_module.render(scene, sensor, spp=spp, max_depth=5, seed=0, device=fake_device)
        same = np.array_equal(fake.depth, frame.depth, equal_nan=True)
        print(f"Kinect room, {spp:2d} spp: post-trace CPU median {statistics.median(times) * 1e3:7.1f} ms "
              f"(all {[round(t * 1e3, 1) for t in times]}); fake GPU: {counts['arrays']} device arrays "
              f"({counts['uploads']} uploads), {counts['syncs']} host syncs; GPU frame == CPU frame: {same}")
    patches.undo()


if __name__ == "__main__":
    main()
