"""Where a run's worker time went: the records' ``timing`` summed up per worker process.

Every record a worker writes has ``timing`` (:mod:`batch.worker`): when the process started, when
it took the view, the seconds of scene loading and rendering, and, from the writer thread
(:mod:`batch.writer`), when the frame's writing started, its seconds and how long the render thread
waited to hand it over. Per worker (host, pid) this module gives

=============  =================================================================================
``startup_s``  process launched → its first render began (spawn, imports, waiting for the first view)
``first_s``    the first render: on a GPU it also pays importing CuPy, the CUDA context and the
               kernels (compiled when the cache is cold, else loaded from it)
``render_s``   the later renders, summed (``render_median_s``: their median)
``write_s``    metrics and files of every frame, summed (on the writer thread)
``overlap_s``  the part of ``write_s`` spent while the same worker rendered: off the critical path
``wait_s``     the render thread blocked on the writer (its queue full), summed
``idle_s``     the rest of the worker's span (start → last frame finished): waiting for views,
               results travelling to the parent
=============  =================================================================================

so ``startup_s + first_s + render_s + (write_s - overlap_s) + load_s + idle_s`` is the worker's span
(a wait of the render thread is writing that no render overlaps, so it is in ``write_s - overlap_s``).
Records written before the writer thread (no ``write_started``) count their write after their render.
"""

from __future__ import annotations

import statistics


def _write_interval(timing: dict) -> tuple[float, float]:
    start = timing.get("write_started", timing["render_started"] + timing["render_s"])
    return start, start + timing["write_s"]


def _overlap(intervals: list[tuple[float, float]], others: list[tuple[float, float]]) -> float:
    """Seconds of ``intervals`` that lie inside one of ``others`` (each list's intervals disjoint)."""
    total = 0.0
    for a0, a1 in intervals:
        for b0, b1 in others:
            total += max(0.0, min(a1, b1) - max(a0, b0))
    return total


def worker_timing(records: list[dict]) -> list[dict]:
    """One summary per worker process that rendered ``records`` (those with ``timing``), by first start."""
    by_worker: dict[tuple, list[dict]] = {}
    for record in records:
        timing = record.get("timing") or {}
        if "render_started" in timing and "finished" in timing and "write_s" in timing:
            by_worker.setdefault((record.get("host"), record.get("pid")), []).append(record)
    summaries = []
    for (host, pid), rows in by_worker.items():
        rows.sort(key=lambda r: r["timing"]["render_started"])
        timings = [r["timing"] for r in rows]
        first, later = timings[0], timings[1:]
        started = first["worker_started"]
        span = max(t["finished"] for t in timings) - started
        startup = first["render_started"] - started - first.get("load_s", 0.0)
        renders = [t["render_s"] for t in later]
        load = sum(t.get("load_s", 0.0) for t in timings)
        write = sum(t["write_s"] for t in timings)
        overlap = _overlap([_write_interval(t) for t in timings],
                           [(t["render_started"], t["render_started"] + t["render_s"]) for t in timings])
        busy = startup + first["render_s"] + sum(renders) + write - overlap + load
        summaries.append({
            "host": host, "pid": pid, "gpu": rows[0].get("cuda_visible_devices"), "frames": len(rows),
            "worker_started": started, "span_s": span, "startup_s": startup, "first_s": first["render_s"],
            "render_s": sum(renders), "render_median_s": statistics.median(renders) if renders else None,
            "write_s": write, "overlap_s": overlap, "wait_s": sum(t.get("handoff_wait_s", 0.0) for t in timings),
            "load_s": load, "idle_s": max(0.0, span - busy),
        })
    return sorted(summaries, key=lambda s: s["worker_started"])


def timing_lines(summaries: list[dict]) -> list[str]:
    """One log line per worker."""
    lines = []
    for s in summaries:
        where = f"GPU {s['gpu']}" if s["gpu"] else "CPU"
        median = "–" if s["render_median_s"] is None else f"{s['render_median_s']:.2f} s"
        lines.append(f"worker {s['pid']} ({where}): {s['frames']} frame(s) in {s['span_s']:.1f} s: start-up "
                     f"{s['startup_s']:.1f} s, first render {s['first_s']:.1f} s, then render "
                     f"{s['render_s']:.1f} s (median {median}), write {s['write_s']:.1f} s ({s['overlap_s']:.1f} s "
                     f"of it while rendering; rendering waited {s['wait_s']:.1f} s for the writer), scene load "
                     f"{s['load_s']:.1f} s, idle {s['idle_s']:.1f} s")
    return lines
