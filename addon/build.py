#!/usr/bin/env python3
"""Build the installable Blender extension zip: ``python addon/build.py --out dist/``.

Steps (``make addon`` runs them):

1. Read ``blender_manifest.toml`` (repository top). Its ``wheels`` list is the
   single source of what is bundled, and it holds pure-Python wheels only: a
   compiled wheel loads native libraries into Blender's process, where a second
   copy of a library Blender already has (OpenEXR, libpng, zlib, …) can crash
   Blender (issue 19: the OpenEXR wheel did). A compiled wheel, NumPy (Blender
   ships it) or the GPU packages (:data:`NOT_BUNDLED`; the add-on installs CuPy
   on request, ``addon/gpu.py``) in the list are refused.
2. Build the pure-Python ``tofcore`` wheel (``pip wheel --no-deps .``; the
   presets ride along as ``tofcore/_presets``) and check its file name is the
   one the manifest lists.
3. Stage ``addon/*`` + the manifest + ``wheels/`` in one folder (the manifest
   must sit next to the add-on's ``__init__.py`` at the root of the zip).
4. Run Blender's own extension tool (``blender_ext.py``, shipped inside the
   ``bpy`` wheel — no Blender binary needed): ``validate`` on the staging
   folder, ``build`` (one zip for every platform: the manifest names none),
   then ``validate`` on the zip.

Exit codes: 0 success, 1 build or validation error, 2 bad arguments.

Options (defaults in brackets): ``--out DIR`` [dist], ``--work-dir DIR``
[build/extension], ``--addon-dir DIR`` [addon], ``--blender-ext PATH`` [found
in the installed bpy module, or $BLENDER_EXT], ``--verbose``.
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import os
import shutil
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
MANIFEST_NAME = "blender_manifest.toml"
#: Files of the add-on folder that are development tools, not part of the extension.
NOT_SHIPPED = ("build.py",)
#: Distributions never bundled (name prefixes): Blender ships NumPy; the GPU packages are installed on
#: request into the extension's user folder (addon/gpu.py), which keeps the zip small.
NOT_BUNDLED = ("numpy", "cupy", "nvidia-", "cuda-", "fastrlock")


class BuildError(RuntimeError):
    """A step failed; the message says which and why."""

    exit_code = 1


@dataclass(frozen=True)
class Wheel:
    """One entry of the manifest's ``wheels`` list, parsed from its file name."""

    entry: str          # as written in the manifest, e.g. "./wheels/tofcore-0.1.0-py3-none-any.whl"
    filename: str
    distribution: str
    version: str
    python_tag: str
    abi_tag: str
    platform_tag: str

    @classmethod
    def parse(cls, entry: str) -> Wheel:
        filename = entry.rsplit("/", 1)[-1]
        parts = filename[:-len(".whl")].split("-") if filename.endswith(".whl") else []
        if len(parts) != 5:
            raise BuildError(f"{MANIFEST_NAME}: wheels entry must be a wheel file name "
                             f"'name-version-python-abi-platform.whl', got {entry!r}")
        return cls(entry, filename, *parts)

    @property
    def is_pure(self) -> bool:
        return self.platform_tag == "any" and self.abi_tag == "none"


# =========================================================================== steps
def read_manifest(path: Path) -> dict:
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise BuildError(f"{path}: cannot read the manifest: {error}") from None


def check_wheels(manifest: dict) -> list[Wheel]:
    """The manifest's wheels, or BuildError for a compiled one, NumPy or a GPU package."""
    wheels = [Wheel.parse(entry) for entry in manifest.get("wheels", [])]
    for wheel in wheels:
        if wheel.distribution.lower().replace("_", "-").startswith(NOT_BUNDLED):
            raise BuildError(f"{MANIFEST_NAME}: wheels must not bundle {wheel.filename!r}: Blender ships NumPy, "
                             f"and CuPy with the CUDA libraries is installed on request by the add-on "
                             f"(Preferences > Install CuPy for GPU rendering)")
        if not wheel.is_pure:
            raise BuildError(f"{MANIFEST_NAME}: wheels must be pure Python (py3-none-any), got {wheel.filename!r}: "
                             f"a compiled wheel loads native libraries into Blender's process, where a second "
                             f"copy of one Blender has (OpenEXR, libpng, zlib…) can crash it (issue 19)")
    if "platforms" in manifest:
        raise BuildError(f"{MANIFEST_NAME}: with pure-Python wheels only, leave 'platforms' out "
                         f"(one zip for every platform)")
    return wheels


