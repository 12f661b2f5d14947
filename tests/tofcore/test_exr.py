"""tofcore.exr: the NumPy OpenEXR codec against a hand-computed file, the OpenEXR package (both ways: all
pixel types, all three compressions, custom attributes, long names) and OpenCV's reader; damaged files are
one-line ValueErrors naming the file; writes are atomic."""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np
import pytest

import tofcore
from tofcore.output import exr

COMPRESSIONS = ("none", "zips", "zip")
LONG = "a_channel_name_longer_than_thirty_one_bytes"


def channels(height: int = 37, width: int = 29, seed: int = 1) -> dict[str, np.ndarray]:
    """One channel of each pixel type (random bits for UINT, NaN and ±inf in FLOAT), plus a long name."""
    rng = np.random.default_rng(seed)
    depth = rng.normal(2.0, 0.5, (height, width)).astype(np.float32)
    depth[0, :3] = np.nan, np.inf, -np.inf
    return {"depth": depth, "half": rng.random((height, width)).astype(np.float16),
            "id": rng.integers(0, 2**32, (height, width), dtype=np.uint32),
            LONG: rng.random((height, width)).astype(np.float32)}


ATTRIBUTES = {"tofcore": '{"note": "héllo"}', "count": -7, "scale": 0.1, "world_from_sensor": np.arange(16.).reshape(4, 4),
              "m44f": np.eye(4, dtype=np.float32), "size": np.array([3, 4], np.int32), "centre": np.array([1.5, 2.5])}


def assert_same(got: dict, expected: dict) -> None:
    assert sorted(got) == sorted(expected)
    for name, array in expected.items():
        assert got[name].dtype == array.dtype, name
        np.testing.assert_array_equal(got[name], array, err_msg=name)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_round_trip(tmp_path, compression):
    data = channels()
    exr.write(tmp_path / "a.exr", data, attributes=ATTRIBUTES, compression=compression)
    assert_same(exr.read(tmp_path / "a.exr"), data)
    header = exr.read_header(tmp_path / "a.exr")
    assert header["compression"] == compression
    assert header["channels"] == {"depth": "FLOAT", "half": "HALF", "id": "UINT", LONG: "FLOAT"}
    for name, value in ATTRIBUTES.items():
        np.testing.assert_array_equal(header[name], value, err_msg=name)
        assert type(header[name]) is type(value)
    assert header["world_from_sensor"].dtype == np.float64 and header["m44f"].dtype == np.float32


def test_subset_in_asked_order(tmp_path):
    data = channels()
    exr.write(tmp_path / "a.exr", data)
    got = exr.read(tmp_path / "a.exr", ["id", "depth"])
    assert list(got) == ["id", "depth"]
    np.testing.assert_array_equal(got["id"], data["id"])
    with pytest.raises(ValueError, match=r"a\.exr: channels \['nope'\] not in the file; it holds"):
        exr.read(tmp_path / "a.exr", ["nope"])


def test_hand_computed_layout():
    """A 2×1 image, one FLOAT channel "Y" = [1.0, 2.0], no compression, no extra attributes: every byte."""
    data = exr.encode({"Y": np.array([[1.0, 2.0]], np.float32)}, compression="none")

    def attr(name: str, kind: str, value: bytes) -> bytes:
        return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value

    box = struct.pack("<4i", 0, 0, 1, 0)
    header = (b"\x76\x2f\x31\x01" + struct.pack("<i", 2)
              + attr("channels", "chlist", b"Y\0" + struct.pack("<i", 2) + b"\0\0\0\0" + struct.pack("<ii", 1, 1) + b"\0")
              + attr("compression", "compression", b"\0")
              + attr("dataWindow", "box2i", box) + attr("displayWindow", "box2i", box)
              + attr("lineOrder", "lineOrder", b"\0")
              + attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
              + attr("screenWindowCenter", "v2f", struct.pack("<2f", 0, 0))
              + attr("screenWindowWidth", "float", struct.pack("<f", 1.0)) + b"\0")
    offset_table = struct.pack("<Q", len(header) + 8)
    chunk = struct.pack("<ii", 0, 8) + struct.pack("<2f", 1.0, 2.0)
    assert data == header + offset_table + chunk


