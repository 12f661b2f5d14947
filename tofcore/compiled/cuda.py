"""The compiled tracer on the GPU: the same source (kernels.py) compiled by numba.cuda, as a wavefront.

:func:`load_kernels` executes ``kernels.py`` a second time under the module name
``tofcore.compiled.kernels_cuda``, for which every scalar function becomes a ``numba.cuda`` device
function and the ``wf_*`` functions kernels (:mod:`tofcore.compiled._target`). :func:`trace_pass` runs
the path in stages over groups of paths — start (camera and light rays), light vertices, then per depth
shade, resolve — with the BVH's own CUDA traversal (:mod:`tofcore.gpu.traversal`, one thread per ray,
bit for bit NumPy's) tracing every ray set in between, and gathers each pixel's addends in sample order:
the pass's sums are the CPU's addend by addend, so a GPU frame is the CPU frame up to the GPU's libm and
its fused multiply–adds in the shading code (tests/tofcore/test_gpu.py states the tolerance). No atomics:
the same frame on every run.

Why a wavefront (docs/benchmarks.md, issue 21): the whole path as one kernel (a megakernel) needed 255
registers a thread and ran at 12.5 % occupancy with 13 of 32 threads of a warp active — 208–229 ms for
the bench_peers frame, against 126 ms for these stages.

The machine code is cached by numba (``cache=True``) beside the sources (``tofcore/compiled/__pycache__``)
or under ``NUMBA_CACHE_DIR``: the first process on a machine compiles for ~15–30 s, later ones load it
(``tofcore warmup --device gpu``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import numba

from ._target import load_cuda_build, numba_cuda
from .launch import PreparedKernel, Slot
from .layout import N_COUNTERS

cuda = numba_cuda()

THREADS_PER_BLOCK = 256
"""Threads per block of the stage kernels (128 measured the same, docs/benchmarks.md)."""

GROUP_BYTES = 512 << 20
"""Device memory one group's per-path state may take: the group size follows from it (about 0.4–0.9 M paths;
the Kinect v2 frame peaked at 2.3 GiB on the device with 768 MiB)."""

MAX_GROUP_PATHS = 1 << 20


STAGE_SECONDS: dict[str, float] = {}
"""Seconds per stage summed over the passes traced while :data:`PROFILE` is on (benchmarks only: each stage
then ends with a device synchronisation)."""

PROFILE = False


def _stage_done(name: str, since: float) -> float:
    """With :data:`PROFILE` on, wait for the device and add the time since ``since`` to stage ``name``."""
    if not PROFILE:
        return since
    cuda.synchronize()
    now = time.perf_counter()
    STAGE_SECONDS[name] = STAGE_SECONDS.get(name, 0.0) + now - since
    return now


def load_kernels():
    """The CUDA build of kernels.py (loaded once per process)."""
    return load_cuda_build(__name__.rsplit(".", 1)[0] + ".kernels", str(Path(__file__).with_name("kernels.py")))


@dataclass(eq=False)
class DeviceScene:
    """A render's packed arrays (:class:`tofcore.compiled.setup.Packed`) on the GPU (``arrays``, CuPy; NumPy
    under numba's CUDA simulator) and as the kernels take them (``scene``), its settings (key, max_depth,
    independent, light_paths, ambient radiance, transient bin width), the scene's BVH (its records are uploaded by
    :mod:`tofcore.gpu.traversal` at the first ray), and the wavefront's :class:`Workspace` (made at the
    first pass). After its trace (:func:`release`) it serves the next trace of the same ``layout``: the
    arrays get the new contents, the workspace and its prepared kernels stay. ``host`` keeps the host arrays
    last copied, so an array the next trace passes again (the same memory: a BVH's records, a mesh's tables)
    is not copied again — the policy of :func:`tofcore.backend.device_copy`: host tables are not changed in
    place."""

    arrays: tuple
    host: tuple
    scene: tuple
    settings: tuple
    n_correlations: int
    max_depth: int
    bvh: object
    layout: tuple
    work: dict = field(default_factory=dict)


_IDLE: dict = {}
"""The device scene of the last finished trace, by layout (at most one, so its memory stays bounded)."""


def upload(packed, bvh) -> DeviceScene:
    """The packed scene, camera, LED and channel tables on the GPU: copied into the arrays of the last
    finished trace's device scene where their shapes and types match (its kernels stay prepared), else
    into new ones."""
    module = load_kernels()
    n_corr = len(packed.corr_kinds)
    if n_corr + 2 > module.GPU_MAX_CHANNELS:
        raise ValueError(f"the GPU tracer takes at most {module.GPU_MAX_CHANNELS - 2} correlation channels, "
                         f"got {n_corr}")
    geo, cam, cam_table, frame, leds, corr_kinds, corr_table, corr_data, sky = packed.scene()
    corr_table = corr_table if n_corr else np.zeros((1, 6))  # numba types an empty table by a row
    host = (tuple(np.ascontiguousarray(a) for a in geo), cam, cam_table, frame,
            tuple(np.ascontiguousarray(a) for a in leds), corr_kinds, corr_table, corr_data, sky)
    settings = packed.settings()
    layout = (tuple((a.shape, a.dtype.str) for a in _leaves(host)), int(packed.max_depth))
    device_scene = _IDLE.pop(layout, None)
    if device_scene is None:
        arrays = _nest_map(_device_namespace().array, host)  # a copy: the host arrays stay the caller's
        return DeviceScene(arrays, host, _nest_map(_kernel_array, arrays), settings, n_corr, int(packed.max_depth),
                           bvh, layout)
    for target, values, before in zip(_leaves(device_scene.arrays), _leaves(host), _leaves(device_scene.host)):
        if _same_memory(values, before):
            continue
        if hasattr(target, "set"):
            target.set(values)  # CuPy: one copy to the device
        else:
            target[...] = values
    device_scene.host, device_scene.settings, device_scene.bvh = host, settings, bvh
    return device_scene


def _same_memory(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether host arrays ``a`` and ``b`` are the same memory seen the same way (``b`` is kept alive, so its
    address cannot have been given to another array)."""
    return (a.__array_interface__["data"][0] == b.__array_interface__["data"][0] and a.shape == b.shape
            and a.strides == b.strides and a.dtype == b.dtype)


