#!/usr/bin/env bash
# Fetch the GPU peers for bench/bench_gpu.py into .peers/ (run HERE, on a machine with internet).
#
# The GPU machine has no internet and takes at most 64 MiB of files with the working tree, so the
# peers travel as files in .peers/ (ignored through .git/info/exclude; name ".peers" in the device
# tool's carry list):
#
#   mitsuba-3.9.1-cp312-cuda-trimmed.zip  the Mitsuba 3.9.1 cp312 manylinux wheel (62.6 MB) cut down to
#                                         what the bench_peers frame loads with cuda_ad_rgb / cuda_ad_mono
#   drjit-1.5.0-cp312-*.whl               the Dr.Jit wheel Mitsuba 3.9.1 pins (drjit==1.5.0), as downloaded
#   mitransient-1.3.1-py3-none-any.whl    pure Python; needs only mitsuba (>=3.6,<3.10) and numpy
#   MANIFEST.txt                          what was fetched and removed, with SHA-256 sums
#
# bench/gpu/setup_peers.sh unpacks them on the GPU machine into /tmp/peers (PYTHONPATH).
#
# Trimming (shared/NOTES-gpu.md): the llvm_ad_* / *spectral* / *polarized* variant modules, include/,
# cmake/, pkgconfig/, mitsuba_stubs/, the .pyi stubs, data/sunsky, share/doc and every plugin the frame
# does not load. The plugins the frame loads were read from /proc/self/maps after rendering it with
# llvm_ad_rgb and llvm_ad_mono (bench_peers.run_mitsuba): box diffuse hdrfilm independent merge path
# perspective point roughconductor srgb twosided uniform (merge: the scene merges its meshes at load;
# mitransient's transient_path, phasor_hdr_film and transient_hdr_film are Python; bench/bench_transient.py's
# transient_hdr_film frame loads box diffuse hdrfilm independent merge perspective ply point twosided uniform,
# read the same way with llvm_ad_mono: nothing more to keep). A few small plugins that a dict
# without an explicit choice falls back to are kept too (gaussian rfilter, d65, the mesh loaders).
#
# Usage: bench/gpu/fetch_peers.sh            (from anywhere inside the repository)
#        KEEP_VARIANTS="cuda_ad_rgb cuda_ad_mono scalar_rgb llvm_ad_rgb llvm_ad_mono" bench/gpu/fetch_peers.sh
#            also keeps the LLVM variants (larger; for testing the trimmed copy on a CPU machine)
set -euo pipefail

MITSUBA=3.9.1
DRJIT=1.5.0          # mitsuba 3.9.1's METADATA: Requires-Dist: drjit==1.5.0
MITRANSIENT=1.3.1    # Requires-Dist: mitsuba<3.10.0,>=3.6.0, numpy (numpy is on the GPU machine)
KEEP_VARIANTS=${KEEP_VARIANTS:-"cuda_ad_rgb cuda_ad_mono scalar_rgb"}
PYTHON=${PYTHON:-python3}

root=$(git rev-parse --show-toplevel)
cd "$root"
out=.peers
exclude=$(git rev-parse --git-path info/exclude)
mkdir -p "$(dirname "$exclude")"
grep -qxF '/.peers/' "$exclude" 2>/dev/null || echo '/.peers/' >>"$exclude"

dl=$(mktemp -d "${TMPDIR:-/tmp}/tofcore-peers.XXXXXX")
trap 'rm -rf "$dl"' EXIT
"$PYTHON" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d "$dl" \
    "mitsuba==$MITSUBA" "drjit==$DRJIT" "mitransient==$MITRANSIENT"

rm -rf "$out.new"
mkdir -p "$out.new"
cp "$dl"/drjit-"$DRJIT"-*.whl "$dl"/mitransient-"$MITRANSIENT"-*.whl "$out.new"/

KEEP_VARIANTS="$KEEP_VARIANTS" "$PYTHON" - "$dl"/mitsuba-"$MITSUBA"-*.whl "$out.new" "$MITSUBA" <<'EOF'
"""Copy the Mitsuba wheel into a zip without what the GPU frame does not need; write MANIFEST.txt."""
import hashlib
import os
import re
import sys
import zipfile
from pathlib import Path

wheel, out, version = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
keep_variants = set(os.environ["KEEP_VARIANTS"].split())
# Plugins the bench_peers frame loads (see the header of fetch_peers.sh), then small fallbacks.
PLUGINS = {"box", "diffuse", "hdrfilm", "independent", "merge", "path", "perspective", "point",
           "roughconductor", "srgb", "twosided", "uniform",
           "gaussian", "d65", "regular", "irregular", "rawconstant", "conductor", "null",
           "ply", "obj", "serialized", "shapegroup", "instance", "direct", "depth", "stratified"}
VARIANT = re.compile(r"^mitsuba/((?:scalar|llvm|cuda)_\w+)\.cpython-[^/]*\.so$")
DROP_DIRS = ("mitsuba/include/", "mitsuba/cmake/", "mitsuba/pkgconfig/", "mitsuba/mitsuba_stubs/",
             "mitsuba/data/sunsky/", "share/", "mitsuba/python/test/")


def keep(name: str) -> bool:
    if name.startswith(DROP_DIRS) or name.endswith((".pyi", "/RECORD", "py.typed")):
        return False
    m = VARIANT.match(name)
    if m:
        return m.group(1) in keep_variants
    if name.startswith("mitsuba/plugins/"):
        return Path(name).stem in PLUGINS
    return True


zin = zipfile.ZipFile(wheel)
dest = out / f"mitsuba-{version}-cp312-cuda-trimmed.zip"
kept, dropped = [], []
with zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zout:
    for info in zin.infolist():
        if keep(info.filename):
            kept.append(info)
            zout.writestr(info, zin.read(info), compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)
        else:
            dropped.append(info)
plugins = sorted(Path(i.filename).stem for i in kept if i.filename.startswith("mitsuba/plugins/"))
missing = sorted(PLUGINS - set(plugins))
if missing:
    sys.exit(f"fetch_peers: plugins not in the wheel: {missing}")
variants = sorted(VARIANT.match(i.filename).group(1) for i in kept if VARIANT.match(i.filename))
if not {"cuda_ad_rgb", "cuda_ad_mono"} <= set(variants):
    sys.exit(f"fetch_peers: the wheel lacks cuda_ad_rgb / cuda_ad_mono (kept {variants})")


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


lines = [f"# .peers/ for bench/bench_gpu.py, written by bench/gpu/fetch_peers.sh",
         f"source wheel: {wheel.name} ({wheel.stat().st_size / 2**20:.1f} MiB, sha256 {sha(wheel)})",
         f"variants kept: {' '.join(variants)}",
         f"plugins kept ({len(plugins)}): {' '.join(plugins)}",
         f"entries kept {len(kept)} ({sum(i.file_size for i in kept) / 2**20:.1f} MiB unpacked), "
         f"dropped {len(dropped)} ({sum(i.file_size for i in dropped) / 2**20:.1f} MiB unpacked)", ""]
for f in sorted(out.iterdir()):
    lines.append(f"{sha(f)}  {f.stat().st_size:>10}  {f.name}")
(out / "MANIFEST.txt").write_text("\n".join(lines) + "\n")
EOF

rm -rf "$out"
mv "$out.new" "$out"
cat "$out/MANIFEST.txt"
du -sh "$out"
size=$(du -sm "$out" | cut -f1)
if [ "$size" -ge 40 ]; then
    echo "fetch_peers: $out is $size MiB, over the 40 MiB meant for it" >&2
    exit 1
fi
