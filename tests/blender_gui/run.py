"""``make test-blender``: the add-on in a real Blender GUI (scenario.py), judged from what it left behind.

    python tests/blender_gui/run.py dist/tof_camera-0.1.0.zip [--out out/blender-gui] [--docs docs/images]

Runs :file:`scenario.py` in Debian 13's Blender 4.3.2 (Python 3.13) on a virtual display through
:file:`real_blender.sh` (root; the first run builds the Debian root, ~3 min, ~1.9 GB, needs Debian's mirror),
then passes only when

* Blender exited 0 (a crash — issue 19's segfault — ends it with a signal, or the scenario never finishes),
* every step of the scenario reported and passed (``results.json``),
* Blender printed no ``Error:`` report before the scenario's deliberate one (step 8), and printed that one
  (Blender prints the reports of operators called from Python; a modal operator's later reports show in the
  status bar, which the scenario checks on every screenshot).

``--docs DIR`` also writes the README's pictures from the screenshots: ``blender-render.png`` (the depth image
and the ToF panels after Render ToF) and ``blender-panels.png`` (the panels with a saved sensor preset and the
unsaved file's output folder). Exit code 0 pass, 1 fail, 2 bad arguments.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
STEPS = ("render", "textured", "live_preview", "cancel", "animation", "preset", "error_report")
MARKER = "GUI-TEST: an error report on purpose follows"


def judge(out: Path, returncode: int) -> list[str]:
    """The reasons the run failed (empty: it passed)."""
    problems = []
    if returncode != 0:
        problems.append(f"Blender exited {returncode} (124: timed out; 128+N: killed by signal N, e.g. 139 = a "
                        f"segmentation fault)")
    results_path = out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else []
    problems += [f"{r['step']}: {r['detail']}" for r in results if not r["ok"]]
    missing = [step for step in STEPS if step not in {r["step"] for r in results}]
    if not results_path.is_file():
        problems.append("no results.json: the scenario never finished (blender.crash.txt holds a crash's backtrace)")
    elif missing:
        problems.append(f"steps that never reported: {missing}")
    log = (out / "blender.log").read_text(errors="replace") if (out / "blender.log").is_file() else ""
    before, _, after = log.partition(MARKER)
    problems += [f"Blender reported: {line}" for line in before.splitlines() if line.startswith("Error:")]
    if MARKER in log and not any(line.startswith("Error:") and "Preset File" in line for line in after.splitlines()):
        problems.append("the deliberate 'Preset File' error of step 8 was not printed as 'Error:'")
    return problems


def crop(screen: Path, box: tuple[int, int, int, int], target: Path, screen_height: int = 1000) -> None:
    """Cut ``box`` (Blender's x, y from the bottom, width, height) out of ``screen`` into ``target``."""
    import cv2

    x, y, w, h = box
    image = cv2.imread(str(screen), cv2.IMREAD_COLOR)
    top = screen_height - (y + h)
    if not cv2.imwrite(str(target), image[top:top + h, x:x + w]):
        raise OSError(f"{target}: could not be written")


def write_docs(out: Path, docs: Path) -> list[Path]:
    shots = json.loads((out / "shots.json").read_text())
    image, panels = shots["areas"]["image"], shots["areas"]["panels"]
    both = (panels[0], image[1], image[0] + image[2] - panels[0], image[3])    # panels on the left, image right
    docs.mkdir(parents=True, exist_ok=True)
    written = [docs / "blender-render.png", docs / "blender-panels.png"]
    crop(out / shots["render"], both, written[0])
    crop(out / shots["preset"], tuple(panels), written[1])
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tests/blender_gui/run.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("zip", type=Path, help="the extension zip (make addon)")
    parser.add_argument("--out", type=Path, default=Path("out/blender-gui"), help="where the run's files go")
    parser.add_argument("--docs", type=Path, default=None, help="write the README screenshots into this folder")
    args = parser.parse_args(argv)
    if not args.zip.is_file():
        parser.error(f"{args.zip}: no such extension zip (make addon builds it)")
    env = {**os.environ, "BLENDER_ARGS": "--enable-event-simulate"}   # the scenario presses Esc
    proc = subprocess.run([str(HERE / "real_blender.sh"), str(args.zip), str(HERE / "scenario.py"), str(args.out)],
                          env=env)
    for line in (args.out / "blender.log").read_text(errors="replace").splitlines() \
            if (args.out / "blender.log").is_file() else []:
        if line.startswith(("GUI-TEST", "Error:", "Info:")):
            print(line)
    problems = judge(args.out, proc.returncode)
    if problems:
        print("make test-blender: FAILED\n  " + "\n  ".join(problems))
        return 1
    if args.docs is not None:
        for path in write_docs(args.out, args.docs):
            print(f"wrote {path}")
    print(f"make test-blender: passed ({len(STEPS)} steps in a real Blender; screenshots in {args.out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