def _device_namespace():
    """CuPy, or NumPy under numba's CUDA simulator (tests)."""
    from .. import backend

    return np if numba.config.ENABLE_CUDASIM else backend.select_device("gpu").xp


def release(device_scene: DeviceScene) -> None:
    """Keep a finished trace's device scene for the next trace of its layout (dropping any other kept one)."""
    _IDLE.clear()
    _IDLE[device_scene.layout] = device_scene


def launch_plan(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, active): pixels by decreasing sample count (stable), and for each sample index s < the
    largest count how many pixels have more than s samples — pixel order[i] has sample s for i < active[s]."""
    counts = np.asarray(counts, dtype=np.int64)
    most = int(counts.max()) if counts.size else 0
    if counts.size and int(counts.min()) == most:
        order = np.arange(counts.size)  # a uniform pass
    else:  # NumPy's stable sort of 16-bit keys is a radix sort: 217,088 adaptive counts in 4 ms, not 13 ms
        shortfall = most - counts
        order = np.argsort(shortfall.astype(np.uint16) if most < 1 << 16 else shortfall, kind="stable")
    more_than = counts.size - np.cumsum(np.bincount(counts, minlength=most + 1))  # [s]: #pixels with count > s
    return order, more_than[:most]


def groups(active: np.ndarray, limit: int) -> list[tuple[int, int]]:
    """Consecutive sample-index ranges [s0, s1) of at most ``limit`` paths each (at least one index)."""
    out, s0 = [], 0
    while s0 < len(active):
        s1, paths = s0 + 1, int(active[s0])
        while s1 < len(active) and paths + int(active[s1]) <= limit:
            paths += int(active[s1])
            s1 += 1
        out.append((s0, s1))
        s0 = s1
    return out


def path_bytes(n_depth: int, n_corr: int, n_led: int) -> int:
    """Device bytes of one path's state in a group: what :func:`_group_arrays` allocates for one path."""
    arrays = _group_arrays(np, 1, n_depth, n_corr, n_led + 1, load_kernels().LIGHT_COLUMNS)
    return sum(a.nbytes for a in _leaves(arrays))


