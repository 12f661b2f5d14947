"""OpenEXR files with NumPy and the standard library: scanline images, no native library.

tofcore writes and reads its EXR files with this module instead of the ``OpenEXR`` package, so
that no second OpenEXR library is ever loaded into a host process that has its own (Blender:
issue 19, where the wheel's calls were resolved against Blender's ``libOpenEXRCore`` and
Blender crashed). It covers the single-part scanline subset of the OpenEXR 2 file layout
("OpenEXR File Layout", openexr.com):

=====================  ==========================================================================
part                   layout (all numbers little-endian)
=====================  ==========================================================================
magic, version         ``76 2f 31 01``; int32 ``2 | flags``; flag ``0x400`` = long names (attribute
                       and channel names up to 255 bytes instead of 31), set only when needed
header                 attributes ``name\\0 type\\0 int32 size value``, ended by one ``\\0``
offset table           one uint64 file offset per chunk, ``ceil(height / lines_per_chunk)`` chunks
chunk                  int32 y of its first line, int32 data size, data
data (uncompressed)    for each line of the chunk, for each channel in name order, the line's pixels
=====================  ==========================================================================

Compressions (``compression`` of :func:`write`; :func:`read` takes all three):

============  ==================  ===============================================================
name          lines per chunk     data
============  ==================  ===============================================================
``"none"``    1                   as above
``"zips"``    1                   zlib of the predicted, interleaved bytes (below)
``"zip"``     16                  same, 16 lines a chunk (tofcore's default: lossless, ~2× smaller)
============  ==================  ===============================================================

ZIP/ZIPS: the chunk's bytes ``b`` are split into even and odd positions,
``t = b[0::2] ‖ b[1::2]``, then delta-coded, ``d[0] = t[0]``,
``d[i] = (t[i] − t[i−1] + 128) mod 256``, and compressed with zlib. A chunk that would not
get smaller is stored as it is (its size then equals the uncompressed size, which is how a
reader tells).

Channels: ``float32`` arrays are FLOAT, ``float16`` HALF, ``uint32`` UINT; every channel is
(H, W), sampled 1 × 1. Header attributes beyond the required ones (written by :func:`write`
from the image size and compression) come from Python values:

===============================  ==========  ==================================================
value                            EXR type    read back as
===============================  ==========  ==================================================
``str``                          string      ``str`` (UTF-8)
``int``                          int         ``int``
``float``                        double      ``float`` (exact; type ``float`` is read too)
NumPy (2,) / (3,) int32          v2i / v3i   int32 array
NumPy (2,) / (3,) float32/64     v2f/d, v3f/d  float32 / float64 array
NumPy (3, 3) / (4, 4) float32/64  m33f/d, m44f/d  float32 / float64 array
===============================  ==========  ==================================================

:func:`read_header` returns every attribute: the types above, the standard ones (``channels``
as ``{name: "FLOAT"|"HALF"|"UINT"}``, ``compression`` as its name, ``dataWindow``/
``displayWindow`` as int32 ``[x_min, y_min, x_max, y_max]``, ``lineOrder`` as its name), and any
other type as ``bytes``. Not covered (a one-line error naming the file): tiled,
multi-part and deep files, sub-sampled channels, and the RLE, PIZ, PXR24, B44, DWA compressions.

Reading hostile files
---------------------
Every file that cannot be read is one :class:`~tofcore.errors.ExrError` (a ``TofError`` and a
``ValueError``), one line ``"{path}: {defect}"``: not an EXR file, truncated, damaged, of a kind
not covered, or declaring more than it holds. A read takes memory bounded by what the file holds:

* the file must be a regular file of at most :data:`tofcore.limits.MAX_EXR_BYTES` (4 GiB,
  ``TOFCORE_MAX_EXR_BYTES``);
* the standard attributes must have their standard types (``dataWindow`` a ``box2i``, …), named
  when one does not;
* the pixel bytes the header declares (dataWindow × channels) are checked before anything is
  allocated: at most the file's size when stored as they are, at most :data:`DEFLATE_MAX_RATIO`
  (1032, deflate's largest ratio) times it for ZIP/ZIPS, and at most ``MAX_EXR_BYTES``;
* every chunk inflates at most the bytes of its lines (zlib's ``max_length``); a stream holding
  more (a ZIP bomb) is refused there, so the peak is the image plus one chunk;
* every offset, size and chunk line is checked against the file and the dataWindow.

:func:`check` does all but the inflating (``tofcore-batch verify`` uses it).

Example
-------
>>> from tofcore import exr
>>> exr.write("depth.exr", {"Y": depth.astype(np.float32)}, attributes={"units": "m"})  # doctest: +SKIP
>>> exr.read("depth.exr")["Y"].shape                                                       # doctest: +SKIP
(424, 512)
"""

