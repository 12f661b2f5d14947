"""The README's demo picture is what ``make demo`` renders (issue 36: it showed an older study, 6.4 mm).

``examples/demo_picture.py`` makes it from that render's previews and records the command in the PNG;
this checks the record against the Makefile and the README, not the pixels (the render takes minutes).
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PICTURE = REPO / "docs" / "images" / "estimator_demo.png"

_spec = importlib.util.spec_from_file_location("demo_picture", REPO / "examples" / "demo_picture.py")
demo_picture = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(demo_picture)


def test_the_readme_demo_picture_records_the_make_demo_command_and_its_numbers():
    text = demo_picture.read_text(PICTURE.read_bytes())
    command = demo_picture.demo_command()
    assert command.startswith("tofcore render --scene room --preset kinect_v2 --spp 64 --target-error 2mm")
    assert text.get("Command") == command, "the picture is not from `make demo`: run examples/demo_picture.py"
    spp_max = int(re.search(r"--spp (\d+)", command).group(1))
    summary = re.fullmatch(r"(\d+) spp, estimated render noise ([\d.]+) mm RMS, [\d.]+ s", text["Summary"])
    assert summary and int(summary.group(1)) <= spp_max and float(summary.group(2)) <= 2.0, text["Summary"]
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert "docs/images/estimator_demo.png" in readme


def test_text_chunks_round_trip():
    png = demo_picture.with_text(demo_picture.encode_png(__import__("numpy").zeros((2, 3, 3), "uint8")),
                                 {"Command": "tofcore render", "Summary": "1 spp"})
    assert demo_picture.read_text(png) == {"Command": "tofcore render", "Summary": "1 spp"}
    import zlib

    assert png.endswith(b"IEND" + zlib.crc32(b"IEND").to_bytes(4, "big"))
