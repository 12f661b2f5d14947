"""The README's demo picture from what ``make demo`` wrote: its ``depth.png`` beside its ``intensity.png``.

Run ``make demo`` first (it writes ``out/demo/``), then::

    python examples/demo_picture.py out/demo docs/images/estimator_demo.png

The picture holds nothing but the two previews of that render, side by side on white; its PNG text
chunks record the command that rendered it (``Command``, the Makefile's ``demo`` recipe) and the frame's
numbers (``Summary``: spp, estimated render noise, render time, from ``frame.json``), which
``tests/tofcore/test_demo_picture.py`` checks against the Makefile. Needs OpenCV (``cv2``) to read the
previews.
"""

from __future__ import annotations

import argparse
import json
import re
import zlib
from pathlib import Path

import numpy as np

from tofcore.output.png import encode_png

REPO = Path(__file__).resolve().parents[1]
GAP_PX = 8


def demo_command(makefile: Path = REPO / "Makefile") -> str:
    """The ``tofcore render …`` line of the Makefile's ``demo`` recipe, ``$(PY) -m tofcore`` as ``tofcore``."""
    recipe = re.search(r"^demo:.*\n\t(.+)$", makefile.read_text(encoding="utf-8"), re.M)
    if recipe is None:
        raise SystemExit(f"{makefile}: no demo recipe")
    return recipe.group(1).replace("$(PY) -m tofcore", "tofcore").strip()


def summary(document: dict) -> str:
    """The frame's numbers in one line, from its ``frame.json``."""
    stats = document["stats"]
    est = stats["convergence"][-1]["est_depth_error_m"]
    return f"{stats['spp']} spp, estimated render noise {est * 1000:.2f} mm RMS, {stats['seconds']:.1f} s"


def text_chunk(key: str, value: str) -> bytes:
    """A PNG ``tEXt`` chunk (Latin-1 key and text)."""
    data = key.encode("latin-1") + b"\0" + value.encode("latin-1", "replace")
    return len(data).to_bytes(4, "big") + b"tEXt" + data + zlib.crc32(b"tEXt" + data).to_bytes(4, "big")


def with_text(png: bytes, chunks: dict[str, str]) -> bytes:
    """``png`` with ``tEXt`` chunks inserted before its ``IEND`` chunk (the last 12 bytes)."""
    return png[:-12] + b"".join(text_chunk(k, v) for k, v in chunks.items()) + png[-12:]


def read_text(png: bytes) -> dict[str, str]:
    """The ``tEXt`` chunks of a PNG file's bytes."""
    out, at = {}, 8
    while at + 8 <= len(png):
        length, kind = int.from_bytes(png[at:at + 4], "big"), png[at + 4:at + 8]
        if kind == b"tEXt":
            key, _, value = png[at + 8:at + 8 + length].partition(b"\0")
            out[key.decode("latin-1")] = value.decode("latin-1")
        at += 12 + length
    return out


def compose(depth: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """(H, W_d + GAP_PX + W_i, 3) uint8: the two previews side by side on white, tops aligned."""
    def rgb(image):
        return np.repeat(image[..., None], 3, axis=2) if image.ndim == 2 else image[..., :3]

    left, right = rgb(depth), rgb(intensity)
    height = max(left.shape[0], right.shape[0])
    out = np.full((height, left.shape[1] + GAP_PX + right.shape[1], 3), 255, np.uint8)
    out[:left.shape[0], :left.shape[1]] = left
    out[:right.shape[0], left.shape[1] + GAP_PX:] = right
    return out


def main() -> None:
    import cv2

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("demo", type=Path, help="the folder `make demo` wrote (out/demo)")
    parser.add_argument("picture", type=Path, help="the PNG to write (docs/images/estimator_demo.png)")
    args = parser.parse_args()
    depth = cv2.cvtColor(cv2.imread(str(args.demo / "depth.png"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    intensity = cv2.imread(str(args.demo / "intensity.png"), cv2.IMREAD_GRAYSCALE)
    document = json.loads((args.demo / "frame.json").read_text())
    picture = with_text(encode_png(compose(depth, intensity)),
                        {"Command": demo_command(), "Summary": summary(document),
                         "Source": "depth.png and intensity.png of that render (examples/demo_picture.py)"})
    args.picture.write_bytes(picture)
    print(f"wrote {args.picture}: {summary(document)}")


if __name__ == "__main__":
    main()
