#!/usr/bin/env python3
"""Build the installable Blender extension zips: ``python addon/build.py --out dist/``.

Steps (``make addon`` runs them):

1. Read ``blender_manifest.toml`` (repository top). Its ``wheels`` list is the
   single source of what is bundled.
2. Build the pure-Python ``tofcore`` wheel (``pip wheel --no-deps .``; the
   presets ride along as ``tofcore/_presets``) and check its file name is the
   one the manifest lists.
3. Download the listed OpenEXR wheels (cp311 for Blender 4.2–5.0, cp313 for
   5.1+, per platform) with ``pip download --only-binary=:all:``; they are
   kept in a cache folder and reused. NumPy is not bundled: Blender ships it.
   Nor are CuPy and NVIDIA's CUDA libraries (about 1 GB): the add-on installs
   them on request (Preferences › Install CuPy for GPU rendering, ``addon/gpu.py``).
   A manifest that lists any of these (:data:`NOT_BUNDLED`) is refused.
4. Stage ``addon/*`` + the manifest + ``wheels/`` in one folder (the manifest
   must sit next to the add-on's ``__init__.py`` at the root of the zip).
5. Run Blender's own extension tool (``blender_ext.py``, shipped inside the
   ``bpy`` wheel — no Blender binary needed): ``validate`` on the staging
   folder, ``build --split-platforms`` (one zip per platform, since the
   OpenEXR wheels differ), then ``validate`` on every zip.

Exit codes: 0 success, 1 build or validation error, 2 bad arguments,
3 a wheel could not be downloaded (e.g. no network).

Options (defaults in brackets): ``--out DIR`` [dist], ``--platforms LIST``
(comma-separated Blender platforms, e.g. ``linux-x64``) [all in the
manifest], ``--work-dir DIR`` [build/extension], ``--wheel-cache DIR``
[<work-dir>/wheel-cache], ``--addon-dir DIR`` [addon], ``--blender-ext PATH``
[found in the installed bpy module, or $BLENDER_EXT], ``--verbose``.
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
MANIFEST_NAME = "blender_manifest.toml"
#: Files of the add-on folder that are development tools, not part of the extension.
NOT_SHIPPED = ("build.py",)
#: Distributions never bundled (name prefixes): Blender ships NumPy; the GPU packages are installed on
#: request into the extension's user folder (addon/gpu.py), which keeps the zips small.
NOT_BUNDLED = ("numpy", "cupy", "nvidia-", "cuda-", "fastrlock")

#: Wheel platform tag prefix → Blender platform (the rule of blender_ext.py, for the tags used here).
_WHEEL_SYSTEMS = {"manylinux": "linux", "musllinux": "linux", "linux": "linux", "macosx": "macos", "win": "windows"}
_WHEEL_MACHINES = {"x86_64": "x64", "amd64": "x64", "aarch64": "arm64", "arm64": "arm64"}


class BuildError(RuntimeError):
    """A step failed; the message says which and why."""

    exit_code = 1


class DownloadError(BuildError):
    """A wheel could not be downloaded (network, index or an unknown version)."""

    exit_code = 3


@dataclass(frozen=True)
class Wheel:
    """One entry of the manifest's ``wheels`` list, parsed from its file name."""

    entry: str          # as written in the manifest, e.g. "./wheels/openexr-3.5.3-cp311-....whl"
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
        return self.platform_tag == "any"

    @property
    def blender_platforms(self) -> set[str]:
        """Blender platforms this wheel serves (empty set = all)."""
        if self.is_pure:
            return set()
        out = set()
        for tag in self.platform_tag.split("."):
            system = next((v for k, v in _WHEEL_SYSTEMS.items() if tag.startswith(k)), tag.split("_")[0])
            if tag.endswith("universal2"):
                out |= {f"{system}-x64", f"{system}-arm64"}
                continue
            machine = next((v for k, v in _WHEEL_MACHINES.items() if tag.endswith("_" + k)), tag.rsplit("_", 1)[-1])
            out.add(f"{system}-{machine}")
        return out

    @property
    def python_version(self) -> str:
        """"3.11" for cp311."""
        digits = re.sub(r"\D", "", self.python_tag)
        return f"{digits[0]}.{digits[1:]}"


