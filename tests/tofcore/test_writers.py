"""Writers: EXR round trip, PNG depth and previews, PLY, JSON checksums, atomic writes."""

import hashlib
import os
import subprocess
import sys
import json
import re
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from tofcore.output import exr, png, writers
from tofcore.output.frame import Frame, Reason

H, W, K = 6, 8, 3
LABELS = ("f80MHz_s0", "f80MHz_s1", "f80MHz_s2", "f80MHz_s3")


def make_frame() -> Frame:
    """A 6×8 frame with a few invalid pixels, 4 raw images, K = 3, a 4×4 pose and NumPy metadata."""
    rng = np.random.default_rng(7)
    f32 = np.float32
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - 3.5) / 10, (v - 2.5) / 10, np.ones((H, W))], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    gt_distance = (1.0 + 0.25 * rng.random((H, W))).astype(f32)
    distance = (gt_distance + 0.01 * rng.standard_normal((H, W))).astype(f32)
    reason = np.zeros((H, W), np.uint8)
    reason[0, 0], reason[2, 5], reason[5, 7] = Reason.NO_RETURN, Reason.LOW_AMPLITUDE, Reason.SATURATED
    valid = reason == 0
    distance[~valid] = np.nan
    gt_distance[0, 0] = np.nan
    amplitude = (100 + 900 * rng.random((H, W))).astype(f32)
    amplitude[0, 0] = 0
    pose = np.array([[0, -1, 0, 0.5], [0, 0, -1, 1.25], [1, 0, 0, 1.5], [0, 0, 0, 1]], dtype=np.float64)
    return Frame(
        depth=distance.copy(), distance=distance, amplitude=amplitude, offset=(amplitude * 2).astype(f32),
        intensity=(amplitude * 2.5).astype(f32), valid=valid, reason=reason,
        confidence=np.where(valid, 0.9, 0).astype(f32), raw=(1000 * rng.random((4, H, W))).astype(f32),
        raw_labels=LABELS, gt_distance=gt_distance, gt_depth=gt_distance.copy(),
        direct_distance=(gt_distance + 0.001).astype(f32),
        distance_per_k=np.stack([gt_distance + 0.002 * k for k in range(1, K + 1)]).astype(f32),
        ray_directions=rays.astype(f32), object_id=np.where(valid, v % 3, -1).astype(np.int32),
        world_from_sensor=pose,
        stats={"time_s": np.float64(1.5), "rays": np.int64(48), "nan": np.nan, "log": np.array([1.0, np.nan])},
        metadata={"sensor": {"name": "test"}, "intrinsics": {"fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5},
                  "world_from_sensor": pose, "settings": {"spp": 4}},
    )


@pytest.fixture(scope="module")
def frame() -> Frame:
    return make_frame()


@pytest.fixture
def written(frame, tmp_path):
    return writers.write_frame(frame, tmp_path / "out", writers.FORMATS, prefix="f0_")


def test_exr_round_trip_is_bit_exact(frame, tmp_path):
    path = writers.write_frame(frame, tmp_path, "exr")["exr"]
    channels = writers.read_exr(path)
    expected = {name: getattr(frame, name) for name in writers._EXR_IMAGES}
    expected |= {f"raw.{label}": raw for label, raw in zip(LABELS, frame.raw)}
    expected |= {f"distance_k{k}": d for k, d in enumerate(frame.distance_per_k, 1)}
    assert set(channels) == set(expected)
    for name, image in expected.items():
        assert channels[name].dtype == np.float32 and channels[name].shape == (H, W), name
        assert channels[name].tobytes() == np.asarray(image, np.float32).tobytes(), name
    header = exr.read_header(path)
    assert header["compression"] == "zip"
    np.testing.assert_array_equal(header["world_from_sensor"], frame.world_from_sensor)
    document = json.loads(header["tofcore"])
    assert document["metadata"]["intrinsics"]["fx"] == 10.0 and document["raw_labels"] == list(LABELS)
    openexr = pytest.importorskip("OpenEXR")   # the reference library reads the same
    theirs = openexr.File(str(path), separate_channels=True)
    assert json.loads(theirs.header()["tofcore"]) == document
    for name, channel in theirs.channels().items():
        assert channel.pixels.tobytes() == channels[name].tobytes(), name


def test_a_frame_is_written_and_read_without_native_packages(tmp_path):
    """No OpenEXR, OpenCV or matplotlib is imported by rendering and writing every format and reading the EXR
    while bpy is loaded (a stand-in module here): the rule of tofcore.native that keeps Blender alive."""
    code = ("import sys, types\n"
            "sys.modules['bpy'] = types.ModuleType('bpy')\n"
            f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
            "from test_writers import make_frame\n"
            "import tofcore\n"
            f"written = tofcore.write_frame(make_frame(), {str(tmp_path / 'out')!r})\n"
            "assert 'depth' in tofcore.read_exr(written['exr']) and 'depth_exr' in written and 'depth' in written, written\n"
            "print(sorted(m for m in ('OpenEXR', 'cv2', 'matplotlib') if m in sys.modules))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_depth_mm_png_is_millimetres_with_zero_invalid(frame, written):
    cv2 = pytest.importorskip("cv2")
    depth_mm = cv2.imread(str(written["depth_mm"]), cv2.IMREAD_UNCHANGED)
    assert depth_mm.dtype == np.uint16 and depth_mm.shape == (H, W)
    expected = np.where(frame.valid, np.rint(np.nan_to_num(frame.depth.astype(np.float64)) * 1000), 0)
    np.testing.assert_array_equal(depth_mm, expected)
    assert depth_mm[0, 0] == 0


def test_depth_mm_clips_far_depth():
    far = make_frame()
    far.depth[1, 1] = 70.0
    assert writers._depth_mm(far)[1, 1] == 65535


def test_previews_are_rgb8(written):
    """The image is the top-left H x W of every preview; depth and error carry a colour bar on the right,
    reason its legend below (one swatch per Reason, in the reason colours)."""
    cv2 = pytest.importorskip("cv2")
    for kind in ("depth", "intensity", "error", "reason"):
        image = cv2.imread(str(written[kind]), cv2.IMREAD_UNCHANGED)
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3, kind
        assert image.shape[:2] == (H, W) if kind == "intensity" else image.shape[0] >= H and image.shape[1] >= W
    for kind, lut in (("depth", png.TURBO), ("error", png.DIVERGING)):
        rgb = cv2.imread(str(written[kind]), cv2.IMREAD_UNCHANGED)[..., ::-1]
        assert rgb.shape[1] > W + 16
        bar_column = rgb[:, W + 6 + 8]           # the middle of the bar: top = highest entry, bottom = lowest
        np.testing.assert_array_equal(bar_column[0], lut[-1])
        np.testing.assert_array_equal(bar_column[-1], lut[0])
    reason = cv2.imread(str(written["reason"]), cv2.IMREAD_UNCHANGED)[..., ::-1]
    legend = reason[H:].reshape(-1, 3)
    for colour in writers._REASON_RGB.values():
        assert (legend == colour).all(axis=1).any(), colour
    depth_bgr = cv2.imread(str(written["depth"]), cv2.IMREAD_UNCHANGED)
    assert (depth_bgr[0, 0] == 0).all() and depth_bgr[1, 1].any()


@pytest.mark.parametrize("image", [np.arange(H * W, dtype=np.uint16).reshape(H, W) * 1361,
                                   np.arange(H * W * 3, dtype=np.uint8).reshape(H, W, 3)])
def test_numpy_png_encoder_matches_opencv(image):
    cv2 = pytest.importorskip("cv2")
    decoded = cv2.imdecode(np.frombuffer(png.encode_png_numpy(image), np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(decoded[..., ::-1] if image.ndim == 3 else decoded, image)


def test_png_without_opencv(frame, tmp_path, monkeypatch):
    monkeypatch.setattr(png, "cv2", None)
    path = writers.write_frame(frame, tmp_path, "png")["depth_mm"]
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    width, height, bit_depth, colour_type = np.frombuffer(data[16:26], ">u4", 2).tolist() + list(data[24:26])
    assert (width, height, bit_depth, colour_type) == (W, H, 16, 0)
    idat_len = int.from_bytes(data[33:37], "big")
    rows = np.frombuffer(zlib.decompress(data[41:41 + idat_len]), np.uint8).reshape(H, 1 + 2 * W)
    np.testing.assert_array_equal(rows[:, 1:].copy().view(">u2"), writers._depth_mm(frame))


def test_colour_maps():
    assert png.TURBO.shape == png.DIVERGING.shape == (256, 3)
    blue, red = png.DIVERGING[0], png.DIVERGING[255]
    assert blue[2] > blue[0] and red[0] > red[2]
    assert png.DIVERGING[127:129].min() >= 250  # white in the middle
    assert set(writers._REASON_RGB) == set(Reason)
    assert len({tuple(c) for c in writers._REASON_RGB.values()}) == len(Reason)


def test_reason_out_of_range_raises(frame):
    bad = make_frame()
    bad.reason[0, 1] = 17
    with pytest.raises(ValueError, match=r"got \[17\]"):
        writers._reason_preview(bad)


def test_ply_parses_back_to_valid_points(frame, written):
    data = written["ply"].read_bytes()
    header, body = data.split(b"end_header\n", 1)
    lines = header.decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    count = int(next(line for line in lines if line.startswith("element vertex")).split()[-1])
    assert count == frame.valid.sum() == H * W - 3
    vertices = np.frombuffer(body, writers._PLY_VERTEX)
    assert len(vertices) == count
    xyz = np.stack([vertices["x"], vertices["y"], vertices["z"]], axis=1)
    np.testing.assert_array_equal(xyz, frame.points("sensor"))
    np.testing.assert_array_equal(vertices["amplitude"], frame.amplitude[frame.valid])


def test_json_checksums_units_and_no_nan(frame, written):
    text = written["json"].read_text("utf-8")
    assert not re.search(r"\bNaN\b|\bInfinity\b", text)
    document = json.loads(text)
    files = {record["kind"]: record for record in document["files"]}
    assert set(files) == set(written) - {"json"}
    for kind, record in files.items():
        data = written[kind].read_bytes()
        assert record["name"] == written[kind].name and record["name"].startswith("f0_")
        assert record["bytes"] == len(data) and record["sha256"] == hashlib.sha256(data).hexdigest()
    assert document["stats"] == {"time_s": 1.5, "rays": 48, "nan": None, "log": [1.0, None]}
    assert document["metadata"]["world_from_sensor"] == frame.world_from_sensor.tolist()
    assert document["units"]["depth"] == "m" and document["reason_codes"]["SATURATED"] == 3
    assert document["previews"]["error"]["limit_mm"] >= 1.0
    assert document["previews"]["depth"]["min_m"] == pytest.approx(np.nanmin(frame.depth[frame.valid]))


def test_unknown_format_raises_before_writing(frame, tmp_path):
    valid = r"\('exr', 'png', 'ply', 'json', 'transient'\)"
    with pytest.raises(ValueError, match=rf"formats must be among {valid}, got unknown \['tiff'\]"):
        writers.write_frame(frame, tmp_path / "out", ("png", "tiff"))
    assert not (tmp_path / "out").exists()


def test_failure_mid_write_leaves_no_partial_file(frame, tmp_path, monkeypatch):
    def explode(_frame):
        assert [p.name[:len(".points.ply.tmp-")] for p in tmp_path.iterdir()] == [".points.ply.tmp-"]
        raise RuntimeError("encoder failed")

    monkeypatch.setattr(writers, "_ply_vertices", explode)  # after the header is in the temp file
    with pytest.raises(RuntimeError, match="encoder failed"):
        writers.write_frame(frame, tmp_path, ("ply", "json"))
    assert list(tmp_path.iterdir()) == []


def test_failure_keeps_previous_file_and_drops_done_record(frame, tmp_path, monkeypatch):
    first = writers.write_frame(frame, tmp_path, ("ply", "json"))
    before = first["ply"].read_bytes()
    monkeypatch.setattr(writers, "_ply_vertices", lambda _frame: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        writers.write_frame(frame, tmp_path, ("ply", "json"))
    assert first["ply"].read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["points.ply"]


def test_unconvertible_stats_raise_before_writing(tmp_path):
    bad = make_frame()
    bad.stats["plan"] = {"skip": object()}
    with pytest.raises(TypeError, match=r"frame\['stats'\]\['plan'\]\['skip'\]: .* got object"):
        writers.write_frame(bad, tmp_path / "out", ("png", "json"))
    assert not (tmp_path / "out").exists()


def test_prefix_with_separator_raises(frame, tmp_path):
    with pytest.raises(ValueError, match="prefix"):
        writers.write_frame(frame, tmp_path, "json", prefix="a/b")


def test_convergence_png_is_written_and_listed(tmp_path):
    from tofcore.output import convergence_plot

    logged = make_frame()
    logged.stats["convergence"] = [{"pass": i + 1, "seconds": 0.1 * 2 ** i, "spp": 2 ** i, "rays": 48,
                                    "est_depth_error_m": 0.01 / 2 ** (i / 2)} for i in range(3)]
    written = writers.write_frame(logged, tmp_path, ("png", "json"), prefix="f0_")
    path = written["convergence"]
    assert path.name == "f0_convergence.png" and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in written.values())  # no temp files
    width, height = np.frombuffer(path.read_bytes()[16:24], ">u4").tolist()
    assert (width, height) == (640, 400)
    files = {r["kind"]: r for r in json.loads(written["json"].read_text("utf-8"))["files"]}
    assert files["convergence"]["name"] == "f0_convergence.png"
    assert files["convergence"]["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert path.read_bytes() == convergence_plot.convergence_png(logged.stats["convergence"])  # a pure function


def test_convergence_png_without_log_or_plotting_packages(frame, tmp_path, monkeypatch):
    from tofcore.output import convergence_plot

    monkeypatch.setattr(png, "cv2", None)
    monkeypatch.setattr(convergence_plot, "cv2", None)
    monkeypatch.setattr(convergence_plot, "_MATPLOTLIB", [None])
    assert "convergence" not in frame.stats
    written = writers.write_frame(frame, tmp_path, "png")   # no log at all: "no convergence log"
    data = written["convergence"].read_bytes()
    assert data[12:16] == b"IHDR" and np.frombuffer(data[16:24], ">u4").tolist() == [640, 400]
    assert "convergence" not in writers.write_frame(frame, tmp_path / "json", "json")


# --------------------------------------------------------------------------- files the user's tools read

def test_depth_exr_is_one_y_channel_that_opencv_opens(frame, tmp_path):
    """OpenCV reads EXR only with OPENCV_IO_ENABLE_OPENEXR set before its first EXR call: a child process."""
    cv2 = pytest.importorskip("cv2")
    pytest.importorskip("OpenEXR")
    if not re.search(r"OpenEXR:\s+(build|/|YES|\S*lib)", cv2.getBuildInformation()):
        pytest.skip(f"this OpenCV {cv2.__version__} is built without OpenEXR")
    written = writers.write_frame(frame, tmp_path, ("exr",))
    assert set(writers.read_exr(written["depth_exr"])) == {"Y"}
    code = ("import sys, cv2, numpy as np; d = cv2.imread(sys.argv[1], cv2.IMREAD_UNCHANGED); "
            "f = cv2.imread(sys.argv[2], cv2.IMREAD_UNCHANGED); np.save(sys.argv[3], d); print(d.dtype, d.shape, f)")
    out = tmp_path / "depth.npy"
    proc = subprocess.run([sys.executable, "-c", code, str(written["depth_exr"]), str(written["exr"]), str(out)],
                          env={**os.environ, "OPENCV_IO_ENABLE_OPENEXR": "1"}, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split()[:3] == ["float32", f"({H},", f"{W})"]   # frame.exr (26 channels): None
    np.testing.assert_array_equal(np.load(out), frame.depth)           # NaN where invalid, bit for bit


def test_exr_half_and_a_channel_subset(frame, tmp_path):
    pytest.importorskip("OpenEXR")
    import OpenEXR

    written = writers.write_frame(frame, tmp_path, ("exr",), exr_half=True, exr_channels=["depth", "valid"])
    stored = OpenEXR.File(str(written["exr"]), separate_channels=True).channels()
    assert set(stored) == {"depth", "valid"} and all(c.pixels.dtype == np.float16 for c in stored.values())
    np.testing.assert_array_equal(stored["depth"].pixels, frame.depth.astype(np.float16))
    depth = OpenEXR.File(str(written["depth_exr"]), separate_channels=True).channels()["Y"].pixels
    assert depth.dtype == np.float16
    with pytest.raises(ValueError, match=r"exr_channels must be a non-empty subset of \['depth', .*got unknown "
                                         r"\['dpeth'\]"):
        writers.write_frame(frame, tmp_path / "bad", ("exr",), exr_channels=["dpeth"])
    assert not (tmp_path / "bad").exists()
    names = writers.exr_channel_names(LABELS, K)
    assert names[:-3] == list(writers._exr_channels(frame)) and names[-3:] == ["render_error", "samples",
                                                                               "unwrap_flip"]


def test_ir_png_is_16_bit_amplitude_exposed_for_display(frame, tmp_path):
    """Issue 36: in full-well counts a room's ir.png held at most 922 of 65,535 and opened black. Exposed for
    display, the valid pixels' 99.5th percentile is at 80 % of 65,535; frame.json's e_per_count gives the
    electrons back; a frame without a valid pixel keeps the full well's scale."""
    cv2 = pytest.importorskip("cv2")
    sensor = {"readout": {"full_well_e": 65535.0 * 2}}
    with_well = Frame(**{**vars(frame), "metadata": {**frame.metadata, "sensor": sensor}})
    written = writers.write_frame(with_well, tmp_path, ("png", "json"))
    ir = cv2.imread(str(written["ir"]), cv2.IMREAD_UNCHANGED)
    assert ir.dtype == np.uint16 and ir.shape == (H, W)
    e_per_count = json.loads(written["json"].read_text())["previews"]["ir"]["e_per_count"]
    amplitude = np.nan_to_num(frame.amplitude)
    np.testing.assert_array_equal(ir, np.clip(np.rint(amplitude / e_per_count), 0, 65535))
    lit = frame.valid & (amplitude > 0)
    assert np.isclose(np.percentile(amplitude[lit], 99.5) / e_per_count, 0.8 * 65535)
    assert np.percentile(ir[lit], 50) > 0.1 * 65535 > 922, "ir.png opens dark"
    dark = Frame(**{**vars(with_well), "valid": np.zeros_like(frame.valid)})
    written = writers.write_frame(dark, tmp_path / "dark", ("png", "json"))
    assert json.loads(written["json"].read_text())["previews"]["ir"]["e_per_count"] == 2.0


def test_camera_files_open_in_opencv_ros_and_bop(tmp_path):
    cv2 = pytest.importorskip("cv2")
    yaml = pytest.importorskip("yaml")
    intrinsics = {"width": 512, "height": 424, "fx": 365.5, "fy": 366.25, "cx": 255.75, "cy": 205.5,
                  "k1": 0.09, "k2": -0.27, "p1": 0.001, "p2": -0.002, "k3": 0.097}
    frame = Frame(**{**vars(make_frame()), "metadata": {"intrinsics": intrinsics}})
    written = writers.write_frame(frame, tmp_path, ("json",))
    k = np.array([[365.5, 0, 255.75], [0, 366.25, 205.5], [0, 0, 1]])
    dist = [0.09, -0.27, 0.001, -0.002, 0.097]
    storage = cv2.FileStorage(str(written["opencv_yaml"]), cv2.FILE_STORAGE_READ)
    np.testing.assert_array_equal(storage.getNode("camera_matrix").mat(), k)
    np.testing.assert_array_equal(storage.getNode("distortion_coefficients").mat(), [dist])
    assert (storage.getNode("image_width").real(), storage.getNode("image_height").real()) == (512, 424)
    ros = yaml.safe_load(written["ros_yaml"].read_text())
    assert (ros["image_width"], ros["image_height"], ros["distortion_model"]) == (512, 424, "plumb_bob")
    assert ros["camera_matrix"]["data"] == k.ravel().tolist() and ros["distortion_coefficients"]["data"] == dist
    assert ros["projection_matrix"]["data"] == np.hstack([k, np.zeros((3, 1))]).ravel().tolist()
    bop = json.loads(written["bop_camera"].read_text())
    assert bop == {"cx": 255.75, "cy": 205.5, "depth_scale": 1.0, "fx": 365.5, "fy": 366.25, "height": 424,
                   "width": 512}
    listed = {entry["name"] for entry in json.loads(written["json"].read_text())["files"]}
    assert {"camera_opencv.yml", "camera_info.yaml", "camera.json"} <= listed


def test_transient_histogram_file_and_its_bin_width(frame, tmp_path):
    hist = np.random.default_rng(1).random((H, W, 5)).astype(np.float32)
    with_hist = Frame(**{**vars(frame), "transient": hist, "transient_bin_m": 0.05})
    written = writers.write_frame(with_hist, tmp_path, ("transient", "json"))
    np.testing.assert_array_equal(np.load(written["transient"]), hist)
    entry = json.loads(written["json"].read_text())["previews"]["transient"]
    assert (entry["bin_width_m"], entry["bins"], entry["shape"]) == (0.05, 5, [H, W, 5])
    assert "transient" not in writers.write_frame(frame, tmp_path / "none", ("transient",))
