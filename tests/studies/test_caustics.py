"""studies/caustics: the class split adds up to the tracer's frame, and light tracing to the camera is right.

* The classes of :mod:`classify` sum to the NumPy tracer's bounce buckets of the same seed (the split
  multiplies each contribution by f_s/f and 1 − f_s/f: equal within float rounding, 1e-12).
* :mod:`light_tracer` against the closed form of a Lambertian wall lit by the Kinect's LED through its
  distorted camera (``check_plane``): radiance and radiance × delay per 8 × 8 block within 4.5 standard
  errors (from the spread over seeds), the frame total within 4.
* (slow) Light tracing and the path tracer agree per bounce bucket and per class on the room: frame totals
  within 4 standard errors of their difference; and the path tracer with the three-strategy MIS weights plus
  light tracing with its weights equals the plain path tracer's caustics per bucket (4 standard errors),
  with a lower variance.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

STUDY = Path(__file__).resolve().parents[2] / "studies" / "caustics"
sys.path.insert(0, str(STUDY))

import tofcore  # noqa: E402
from tofcore import backend  # noqa: E402
from tofcore.scene.demo import suggested_pose  # noqa: E402
from tofcore.tracer.setup import TraceSettings, make_setup  # noqa: E402
from tofcore.tracer.trace import trace  # noqa: E402

import check_plane  # noqa: E402
from classify import caustic_classes, trace_classified  # noqa: E402
from frames import sensor_at, setup_for  # noqa: E402
from light_tracer import trace_light  # noqa: E402


def test_classes_sum_to_the_tracer_frame():
    scene, sensor = tofcore.demo_scene("room"), sensor_at(1 / 32)
    setup = setup_for(scene, sensor, seed=3)
    n_pix = sensor.camera.width * sensor.camera.height
    sums = trace_classified(setup, 0, n_pix, 8)
    frame = trace(scene, sensor.camera, sensor.leds, world_from_sensor=suggested_pose(scene),
                  correlations=sensor.modulation.correlation_bank(), spp=8, seed=3, workers=1)
    np.testing.assert_allclose(sums.signal.sum(axis=0), frame.signal_sum, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(sums.correlation.sum(axis=0), frame.correlation_sum, rtol=1e-12, atol=1e-18)
    assert (sums.signal[1:5] > 0).any(axis=(1, 2)).all()   # every material's specular lobe lights something


def test_light_tracer_matches_the_closed_form_of_a_lambertian_wall():
    sensor = sensor_at(1 / 16)
    scene = check_plane.lambert_wall()
    pose = suggested_pose(scene)
    ref_l, ref_lt = check_plane.exact(sensor, pose)
    shape = ref_l.shape
    radiance, delay, paths = [], [], 100_000
    for seed in range(8):
        settings = TraceSettings(world_from_sensor=pose, correlations=[lambda tau: tau], seed=seed, max_depth=1,
                                 sampler="independent")
        setup = make_setup(scene, sensor.camera, sensor.leds, settings, backend.select_device("cpu"))
        sums = trace_light(setup, 0, paths)
        radiance.append(sums.signal[0, 0].reshape(shape) / paths)
        delay.append(sums.correlation[0, 0, 0].reshape(shape) / paths)
    for images, ref in ((np.array(radiance), ref_l), (np.array(delay), ref_lt)):
        est, truth = check_plane.block_means(images), check_plane.block_means(ref[None])[0]
        z = (est.mean(axis=0) - truth) / (est.std(axis=0, ddof=1) / np.sqrt(len(est)))
        assert np.abs(z).max() < 4.5, z
        total = images.sum(axis=(1, 2))
        assert abs(total.mean() - ref.sum()) < 4 * total.std(ddof=1) / np.sqrt(len(total))


@pytest.mark.slow
def test_light_tracing_and_path_tracing_agree_per_bucket_and_class():
    scene, sensor = tofcore.demo_scene("room"), sensor_at(1 / 16)
    n_pix = sensor.camera.width * sensor.camera.height
    lt, pt = [], []
    for seed in range(6):
        sums = trace_light(setup_for(scene, sensor, seed=100 + seed), 0, 64 * n_pix)
        lt.append(sums.signal.sum(axis=2) / sums.samples)
        sums = trace_classified(setup_for(scene, sensor, seed=seed), 0, n_pix, 32)
        pt.append(sums.signal.sum(axis=2) / sums.samples)
    lt, pt = np.array(lt), np.array(pt)                       # (seeds, classes, buckets)
    for a, b in ((lt.sum(axis=1), pt.sum(axis=1)), (lt.sum(axis=2), pt.sum(axis=2))):
        se = np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))
        diff = a.mean(axis=0) - b.mean(axis=0)
        assert (np.abs(diff) <= 4 * se + 1e-12 * np.abs(b.mean(axis=0))).all(), (diff, se)


@pytest.mark.slow
def test_path_tracing_and_light_tracing_under_mis_sum_to_the_path_tracer():
    scene, sensor = tofcore.demo_scene("room"), sensor_at(1 / 16)
    n_pix = sensor.camera.width * sensor.camera.height
    cls_c = caustic_classes(scene.materials)
    spp, n_paths = 16, 16 * n_pix
    plain, combined = [], []
    for seed in range(8):
        a = trace_classified(setup_for(scene, sensor, seed=seed), 0, n_pix, spp)
        b = trace_classified(setup_for(scene, sensor, seed=seed), 0, n_pix, spp, lt_ratio=n_paths / spp)
        c = trace_light(setup_for(scene, sensor, seed=500 + seed), 0, n_paths, caustic_only=True,
                        mis_ratio=n_paths / spp)
        rest = [i for i in range(a.signal.shape[0]) if i not in cls_c]
        np.testing.assert_array_equal(a.signal[rest], b.signal[rest])   # only the caustics change weights
        plain.append(a.signal[cls_c].sum(axis=(0, 2)) / spp)
        combined.append(b.signal[cls_c].sum(axis=(0, 2)) / spp + c.signal[cls_c].sum(axis=(0, 2)) / n_paths)
    plain, combined = np.array(plain)[:, 1:], np.array(combined)[:, 1:]   # buckets k = 2..5
    se = np.sqrt(plain.var(axis=0, ddof=1) / len(plain) + combined.var(axis=0, ddof=1) / len(combined))
    assert (np.abs(plain.mean(axis=0) - combined.mean(axis=0)) <= 4 * se).all()
    assert (combined.var(axis=0) < plain.var(axis=0)).all()   # and light tracing lowers their variance
