"""The GPU wavefront's passes on the bench_peers frame, for developers: where a pass's milliseconds go.

The frame of ``bench/bench_compiled.py`` (demo room, 9,800 triangles, 512 × 424, 5 vertices, one point LED,
an 80 MHz phasor), traced by :func:`tofcore.compiled.cuda.trace_pass` on a prepared device scene:

* the median of ``--repeat`` warm passes of 16 spp and of 1 spp (device synchronised before and after);
* the same pass with ``cuda.PROFILE`` on (a synchronisation after every stage, so the parts sum to a little
  more than the pass): start, closest-hit traversal, light vertices, shade, shadow traversal, resolve, gather;
* ``--trace``: the whole ``tofcore.trace(..., progressive=False)`` call with the image read back (the
  per-trace set-up: first hits, upload, workspace), as ``bench/bench_gpu.py`` times it;
* ``--group-mib 256,512,1024``: the 16-spp pass with ``GROUP_BYTES`` of path state per group.

Needs CuPy, numba-cuda and a CUDA GPU: ``python3 bench/gpu_wavefront.py --trace --json $OUT/wavefront.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def prepared(spp: int, width: int = 512, height: int = 424):
    """(device scene, sums, first, counts) of the bench frame at ``spp``."""
    from bench_compiled import frame_args, packed_for

    from tofcore import backend
    from tofcore.compiled import cuda
    from tofcore.tracer import qmc

    cp = backend.select_device("gpu").xp
    args, kwargs = frame_args(width, height, spp)
    packed = packed_for(args, kwargs)
    device_scene = cuda.upload(packed, args[0].bvh)
    n_pix, n_corr = width * height, device_scene.n_correlations
    sums = cuda.Sums(cp.zeros((packed.max_depth, n_pix)), cp.zeros((packed.max_depth, n_corr, n_pix)),
                     cp.zeros((qmc.REPLICATES, n_corr + 2, n_pix)))
    return device_scene, sums, np.zeros(n_pix, np.int64), np.full(n_pix, spp, np.int64)


def pass_ms(setup, repeat: int) -> float:
    """Median ms of ``repeat`` warm passes."""
    from numba import cuda as numba_cuda

    from tofcore.compiled import cuda

    cuda.trace_pass(*setup)
    numba_cuda.synchronize()
    times = []
    for _ in range(repeat):
        numba_cuda.synchronize()
        start = time.perf_counter()
        cuda.trace_pass(*setup)
        numba_cuda.synchronize()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def stage_ms(setup) -> dict:
    """ms per stage of one pass (cuda.PROFILE)."""
    from tofcore.compiled import cuda

    cuda.PROFILE, cuda.STAGE_SECONDS = True, {}
    try:
        cuda.trace_pass(*setup)
    finally:
        cuda.PROFILE = False
    return {name: round(1e3 * s, 2) for name, s in cuda.STAGE_SECONDS.items()}


def trace_ms(spp: int, repeat: int) -> float:
    """Median ms of ``tofcore.trace(..., progressive=False)`` with the correlation image read back."""
    from bench_compiled import frame_args

    import tofcore
    from tofcore import backend

    args, kwargs = frame_args(512, 424, spp)
    times = []
    for i in range(repeat + 1):
        start = time.perf_counter()
        t = tofcore.trace(*args, **kwargs, device="gpu", progressive=False)
        backend.to_host(t.correlation())
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times[1:])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--trace", action="store_true", help="also time tofcore.trace() with its set-up")
    p.add_argument("--group-mib", default="", help="comma list of GROUP_BYTES in MiB for the 16-spp pass")
    p.add_argument("--json", help="write the results here")
    a = p.parse_args()
    from tofcore.compiled import cuda

    results = {}
    for spp in (16, 1):
        setup = prepared(spp)
        results[f"pass_ms_{spp}spp"] = round(pass_ms(setup, a.repeat), 2)
        results[f"stages_ms_{spp}spp"] = stage_ms(setup)
        print(f"{spp:2d} spp: pass {results[f'pass_ms_{spp}spp']} ms; stages {results[f'stages_ms_{spp}spp']}",
              flush=True)
        if a.trace:
            results[f"trace_ms_{spp}spp"] = round(trace_ms(spp, a.repeat), 2)
            print(f"{spp:2d} spp: tofcore.trace() {results[f'trace_ms_{spp}spp']} ms", flush=True)
    default = cuda.GROUP_BYTES
    for mib in (int(m) for m in a.group_mib.split(",") if m):
        cuda.GROUP_BYTES = mib << 20
        setup = prepared(16)
        results[f"pass_ms_group_{mib}mib"] = round(pass_ms(setup, a.repeat), 2)
        print(f"GROUP_BYTES {mib} MiB ({cuda.group_limit(setup[0])} paths): pass "
              f"{results[f'pass_ms_group_{mib}mib']} ms", flush=True)
    cuda.GROUP_BYTES = default
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