def group_limit(device_scene: DeviceScene) -> int:
    """Most paths a group holds: :data:`GROUP_BYTES` of path state, at most :data:`MAX_GROUP_PATHS`."""
    n_led = int(device_scene.scene[4][0].shape[0])
    return max(1, min(MAX_GROUP_PATHS, GROUP_BYTES // path_bytes(device_scene.max_depth,
                                                                 device_scene.n_correlations, n_led)))


def trace_pass(device_scene: DeviceScene, out, first: np.ndarray, counts: np.ndarray,
               threads_per_block: int = THREADS_PER_BLOCK) -> np.ndarray:
    """Trace samples [first[p], first[p] + counts[p]) of every pixel into ``out``'s sums on the GPU.

    ``out`` holds CuPy arrays ``signal_sum`` (K, P), ``correlation_sum`` (K, J, P), ``replicate_sum``
    (R, J + 2, P), ``ambient_sum`` (P,) and ``transient_sum`` (P, B) or None (a
    :class:`tofcore.tracer.transport.Transport` on the GPU); NumPy arrays under numba's CUDA simulator (tests).
    Per group of sample indices (:func:`groups`): start every path, trace the
    camera and light rays, the light vertices; per depth shade the live paths, trace the shadow rays that
    need a test, resolve, gather the depth's addends, trace the next rays. No synchronisation until the pass's ray counts are
    read back at its end. Returns those counts (N_COUNTERS,) on the host.
    """
    from .. import backend

    xp = backend.namespace(out.signal_sum)
    n_pix = int(np.asarray(counts).size)
    order, active = launch_plan(counts)
    offsets = np.concatenate([[0], np.cumsum(active)]).astype(np.int64)
    plan = [(s0, s1, int(offsets[s1] - offsets[s0])) for s0, s1 in groups(active, group_limit(device_scene))]
    n_bins = 0 if getattr(out, "transient_sum", None) is None else int(out.transient_sum.shape[1])
    ws = workspace(device_scene, xp, n_pix, len(offsets), max((n for *_, n in plan), default=0), threads_per_block,
                   n_bins)
    ws.begin_pass(device_scene.settings, order, first, offsets)
    for s0, s1, n in plan:
        ws.trace_group(device_scene.bvh, s0, s1, n, int(active[s0]))
    nee_w, nee_wg, con_w, con_wg, replicate, ambient = ws.sums
    out.signal_sum += con_w          # the reference's order: connections, then next-event estimates
    out.signal_sum += nee_w
    out.correlation_sum += con_wg
    out.correlation_sum += nee_wg
    out.replicate_sum += replicate
    out.ambient_sum += ambient
    if n_bins:
        out.transient_sum += ws.film
    return ws.end_pass()


def workspace(device_scene: DeviceScene, xp, n_pix: int, n_offsets: int, n_paths: int,
              threads_per_block: int, n_bins: int = 0) -> Workspace:
    """The scene's :class:`Workspace` for a pass of ``n_pix`` pixels, ``n_offsets`` − 1 sample indices,
    groups of at most ``n_paths`` paths and ``n_bins`` transient bins: the last pass's where it has the
    room, else a new one (with twice the room it grows from, as far as :func:`group_limit` allows, so
    progressive passes make few)."""
    ws = device_scene.work.get("wavefront")
    if (ws is not None and ws.n_pix == n_pix and ws.limit >= n_paths and len(ws.offsets) >= n_offsets
            and ws.threads_per_block == threads_per_block and ws.n_bins == n_bins):
        return ws
    grown = 2 * ws.limit if ws is not None and ws.n_pix == n_pix else 0
    paths = max(n_paths, min(grown, group_limit(device_scene)), 1)
    room = max(n_offsets, 2 * len(ws.offsets) if ws is not None else 0, 65)
    ws = device_scene.work["wavefront"] = None  # the old buffers go back to the pool before new ones are taken
    ws = device_scene.work["wavefront"] = Workspace(device_scene, xp, n_pix, paths, room, threads_per_block, n_bins)
    return ws


