"""batch.card: the dataset card's convergence summary (per preset, tolerant of records from older runs)."""

from __future__ import annotations

from batch.card import convergence_example, convergence_rows, dataset_card


def record(preset: str, job_id: str, *, status: str = "ok", error_m=0.002, spp=16, seconds=1.5,
           convergence_png: bool = True) -> dict:
    files = [{"kind": "json", "name": "frame.json"}]
    if convergence_png:
        files.append({"kind": "convergence", "name": "convergence.png"})
    r = {"job_id": job_id, "status": status, "scene": "corner", "view": {"label": "v0"}, "preset": preset,
         "sensor_name": preset, "settings": {"spp": 16, "max_depth": 2, "width": 16, "height": 12,
                                             "formats": ["png", "json"]},
         "dir": f"frames/{job_id}", "files": files, "spp": spp, "render_seconds": seconds}
    if error_m != "absent":
        r["est_depth_error_m"] = error_m
    return r


def test_convergence_rows_median_max_and_old_records():
    records = [record("kinect_v2", "b", error_m=0.001, spp=8, seconds=1.0),
               record("kinect_v2", "a", error_m=0.003, spp=16, seconds=2.0),
               record("kinect_v2", "c", error_m=0.010, spp=32, seconds=4.0),
               record("kinect_v2", "f", status="failed", error_m=1.0),
               record("o3d303", "d", error_m="absent"),           # written before records held the error
               record("o3d303", "e", error_m=None, spp=None, seconds=None)]
    assert convergence_rows(records) == [("kinect_v2", 3, 0.003, 0.010, 16, 2.0),
                                         ("o3d303", 2, None, None, 16, 1.5)]


def test_the_card_summarises_convergence_and_links_an_example():
    records = [record("kinect_v2", "b2", error_m=0.0012), record("kinect_v2", "a1", error_m=0.0034),
               record("o3d303", "c3", error_m="absent", convergence_png=False)]
    card = dataset_card(records, set_file="set.toml")
    assert "## Convergence" in card
    assert "| kinect_v2 | 2 | 2.30 | 3.40 | 16 | 1.50 |" in card
    assert "| o3d303 | 1 | – | – | 16 | 1.50 |" in card
    assert "![convergence of one frame](frames/a1/convergence.png)" in card


def test_no_example_without_a_convergence_png():
    records = [record("kinect_v2", "a", convergence_png=False), record("kinect_v2", "b", status="failed")]
    assert convergence_example(records) is None
    card = dataset_card(records, set_file=None)
    assert "## Convergence" in card and "![convergence" not in card
    assert "## Convergence" not in dataset_card([record("kinect_v2", "x", status="failed")], set_file=None)
