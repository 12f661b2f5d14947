"""batch.compare: one view, several presets → compare.png, compare.md, compare.json."""

from __future__ import annotations

import json
import struct

import numpy as np

from batch.compare import CELL_WIDTH, comparison_image
from batch_helpers import batch, read_index


def test_compare_writes_the_image_and_the_tables(tmp_path):
    out = tmp_path / "report"
    proc = batch("compare", "--scene", "box_on_wall", "--presets", "kinect_v2,o3d303", "--out", str(out),
                 "--spp", "2", "--max-depth", "2", "--resolution-scale", "0.0625", "--quiet")
    assert proc.returncode == 0, proc.stderr
    png = (out / "compare.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", png[16:24])
    assert width > 3 * CELL_WIDTH and height > 2 * 100
    report = json.loads((out / "compare.json").read_text())
    assert [row["preset"] for row in report["rows"]] == ["kinect_v2", "o3d303"]
    for row in report["rows"]:
        assert row["rms_depth_error_m"] > 0 and row["median_abs_depth_error_m"] > 0
        assert row["multipath_rms_m"] is not None and 0 <= row["invalid_fraction"] <= 1
        assert row["render_seconds"] > 0
    assert (row["width"], row["height"]) == (22, 17)  # O3D303 352 x 264 / 16
    assert report["image_columns"] == ["depth", "depth - gt_depth", "invalid pixels (reason)"]
    table = (out / "compare.md").read_text()
    assert "| kinect_v2 | 32×27 | 2 |" in table and "| o3d303 | 22×17 | 2 |" in table
    assert "multipath RMS mm" in table
    # Both presets saw the same pose.
    records = read_index(out)
    assert records[0]["world_from_sensor"] == records[1]["world_from_sensor"]


def test_comparison_image_rows_share_colour_limits():
    h, w = 10, 20
    depth = np.linspace(1.0, 2.0, h * w, dtype=np.float32).reshape(h, w)
    ch = {"depth": depth, "gt_depth": depth + 0.01, "valid": np.ones((h, w), np.float32),
          "reason": np.zeros((h, w), np.float32)}
    half = dict(ch, valid=ch["valid"].copy(), reason=ch["reason"].copy())
    half["valid"][:, :10] = 0
    half["reason"][:, :10] = 4  # out of range
    image, limits = comparison_image([("a", ch), ("b", half)])
    assert image.dtype == np.uint8 and image.ndim == 3
    assert limits["depth_m"] == [1.0, 2.0]
    assert np.isclose(limits["error_limit_mm"], 10.0, atol=0.01)
    assert limits["reason_colours"]["OUT_OF_RANGE"] == [220, 0, 220]