class Workspace:
    """The wavefront's device buffers for one render's passes and its kernels prepared over them
    (:class:`tofcore.compiled.launch.PreparedKernel`): from group to group only the group's bounds (s0,
    s1, n) and the depth change, so each stage is one ``cuLaunchKernel`` and each ray set one traversal
    launch — no allocation, no host synchronisation inside a pass. A transient render's histogram of the
    pass (``film``, P × B) is filled by ``wf_transient`` after each depth's resolve."""

    def __init__(self, device_scene: DeviceScene, xp, n_pix: int, limit: int, room: int, threads_per_block: int,
                 n_bins: int = 0):
        from ..tracer import qmc

        module = load_kernels()
        self.xp, self.n_pix, self.limit, self.max_depth = xp, n_pix, limit, device_scene.max_depth
        self.threads_per_block = threads_per_block
        self.n_bins = n_bins
        self.film = xp.zeros((n_pix, n_bins) if n_bins else (1, 1))
        k_max, n_corr = device_scene.max_depth, device_scene.n_correlations
        self.slots = int(device_scene.scene[4][0].shape[0]) + 1
        self.n_corr = n_corr
        self.arrays = _group_arrays(xp, limit, k_max, n_corr, self.slots, module.LIGHT_COLUMNS)
        a = self.arrays
        self.hits = (xp.empty(limit, np.int32), xp.empty(limit, np.float32), xp.empty(limit, np.float32),
                     xp.empty(limit, np.float32))  # prim, u, v, t
        self.light_hits = tuple(xp.empty_like(h) for h in self.hits)
        self.light_t_max = xp.full(limit, np.inf, np.float32)
        self.occluded = xp.zeros(limit * self.slots, np.bool_)
        self.status = xp.zeros(1, np.int32)
        self.pixels = (xp.zeros(n_pix, np.int64), xp.zeros(n_pix, np.int64))  # order, first
        self.offsets = xp.zeros(room, np.int64)
        self.sums = (xp.zeros((k_max, n_pix)), xp.zeros((k_max, n_corr, n_pix)), xp.zeros((k_max, n_pix)),
                     xp.zeros((k_max, n_corr, n_pix)), xp.zeros((qmc.REPLICATES, n_corr + 2, n_pix)), xp.zeros(n_pix))
        k = _kernel_arrays
        scene = device_scene.scene
        settings = (Slot("key", np.uint64), Slot("max_depth"), Slot("independent", np.bool_),
                    Slot("light_paths", np.bool_), Slot("ambient", np.float64),
                    Slot("transient_bin_m", np.float64))  # set per pass (begin_pass)
        group = (*k(self.pixels), _kernel_array(self.offsets), Slot("s0"), Slot("s1"))
        path, counters = k(a["path"]), _kernel_array(a["counters"])
        buffers = (k(a["pstate"]), _kernel_array(a["light"]), k(a["pend"]), k(a["shadow"]), k(a["rays"]), counters,
                   _kernel_array(a["total"]))
        self.arguments = {
            "wf_start": (scene, settings, group, path, buffers[0], buffers[4], k(a["light_rays"]), counters),
            "wf_light": (scene, settings, Slot("n"), path, k(self.light_hits[:3]), buffers[1]),
            "wf_shade": (scene, settings, Slot("depth"), Slot("n"), path, k(self.hits[:3]), buffers),
            "wf_resolve": (scene, Slot("depth"), Slot("n"), path, buffers[2], _kernel_array(self.occluded),
                           _kernel_array(a["total"]), k(a["contrib"])),
            "wf_gather": (group, Slot("depth"), _kernel_array(a["path"][1]), k(a["contrib"]),
                          _kernel_array(a["total"]), k(self.sums))}
        if n_bins:
            self.arguments["wf_transient"] = (group, Slot("transient_bin_m", np.float64), path, k(a["pend"]),
                                              _kernel_array(self.occluded), _kernel_array(self.film))
        """Each stage kernel's arguments (:class:`tofcore.compiled.launch.Slot` where they change)."""
        self.kernels = {name: PreparedKernel(getattr(module, name), arguments, threads_per_block)
                        for name, arguments in self.arguments.items()}

    def begin_pass(self, settings: tuple, order: np.ndarray, first: np.ndarray, offsets: np.ndarray) -> None:
        """Set the render's ``settings`` (key, max_depth, independent, light_paths, ambient, transient bin
        width); upload the pass's pixel order, first sample indices and offsets; zero its sums, histogram and
        ray counts."""
        xp = self.xp
        values = dict(zip(("key", "max_depth", "independent", "light_paths", "ambient", "transient_bin_m"), settings))
        for name in ("wf_start", "wf_light", "wf_shade"):
            self.kernels[name].set(**values)
        if self.n_bins:
            self.kernels["wf_transient"].set(transient_bin_m=values["transient_bin_m"])
            self.film.fill(0)
        self.light_paths = bool(values["light_paths"])
        self.pixels[0][:] = xp.asarray(order, dtype=np.int64)
        self.pixels[1][:] = xp.asarray(first, dtype=np.int64)
        self.offsets[:len(offsets)] = xp.asarray(offsets)
        for a in (*self.sums, self.arrays["counters"]):
            a.fill(0)

    def trace_group(self, bvh, s0: int, s1: int, n: int, lead: int) -> None:
        """The stages of the group of sample indices [s0, s1) (n paths; ``lead`` pixels in its first index):
        start, light vertices, then per depth trace, shade, trace the shadow rays, resolve, gather. Every
        slot is traced at every depth: an ended path's ray and a shadow slot without a test have t_max −1,
        which the traversal rejects at the root — no compaction and no host synchronisation to count them."""
        a, tr, kernel = self.arrays, _traversal(), self.kernels
        a["total"].fill(0)
        t = _stage_done("zero", time.perf_counter())
        kernel["wf_start"].launch(n, s0=s0, s1=s1)
        t = _stage_done("start", t)
        if self.light_paths:
            o, d, ig = a["light_rays"]
            tr.closest_hits_into(bvh, (o, d, self.light_t_max, ig), n, self.light_hits, self.status)
            t = _stage_done("trace", t)
            kernel["wf_light"].launch(n, n=n)
            t = _stage_done("light", t)
        rays, shadow = a["rays"], a["shadow"]
        for depth in range(1, self.max_depth + 1):
            tr.closest_hits_into(bvh, (rays[0], rays[1], rays[3], rays[2]), n, self.hits, self.status)
            t = _stage_done("trace", t)
            kernel["wf_shade"].launch(n, depth=depth, n=n)
            t = _stage_done("shade", t)
            tr.occluded_into(bvh, (shadow[0], shadow[1], shadow[2], shadow[3]), n * self.slots, self.occluded,
                             self.status)
            t = _stage_done("trace shadows", t)
            kernel["wf_resolve"].launch(n, depth=depth, n=n)
            t = _stage_done("resolve", t)
            kernel["wf_gather"].launch(lead * self.gather_outputs(depth), depth=depth, s0=s0, s1=s1)
            t = _stage_done("gather", t)
            if self.n_bins:
                kernel["wf_transient"].launch(lead, s0=s0, s1=s1)
                t = _stage_done("transient", t)

    def gather_outputs(self, depth: int) -> int:
        """Sums per pixel that wf_gather adds to after ``depth`` (kernels.gather_outputs)."""
        n_corr = self.n_corr
        return (1 + n_corr) * (2 if depth < self.max_depth else 1) + (n_corr + 3 if depth == self.max_depth else 0)

    def end_pass(self) -> np.ndarray:
        """The pass's ray counts (N_COUNTERS,) on the host (the pass's one synchronisation), after checking
        that no traversal overflowed its stack."""
        from .. import backend

        _traversal().check_status(self.status)
        return backend.to_host(self.arrays["counters"].sum(axis=1))