def test_zip_chunk_by_hand():
    """ZIP: 16 lines a chunk; the bytes interleaved (even positions, then odd) and delta-coded + 128."""
    image = np.arange(2 * 17, dtype=np.float32).reshape(17, 2)   # 17 lines: chunks of 16 and 1 line
    data = exr.encode({"Y": image}, compression="zip")
    table_at = exr._Reader(data, "zip").header()[1]   # the offset table follows the header
    offsets = struct.unpack("<2Q", data[table_at:table_at + 16])
    y0, size0 = struct.unpack("<ii", data[offsets[0]:offsets[0] + 8])
    y1, size1 = struct.unpack("<ii", data[offsets[1]:offsets[1] + 8])
    assert (y0, y1) == (0, 16)
    raw = image[:16].tobytes()
    t = raw[0::2] + raw[1::2]
    d = bytes([t[0]] + [(t[i] - t[i - 1] + 128) % 256 for i in range(1, len(t))])
    assert zlib.decompress(data[offsets[0] + 8:offsets[0] + 8 + size0]) == d
    assert size1 == 8 and data[offsets[1] + 8:] == image[16:].tobytes()   # 8 bytes do not shrink: stored raw


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_openexr_reads_ours_and_we_read_openexr(tmp_path, compression):
    openexr = pytest.importorskip("OpenEXR")
    data = channels()
    exr.write(tmp_path / "ours.exr", data, attributes=ATTRIBUTES, compression=compression)
    theirs = openexr.File(str(tmp_path / "ours.exr"), separate_channels=True)
    assert_same({name: c.pixels for name, c in theirs.channels().items()}, data)
    header = theirs.header()
    assert header["tofcore"] == ATTRIBUTES["tofcore"] and header["count"] == -7
    np.testing.assert_array_equal(header["world_from_sensor"], ATTRIBUTES["world_from_sensor"])
    np.testing.assert_array_equal(np.ravel(header["scale"]), [0.1])

    code = {"none": openexr.NO_COMPRESSION, "zips": openexr.ZIPS_COMPRESSION, "zip": openexr.ZIP_COMPRESSION}
    openexr.File({"compression": code[compression], "type": openexr.scanlineimage, "note": "x",
                  "pose": np.eye(4), "n": 3, "f": 2.5}, dict(data)).write(str(tmp_path / "theirs.exr"))
    assert_same(exr.read(tmp_path / "theirs.exr"), data)
    header = exr.read_header(tmp_path / "theirs.exr")
    assert (header["note"], header["n"], header["f"], header["compression"]) == ("x", 3, 2.5, compression)
    np.testing.assert_array_equal(header["pose"], np.eye(4))


@pytest.mark.parametrize("count", [1, 3])
def test_opencv_reads_ours(tmp_path, monkeypatch, count):
    """OpenCV reads 1-channel ("Y") and 3-channel ("B", "G", "R") float files."""
    monkeypatch.setenv("OPENCV_IO_ENABLE_OPENEXR", "1")
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(2)
    names = ["Y"] if count == 1 else ["B", "G", "R"]
    data = {name: rng.random((21, 33)).astype(np.float32) for name in names}
    exr.write(tmp_path / "cv.exr", data)
    image = cv2.imread(str(tmp_path / "cv.exr"), cv2.IMREAD_UNCHANGED)
    if image is None:
        pytest.skip(f"this OpenCV ({cv2.__version__}) has no EXR codec")
    expected = data["Y"] if count == 1 else np.stack([data[n] for n in names], axis=-1)
    np.testing.assert_array_equal(image, expected)


def test_non_ascii_and_bytes_paths(tmp_path):
    data = {"Y": np.ones((2, 3), np.float32)}
    path = tmp_path / "tiefe ü 深度.exr"
    exr.write(path, data)
    assert_same(exr.read(os.fsencode(path)), data)
    exr.write(os.fsencode(tmp_path / "b.exr"), data)
    assert_same(exr.read(str(tmp_path / "b.exr")), data)


def test_atomic_write_leaves_nothing_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "frame.exr"
    exr.write(path, {"Y": np.ones((2, 2), np.float32)})
    before = path.read_bytes()

    def fail(*_args):
        raise OSError("disk full")
    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        exr.write(path, {"Y": np.zeros((2, 2), np.float32)})
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.exr"]


