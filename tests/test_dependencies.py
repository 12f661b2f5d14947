"""What the project installs: OpenCV as the contrib build (cv2.ximgproc), pinned for NumPy 1.26; tqdm.

OpenCV stays optional for tofcore (NumPy fall-backs, tested in the module tests); where it is installed
from requirements-dev.txt it must be the contrib build, alone (the plain build shares its cv2 folder).
"""

from __future__ import annotations

import importlib.metadata
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
CONTRIB = "opencv-contrib-python-headless"
PLAIN = ("opencv-python-headless", "opencv-python", "opencv-contrib-python")


def _requirements() -> dict[str, str]:
    """requirements-dev.txt as {name: specifier}."""
    out = {}
    for line in (REPO / "requirements-dev.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name = re.match(r"[A-Za-z0-9_.\-]+", line).group(0).lower()
            out[name] = line[len(name):].split(";")[0].strip()
    return out


def _installed(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def test_requirements_name_the_contrib_build_pinned_for_numpy_1_26():
    req = _requirements()
    assert req.get(CONTRIB) == "==4.11.0.86"        # 4.12+ require numpy>=2; bpy 5.0 needs numpy<2
    assert not set(PLAIN) & set(req)
    assert "tqdm" in req
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert any(d.startswith("tqdm") for d in project["dependencies"])
    for extra in ("cv", "test"):
        names = [re.match(r"[A-Za-z0-9_.\-]+", d).group(0) for d in project["optional-dependencies"][extra]]
        assert CONTRIB in names and not set(PLAIN) & set(names), extra
    numpy2 = next(line for line in (REPO / "Makefile").read_text().splitlines() if '"numpy>=2"' in line)
    assert CONTRIB in numpy2.split() and not set(PLAIN) & set(numpy2.split())    # make test-numpy2


def test_cv2_has_the_contrib_modules():
    cv2 = pytest.importorskip("cv2")
    if _installed(CONTRIB) is None:
        pytest.skip(f"cv2 {cv2.__version__} is not from {CONTRIB} (an environment made before the switch: "
                    f"`make venv` replaces it)")
    both = [name for name in PLAIN if _installed(name) is not None]
    assert not both, f"{both} installed beside {CONTRIB}: they share the cv2 folder (`make venv` removes them)"
    assert hasattr(cv2, "ximgproc"), f"cv2 {cv2.__version__} has no ximgproc"
    guide = np.tile(np.linspace(0, 1, 16, dtype=np.float32), (12, 1))
    image = guide + np.float32(0.1) * (np.indices(guide.shape).sum(axis=0) % 2).astype(np.float32)
    guided = cv2.ximgproc.guidedFilter(guide, image, 2, 1e-3)
    bilateral = cv2.ximgproc.jointBilateralFilter(guide, image, 5, 0.1, 3.0)
    for out in (guided, bilateral):
        assert out.shape == image.shape and np.isfinite(out).all()
        assert np.abs(np.diff(out, axis=0)).mean() < np.abs(np.diff(image, axis=0)).mean()   # the checkerboard smoothed
