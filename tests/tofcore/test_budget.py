"""The pass schedule (tofcore/tracer/trace.py): its policy, the caller's reports, and the time budget that sizes
the passes from their measured cost (tofcore/tracer/budget.py), tested on a fake clock.

No timing is asserted: the clock is replaced by one that charges a fixed cost per pass and per sample,
so the pass sizes the budget must choose follow by hand from t(n) = a + b·n.
"""

import dataclasses

import numpy as np
import pytest

import tofcore
from tofcore import Camera, ConfigError, load_preset, render
from tofcore.sensor.config import Noise, Scattering
from tofcore.tracer.budget import TimeBudget, budgeted_pass, pass_cost_model
from tofcore.tracer.estimator import allocate_samples
from tofcore.tracer.trace import (PassPolicy, PassReport, next_pass_size, pass_schedule, samples_to_target,
                                  trace_progressive)
from tofcore.scene.led import LED

render_module = __import__("tofcore.render", fromlist=["_clock"])
trace_module = __import__("tofcore.tracer.trace", fromlist=["_clock"])


def test_cost_model_recovers_a_line_and_falls_back_to_the_mean_rate():
    n = [1.0, 2.0, 4.0, 8.0]
    a, b = pass_cost_model(n, [0.3 + 1.5 * x for x in n])
    assert a == pytest.approx(0.3) and b == pytest.approx(1.5)
    # one size only: the fixed cost is charged to the samples (b = Σt / Σn)
    assert pass_cost_model([16.0, 16.0], [25.0, 27.0]) == (0.0, pytest.approx(52.0 / 32.0))
    # a fit with a negative fixed cost (noise) falls back the same way
    assert pass_cost_model([1.0, 2.0], [1.0, 3.0]) == (0.0, pytest.approx(4.0 / 3.0))


def test_budgeted_pass_is_the_schedule_when_it_fits_else_the_largest_that_fits():
    assert budgeted_pass(16, remaining_s=100.0, a=0.5, b=1.0) == 16
    assert budgeted_pass(16, remaining_s=10.0, a=0.5, b=1.0) == 9      # 0.5 + 9 ≤ 10 < 0.5 + 10
    assert budgeted_pass(16, remaining_s=1.4, a=0.5, b=1.0) == 0
    assert budgeted_pass(16, remaining_s=-3.0, a=0.5, b=1.0) == 0


@pytest.mark.parametrize("budget_s", [5.0, 20.0, 50.0, 333.0])
@pytest.mark.parametrize("a, b", [(0.3, 1.5), (0.3, 0.06), (2.0, 0.5)])
def test_simulated_renders_use_the_budget(budget_s, a, b):
    """Passes that cost exactly a + b·n after a 3 s set-up, the first one 5 s more (warm-up), and a final
    frame of 1 s (3 error estimates of 1/3 s): the render ends less than the smallest pass short of the
    budget, so within 10 % wherever a + b is at most a tenth of it, and past it by at most one small pass
    (the second, run before any pass but the warm-up is measured)."""
    clock, spp, budget = 3.0, 0, TimeBudget(budget_s)
    budget.estimate_s = 1.0 / 3.0
    n = next_pass_size(0, 100_000)
    while n:
        cost = a + b * n + (5.0 if spp == 0 else 0.0)
        clock, spp = clock + cost, spp + n
        budget.record(n, cost)
        n = budget.next_pass(next_pass_size(spp, 100_000), clock)
    used = clock + 1.0
    if 3.0 + 5.0 + a + b + 1.0 >= budget_s:   # the first pass alone uses the budget up: it stops there
        assert spp == 1
        return
    assert budget_s - (a + b) < used <= budget_s + a + b
    if spp > 2:
        assert used <= budget_s
    if a + b <= 0.1 * budget_s:
        assert used >= 0.9 * budget_s


def _sensor():
    sensor = load_preset("kinect_v2")
    return dataclasses.replace(sensor, camera=Camera.from_fov(24, 18, 60.0), noise=Noise(model="none"),
                               scattering=Scattering(model="none"))