class FirstHitWork:
    """The device buffers and prepared kernels of the ground truth's P pixel-centre rays
    (:func:`first_hit`), kept with the device scene while the frame size stays."""

    def __init__(self, device_scene: DeviceScene, xp, n_pix: int, threads_per_block: int):
        module = load_kernels()
        self.n_pix = n_pix
        self.directions = xp.zeros((n_pix, 3), np.float32)  # the camera's sensor-frame pixel directions
        self.camera_directions = None  # the host array they were copied from (kept alive: its id stays its own)
        self.object_ids = xp.zeros(len(device_scene.host[0][8]), np.int32)
        self.rays = (xp.empty((n_pix, 3), np.float32), xp.empty((n_pix, 3), np.float32), xp.empty(n_pix, np.float32),
                     xp.empty(n_pix, np.int32))  # origin, direction, t_max, ignore: the traversal's order
        self.hits = (xp.empty(n_pix, np.int32), xp.empty(n_pix, np.float32), xp.empty(n_pix, np.float32),
                     xp.empty(n_pix, np.float32))  # prim, u, v, t
        self.record = (xp.empty(n_pix), xp.empty((3, n_pix, 3), np.float32), xp.empty((2, n_pix), np.int32))
        self.status = xp.zeros(1, np.int32)
        scene, k = device_scene.scene, _kernel_arrays
        origin = (Slot("ox", np.float64), Slot("oy", np.float64), Slot("oz", np.float64))
        self.kernels = {
            "rays": PreparedKernel(module.wf_first_rays, (scene[3], _kernel_array(self.directions), k(self.rays)),
                                   threads_per_block),
            "record": PreparedKernel(module.wf_first_hit, (scene[0], _kernel_array(self.object_ids), origin, scene[3],
                                                           _kernel_array(self.directions), k(self.hits[:3]),
                                                           k(self.record)), threads_per_block)}