@pytest.mark.parametrize("channels_, attributes, message", [
    ({}, None, "at least one"),
    ({"a\0b": np.ones((2, 2), np.float32)}, None, "channel names must be 1-255 bytes without NUL"),
    ({1: np.ones((2, 2), np.float32)}, None, "channel names must be 1-255 bytes without NUL, got 1"),
    ({"Y": np.ones((2, 2))}, None, "'Y' must be float32, float16 or uint32, got float64"),
    ({"Y": np.ones(3, np.float32)}, None, "must be a non-empty \\(H, W\\) array"),
    ({"A": np.ones((2, 2), np.float32), "B": np.ones((2, 3), np.float32)}, None, "like the others"),
    ({"Y": np.ones((2, 2), np.float32)}, {"dataWindow": 1}, "written from the image"),
    ({"Y": np.ones((2, 2), np.float32)}, {"flag": True}, "a bool has no EXR type"),
    ({"Y": np.ones((2, 2), np.float32)}, {"m": np.ones((2, 5))}, "attribute 'm' must be"),
])
def test_bad_input(channels_, attributes, message):
    with pytest.raises(ValueError, match=message):
        exr.encode(channels_, attributes=attributes)


def test_unknown_compression():
    with pytest.raises(ValueError, match=r"compression must be one of \['none', 'zip', 'zips'\], got 'piz'"):
        exr.encode({"Y": np.ones((2, 2), np.float32)}, compression="piz")


def test_damaged_files_are_one_line_errors_naming_the_file(tmp_path):
    good = exr.encode(channels(), attributes=ATTRIBUTES)
    path = tmp_path / "bad.exr"
    cases = {
        "not an OpenEXR file": b"PNG....",
        "truncated EXR": good[:len(good) // 2],
        "truncated EXR: the type of attribute": good[:200],
        "a ZIP chunk does not decompress": _corrupt_first_chunk(exr.encode({"Y": np.zeros((40, 40), np.float32)})),
        "tiled EXR files are not supported": good[:4] + struct.pack("<i", 2 | 0x200) + good[8:],
        "version 3 is not supported": good[:4] + struct.pack("<i", 3) + good[8:],
    }
    for message, data in cases.items():
        path.write_bytes(data)
        with pytest.raises(ValueError) as info:
            exr.read(path)
        text = str(info.value)
        assert text.startswith(f"{path}: ") and "\n" not in text and message in text, (message, text)


def _corrupt_first_chunk(data: bytes) -> bytes:
    """``data`` with bytes of its first (compressed) chunk's zlib stream overwritten."""
    first = exr._Reader(data, "x").header()[1]
    offset = struct.unpack("<Q", data[first:first + 8])[0]
    body = bytearray(data)
    body[offset + 8:offset + 40] = b"\xff" * 32
    return bytes(body)


def test_rejects_unsupported_compression_by_name(tmp_path):
    data = bytearray(exr.encode({"Y": np.ones((2, 2), np.float32)}, compression="none"))
    at = data.index(b"compression\0compression\0") + len(b"compression\0compression\0") + 4
    data[at] = 4   # PIZ
    (tmp_path / "piz.exr").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"piz\.exr: EXR compression 'piz' is not supported"):
        exr.read(tmp_path / "piz.exr")


# --------------------------------------------------------------------------- hostile files (issue 35)

def _rebuild(data: bytes, changes: dict[str, tuple[str, bytes] | None]) -> bytes:
    """``data`` with header attributes replaced (``{name: (type, value bytes)}``; None removes one), the
    offset table moved by the header's change in size."""
    _, end, raw = exr._Reader(data, "x").header()
    raw = {**raw, **changes}
    head = bytearray(data[:8])
    for name, item in raw.items():
        if item is not None:
            head += name.encode() + b"\0" + item[0].encode() + b"\0" + struct.pack("<i", len(item[1])) + item[1]
    head += b"\0"
    count = (len(data) - end) and _chunk_count(data)
    offsets = np.frombuffer(data[end:end + 8 * count], "<u8").astype(np.int64) + (len(head) - end)
    return bytes(head) + offsets.astype("<u8").tobytes() + data[end + 8 * count:]