def _fake_clock(monkeypatch, setup_s: float, pass_s: float, sample_s: float):
    """Replace the render's clock and the pass schedule's: set-up, then pass_s per pass and sample_s per mean
    sample per pixel, counted from the progress rows (the schedule reads the clock after each row)."""
    traced = {"spp": 0.0, "passes": 0}

    def progress(row):
        traced["spp"], traced["passes"] = row["spp"], row["pass"]

    def clock():
        return setup_s * (traced["passes"] > 0) + pass_s * traced["passes"] + sample_s * traced["spp"]

    monkeypatch.setattr(render_module, "_clock", clock)
    monkeypatch.setattr(trace_module, "_clock", clock)
    return progress


def test_render_sizes_its_last_pass_to_the_budget(monkeypatch):
    """Set-up 1 s, each pass 0.2 s + 0.4 s per sample per pixel, budget 12 s: after 1, 1, 2, 4, 8 samples
    (8.4 s) the scheduled 16 would end at 15 s; 8 fit (11.8 s), then nothing does."""
    progress = _fake_clock(monkeypatch, 1.0, 0.2, 0.4)
    scene, sensor = tofcore.demo_scene("corner"), _sensor()
    frame = render(scene, sensor, spp=4096, max_depth=2, seed=3, time_budget_s=12.0, adaptive=False,
                   progress=progress)
    assert [row["spp"] for row in frame.stats["convergence"]] == [1, 2, 4, 8, 16, 24]
    assert frame.stats["final"] and frame.stats["spp"] == 24
    # the same samples as a 24-spp render: pass sizes only move samples between passes
    whole = render(scene, sensor, spp=24, max_depth=2, seed=3, adaptive=False)
    np.testing.assert_allclose(frame.distance, whole.distance, rtol=1e-6, equal_nan=True)
    np.testing.assert_allclose(frame.render_error, whole.render_error, rtol=1e-5, equal_nan=True)


def test_adaptive_render_sizes_passes_from_the_samples_it_traced(monkeypatch):
    """With the adaptive sampler the passes after the 16-sample pilot are multiples of R per pixel; the
    budget is charged for the mean samples traced, and the render stops inside it."""
    progress = _fake_clock(monkeypatch, 1.0, 0.2, 0.25)
    frame = render(tofcore.demo_scene("corner"), _sensor(), spp=4096, max_depth=2, seed=3, time_budget_s=20.0,
                   progress=progress)
    rows = frame.stats["convergence"]
    used = 1.0 + 0.2 * len(rows) + 0.25 * rows[-1]["spp"]
    assert 0.9 * 20.0 <= used <= 20.0
    assert (frame.samples % 4 == 0).all() and frame.samples.min() >= 16
    assert np.isfinite(frame.render_error[np.isfinite(frame.gt_distance)]).all()


def test_first_pass_always_runs_and_a_spent_budget_stops_after_it(monkeypatch):
    progress = _fake_clock(monkeypatch, 100.0, 0.0, 1.0)
    frame = render(tofcore.demo_scene("corner"), _sensor(), spp=64, max_depth=1, time_budget_s=1.0,
                   progress=progress)
    assert [row["spp"] for row in frame.stats["convergence"]] == [1] and frame.stats["final"]


def test_trace_pass_size_is_checked_and_zero_ends_the_trace():
    scene, cam = tofcore.demo_scene("corner"), Camera.from_fov(8, 6, 60.0)
    sizes = iter([1, 1, 2, 0])
    passes = list(trace_progressive(scene, cam, [LED()], spp=64, max_depth=1,
                                    pass_size=lambda transport, scheduled: next(sizes)))
    assert len(passes) == 3 and int(passes[-1].sample_count[0]) == 4
    with pytest.raises(ConfigError, match=r"pass_size must return an integer in \[0, 1\], got 5"):
        list(trace_progressive(scene, cam, [LED()], spp=64, max_depth=1, pass_size=lambda t, n: 5))


def test_schedule_doubles_from_what_is_done():
    assert pass_schedule(40) == [1, 1, 2, 4, 8, 16, 8]
    assert pass_schedule(40, progressive=False) == [16, 16, 8]
    assert next_pass_size(24, 4096) == 16 and next_pass_size(3, 4096) == 3


