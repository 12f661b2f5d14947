"""batch.compare: one view, several presets → compare.png, compare.md, compare.json."""

from __future__ import annotations

import json
import struct

import numpy as np

from batch.compare import CELL_WIDTH, comparison_image
from batch_helpers import batch, match_checksums, read_index


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

    # A frame.exr damaged with its checksums made to match (issue 35): verify names it; compare renders it
    # again instead of a traceback (the codec's ExrError is a TofError both CLIs catch).
    frame = out / records[0]["dir"] / "frame.exr"
    frame.write_bytes(frame.read_bytes()[:500])
    match_checksums(out, records[0]["job_id"])
    proc = batch("verify", str(out))
    assert proc.returncode == 1 and f"frames/{records[0]['job_id']}: frame.exr: truncated EXR" in proc.stdout, \
        proc.stdout + proc.stderr
    proc = batch("compare", "--scene", "box_on_wall", "--presets", "kinect_v2,o3d303", "--out", str(out),
                 "--spp", "2", "--max-depth", "2", "--resolution-scale", "0.0625", "--quiet")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert read_index(out)[0]["finished"] != records[0]["finished"]  # rendered again


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


def test_the_comparison_image_has_colour_bars_and_the_table_says_what_rows_and_columns_are():
    from batch.compare import _HEADER_HEIGHT, _LABEL_WIDTH, markdown_table
    from tofcore.output.png import DIVERGING as _DIVERGING, TURBO as _TURBO

    h, w = 10, 20
    depth = np.linspace(1.0, 2.0, h * w, dtype=np.float32).reshape(h, w)
    ch = {"depth": depth, "gt_depth": depth + 0.01, "valid": np.ones((h, w), np.float32),
          "reason": np.zeros((h, w), np.float32)}
    image, _ = comparison_image([("a", ch)])
    cell_h = round(h * CELL_WIDTH / w)
    bar_y = _HEADER_HEIGHT + cell_h + 4 + 10                  # the middle of the 12-px bars below the one row
    for column, lut in ((0, _TURBO), (1, _DIVERGING)):
        x0 = _LABEL_WIDTH + column * (CELL_WIDTH + 4)
        strip = image[bar_y, x0 + 6:x0 + CELL_WIDTH - 6]
        np.testing.assert_array_equal(strip[0], lut[0])
        np.testing.assert_array_equal(strip[-1], lut[-1])
    table = markdown_table([], "t")
    assert "compare.png: one row per preset, in this table's order; columns: depth, depth − ground truth" in table
    assert "Rows of compare.png in this order" not in table


def test_compare_takes_a_mesh_file(tmp_path):
    trimesh = __import__("pytest").importorskip("trimesh")
    path = tmp_path / "wall.stl"
    trimesh.creation.box(extents=[3.0, 0.1, 2.0]).export(str(path))
    out = tmp_path / "report"
    proc = batch("compare", "--scene", str(path), "--presets", "kinect_v2", "--out", str(out), "--spp", "1",
                 "--max-depth", "1", "--resolution-scale", "0.0625", "--quiet")
    assert proc.returncode == 0, proc.stderr
    (record,) = read_index(out)
    assert record["source"]["kind"] == "mesh" and record["objects"] == [
        {"id": 0, "name": "wall.stl", "materials": ["default"]}]


def test_all_nan_frame_data_gives_the_image_and_rows_without_a_numpy_warning():
    """A frame whose channels are all NaN (reason too): a RuntimeWarning about casting NaN before (issue 35)."""
    import warnings

    from batch.compare import table_rows

    nan = np.full((6, 8), np.nan, np.float32)
    channels = {name: nan.copy() for name in ("depth", "gt_depth", "valid", "reason")}
    record = {"preset": "kinect_v2", "settings": {"width": 8, "height": 6}, "job_id": "0" * 16, "dir": "frames/x",
              "valid_fraction": 0.0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        image, limits = comparison_image([("kinect_v2", channels), ("o3d303", channels)])
        [row] = table_rows([record], [channels])
    assert image.ndim == 3 and limits["depth_m"] == [0.0, 1.0]
    assert row["invalid_by_reason"] == {} and row["invalid_fraction"] == 1.0