def _chunk_count(data: bytes) -> int:
    reader = exr._Reader(data, "x")
    layout = reader.layout()
    return -(-layout.height // layout.lines)


def _zip_bomb(mib: int) -> bytes:
    """A 64 x 16 FLOAT image (4 KiB of pixels, one ZIP chunk) whose zlib stream inflates to ``mib`` MiB."""
    good = exr.encode({"Y": np.zeros((16, 64), np.float32)}, compression="zip")
    end = exr._Reader(good, "x").header()[1]
    packer = zlib.compressobj(9)
    stream = b"".join(packer.compress(bytes(1 << 20)) for _ in range(mib)) + packer.flush()
    return good[:end] + struct.pack("<Q", end + 8) + struct.pack("<ii", 0, len(stream)) + stream


def _one_line_naming(info: pytest.ExceptionInfo, path) -> str:
    assert isinstance(info.value, tofcore.TofError) and isinstance(info.value, ValueError), type(info.value)
    text = str(info.value)
    assert text.startswith(f"{path}: ") and "\n" not in text, text
    return text


def test_a_zip_bomb_is_refused_after_the_declared_bytes_in_bounded_memory(tmp_path):
    """16 MiB from a 16 KiB stream declared as 4 KiB: refused after inflating 4 KiB, not 16 MiB (the old
    reader inflated it all: 0.56 GB at 256 MiB, 2.1 GB at 1 GiB)."""
    import tracemalloc

    path = tmp_path / "bomb.exr"
    path.write_bytes(_zip_bomb(16))
    tracemalloc.start()
    try:
        with pytest.raises(exr.ExrError) as info:
            exr.read(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert "a ZIP chunk inflates to more than the 4,096 bytes its lines hold" in _one_line_naming(info, path)
    assert peak < 8 * path.stat().st_size + (1 << 20), peak


def test_declared_sizes_are_checked_against_the_file_before_allocating(tmp_path):
    """A tiny file declaring 2^31 pixels x 40 channels (320 GiB: a MemoryError before)."""
    names = [f"c{i:02d}" for i in range(40)]
    for compression in ("none", "zip"):
        good = exr.encode({n: np.zeros((1, 1), np.float32) for n in names}, compression=compression)
        data = _rebuild(good, {"dataWindow": ("box2i", struct.pack("<4i", 0, 0, 2**31 - 1, 0))})
        path = tmp_path / f"huge_{compression}.exr"
        path.write_bytes(data)
        with pytest.raises(exr.ExrError) as info:
            exr.read(path)
        text = _one_line_naming(info, path)
        assert f"declares 343,597,383,680 bytes of pixels (2147483648 x 1, 40 channels), more than a " \
               f"'{compression}' file of {len(data):,} bytes can hold" in text, text


def test_the_size_limit_is_checked_before_reading(tmp_path, monkeypatch):
    path = tmp_path / "a.exr"
    exr.write(path, {"Y": np.zeros((37, 29), np.float32)})
    monkeypatch.setenv("TOFCORE_MAX_EXR_BYTES", str(path.stat().st_size - 1))
    with pytest.raises(exr.ExrError) as info:
        exr.read(path)
    assert "TOFCORE_MAX_EXR_BYTES" in _one_line_naming(info, path)
    monkeypatch.setenv("TOFCORE_MAX_EXR_BYTES", str(path.stat().st_size))
    with pytest.raises(exr.ExrError) as info:  # the file fits; its 37 x 29 x 4 bytes of pixels do not
        exr.read(path)
    assert "the header declares 4,292 bytes of pixels" in _one_line_naming(info, path)


def test_a_folder_is_not_read_as_an_exr_file(tmp_path):
    with pytest.raises(exr.ExrError) as info:
        exr.read(tmp_path)
    assert "not a regular file" in _one_line_naming(info, tmp_path)


@pytest.mark.parametrize("name, kind, value", [
    ("dataWindow", "int", struct.pack("<i", 7)),
    ("dataWindow", "string", b"0 0 28 36"),
    ("channels", "string", b"depth"),
    ("compression", "int", struct.pack("<i", 3)),
    ("lineOrder", "float", struct.pack("<f", 0.0)),
    ("displayWindow", "v2i", struct.pack("<2i", 1, 1)),
])
def test_a_wrongly_typed_standard_attribute_is_refused_by_name(tmp_path, name, kind, value):
    path = tmp_path / "typed.exr"
    path.write_bytes(_rebuild(exr.encode(channels()), {name: (kind, value)}))
    for reader in (exr.read, exr.read_header, exr.check):
        with pytest.raises(exr.ExrError) as info:
            reader(path)
        text = _one_line_naming(info, path)
        assert f"attribute {name!r} must be of type " in text and f"got {kind!r}" in text, text


def test_check_reads_no_pixels_but_finds_what_read_finds(tmp_path):
    path = tmp_path / "a.exr"
    good = exr.encode(channels())
    path.write_bytes(good)
    exr.check(path)
    end = exr._Reader(good, "x").header()[1]
    path.write_bytes(good[:end] + struct.pack("<Q", len(good) + 5) + good[end + 8:])
    with pytest.raises(exr.ExrError) as info:
        exr.check(path)
    assert "truncated EXR: a chunk's header runs past the end" in _one_line_naming(info, path)


def _mutations(good: bytes, rng: np.random.Generator):
    """Hostile variants of ``good``: header fields, the chunk table, the chunks' headers and streams."""
    reader = exr._Reader(good, "x")
    _, end, raw = reader.header()
    count = _chunk_count(good)
    offsets = np.frombuffer(good[end:end + 8 * count], "<u8").copy()
    int32 = lambda: [0, 1, -1, 2**31 - 1, -2**31, 16, 2**16, int(rng.integers(-2**31, 2**31))][int(rng.integers(8))]

    def patched(at: int, fmt: str, *values) -> bytes:
        body = bytearray(good)
        body[at:at + struct.calcsize(fmt)] = struct.pack(fmt, *values)
        return bytes(body)

    kind = int(rng.integers(9))
    if kind == 0:  # the dataWindow
        return _rebuild(good, {"dataWindow": ("box2i", struct.pack("<4i", *(int32() for _ in range(4))))})
    if kind == 1:  # a standard attribute typed or sized otherwise
        name = str(rng.choice(["channels", "compression", "dataWindow", "lineOrder", "displayWindow"]))
        kinds = ["int", "string", "box2i", "chlist", "compression", "v2f", "float", "lineOrder"]
        return _rebuild(good, {name: (str(rng.choice(kinds)), rng.bytes(int(rng.integers(0, 24))))})
    if kind == 2:  # the channel list: pixel types, sampling, truncation
        value = bytearray(raw["channels"][1])
        value[int(rng.integers(len(value)))] = int(rng.integers(256))
        return _rebuild(good, {"channels": ("chlist", bytes(value[:int(rng.integers(len(value) + 1))]))})
    if kind == 3:  # the compression byte, the version and flags
        if rng.random() < 0.5:
            return _rebuild(good, {"compression": ("compression", bytes([int(rng.integers(12))]))})
        return patched(4, "<i", int32())
    if kind == 4:  # an offset
        choices = [0, len(good), 2**64 - 1, int(rng.integers(len(good)))]
        offsets[int(rng.integers(count))] = choices[int(rng.integers(4))]
        return good[:end] + offsets.astype("<u8").tobytes() + good[end + 8 * count:]
    if kind == 5:  # a chunk's line or size
        at = int(offsets[int(rng.integers(count))]) + int(rng.integers(2)) * 4
        return patched(at, "<i", int32())
    if kind == 6:  # a chunk's stream: more (a bomb), less, or garbage
        at = int(offsets[int(rng.integers(count))])
        stream = zlib.compress(rng.bytes(int(rng.integers(0, 64))) + bytes(int(rng.integers(0, 1 << 20))))
        return good[:at] + struct.pack("<ii", struct.unpack("<i", good[at:at + 4])[0], len(stream)) + stream
    if kind == 7:  # an attribute's size
        at = good.index(str(rng.choice(list(raw))).encode() + b"\0")
        at = good.index(b"\0", good.index(b"\0", at) + 1) + 1
        return patched(at, "<i", int32())
    return good[:int(rng.integers(len(good)))]  # truncated anywhere


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_fuzzed_headers_and_chunk_tables_give_one_line_or_the_right_shapes(compression):
    """Seeded: 300 mutations per compression of a 4-channel file (a few seconds in all). Every outcome is
    arrays of the dataWindow's shape or one ExrError naming the file; memory stays bounded by the file."""
    import tracemalloc

    rng = np.random.default_rng(35)
    good = exr.encode(channels(height=20, width=7), attributes={"note": "x"}, compression=compression)
    outcomes = {"read": 0, "refused": 0}
    for case in range(300):
        data = _mutations(good, rng)
        tracemalloc.start()
        try:
            try:
                got = exr.decode(data, where="fuzz.exr")
            except exr.ExrError as err:
                text = str(err)
                assert text.startswith("fuzz.exr: ") and "\n" not in text, (case, text)
                outcomes["refused"] += 1
            else:
                window = exr._Reader(data, "x").header()[0]["dataWindow"]
                shape = (int(window[3]) - int(window[1]) + 1, int(window[2]) - int(window[0]) + 1)
                assert all(a.shape == shape for a in got.values()), case
                outcomes["read"] += 1
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 16 * len(data) + (4 << 20), (case, peak)
    assert outcomes["refused"] > 100, outcomes
