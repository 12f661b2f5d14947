"""Where a GPU frame's host time goes: cProfile of a dataset worker's frames and of live-preview frames.

Two profiles in one process on the GPU (both warm: a frame of each kind renders first, unprofiled):

* **dataset**: ``batch.run.run_jobs(..., inline=True, device=device)`` on a ``--frames`` Kinect v2 set of the demo
  room (64 spp, PNG + JSON, random poses) — the worker's render loop in this process, its writer thread beside it
  (cProfile sees the render thread only);
* **preview**: ``tofcore.render(..., spp=1)`` of the Kinect v2 room at full size, the camera moving a little each
  frame (what the add-on's live preview asks for after a camera move).

Writes ``<name>.txt`` (the top functions by cumulative and by own time) and ``<name>.prof`` into ``--out``, and
prints ms per frame.

    PYTHONPATH=. python3 bench/gpu/profile_frames.py --out $OUT
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from bench_multigpu import SET  # noqa: E402


def dump(profile: cProfile.Profile, out: Path, name: str, top: int) -> None:
    profile.dump_stats(out / f"{name}.prof")
    text = io.StringIO()
    stats = pstats.Stats(profile, stream=text)
    stats.sort_stats("cumulative").print_stats(top)
    stats.sort_stats("tottime").print_stats(top)
    (out / f"{name}.txt").write_text(text.getvalue())


def dataset_profile(frames: int, spp: int, out: Path, top: int, device: str) -> float:
    from batch.jobs import expand
    from batch.run import run_jobs
    from batch.setfile import load_set

    work = Path(tempfile.mkdtemp(prefix="profile-frames-"))
    args = dict(spp=spp, max_depth=5, scale=1.0)

    def jobs_of(n: int):
        set_file = work / f"set-{n}.toml"
        set_file.write_text(SET.format(frames=n, **args))
        return expand(load_set(set_file)).jobs

    run_jobs(jobs_of(2), work / "warm", inline=True, device=device, quiet=True)
    jobs = jobs_of(frames)
    profile = cProfile.Profile()
    start = time.perf_counter()
    profile.enable()
    run_jobs(jobs, work / "profiled", inline=True, device=device, quiet=True)
    profile.disable()
    seconds = time.perf_counter() - start
    dump(profile, out, "dataset", top)
    return seconds / frames


def preview_profile(frames: int, out: Path, top: int, device: str) -> float:
    import numpy as np

    import tofcore
    from tofcore.scene.demo import suggested_pose

    scene, sensor = tofcore.demo_scene("room"), tofcore.load_preset("kinect_v2")
    pose = suggested_pose(scene, [sensor])
    poses = []
    for k in range(frames + 1):
        moved = np.array(pose, dtype=float)
        moved[0, 3] += 0.002 * k
        poses.append(moved)
    tofcore.render(scene, sensor, poses[0], spp=1, max_depth=5, device=device)
    profile = cProfile.Profile()
    start = time.perf_counter()
    profile.enable()
    for p in poses[1:]:
        tofcore.render(scene, sensor, p, spp=1, max_depth=5, device=device)
    profile.disable()
    seconds = time.perf_counter() - start
    dump(profile, out, "preview", top)
    return seconds / frames


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--preview-frames", type=int, default=40)
    p.add_argument("--top", type=int, default=70)
    p.add_argument("--device", default="gpu", help="cpu: a smoke test of this script")
    a = p.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    print(f"preview: {1e3 * preview_profile(a.preview_frames, a.out, a.top, a.device):.1f} ms a frame (profiled)", flush=True)
    print(f"dataset: {1e3 * dataset_profile(a.frames, a.spp, a.out, a.top, a.device):.1f} ms a frame (profiled)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