def first_hit(device_scene: DeviceScene, setup, stats, threads_per_block: int = THREADS_PER_BLOCK):
    """The noise-free ground truth of a GPU trace (:func:`tofcore.tracer.stages.first_hit`: the same rays,
    traversal and hit geometry), as the :class:`~tofcore.tracer.transport.FirstHit` of host arrays: one thread
    per pixel makes the rays (``wf_first_rays``), the BVH's traversal traces them, one thread per pixel makes the
    record (``wf_first_hit``), which comes back in three copies."""
    from .. import backend
    from ..tracer.transport import FirstHit

    camera = setup.camera
    shape = (camera.height, camera.width)
    n_pix = shape[0] * shape[1]
    work = device_scene.work.get("first_hit")
    if work is None or work.n_pix != n_pix or len(work.object_ids) != len(setup.table.object_ids):
        work = device_scene.work["first_hit"] = None  # the old buffers go back to the pool first
        work = device_scene.work["first_hit"] = FirstHitWork(device_scene, _device_namespace(), n_pix,
                                                             threads_per_block)
    directions = camera.pixel_center_directions()  # cached per camera, read-only
    if directions is not work.camera_directions:
        work.directions[...] = _device_namespace().asarray(directions.reshape(n_pix, 3))
        work.camera_directions = directions
    work.object_ids[...] = setup.table.object_ids
    origin = np.asarray(setup.scene.origin_m, dtype=np.float64)
    work.kernels["record"].set(ox=origin[0], oy=origin[1], oz=origin[2])
    work.kernels["rays"].launch(n_pix)
    tr = _traversal()
    tr.closest_hits_into(device_scene.bvh, work.rays, n_pix, work.hits, work.status)
    work.kernels["record"].launch(n_pix)
    tr.check_status(work.status)
    distance, vectors, ids = (backend.to_host(a) for a in work.record)
    stats.camera_rays += n_pix
    return FirstHit(distance_m=distance.reshape(shape), position_m=vectors[0].reshape(shape + (3,)),
                    normal=vectors[1].reshape(shape + (3,)), material_id=ids[0].reshape(shape),
                    object_id=ids[1].reshape(shape), direction=vectors[2].reshape(shape + (3,)))


def _traversal():
    """The traversal of the rays (tofcore.gpu.traversal on the GPU; the NumPy BVH under the simulator)."""
    if numba.config.ENABLE_CUDASIM:
        return _SimulatedTraversal
    from ..gpu import traversal

    return traversal


class _SimulatedTraversal:
    """tofcore.gpu.traversal's wavefront entry points over the NumPy BVH (numba's CUDA simulator, tests)."""

    @staticmethod
    def closest_hits_into(bvh, rays, n, hits, status):
        if n:
            o, d, t_max, ignore = (r[:n] for r in rays)
            h = bvh.intersect(o, d, t_max, ignore_prim=ignore)
            for dst, src in zip(hits, (h.prim, h.u, h.v, h.t)):
                dst[:n] = src

    @staticmethod
    def occluded_into(bvh, rays, n, out, status):
        if n:
            o, d, t_max, ignore = (r[:n] for r in rays)
            out[:n] = bvh.occluded(o, d, t_max, ignore_prim=ignore)

    @staticmethod
    def check_status(status):
        pass