# =========================================================================== steps
def read_manifest(path: Path) -> dict:
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise BuildError(f"{path}: cannot read the manifest: {error}") from None


def select_wheels(manifest: dict, platforms: list[str] | None) -> tuple[list[Wheel], list[str]]:
    """The manifest's wheels and platforms, limited to ``platforms`` when given."""
    all_platforms = list(manifest.get("platforms", []))
    wheels = [Wheel.parse(entry) for entry in manifest.get("wheels", [])]
    for wheel in wheels:
        if wheel.distribution.lower().replace("_", "-").startswith(NOT_BUNDLED):
            raise BuildError(f"{MANIFEST_NAME}: wheels must not bundle {wheel.filename!r}: Blender ships NumPy, "
                             f"and CuPy with the CUDA libraries is installed on request by the add-on "
                             f"(Preferences > Install CuPy for GPU rendering)")
    if not platforms:
        return wheels, all_platforms
    unknown = [p for p in platforms if p not in all_platforms]
    if unknown:
        raise BuildError(f"--platforms: {unknown[0]!r} is not in the manifest's platforms {all_platforms}")
    keep = [w for w in wheels if w.is_pure or w.blender_platforms & set(platforms)]
    return keep, [p for p in all_platforms if p in platforms]


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


def download_wheel(wheel: Wheel, cache_dir: Path, verbose: bool) -> Path:
    """The compiled wheel from the package index (cached); pip chooses nothing: the name is exact."""
    target = cache_dir / wheel.filename
    if target.is_file():
        return target
    cache_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=cache_dir) as tmp:
        cmd = [sys.executable, "-m", "pip", "download", f"{wheel.distribution}=={wheel.version}", "--no-deps",
               "--only-binary=:all:", "--python-version", wheel.python_version, "--implementation", "cp",
               "--abi", wheel.abi_tag, "--platform", wheel.platform_tag, "--dest", tmp]
        try:
            run(cmd, f"downloading {wheel.filename}", verbose)
        except BuildError as error:
            raise DownloadError(str(error)) from None
        got = {p.name.lower(): p for p in Path(tmp).glob("*.whl")}
        if wheel.filename.lower() not in got:
            raise DownloadError(f"downloading {wheel.filename}: pip fetched {sorted(got)} instead; "
                                f"fix the name in {MANIFEST_NAME}")
        os.replace(got[wheel.filename.lower()], target)
    return target


