"""The compiled tracer (numba) inside a real Blender: install it the add-on's way, render cold, warm and NumPy.

    sudo python tests/blender_gui/numba_run.py dist/tof_camera-0.1.0.zip --wheels DIR [--out out/blender-numba]

Runs :file:`numba_scenario.py` in Debian 13's Blender 4.3.2 (Python 3.13, ``blender -b``: nothing here needs
the UI) inside the root that :file:`real_blender.sh` builds (``$ROOT``, default /opt/blender-trixie), with
one fresh HOME for all its Blender processes, in this order:

1. the extension zip installed and enabled (``blender --command extension install-file``);
2. ``install-nopip``: the add-on's "Install numba" where Blender's Python has no pip (Debian's): the error;
3. ``install``: the add-on's "Install numba for the compiled tracer" operator with ``--online-mode``. pip
   reads the wheels of ``--wheels DIR`` (``PIP_NO_INDEX``, ``PIP_FIND_LINKS``: no network at test time):
   ``numba-0.68.*``, ``llvmlite-0.50.*`` cp313 manylinux_2_28 x86-64 and a ``pip-*.whl``, which runs as
   ``python -m pip`` through ``PYTHONPATH`` since Debian's Python 3.13 has neither pip nor ensurepip;
4. ``render cold``: Render ToF of the default cube and World (constant ambient light) in a new Blender
   process (compiles the kernels, caches them);
5. ``render warm``: the same in another new process (loads the cache);
6. ``render numpy``: the same with ``TOFCORE_TRACER=numpy``;
   ``render textured`` and ``render textured-numpy``: the same camera on scenario.py's step 2 scene — a
   checker Image Texture on Base Color and Roughness, the World an Environment Texture (HDRI), both
   generated and packed — compiled (warm cache), then with ``TOFCORE_TRACER=numpy``;
   then ``cancel-cold``: on an empty kernel cache (its own ``NUMBA_CACHE_DIR``), the Render ToF job cancelled
   3 s into the compile (what Esc does), and a second job that waits for the compile going on in its child
   process;
7. ``gui``: the GUI scenario of ``make test-blender`` (:file:`scenario.py`: Render ToF, live preview, Esc,
   animation, presets, an error report) in Blender's GUI on a virtual display, numba installed and its
   cache warm — a user's second session — judged as :file:`run.py` judges it.

Then checks that numba was installed into the add-on's folder, that the cold and warm renders used the
compiled tracer and the add-on says so, that the warm one compiled nothing new (the cache's files are the
same), that the compiled depth equals the NumPy depth as tests/tofcore/test_compiled.py requires
(``isclose(rtol=1e-9, atol=1e-9)`` or both NaN on ≥ 99.5 % of the pixels), that the textured scene under
the HDRI World exported its two textures and its environment map without a warning, rendered with the
compiled tracer (``tracer == "compiled"``, empty ``tracer_reason``) and gave the NumPy tracer's depth at that
tolerance, and that the GUI scenario
passed with every frame it wrote traced by the compiled tracer. Prints one line per check and
the timings; exit code 0 pass, 1 fail, 2 bad arguments. Needs root (chroot); one Blender at a time.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

import run  # tests/blender_gui/run.py: how the GUI scenario is judged

HERE = Path(__file__).resolve().parent
ROOT = Path(os.environ.get("ROOT", "/opt/blender-trixie"))
WHEELS = ("numba-0.68.*-cp313-*.whl", "llvmlite-0.50.*-cp313-*.whl", "pip-*.whl")
RENDERS = (("cold", ""), ("warm", ""), ("numpy", "TOFCORE_TRACER=numpy "), ("textured", ""),
           ("textured-numpy", "TOFCORE_TRACER=numpy "))


def run_script(work: str) -> str:
    """The shell script run inside the root: the steps of the module docstring, each timed."""
    blender = f"blender -b --python {work}/numba_scenario.py --"
    lines = [
        "set -u",
        f"export HOME={work} TOF_GUI_OUT={work}/out",
        f"cd {work}",
        f"blender -b --factory-startup --command extension install-file -r user_default -e {work}/ext.zip "
        f">{work}/out/install-extension.log 2>&1 || {{ cat {work}/out/install-extension.log; exit 3; }}",
        "t() { local label=$1 s=$(date +%s%N); shift; \"$@\"; local rc=$?; "
        f"echo \"$label: $(( ($(date +%s%N) - s) / 1000000 )) ms wall (Blender start to exit)\" >>{work}/out/wall.txt; "
        "return $rc; }",
        f"t install-nopip blender -b --online-mode --python {work}/numba_scenario.py -- install-nopip "
        f">{work}/out/install-nopip.log 2>&1 || exit 4",
        f"PYTHONPATH=$(ls {work}/wheels/pip-*.whl) PIP_NO_INDEX=1 PIP_FIND_LINKS={work}/wheels "
        f"t install blender -b --online-mode --python {work}/numba_scenario.py -- install >{work}/out/install.log 2>&1 "
        "|| exit 4",
    ]
    for label, env in RENDERS:
        lines.append(f"{env}t render-{label} {blender} render {label} >{work}/out/render-{label}.log 2>&1 || exit 5")
    lines.append(f"NUMBA_CACHE_DIR={work}/cold-cache t cancel-cold {blender} cancel-cold >{work}/out/cancel-cold.log "
                 "2>&1 || exit 5")
    gui, display = f"{work}/out/gui", 500 + os.getpid() % 400
    screenshot = (f"n=$(ls {gui}/screen-*.png 2>/dev/null | wc -l); xwd -root -display :{display} -silent | "
                  f"convert xwd:- {gui}/screen-$n.png")
    lines += [
        "blender -b --python-expr 'import bpy; bpy.context.preferences.view.show_splash = False; "
        f"bpy.ops.wm.save_userpref()' >>{work}/out/install-extension.log 2>&1",  # no splash over the screenshots
        f"mkdir -p {gui}",
        f"Xvfb :{display} -screen 0 1600x1000x24 -nolisten tcp >{gui}/xvfb.log 2>&1 & xpid=$!",
        "sleep 2",
        f"DISPLAY=:{display} TOF_GUI_OUT={gui} SCREENSHOT_CMD='{screenshot}' t gui timeout 900 blender "
        f"--enable-event-simulate --python {work}/scenario.py >{gui}/blender.log 2>&1; echo $? >{gui}/rc",
        "kill $xpid 2>/dev/null",
        f"[ /tmp/blender.crash.txt -nt {work}/scenario.py ] && cp /tmp/blender.crash.txt {gui}/",
        "exit 0",
    ]
    return "\n".join(lines) + "\n"


def same_depth(out: Path, compiled: str, numpy_: str) -> tuple[bool, str]:
    """The compiled depth (``depth-COMPILED.npy``) against the NumPy one, at tests/tofcore/test_compiled.py's
    tolerance: ``isclose(rtol=1e-9, atol=1e-9)`` or both NaN on ≥ 99.5 % of the pixels."""
    if not ((out / f"depth-{compiled}.npy").is_file() and (out / f"depth-{numpy_}.npy").is_file()):
        return False, f"depth arrays {compiled}, {numpy_} missing"
    a, b = np.load(out / f"depth-{numpy_}.npy"), np.load(out / f"depth-{compiled}.npy")
    same = np.isclose(a, b, rtol=1e-9, atol=1e-9) | (np.isnan(a) & np.isnan(b))
    return (a.shape == b.shape and same.mean() >= 0.995,
            f"depth {compiled} (compiled) vs {numpy_} {a.shape}: {same.mean():.2%} of the pixels within 1e-9, "
            f"{'bit for bit' if np.array_equal(a, b, equal_nan=True) else 'not bit for bit'}; "
            f"{np.isfinite(a).mean():.0%} valid")


def judge(out: Path) -> list[tuple[bool, str]]:
    """(passed, one line) per check of the module docstring."""
    load = lambda name: json.loads((out / f"{name}.json").read_text()) if (out / f"{name}.json").is_file() else {}
    install, cold, warm, numpy_ = load("install"), load("render-cold"), load("render-warm"), load("render-numpy")
    nopip = load("install-nopip")
    checks = [("pip is not available in Blender's Python" in nopip.get("error", ""),
               f"install without pip: {nopip.get('error')!r}")]
    installed = any(c.startswith("numba") for c in install.get("contents", []))
    checks += [(install.get("installer_state") == "done" and installed,
               f"install: {install.get('installer_state')}, {install.get('installer_message')!r} into "
               f"{install.get('folder')} in {install.get('seconds')} s")]
    for label, record in (("cold", cold), ("warm", warm)):
        transport = record.get("transport", {})
        checks.append((transport.get("tracer") == "compiled" and "compiled" in record.get("tracer_text", "")
                       and "the last render used the compiled tracer" in record.get("status_after", [""])[0],
                       f"render {label}: tracer {transport.get('tracer')!r} ({transport.get('parallel')}), "
                       f"{record.get('seconds')} s in Render ToF, threading layer {record.get('threading_layer')}; "
                       f"status {record.get('status_after', [''])[0]!r}"))
    checks.append((bool(cold.get("cache_files")) and cold.get("cache_files") == warm.get("cache_files"),
                   f"cache {cold.get('cache_folder')}: {len(cold.get('cache_files') or {})} files after the cold "
                   f"render, unchanged by the warm one: {cold.get('cache_files') == warm.get('cache_files')}"))
    cancel = load("cancel-cold")
    compile_text = cancel.get("transport", {}).get("compile") or ""
    checks.append((cancel.get("cached_before") is False and cancel.get("first_end") == ["cancelled", "None"]
                   and cancel.get("cancel_seconds", 99) < 2 and cancel.get("compiling_after_cancel") is True
                   and cancel.get("second_end") == "done" and compile_text.startswith("compiled by a child process")
                   and cancel.get("cached_after") is True,
                   f"cancel during the cold compile: cancelled in {cancel.get('cancel_seconds')} s "
                   f"({cancel.get('first_end')}), compile still running {cancel.get('compiling_after_cancel')}; "
                   f"next render {cancel.get('second_end')} in {cancel.get('second_seconds')} s: {compile_text!r}; "
                   f"cached {cancel.get('cached_before')} -> {cancel.get('cached_after')}"))
    checks.append((numpy_.get("transport", {}).get("tracer") == "numpy",
                   f"render numpy: tracer {numpy_.get('transport', {}).get('tracer')!r}, {numpy_.get('seconds')} s"))
    checks.append(same_depth(out, "warm", "numpy"))
    textured, textured_numpy = load("render-textured"), load("render-textured-numpy")
    transport, export = textured.get("transport", {}), textured.get("export", {})
    plan = textured.get("plan") or {}
    checks.append((export.get("textures") == {"GUI Checker": {"reflectance_texture": [64, 64],
                                                              "roughness_texture": [64, 64]}}
                   and export.get("environment") == [32, 64] and export.get("warnings") == []
                   and plan.get("textures") is True and plan.get("ambient") is True,
                   f"textured export: {export.get('textures')}, ambient map {export.get('environment')}, warnings "
                   f"{export.get('warnings')}; plan textures {plan.get('textures')}, ambient {plan.get('ambient')}"))
    checks.append((transport.get("tracer") == "compiled" and transport.get("tracer_reason") == ""
                   and "compiled" in textured.get("tracer_text", ""),
                   f"render textured (Image Textures, HDRI World): tracer {transport.get('tracer')!r}, reason "
                   f"{transport.get('tracer_reason')!r} ({transport.get('parallel')}), {textured.get('seconds')} s "
                   f"in Render ToF; {textured.get('tracer_text')!r}"))
    checks.append((textured_numpy.get("transport", {}).get("tracer") == "numpy",
                   f"render textured-numpy: tracer {textured_numpy.get('transport', {}).get('tracer')!r}, "
                   f"{textured_numpy.get('seconds')} s"))
    checks.append(same_depth(out, "textured", "textured-numpy"))
    gui = out / "gui"
    rc = int((gui / "rc").read_text()) if (gui / "rc").is_file() else -1
    problems = run.judge(gui, rc)
    checks.append((not problems, f"GUI scenario ({', '.join(run.STEPS)}): " + ("; ".join(problems) or "passed")))
    tracers = [json.loads(f.read_text()).get("stats", {}).get("transport", {}).get("tracer")
               for f in sorted(gui.glob("**/frame.json"))]
    checks.append((bool(tracers) and set(tracers) == {"compiled"},
                   f"GUI frames: {len(tracers)} frame.json, tracers {sorted(set(map(str, tracers)))}"))
    return checks


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tests/blender_gui/numba_run.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("zip", type=Path, help="the extension zip (make addon)")
    parser.add_argument("--wheels", type=Path, required=True, help="folder with the numba, llvmlite and pip wheels")
    parser.add_argument("--out", type=Path, default=Path("out/blender-numba"))
    args = parser.parse_args(argv)
    if not args.zip.is_file():
        parser.error(f"{args.zip}: no such extension zip (make addon builds it)")
    wheels = [sorted(glob.glob(str(args.wheels / pattern))) for pattern in WHEELS]
    if not all(wheels):
        parser.error(f"--wheels {args.wheels}: needs {', '.join(WHEELS)}")
    if os.geteuid() != 0 or not (ROOT / "usr/bin/blender").is_file():
        parser.error(f"needs root and the Debian root {ROOT} (tests/blender_gui/real_blender.sh builds it)")
    for mount in ("proc", "dev"):
        if subprocess.run(["mountpoint", "-q", str(ROOT / mount)]).returncode != 0:
            subprocess.run(["mount", "--bind", f"/{mount}", str(ROOT / mount)], check=True)
    work = f"/tof-numba-{os.getpid()}"
    host = ROOT / work[1:]
    shutil.rmtree(host, ignore_errors=True)
    (host / "out").mkdir(parents=True)
    (host / "wheels").mkdir()
    try:
        shutil.copy(args.zip, host / "ext.zip")
        shutil.copy(HERE / "numba_scenario.py", host)
        shutil.copy(HERE / "scenario.py", host)
        for found in wheels:
            shutil.copy(found[-1], host / "wheels")
        (host / "run.sh").write_text(run_script(work))
        proc = subprocess.run(["chroot", str(ROOT), "/bin/bash", f"{work}/run.sh"],
                              env={"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "LANG": "C.UTF-8"})
        shutil.rmtree(args.out, ignore_errors=True)
        shutil.copytree(host / "out", args.out)
    finally:
        shutil.rmtree(host, ignore_errors=True)
    print((args.out / "wall.txt").read_text() if (args.out / "wall.txt").is_file() else "no timings")
    checks = judge(args.out)
    for ok, line in checks:
        print(f"{'PASS' if ok else 'FAIL'} {line}")
    passed = proc.returncode == 0 and all(ok for ok, _ in checks)
    print(f"numba in a real Blender: {'passed' if passed else f'FAILED (run.sh exited {proc.returncode})'}; "
          f"logs in {args.out}")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
