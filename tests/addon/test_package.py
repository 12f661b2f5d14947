"""The extension package: manifest, addon/build.py, and installing the built zip into ``bpy``.

Blender's own extension tool (``blender_ext.py``) ships inside the bpy wheel,
so the manifest and the zips are checked by the same code as
``blender --command extension validate`` — no Blender binary needed.
Installing runs in a subprocess with its own Blender user folders, so the
installed copy never mixes with the add-on the other tests import.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import textwrap
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
ADDON_DIR = REPO_ROOT / "addon"
MANIFEST = REPO_ROOT / "blender_manifest.toml"

_spec = importlib.util.spec_from_file_location("tof_addon_build", ADDON_DIR / "build.py")
build = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = build          # dataclasses look their module up by name
_spec.loader.exec_module(build)

STAND_IN_INIT = '''"""Stand-in used by the packaging test while addon/__init__.py does not exist yet."""


def register():
    pass


def unregister():
    pass
'''


def _blender_ext() -> Path:
    pytest.importorskip("bpy")           # the tool ships inside the bpy wheel
    return build.find_blender_ext()


def _addon_sources(tmp_path: Path) -> Path:
    """addon/ itself, or a temporary copy with a stand-in __init__.py when the real one is missing."""
    if (ADDON_DIR / "__init__.py").is_file():
        return ADDON_DIR
    copy = tmp_path / "addon-src"
    shutil.copytree(ADDON_DIR, copy, ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "__init__.py").write_text(STAND_IN_INIT, encoding="utf-8")
    return copy


def _blender_env(home: Path) -> dict:
    env = dict(os.environ)
    for name in ("BLENDER_USER_RESOURCES", "XDG_CONFIG_HOME", "XDG_CACHE_HOME"):
        env[name] = str(home / name.lower())
    return env


# --------------------------------------------------------------------------- manifest
def test_manifest_declares_what_the_issue_asks():
    manifest = tomllib.loads(MANIFEST.read_text(encoding="utf-8"))
    assert manifest["schema_version"] == "1.0.0"
    assert manifest["id"] == "tof_camera" and manifest["type"] == "add-on"
    assert manifest["blender_version_min"] == "4.2.0"
    assert manifest["license"] == ["SPDX:GPL-3.0-or-later"]
    assert manifest["website"].startswith("https://")
    assert "files" in manifest["permissions"]
    wheels = [build.Wheel.parse(w) for w in manifest["wheels"]]
    assert not any(w.distribution.lower() == "numpy" for w in wheels), "Blender ships NumPy: never bundle it"
    pure = [w for w in wheels if w.is_pure]
    assert [w.distribution for w in pure] == ["tofcore"]
    pyproject = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    assert pure[0].version == pyproject["project"]["version"]
    assert [w.filename for w in wheels] == [pure[0].filename], "pure-Python wheels only (issue 19)"
    assert "platforms" not in manifest, "one zip for every platform"


@pytest.mark.parametrize("wheel", ["openexr-3.5.3-cp313-cp313-manylinux_2_28_x86_64.whl",
                                   "opencv_python_headless-4.11.0.86-cp37-abi3-manylinux_2_17_x86_64.whl"])
def test_compiled_wheels_are_refused(wheel):
    """A native library in Blender's process can crash Blender (issue 19: the OpenEXR wheel did)."""
    manifest = tomllib.loads(MANIFEST.read_text(encoding="utf-8"))
    manifest["wheels"] = [*manifest["wheels"], f"./wheels/{wheel}"]
    with pytest.raises(build.BuildError, match=f"wheels must be pure Python \\(py3-none-any\\), got '{wheel}'"):
        build.check_wheels(manifest)


@pytest.mark.parametrize("wheel", ["cupy_cuda12x-13.6.0-cp311-cp311-manylinux2014_x86_64.whl",
                                   "nvidia_cublas_cu12-12.9.3.13-py3-none-manylinux_2_27_x86_64.whl",
                                   "numpy-1.26.4-cp311-cp311-manylinux_2_17_x86_64.whl"])
def test_gpu_packages_and_numpy_are_never_bundled(wheel):
    """The zips stay small: CuPy and the CUDA libraries are installed on request (addon/gpu.py)."""
    manifest = tomllib.loads(MANIFEST.read_text(encoding="utf-8"))
    assert not any(w.lower().lstrip("./").startswith(("wheels/cupy", "wheels/nvidia", "wheels/numpy"))
                   for w in manifest["wheels"])
    manifest["wheels"] = [*manifest["wheels"], f"./wheels/{wheel}"]
    with pytest.raises(build.BuildError, match=f"wheels must not bundle '{wheel}'"):
        build.check_wheels(manifest)
    assert "network" in manifest["permissions"]    # Install CuPy downloads, only when asked