def stage(addon_dir: Path, manifest_path: Path, wheel_files: list[Path], platforms: list[str],
          wheels: list[Wheel], staging: Path) -> None:
    """Assemble the extension folder: add-on files at the root, the manifest, ``wheels/``."""
    if staging.exists():
        shutil.rmtree(staging)
    shutil.copytree(addon_dir, staging,
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", ".*", *NOT_SHIPPED))
    if not (staging / "__init__.py").is_file():
        raise BuildError(f"{addon_dir}: the add-on has no __init__.py")
    text = manifest_path.read_text(encoding="utf-8")
    # Keep the manifest as written except for the wheels/platforms actually bundled.
    text = _replace_toml_list(text, "platforms", platforms)
    text = _replace_toml_list(text, "wheels", [w.entry for w in wheels])
    (staging / MANIFEST_NAME).write_text(text, encoding="utf-8")
    wheel_dir = staging / "wheels"
    wheel_dir.mkdir()
    for path in wheel_files:
        shutil.copy2(path, wheel_dir / path.name)


def _replace_toml_list(text: str, key: str, values: list[str]) -> str:
    pattern = re.compile(rf"^{key}\s*=\s*\[.*?\]", re.S | re.M)
    if not pattern.search(text):
        raise BuildError(f"{MANIFEST_NAME}: no top-level {key} = [...] list found")
    body = "".join(f'\n  "{v}",' for v in values)
    return pattern.sub(lambda _m: f"{key} = [{body}\n]", text, count=1)


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
def build(out_dir: Path, *, platforms: list[str] | None = None, work_dir: Path | None = None,
          wheel_cache: Path | None = None, addon_dir: Path | None = None, blender_ext_path: str | None = None,
          verbose: bool = False) -> list[Path]:
    """Run all steps; returns the zips written to ``out_dir``."""
    work_dir = Path(work_dir or REPO_ROOT / "build" / "extension")
    wheel_cache = Path(wheel_cache or work_dir / "wheel-cache")
    addon_dir = Path(addon_dir or REPO_ROOT / "addon")
    manifest_path = REPO_ROOT / MANIFEST_NAME
    manifest = read_manifest(manifest_path)
    tool = find_blender_ext(blender_ext_path)
    wheels, platforms = select_wheels(manifest, platforms)

    files = []
    for wheel in wheels:
        if wheel.distribution.lower() == "tofcore":
            files.append(build_tofcore_wheel(wheel, work_dir / "tofcore-wheel", verbose))
        elif wheel.is_pure:
            raise BuildError(f"{MANIFEST_NAME}: don't know how to obtain the pure wheel {wheel.filename!r}")
        else:
            files.append(download_wheel(wheel, wheel_cache, verbose))
        print(f"wheel     {wheel.filename}", flush=True)

    staging = work_dir / "staging"
    stage(addon_dir, manifest_path, files, platforms, wheels, staging)
    print(blender_ext(tool, ["validate", str(staging)], "validating the staged extension", verbose), flush=True)

    out_dir.mkdir(parents=True, exist_ok=True)
    expected_prefix = f"{manifest['id']}-{manifest['version']}"
    for old in out_dir.glob(f"{expected_prefix}*.zip"):
        old.unlink()
    blender_ext(tool, ["build", "--source-dir", str(staging), "--output-dir", str(out_dir), "--split-platforms"],
                "building the extension zips", verbose)
    zips = sorted(out_dir.glob(f"{expected_prefix}*.zip"))
    if not zips:
        raise BuildError(f"blender_ext build wrote no {expected_prefix}*.zip into {out_dir}")
    for path in zips:
        blender_ext(tool, ["validate", str(path)], f"validating {path.name}", verbose)
        print(f"zip       {path}  ({path.stat().st_size / 1e6:.1f} MB, validated)", flush=True)
    return zips


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="addon/build.py", description="Build the ToF Camera Simulator Blender extension zips.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "dist", help="folder for the zips (DIR)")
    parser.add_argument("--platforms", default="",
                        help="comma-separated Blender platforms to build (LIST); empty = all in the manifest")
    parser.add_argument("--work-dir", type=Path, default=REPO_ROOT / "build" / "extension",
                        help="staging and wheel folder (DIR)")
    parser.add_argument("--wheel-cache", type=Path, default=None,
                        help="where downloaded wheels are kept (DIR); default <work-dir>/wheel-cache")
    parser.add_argument("--addon-dir", type=Path, default=REPO_ROOT / "addon", help="the add-on sources (DIR)")
    parser.add_argument("--blender-ext", default=None,
                        help="path of Blender's blender_ext.py (PATH); default: from the installed bpy module")
    parser.add_argument("--verbose", action="store_true", help="print every command and its output")
    args = parser.parse_args(argv)
    platforms = [p.strip() for p in args.platforms.split(",") if p.strip()] or None
    try:
        build(args.out, platforms=platforms, work_dir=args.work_dir, wheel_cache=args.wheel_cache,
              addon_dir=args.addon_dir, blender_ext_path=args.blender_ext, verbose=args.verbose)
    except BuildError as error:
        print(f"addon/build.py: error: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print("addon/build.py: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
