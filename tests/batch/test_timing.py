"""batch.timing: per-worker sums of the records' timing, on records with known phases."""

from __future__ import annotations

import pytest

from batch.timing import timing_lines, worker_timing


def _record(pid: int, gpu: str | None, render_started: float, render_s: float, write_s: float,
            load_s: float = 0.0, worker_started: float = 100.0) -> dict:
    return {"host": "h", "pid": pid, "cuda_visible_devices": gpu, "status": "ok",
            "timing": {"worker_started": worker_started, "task_started": render_started - load_s, "load_s": load_s,
                       "render_started": render_started, "render_s": render_s, "write_s": write_s,
                       "finished": render_started + render_s + write_s}}


def test_phases_add_up_to_each_workers_span():
    # worker 1: launched at 100, first view at 102 (1 s scene load), renders 103–113 (first: imports, kernels),
    # then two frames of 2 s with 0.5 s writes and 0.25 s between views
    rows = [_record(1, "0", 103.0, 10.0, 0.5, load_s=1.0),
            _record(1, "0", 113.75, 2.0, 0.5),
            _record(1, "0", 116.5, 2.5, 0.5),
            _record(2, "1", 104.0, 12.0, 1.0, worker_started=101.0),
            {"job_id": "failed before rendering", "pid": 3, "timing": {"worker_started": 1.0}}]
    one, two = worker_timing(rows)
    assert one["pid"] == 1 and one["gpu"] == "0" and one["frames"] == 3
    assert one["span_s"] == pytest.approx(19.5) and one["startup_s"] == pytest.approx(2.0)
    assert one["first_s"] == 10.0 and one["render_s"] == 4.5 and one["render_median_s"] == 2.25
    assert one["write_s"] == 1.5 and one["load_s"] == 1.0 and one["idle_s"] == pytest.approx(0.5)
    assert two["frames"] == 1 and two["render_median_s"] is None and two["idle_s"] == pytest.approx(0.0)
    lines = timing_lines([one, two])
    assert lines[0] == ("worker 1 (GPU 0): 3 frame(s) in 19.5 s: start-up 2.0 s, first render 10.0 s, then render "
                        "4.5 s (median 2.25 s), write 1.5 s (0.0 s of it while rendering; rendering waited 0.0 s for the "
                        "writer), scene load 1.0 s, idle 0.5 s")
    assert "median –" in lines[1]