def build_tofcore_wheel(wheel: Wheel, out_dir: Path, verbose: bool) -> Path:
    """``pip wheel --no-deps`` of the repository; the file name must match the manifest's."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("*.whl"):
        old.unlink()
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--wheel-dir", str(out_dir), str(REPO_ROOT)],
        "building the tofcore wheel", verbose)
    built = sorted(out_dir.glob("*.whl"))
    names = [p.name for p in built]
    if wheel.filename not in names:
        raise BuildError(f"{MANIFEST_NAME}: wheels lists {wheel.filename!r} but pip built {names}; "
                         f"update the manifest (or pyproject's version) so they agree")
    return out_dir / wheel.filename


def stage(addon_dir: Path, manifest_path: Path, wheel_files: list[Path], staging: Path) -> None:
    """Assemble the extension folder: add-on files at the root, the manifest, ``wheels/``."""
    if staging.exists():
        shutil.rmtree(staging)
    shutil.copytree(addon_dir, staging,
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", ".*", *NOT_SHIPPED))
    if not (staging / "__init__.py").is_file():
        raise BuildError(f"{addon_dir}: the add-on has no __init__.py")
    shutil.copy2(manifest_path, staging / MANIFEST_NAME)
    wheel_dir = staging / "wheels"
    wheel_dir.mkdir()
    for path in wheel_files:
        shutil.copy2(path, wheel_dir / path.name)


def find_blender_ext(explicit: str | None = None) -> Path:
    """Blender's extension command-line tool, from the installed bpy module (bpy is not imported)."""
    candidates = [explicit, os.environ.get("BLENDER_EXT")]
    spec = importlib.util.find_spec("bpy")
    if spec is not None and spec.origin:
        pattern = os.path.join(os.path.dirname(spec.origin), "*", "scripts", "addons_core", "bl_pkg", "cli",
                               "blender_ext.py")
        candidates += sorted(glob.glob(pattern))
    for candidate in candidates:
        if candidate and os.path.isfile(candidate):
            return Path(candidate)
    raise BuildError("Blender's blender_ext.py was not found: install the bpy module "
                     "(pip install -r requirements-dev.txt) or pass --blender-ext PATH")


def blender_ext(tool: Path, args: list[str], what: str, verbose: bool) -> str:
    return run([sys.executable, str(tool), *args], what, verbose)


def run(cmd: list[str], what: str, verbose: bool) -> str:
    if verbose:
        print("$", " ".join(cmd), flush=True)
    proc = subprocess.run(cmd, capture_output=True, text=True)
    output = (proc.stdout + proc.stderr).strip()
    if verbose and output:
        print(output, flush=True)
    if proc.returncode != 0:
        raise BuildError(f"{what} failed (exit {proc.returncode}):\n{output}")
    return output


# =========================================================================== main
def build(out_dir: Path, *, work_dir: Path | None = None, addon_dir: Path | None = None,
          blender_ext_path: str | None = None, verbose: bool = False) -> Path:
    """Run all steps; returns the zip written to ``out_dir``."""
    work_dir = Path(work_dir or REPO_ROOT / "build" / "extension")
    addon_dir = Path(addon_dir or REPO_ROOT / "addon")
    manifest_path = REPO_ROOT / MANIFEST_NAME
    manifest = read_manifest(manifest_path)
    tool = find_blender_ext(blender_ext_path)
    files = []
    for wheel in check_wheels(manifest):
        if wheel.distribution.lower() != "tofcore":
            raise BuildError(f"{MANIFEST_NAME}: don't know how to obtain the wheel {wheel.filename!r}")
        files.append(build_tofcore_wheel(wheel, work_dir / "tofcore-wheel", verbose))
        print(f"wheel     {wheel.filename}", flush=True)

    staging = work_dir / "staging"
    stage(addon_dir, manifest_path, files, staging)
    print(blender_ext(tool, ["validate", str(staging)], "validating the staged extension", verbose), flush=True)

    out_dir.mkdir(parents=True, exist_ok=True)
    expected_prefix = f"{manifest['id']}-{manifest['version']}"
    for old in out_dir.glob(f"{expected_prefix}*.zip"):
        old.unlink()
    blender_ext(tool, ["build", "--source-dir", str(staging), "--output-dir", str(out_dir)],
                "building the extension zip", verbose)
    path = out_dir / f"{expected_prefix}.zip"
    if not path.is_file():
        raise BuildError(f"blender_ext build wrote no {path.name} into {out_dir}")
    blender_ext(tool, ["validate", str(path)], f"validating {path.name}", verbose)
    print(f"zip       {path}  ({path.stat().st_size / 1e6:.2f} MB, validated)", flush=True)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="addon/build.py", description="Build the ToF Camera Simulator Blender extension zip.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "dist", help="folder for the zip (DIR)")
    parser.add_argument("--work-dir", type=Path, default=REPO_ROOT / "build" / "extension",
                        help="staging and wheel folder (DIR)")
    parser.add_argument("--addon-dir", type=Path, default=REPO_ROOT / "addon", help="the add-on sources (DIR)")
    parser.add_argument("--blender-ext", default=None,
                        help="path of Blender's blender_ext.py (PATH); default: from the installed bpy module")
    parser.add_argument("--verbose", action="store_true", help="print every command and its output")
    args = parser.parse_args(argv)
    try:
        build(args.out, work_dir=args.work_dir, addon_dir=args.addon_dir, blender_ext_path=args.blender_ext,
              verbose=args.verbose)
    except BuildError as error:
        print(f"addon/build.py: error: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print("addon/build.py: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