@pytest.mark.bpy
def test_manifest_validates(tmp_path):
    tool = _blender_ext()
    staging = tmp_path / "staging"
    shutil.copytree(_addon_sources(tmp_path), staging, ignore=shutil.ignore_patterns("__pycache__", "build.py"))
    shutil.copy2(MANIFEST, staging / MANIFEST.name)
    proc = subprocess.run([sys.executable, str(tool), "validate", str(staging)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Success parsing TOML" in proc.stdout

    # The validator really checks: a tagline ending with punctuation is refused.
    text = MANIFEST.read_text(encoding="utf-8")
    bad = text.replace('tagline = "', 'tagline = "Bad: ', 1).replace('by path tracing"', 'by path tracing."', 1)
    assert bad != text
    (staging / MANIFEST.name).write_text(bad, encoding="utf-8")
    proc = subprocess.run([sys.executable, str(tool), "validate", str(staging)], capture_output=True, text=True)
    assert proc.returncode != 0 and "tagline" in proc.stdout + proc.stderr


# --------------------------------------------------------------------------- build + install
INSTALL_SCRIPT = textwrap.dedent('''
    import json, os, sys
    import bpy
    zip_path = sys.argv[1]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                      enable_on_install=True)
    site = bpy.utils.user_resource("EXTENSIONS", path=os.path.join(
        ".local", "lib", "python{}.{}".format(*sys.version_info[:2]), "site-packages"))
    package = os.path.join(bpy.utils.user_resource("EXTENSIONS"), "user_default", "tof_camera")
    addon = bpy.context.preferences.addons.get("bl_ext.user_default.tof_camera")
    prefs = addon.preferences if addon is not None else None
    module = sys.modules.get("bl_ext.user_default.tof_camera.preferences")
    print("RESULT " + json.dumps({
        "device": getattr(prefs, "device", None),
        "cupy_package": getattr(prefs, "cupy_package", None),
        "cupy_folder": module.cupy_folder() if module else None,
        "cupy_imported": "cupy" in sys.modules,
        "operator": sorted(result),
        "addons": [a.module for a in bpy.context.preferences.addons],
        "site_packages": sorted(os.listdir(site)) if os.path.isdir(site) else [],
        "presets": sorted(os.listdir(os.path.join(site, "tofcore", "_presets")))
                   if os.path.isdir(os.path.join(site, "tofcore", "_presets")) else [],
        "package": sorted(os.listdir(package)) if os.path.isdir(package) else [],
    }))
''')


@pytest.mark.bpy
def test_built_zip_installs_and_enables(tmp_path):
    """addon/build.py → one zip for every platform → package_install_files → listed in preferences.addons."""
    _blender_ext()
    out = tmp_path / "dist"
    proc = subprocess.run([sys.executable, str(ADDON_DIR / "build.py"), "--out", str(out),
                           "--work-dir", str(tmp_path / "work"), "--addon-dir", str(_addon_sources(tmp_path))],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    manifest = tomllib.loads(MANIFEST.read_text(encoding="utf-8"))
    zips = sorted(out.glob("*.zip"))
    assert [z.name for z in zips] == [f"tof_camera-{manifest['version']}.zip"]
    # The size the documentation states is the zip's (issue 36: the README said 0.34 MB of a 0.48 MB zip).
    import re

    for page in [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]:
        for stated in re.findall(r"tof_camera-[\d.]+\.zip \(([\d.]+) MB\)", page.read_text(encoding="utf-8")):
            assert abs(float(stated) - zips[0].stat().st_size / 1e6) <= 0.03, f"{page.name} states {stated} MB"

    with zipfile.ZipFile(zips[0]) as archive:
        names = set(archive.namelist())
        packed_manifest = tomllib.loads(archive.read("blender_manifest.toml").decode())
    assert {"blender_manifest.toml", "__init__.py", "export.py", "mapping.py"} <= names
    assert "build.py" not in names and not any("__pycache__" in n for n in names)
    wheels = sorted(n for n in names if n.startswith("wheels/"))
    assert wheels == sorted(w.lstrip("./") for w in packed_manifest["wheels"])
    assert not any("numpy" in w.lower() for w in wheels)
    assert not any(name.startswith(("cupy", "nvidia")) for w in wheels for name in [w.split("/")[-1].lower()])
    assert zips[0].stat().st_size < 2e6, f"{zips[0].name}: {zips[0].stat().st_size / 1e6:.1f} MB"
    assert "platforms" not in packed_manifest

    home = tmp_path / "blender-home"
    script = tmp_path / "install.py"
    script.write_text(INSTALL_SCRIPT, encoding="utf-8")
    proc = subprocess.run([sys.executable, str(script), str(zips[0])], capture_output=True, text=True,
                          env=_blender_env(home), timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT "))
    report = json.loads(line[len("RESULT "):])
    assert report["operator"] == ["FINISHED"]
    assert "bl_ext.user_default.tof_camera" in report["addons"], proc.stdout + proc.stderr
    assert "tofcore" in report["site_packages"]
    assert "tofcore_batch" in report["site_packages"]   # batch's frame-range entry (blender_entry) ships too
    assert not any(name.lower().startswith(("openexr", "cv2", "opencv")) for name in report["site_packages"])
    assert report["presets"] == ["kinect_v2.toml", "o3d303.toml", "xtion2.toml"]
    assert "blender_manifest.toml" in report["package"]
    # The GPU preferences of the installed extension: CPU by default; CuPy would go into the extension's
    # user folder (not created, nothing imported at registration).
    assert report["device"] == "cpu" and report["cupy_package"] == "cupy-cuda12x"
    assert report["cupy_folder"].endswith(os.path.join("extensions", ".user", "user_default", "tof_camera",
                                                       "site-packages"))
    assert str(home) in report["cupy_folder"] and not os.path.exists(report["cupy_folder"])
    assert report["cupy_imported"] is False