from __future__ import annotations

import math
import os
import secrets
import stat
import struct
import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from .. import limits
from ..errors import ExrError

MAGIC = b"\x76\x2f\x31\x01"
VERSION = 2
LONG_NAMES_FLAG = 0x400
TILED_FLAG, DEEP_FLAG, MULTIPART_FLAG = 0x200, 0x800, 0x1000
SHORT_NAME_MAX, LONG_NAME_MAX = 31, 255

#: Compression name → (code in the file, lines per chunk).
COMPRESSIONS = {"none": (0, 1), "zips": (2, 1), "zip": (3, 16)}
_COMPRESSION_NAMES = {0: "none", 1: "rle", 2: "zips", 3: "zip", 4: "piz", 5: "pxr24", 6: "b44", 7: "b44a",
                      8: "dwaa", 9: "dwab"}
#: Pixel type code → NumPy dtype and name.
_PIXEL_TYPES = {0: (np.dtype("<u4"), "UINT"), 1: (np.dtype("<f2"), "HALF"), 2: (np.dtype("<f4"), "FLOAT")}
_PIXEL_CODES = {np.dtype(np.uint32): 0, np.dtype(np.float16): 1, np.dtype(np.float32): 2}
_LINE_ORDERS = {0: "increasing_y", 1: "decreasing_y", 2: "random_y"}
#: zlib level of ZIP/ZIPS chunks (OpenEXR's default since 3.1).
ZLIB_LEVEL = 4

# Fixed-size attribute types: type name → (struct format, NumPy dtype, shape) of the value.
_ARRAY_TYPES = {
    "v2i": ("<i4", (2,)), "v2f": ("<f4", (2,)), "v2d": ("<f8", (2,)),
    "v3i": ("<i4", (3,)), "v3f": ("<f4", (3,)), "v3d": ("<f8", (3,)),
    "m33f": ("<f4", (3, 3)), "m33d": ("<f8", (3, 3)), "m44f": ("<f4", (4, 4)), "m44d": ("<f8", (4, 4)),
    "box2i": ("<i4", (4,)), "box2f": ("<f4", (4,)),
}
_STANDARD = ("channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
             "screenWindowCenter", "screenWindowWidth")


# --------------------------------------------------------------------------- public API

