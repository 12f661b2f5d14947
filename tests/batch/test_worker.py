"""batch.worker: what a worker keeps between frames."""

from __future__ import annotations

from batch import worker
from batch.jobs import expand
from batch.setfile import load_set
from batch_helpers import TINY, write_set


def test_a_worker_builds_each_presets_sensor_once(tmp_path, monkeypatch):
    """Building a sensor checks its camera's distortion over the whole image (the Kinect v2's undistortion table):
    a worker builds it once per preset description, not for every frame."""
    jobs = expand(load_set(write_set(tmp_path, """
seed = 3
presets = ["kinect_v2", "o3d303"]
""" + TINY + """
[[scenes]]
demo = "corner"
[[scenes.poses]]
suggested = true
[[scenes.poses]]
eye = [1.2, 0.9, 1.3]
target = [0.0, 0.0, 1.2]
"""))).jobs
    assert len(jobs) == 4
    monkeypatch.setattr(worker, "_SENSOR_CACHE", {})
    sensors = [worker._sensor(job) for job in jobs]
    by_preset = {}
    for job, sensor in zip(jobs, sensors):
        assert by_preset.setdefault(job.preset, sensor) is sensor  # the same object for every frame of a preset
        assert sensor.to_dict() == job.sensor
    assert len(worker._SENSOR_CACHE) == 2