def test_the_policy_stops_at_the_reported_target_error_and_the_report_says_so():
    scene, cam = tofcore.demo_scene("corner"), Camera.from_fov(8, 6, 60.0)
    pose = tofcore.suggested_pose(scene)  # every pixel sees the corner: the target holds over all of them
    passes = trace_progressive(scene, cam, [LED()], world_from_sensor=pose, max_depth=1,
                               policy=PassPolicy(spp=64, target_error_m=0.01))
    spp = []
    for transport in passes:
        spp.append(int(transport.sample_count[0]))
        last = passes.report(PassReport(error_m=np.full((6, 8), 0.02 if len(spp) < 3 else 0.005)))
        assert last == (len(spp) == 3)
    assert spp == [1, 2, 4]
    with pytest.raises(ConfigError, match="one pass report after each pass"):
        passes.report(PassReport(error_m=np.zeros((6, 8))))
    with pytest.raises(ConfigError, match="spp and progressive go into the policy when one is given"):
        trace_progressive(scene, cam, [LED()], spp=4, policy=PassPolicy(spp=8))


def test_a_target_errors_last_pass_is_cut_to_the_samples_it_needs():
    """32 spp at 2.2 mm towards 2 mm: ⌈32 · 1.1²⌉ = 39 spp at σ ∝ n^−½, so the next pass has 7 samples, not the
    schedule's 16; an error far above the target keeps the schedule's pass; NaN (no estimate yet) too."""
    assert samples_to_target(32, 0.0022, 0.002) == 7
    assert samples_to_target(32, 0.0020001, 0.002) == 1
    scene, cam = tofcore.demo_scene("corner"), Camera.from_fov(8, 6, 60.0)
    pose = tofcore.suggested_pose(scene)
    passes = trace_progressive(scene, cam, [LED()], world_from_sensor=pose, max_depth=1,
                               policy=PassPolicy(spp=256, target_error_m=0.002))
    spp = []
    for transport in passes:
        spp.append(int(transport.sample_count[0]))
        error = {1: np.nan, 2: np.nan}.get(spp[-1], 0.02 if spp[-1] < 32 else 0.0022 if spp[-1] == 32 else 0.0019)
        passes.report(PassReport(error_m=np.full((6, 8), error)))
    assert spp == [1, 2, 4, 8, 16, 32, 39]


def test_pixels_reported_apart_do_not_hold_back_the_target():
    """One pixel with a flip's 1 m error among 2 mm ones: counted, the RMS is 0.14 m and the trace goes on;
    reported apart (PassReport.apart), the target of 5 mm is met after the first pass with an estimate."""
    scene, cam = tofcore.demo_scene("corner"), Camera.from_fov(8, 6, 60.0)
    pose = tofcore.suggested_pose(scene)
    error = np.full((6, 8), 0.002)
    error[2, 3] = 1.0
    apart = error > 0.5
    for flags, last_spp in ((None, 8), (apart, 1)):
        passes = trace_progressive(scene, cam, [LED()], world_from_sensor=pose, max_depth=1,
                                   policy=PassPolicy(spp=8, target_error_m=0.005))
        for transport in passes:
            passes.report(PassReport(error_m=error, apart=flags))
        assert int(transport.sample_count[0]) == last_spp


def test_the_adaptive_policy_allocates_by_the_reported_error():
    """After the 16-sample pilot, the pass's 16 samples per pixel go where the caller reports the error
    (estimator.allocate_samples of that error); without reports every pixel gets the same."""
    scene, cam = tofcore.demo_scene("corner"), Camera.from_fov(8, 6, 60.0)
    error = np.ones((6, 8))
    error[0, 0] = 10.0
    passes = trace_progressive(scene, cam, [LED()], max_depth=1, policy=PassPolicy(spp=32, adaptive=True))
    for transport in passes:
        passes.report(PassReport(error_m=error))
    expected = 16 + allocate_samples(error, np.full(48, 16), 16)
    np.testing.assert_array_equal(transport.sample_count, expected)
    assert transport.sample_count[0] > 32 > transport.sample_count.min()
    quiet = trace_progressive(scene, cam, [LED()], max_depth=1, policy=PassPolicy(spp=32, adaptive=True))
    assert (list(quiet)[-1].sample_count == 32).all()