def write(path: str | os.PathLike, channels: Mapping[str, np.ndarray], *,
          attributes: Mapping[str, object] | None = None, compression: str = "zip") -> None:
    """Write a scanline EXR atomically: a temp file beside ``path``, then ``os.replace``.

    Parameters
    ----------
    path : the file (any str, bytes or path-like name; opened by Python).
    channels : ``{name: (H, W) array}``, float32 (FLOAT), float16 (HALF) or uint32 (UINT), all one shape.
    attributes : extra header attributes (table in the module docstring); not a standard name.
    compression : ``"zip"`` (default), ``"zips"`` or ``"none"``.

    Notes
    -----
    On any failure the temp file is removed and ``path`` is left as it was.
    """
    data = encode(channels, attributes=attributes, compression=compression)
    folder, name = os.path.split(os.fsdecode(os.fspath(path)))
    tmp = os.path.join(folder, f".{name}.tmp-{secrets.token_hex(4)}")
    try:
        with open(tmp, "xb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, os.path.join(folder, name))
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def read(path: str | os.PathLike, names: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """Channels of a scanline EXR as ``{name: (H, W) array}`` (float32, float16 or uint32).

    ``names`` picks channels, in that order (a missing one is an ``ExrError`` naming the file and
    the channels it holds); None reads all, in the file's (name) order. A file that cannot be read is
    one :class:`~tofcore.errors.ExrError` (a ``ValueError``) naming it and the defect.
    """
    where = _where(path)
    return decode(_read_file(path, where), names, where=where)


def read_header(path: str | os.PathLike) -> dict[str, object]:
    """Every header attribute of an EXR file (types in the module docstring)."""
    where = _where(path)
    return _Reader(_read_file(path, where), where).header()[0]


def check(path: str | os.PathLike) -> None:
    """Raise :class:`~tofcore.errors.ExrError` unless ``path`` is an EXR file :func:`read` can read, as far
    as its header, declared sizes, offset table and chunk headers tell (the pixels are not inflated)."""
    where = _where(path)
    _Reader(_read_file(path, where), where).check()


def encode(channels: Mapping[str, np.ndarray], *, attributes: Mapping[str, object] | None = None,
           compression: str = "zip") -> bytes:
    """The bytes of the EXR file :func:`write` writes."""
    if compression not in COMPRESSIONS:
        raise ValueError(f"exr: compression must be one of {sorted(COMPRESSIONS)}, got {compression!r}")
    arrays = _check_channels(channels)
    height, width = next(iter(arrays.values())).shape
    code, lines = COMPRESSIONS[compression]
    window = np.array([0, 0, width - 1, height - 1], np.int32)
    header = {
        "channels": ("chlist", _chlist(arrays)),
        "compression": ("compression", bytes([code])),
        "dataWindow": ("box2i", window.tobytes()),
        "displayWindow": ("box2i", window.tobytes()),
        "lineOrder": ("lineOrder", b"\x00"),
        "pixelAspectRatio": ("float", struct.pack("<f", 1.0)),
        "screenWindowCenter": ("v2f", struct.pack("<2f", 0.0, 0.0)),
        "screenWindowWidth": ("float", struct.pack("<f", 1.0)),
    }
    for name, value in (attributes or {}).items():
        if name in _STANDARD:
            raise ValueError(f"exr: attribute {name!r} is written from the image; leave it out of attributes")
        header[name] = _attribute(name, value)
    long_names = any(len(n.encode()) > SHORT_NAME_MAX for n in arrays) or any(
        len(n.encode()) > SHORT_NAME_MAX or len(t.encode()) > SHORT_NAME_MAX for n, (t, _) in header.items())
    head = bytearray(MAGIC + struct.pack("<i", VERSION | (LONG_NAMES_FLAG if long_names else 0)))
    for name in sorted(header):
        kind, value = header[name]
        head += name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value
    head += b"\0"
    rows = _scanlines(arrays)
    chunks = [_compress(rows[y:y + lines].tobytes(), code) for y in range(0, height, lines)]
    offsets, position = [], len(head) + 8 * len(chunks)
    for chunk in chunks:
        offsets.append(position)
        position += 8 + len(chunk)
    parts = [bytes(head), np.asarray(offsets, "<u8").tobytes()]
    for y, chunk in zip(range(0, height, lines), chunks):
        parts += [struct.pack("<ii", y, len(chunk)), chunk]
    return b"".join(parts)


def decode(data: bytes, names: Iterable[str] | None = None, *, where: str = "exr") -> dict[str, np.ndarray]:
    """Channels of the EXR file bytes ``data`` (see :func:`read`); ``where`` names it in errors."""
    return _Reader(data, where).pixels(names)


# --------------------------------------------------------------------------- writing

def _check_channels(channels: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``{name: little-endian C-contiguous (H, W) array}`` in name order, or ValueError."""
    if not channels:
        raise ValueError("exr: channels must hold at least one (H, W) array, got none")
    for name in channels:
        if not isinstance(name, str) or not name or "\0" in name or len(name.encode()) > LONG_NAME_MAX:
            raise ValueError(f"exr: channel names must be 1-{LONG_NAME_MAX} bytes without NUL, got {name!r}")
    arrays, shape = {}, None
    for name in sorted(channels, key=str.encode):   # the file's channel order: by name, bytewise
        array = np.asarray(channels[name])
        if array.dtype not in _PIXEL_CODES:
            raise ValueError(f"exr: channel {name!r} must be float32, float16 or uint32, got {array.dtype}")
        if array.ndim != 2 or 0 in array.shape or (shape is not None and array.shape != shape):
            raise ValueError(f"exr: channel {name!r} must be a non-empty (H, W) array "
                             f"{'like the others ' + str(shape) if shape else ''}, got shape {array.shape}")
        shape = array.shape
        arrays[name] = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))
    return arrays


def _chlist(arrays: Mapping[str, np.ndarray]) -> bytes:
    """The ``chlist`` value: per channel name\\0, int32 pixel type, uint8 pLinear, 3 zero bytes,
    int32 x and y sampling (1); then \\0."""
    entries = [name.encode() + b"\0" + struct.pack("<iB3xii", _PIXEL_CODES[a.dtype.newbyteorder("=")], 0, 1, 1)
               for name, a in arrays.items()]
    return b"".join(entries) + b"\0"


def _attribute(name: str, value: object) -> tuple[str, bytes]:
    """(EXR type, value bytes) of an extra attribute, or ValueError naming it."""
    if not isinstance(name, str) or not name or "\0" in name or len(name.encode()) > LONG_NAME_MAX:
        raise ValueError(f"exr: attribute names must be 1-{LONG_NAME_MAX} bytes without NUL, got {name!r}")
    if isinstance(value, str):
        return "string", value.encode("utf-8")
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"exr: attribute {name!r}: a bool has no EXR type; store 0/1 as int")
    if isinstance(value, (int, np.integer)):
        if not -2**31 <= int(value) < 2**31:
            raise ValueError(f"exr: attribute {name!r} must fit int32, got {value!r}")
        return "int", struct.pack("<i", int(value))
    if isinstance(value, (float, np.floating)):
        return "double", struct.pack("<d", float(value))
    array = np.asarray(value)
    kind = {np.dtype(np.int32): "i", np.dtype(np.float32): "f", np.dtype(np.float64): "d"}.get(array.dtype)
    prefix = {(2,): "v2", (3,): "v3", (3, 3): "m33", (4, 4): "m44"}.get(array.shape)
    if kind is None or prefix is None or (kind == "i" and prefix.startswith("m")):
        raise ValueError(f"exr: attribute {name!r} must be str, int, float or an int32/float32/float64 array "
                         f"of shape (2,), (3,), (3, 3) or (4, 4), got {type(value).__name__} "
                         f"{getattr(array, 'dtype', '')} {array.shape}")
    return prefix + kind, array.astype(array.dtype.newbyteorder("<")).tobytes()


def _scanlines(arrays: Mapping[str, np.ndarray]) -> np.ndarray:
    """(H, bytes per line) uint8: each line holds every channel's pixels in name order."""
    height = next(iter(arrays.values())).shape[0]
    return np.concatenate([a.view(np.uint8).reshape(height, -1) for a in arrays.values()], axis=1)


def _compress(raw: bytes, code: int) -> bytes:
    """One chunk's stored bytes: raw for NO_COMPRESSION, else zlib of the predicted, interleaved bytes
    (raw again when that is not smaller)."""
    if code == 0:
        return raw
    b = np.frombuffer(raw, np.uint8)
    t = np.concatenate([b[0::2], b[1::2]])
    d = np.empty_like(t)
    d[0] = t[0]
    d[1:] = np.diff(t) + np.uint8(128)  # uint8 arithmetic: mod 256
    packed = zlib.compress(d.tobytes(), ZLIB_LEVEL)
    return packed if len(packed) < len(raw) else raw


def _uncompress(stored: bytes, size: int, code: int, where: str) -> np.ndarray:
    """The chunk's ``size`` raw bytes (inverse of :func:`_compress`); zlib inflates at most ``size`` bytes
    (``max_length``), and a stream that holds more is refused before it is inflated further."""
    if code == 0 or size == 0 or len(stored) == size:
        if len(stored) != size:
            raise ExrError(f"{where}: damaged EXR: a chunk holds {len(stored)} bytes, expected {size}")
        return np.frombuffer(stored, np.uint8)
    inflater = zlib.decompressobj()
    try:
        d = inflater.decompress(stored, size)
        more = b"" if inflater.eof else inflater.decompress(inflater.unconsumed_tail, 1)
    except zlib.error as err:
        raise ExrError(f"{where}: damaged EXR: a ZIP chunk does not decompress ({err})") from None
    if more:
        raise ExrError(f"{where}: damaged EXR: a ZIP chunk inflates to more than the {size:,} bytes its lines "
                       f"hold (refused after {size:,})")
    if len(d) != size or not inflater.eof:
        raise ExrError(f"{where}: damaged EXR: a ZIP chunk holds {len(d)} bytes"
                       f"{'' if inflater.eof else ' and no end of stream'}, expected {size}")
    d = np.frombuffer(d, np.uint8).copy()
    d[1:] -= np.uint8(128)
    t = np.cumsum(d, dtype=np.uint8)  # mod 256
    b = np.empty_like(t)
    half = (size + 1) // 2
    b[0::2], b[1::2] = t[:half], t[half:]
    return b


# --------------------------------------------------------------------------- reading

def _where(path: str | os.PathLike) -> str:
    path = os.fspath(path)
    return os.fsdecode(path) if isinstance(path, bytes) else path


def _read_file(path: str | os.PathLike, where: str) -> bytes:
    """The bytes of a regular file of at most :data:`tofcore.limits.MAX_EXR_BYTES` (``/dev/zero`` or a FIFO
    would never end); ``OSError`` (a missing file) reaches the caller."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))  # a FIFO: no wait
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            kind = "folder" if stat.S_ISDIR(info.st_mode) else "special file"
            raise ExrError(f"{where}: not an OpenEXR file (a {kind}, not a regular file)")
        if limits.MAX_EXR_BYTES.exceeded(info.st_size):
            raise ExrError(f"{where}: an EXR file must be {limits.MAX_EXR_BYTES.describe()}, got "
                           f"{info.st_size:,} bytes")
        with open(fd, "rb", closefd=False) as fh:
            return fh.read(info.st_size)
    finally:
        os.close(fd)


#: Standard attributes and the one type each must have (OpenEXR's ``ImfStandardAttributes``); a file
#: that types one otherwise is refused by name.
_STANDARD_TYPES = {"channels": "chlist", "compression": "compression", "dataWindow": "box2i",
                   "displayWindow": "box2i", "lineOrder": "lineOrder", "pixelAspectRatio": "float",
                   "screenWindowCenter": "v2f", "screenWindowWidth": "float"}
_REQUIRED = ("channels", "compression", "dataWindow", "lineOrder")
#: Most bytes deflate can give per stored byte (RFC 1951: a 258-byte match in as little as 2 bits ⇒ 1032:1).
DEFLATE_MAX_RATIO = 1032


class _Reader:
    """Bounds-checked parsing of one file's bytes; every problem is an :class:`ExrError` naming ``where``.

    Memory is bounded by the file: the pixel bytes the header declares are checked against the file's
    size (stored as they are: equal; ZIP: at most :data:`DEFLATE_MAX_RATIO` times) and against
    :data:`tofcore.limits.MAX_EXR_BYTES` before anything is allocated, and each chunk inflates at most
    the bytes of its lines.
    """

    def __init__(self, data: bytes, where: str) -> None:
        self.data, self.where = memoryview(data), where

    def _fail(self, what: str) -> ExrError:
        return ExrError(f"{self.where}: {what}")

    def _take(self, position: int, size: int, what: str) -> bytes:
        if size < 0:
            raise self._fail(f"damaged EXR: {what} has a negative size ({size})")
        if position + size > len(self.data):
            raise self._fail(f"truncated EXR: {what} runs past the end of the file ({len(self.data)} bytes)")
        return bytes(self.data[position:position + size])

    def _name(self, position: int, limit: int, what: str) -> tuple[str, int]:
        end = bytes(self.data[position:position + limit + 1]).find(b"\0")
        if end < 0 and position + limit + 1 > len(self.data):
            raise self._fail(f"truncated EXR: {what} runs past the end of the file ({len(self.data)} bytes)")
        if end < 0:
            raise self._fail(f"damaged EXR: {what} is not NUL-terminated within {limit} bytes")
        return bytes(self.data[position:position + end]).decode("utf-8", "replace"), position + end + 1

    def header(self) -> tuple[dict[str, object], int, dict[str, tuple[str, bytes]]]:
        """(attributes decoded, offset after the header, raw ``{name: (type, bytes)}``)."""
        if self._take(0, 4, "the magic number") != MAGIC:
            raise self._fail("not an OpenEXR file (magic number 76 2f 31 01 missing)")
        version = struct.unpack("<i", self._take(4, 4, "the version"))[0]
        if version & 0xFF != VERSION:
            raise self._fail(f"EXR version {version & 0xFF} is not supported (only 2)")
        for flag, what in ((TILED_FLAG, "tiled"), (DEEP_FLAG, "deep"), (MULTIPART_FLAG, "multi-part")):
            if version & flag:
                raise self._fail(f"{what} EXR files are not supported (scanline, single part only)")
        limit = LONG_NAME_MAX if version & LONG_NAMES_FLAG else SHORT_NAME_MAX
        raw, position = {}, 8
        while True:
            if self._take(position, 1, "the header")[0] == 0:
                position += 1
                break
            name, position = self._name(position, limit, "an attribute name")
            kind, position = self._name(position, limit, f"the type of attribute {name!r}")
            size = struct.unpack("<i", self._take(position, 4, f"the size of attribute {name!r}"))[0]
            raw[name] = (kind, self._take(position + 4, size, f"attribute {name!r}"))
            position += 4 + size
        missing = [name for name in _REQUIRED if name not in raw]
        if missing:
            raise self._fail(f"damaged EXR: the header lacks {missing}")
        for name, kind in _STANDARD_TYPES.items():
            if name in raw and raw[name][0] != kind:
                raise self._fail(f"damaged EXR: attribute {name!r} must be of type {kind}, got {raw[name][0]!r}")
        return {name: self._value(name, kind, value) for name, (kind, value) in raw.items()}, position, raw

    def _value(self, name: str, kind: str, value: bytes) -> object:
        try:
            if kind == "string":
                return value.decode("utf-8", "replace")
            if kind == "int":
                return struct.unpack("<i", value)[0]
            if kind in ("float", "double"):
                return struct.unpack("<f" if kind == "float" else "<d", value)[0]
            if kind in _ARRAY_TYPES:
                dtype, shape = _ARRAY_TYPES[kind]
                return np.frombuffer(value, dtype).reshape(shape).astype(np.dtype(dtype).newbyteorder("="))
            if kind == "compression":
                return _COMPRESSION_NAMES.get(value[0], f"unknown ({value[0]})")
            if kind == "lineOrder":
                return _LINE_ORDERS.get(value[0], f"unknown ({value[0]})")
        except (struct.error, ValueError, IndexError):
            raise self._fail(f"damaged EXR: attribute {name!r} of type {kind} holds {len(value)} bytes") from None
        if kind == "chlist":
            return {name: _PIXEL_TYPES[code][1] for name, (code, _, _) in self._channels(value).items()}
        return value

    def _channels(self, value: bytes) -> dict[str, tuple[int, int, int]]:
        """``{name: (pixel type, x sampling, y sampling)}`` of a chlist value."""
        channels, position = {}, 0
        while position < len(value) and value[position] != 0:
            end = value.find(b"\0", position)
            if end < 0 or end + 17 > len(value):
                raise self._fail("damaged EXR: the channel list (attribute 'channels') ends inside an entry")
            name = value[position:end].decode("utf-8", "replace")
            code, _, xs, ys = struct.unpack("<iB3xii", value[end + 1:end + 17])
            if code not in _PIXEL_TYPES:
                raise self._fail(f"damaged EXR: channel {name!r} has pixel type {code} (0 UINT, 1 HALF, 2 FLOAT)")
            channels[name] = (code, xs, ys)
            position = end + 17
        if position >= len(value):
            raise self._fail("damaged EXR: the channel list (attribute 'channels') is not NUL-terminated")
        return channels

    def layout(self) -> _Layout:
        """The header's layout, the pixel bytes it declares checked against the file and the limit."""
        header, position, raw = self.header()
        channels = self._channels(raw["channels"][1])
        if any((xs, ys) != (1, 1) for _, xs, ys in channels.values()):
            raise self._fail("sub-sampled EXR channels are not supported")
        compression = header["compression"]
        if compression not in COMPRESSIONS:
            raise self._fail(f"EXR compression {compression!r} is not supported (only {sorted(COMPRESSIONS)})")
        code, lines = COMPRESSIONS[compression]
        x_min, y_min, x_max, y_max = (int(v) for v in header["dataWindow"])
        width, height = x_max - x_min + 1, y_max - y_min + 1
        if width < 1 or height < 1 or width * height > 2**31:
            raise self._fail(f"damaged EXR: dataWindow {[x_min, y_min, x_max, y_max]} is empty or too large")
        line_bytes = width * sum(_PIXEL_TYPES[c][0].itemsize for c, _, _ in channels.values())
        declared = height * line_bytes
        if declared > len(self.data) * (1 if code == 0 else DEFLATE_MAX_RATIO):
            raise self._fail(f"damaged EXR: the header declares {declared:,} bytes of pixels ({width} x {height}, "
                             f"{len(channels)} channels), more than a {compression!r} file of {len(self.data):,} "
                             f"bytes can hold")
        if limits.MAX_EXR_BYTES.exceeded(declared):
            raise self._fail(f"the header declares {declared:,} bytes of pixels ({width} x {height}, "
                             f"{len(channels)} channels); an EXR read must be {limits.MAX_EXR_BYTES.describe()}")
        return _Layout(position, channels, code, lines, y_min, width, height, line_bytes)

    def chunks(self, layout: _Layout):
        """``(index, offset of the stored data, its size)`` of every entry of the offset table, each checked to
        lie in the file and to start one of the dataWindow's chunks; then that no chunk is missing."""
        count = math.ceil(layout.height / layout.lines)
        offsets = np.frombuffer(self._take(layout.position, 8 * count, "the offset table"), "<u8")
        seen = np.zeros(count, bool)
        for offset in offsets.tolist():
            y, size = struct.unpack("<ii", self._take(offset, 8, "a chunk's header"))
            index = (y - layout.y_min) // layout.lines
            if (y - layout.y_min) % layout.lines or not 0 <= index < count:
                raise self._fail(f"damaged EXR: a chunk starts at line {y}, outside the dataWindow's "
                                 f"{layout.lines}-line chunks")
            if size < 0 or offset + 8 + size > len(self.data):
                self._take(offset + 8, size, f"the chunk of line {y}")  # raises, naming the defect
            yield index, offset + 8, size
            seen[index] = True
        if not seen.all():
            raise self._fail(f"damaged EXR: {int((~seen).sum())} of {count} chunks missing from the offset table")

    def check(self) -> None:
        """Everything but the pixels: header, declared sizes, offset table and chunk headers (no inflating)."""
        for _ in self.chunks(self.layout()):
            pass

    def pixels(self, names: Iterable[str] | None) -> dict[str, np.ndarray]:
        layout = self.layout()
        channels, lines, line_bytes = layout.channels, layout.lines, layout.line_bytes
        wanted = list(channels) if names is None else list(names)
        unknown = [n for n in wanted if n not in channels]
        if unknown:
            raise self._fail(f"channels {unknown} not in the file; it holds {sorted(channels)}")
        rows = np.empty((layout.height, line_bytes), np.uint8)
        for index, start, size in self.chunks(layout):
            first = index * lines
            n = min(lines, layout.height - first)
            stored = bytes(self.data[start:start + size])
            rows[first:first + n] = _uncompress(stored, n * line_bytes, layout.code, self.where).reshape(n, line_bytes)
        out, start = {}, 0
        for name, (code, _, _) in channels.items():
            dtype = _PIXEL_TYPES[code][0]
            size = layout.width * dtype.itemsize
            if name in wanted:
                out[name] = rows[:, start:start + size].copy().view(dtype).astype(dtype.newbyteorder("="), copy=False)
            start += size
        return {name: out[name] for name in wanted}


@dataclass(frozen=True)
class _Layout:
    """Where a file's pixels are: the offset table's position, the channels ``{name: (pixel type, x and y
    sampling)}``, the compression's code and lines per chunk, the dataWindow's first line, its size, and the
    bytes of one line of every channel."""

    position: int
    channels: dict
    code: int
    lines: int
    y_min: int
    width: int
    height: int
    line_bytes: int