def _group_arrays(xp, n: int, k_max: int, n_corr: int, slots: int, light_columns: int) -> dict:
    """The per-path arrays of a group of ``n`` paths (the table in kernels.py's wavefront section)."""
    f32, i32 = np.float32, np.int32
    return {"path": (xp.empty(n, np.int64), xp.empty(n, np.int64), xp.zeros(n, np.int8), xp.zeros(n, np.int8)),
            "pstate": (xp.empty((13, n)), xp.empty(n, i32)),
            "rays": (xp.empty((n, 3), f32), xp.empty((n, 3), f32), xp.empty(n, i32), xp.empty(n, f32)),
            "light_rays": (xp.zeros((n, 3), f32), xp.zeros((n, 3), f32), xp.full(n, -1, i32)),
            "light": xp.zeros((light_columns, n)),
            "pend": (xp.zeros((slots, n)), xp.zeros((slots, n))),
            "shadow": (xp.zeros((n * slots, 3), f32), xp.zeros((n * slots, 3), f32), xp.zeros(n * slots, f32),
                       xp.full(n * slots, -1, i32)),
            "total": xp.zeros((n_corr + 2, n)),
            "contrib": (xp.zeros((n_corr + 1, n)), xp.zeros((n_corr + 1, n))),
            "counters": xp.zeros((N_COUNTERS, n), np.int64)}


def _leaves(tree):
    """The arrays of a nest of dicts and tuples."""
    if isinstance(tree, dict):
        tree = tuple(tree.values())
    if isinstance(tree, tuple):
        return [a for t in tree for a in _leaves(t)]
    return [tree]


def _nest_map(function, tree: tuple) -> tuple:
    """``tree`` (nested tuples) with ``function`` applied to each leaf."""
    return tuple(_nest_map(function, t) if isinstance(t, tuple) else function(t) for t in tree)


def _kernel_arrays(arrays: tuple) -> tuple:
    """Arrays as the kernels take them (:func:`_kernel_array`)."""
    return tuple(_kernel_array(a) for a in arrays)


def _kernel_array(a):
    """A CuPy array as numba sees it; a NumPy array as it is (numba's CUDA simulator)."""
    return cuda.as_cuda_array(a) if hasattr(a, "__cuda_array_interface__") else a


@dataclass
class Sums:
    """Stand-alone sums for :func:`trace_frame` (the layout of tofcore.tracer.transport.Transport)."""

    signal_sum: object
    correlation_sum: object
    replicate_sum: object
    ambient_sum: object


def trace_frame(packed, bvh, n_pix: int, spp: int, threads_per_block: int = THREADS_PER_BLOCK) -> dict:
    """One pass of ``spp`` samples of every pixel on the GPU, for benchmarks and checks.

    Returns host arrays ``signal_sum`` (K, P), ``correlation_sum`` (K, J, P), ``replicate_sum``
    (R, J + 2, P), ``ambient_sum`` (P,), ``counters`` (N_COUNTERS,), the seconds of the pass (``kernel_s``, synchronised) and
    of the whole call (``seconds``: uploads, pass, read-back).
    """
    from .. import backend
    from ..tracer import qmc

    xp = _device_namespace()
    start = time.perf_counter()
    device_scene = upload(packed, bvh)
    n_corr = device_scene.n_correlations
    out = Sums(xp.zeros((packed.max_depth, n_pix)), xp.zeros((packed.max_depth, n_corr, n_pix)),
               xp.zeros((qmc.REPLICATES, n_corr + 2, n_pix)), xp.zeros(n_pix))
    first, counts = np.zeros(n_pix, np.int64), np.full(n_pix, spp, np.int64)
    cuda.synchronize()
    launch = time.perf_counter()
    counters = trace_pass(device_scene, out, first, counts, threads_per_block)
    cuda.synchronize()
    kernel_s = time.perf_counter() - launch
    return {"signal_sum": backend.to_host(out.signal_sum), "correlation_sum": backend.to_host(out.correlation_sum),
            "replicate_sum": backend.to_host(out.replicate_sum), "ambient_sum": backend.to_host(out.ambient_sum),
            "counters": counters, "kernel_s": kernel_s,
            "seconds": time.perf_counter() - start}
