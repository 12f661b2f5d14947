"""Shared set-up of the cross-check: one scene description rendered by tofcore and by mitransient.

Both renderers get
* the same triangles (tofcore's demo geometry, written to binary PLY files, one per material),
* exact Lambertian materials ρ/π (tofcore: roughness 0, ior 1.0 — no specular lobe; Mitsuba:
  ``diffuse`` wrapped in ``twosided``, because tofcore's surfaces are two-sided),
* the same point LED (isotropic, 1 W/sr) at ``LED_OFFSET_M`` in the sensor frame,
* the same pinhole (OpenCV intrinsics from ``tofcore.Camera.from_fov``; Mitsuba ``perspective``
  with the same horizontal FOV, square pixels, principal point at the image centre),
* the same pixel filter: a uniform jitter over the pixel footprint (tofcore always; Mitsuba's
  ``box`` rfilter, under which mitransient splats each sample into the pixel it was drawn in),
* the same path length: tofcore ``max_depth`` = surface vertices; Mitsuba ``max_depth`` counts the
  camera ray as one, so it is tofcore's + 1. Russian roulette is switched off in Mitsuba
  (``rr_depth`` > ``max_depth``): tofcore has none.

Phasors: for a sine of frequency f, tofcore correlates every contribution with
g_cos(τ) = cos 2πfτ and g_sin(τ) = sin 2πfτ (τ = L/c), so P = Σ w e^{+i 2π f L/c};
mitransient's ``phasor_hdr_film`` stores Σ w e^{−i 2π ν L} with ν in cycles per metre of optical
path, so P_tofcore = conj(P_mitransient) for ν = f/c. Its frequencies are the FFT bins
k / (temporal_bins · bin_width_opl) for k in a window chosen by ``wl_mean``/``wl_sigma``; with
temporal_bins · bin_width_opl = c / 8 MHz the bins k = 2, 10, 15 are exactly 16, 80 and 120 MHz.

Depth: distance = c/(4πf) · arg P (radial, round trip halved); the multipath error is
c/(4πf) · arg(P_full · conj(P_direct)), P_direct = light with one surface vertex only.
"""

from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import tofcore

C = tofcore.SPEED_OF_LIGHT_M_S
LED_OFFSET_M = (0.025, 0.0, 0.0)   # 2.5 cm to the right of the lens (sensor frame: x right, y down, z forward)
HFOV_DEG = 70.6                    # Kinect v2's horizontal field of view
BASE_HZ = 8e6                      # the phasor film's frequency grid: multiples of 8 MHz
WORK = Path(__file__).resolve().parents[2] / "out" / "crosscheck"   # PLY exports, per-pixel arrays (not committed)


@dataclass
class Setup:
    name: str
    scene: tofcore.Scene
    camera: tofcore.Camera
    led: tofcore.LED
    pose: np.ndarray            # world_from_sensor (OpenCV sensor axes)
    albedo: tuple[float, ...]   # ρ per material id


# The diffuse versions of the demo scenes: the demo geometry, exact Lambertian materials.
ALBEDO = {"corner": (0.8,), "box_on_wall": (0.9, 0.5), "room": (0.7, 0.3, 0.5, 0.6)}


def make_setup(name: str, width: int = 128, height: int = 106, detail: int = 4) -> Setup:
    """The demo scene ``name`` with Lambertian materials (same ρ as the demo, the room's metal box ρ = 0.6)."""
    demo = tofcore.demo_scene(name, detail=detail)
    albedo = ALBEDO[name]
    materials = [tofcore.Material(name=f"lambert{i}", reflectance=a, roughness=0.0, ior=1.0)
                 for i, a in enumerate(albedo)]
    scene = tofcore.Scene.from_arrays(demo.vertices, demo.triangles, demo.material_ids, materials,
                                      object_ids=demo.object_ids, object_names=demo.object_names,
                                      name=f"{name}_lambert", metadata=dict(demo.metadata))
    camera = tofcore.Camera.from_fov(width, height, HFOV_DEG)
    led = tofcore.LED(position_m=LED_OFFSET_M, intensity_w_sr=1.0, kind="point")
    return Setup(name, scene, camera, led, tofcore.suggested_pose(demo), albedo)


# ----------------------------------------------------------------------------------------- tofcore
def sine_correlations(freqs_hz):
    """cos 2πfτ, sin 2πfτ per frequency (picklable, so tofcore traces on worker processes)."""
    from tofcore.sensor.modulation import phasor_correlations
    return phasor_correlations(freqs_hz)


def phasors_from_correlation(corr: np.ndarray) -> np.ndarray:
    """(2F, H, W) cos/sin correlation means → (F, H, W) complex phasors."""
    return corr[0::2] + 1j * corr[1::2]


def tofcore_phasors(s: Setup, freqs_hz, spp: int, max_depth: int, seed: int, workers: int | None = None,
                    with_signal: bool = False):
    """(P_full, P_direct, seconds[, signal_full, signal_direct]) of one tofcore render.

    P: (F, H, W) complex phasors Σ w e^{+i2πfL/c}; signal: (H, W) mean radiance Σ w.
    """
    t = tofcore.trace(s.scene, s.camera, [s.led], world_from_sensor=s.pose,
                      correlations=sine_correlations(freqs_hz), spp=spp, max_depth=max_depth, seed=seed,
                      workers=workers)
    out = (phasors_from_correlation(t.correlation()), phasors_from_correlation(t.correlation(max_k=1)),
           t.stats.seconds)
    return out + (t.signal(), t.signal(max_k=1)) if with_signal else out


# ----------------------------------------------------------------------------------------- Mitsuba
def write_ply(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Binary little-endian PLY: float32 x y z per vertex, uchar count + int32 indices per face."""
    used = np.unique(triangles)
    remap = np.full(len(vertices), -1, np.int64)
    remap[used] = np.arange(len(used))
    v = np.ascontiguousarray(vertices[used], dtype="<f4")
    f = remap[triangles].astype("<i4")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    faces = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", 3)])
    faces["n"] = 3
    faces["i"] = f
    tmp = Path(str(path) + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(header)
        fh.write(v.tobytes())
        fh.write(faces.tobytes())
    os.replace(tmp, path)


def export_plys(s: Setup, folder: Path) -> list[tuple[Path, float]]:
    """One PLY per material id: [(path, albedo)]."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for m, a in enumerate(s.albedo):
        sel = s.scene.material_ids == m
        if not sel.any():
            continue
        path = folder / f"{s.name}_m{m}.ply"
        write_ply(path, s.scene.vertices, s.scene.triangles[sel])
        out.append((path, a))
    return out


def mitsuba_to_world(pose: np.ndarray) -> np.ndarray:
    """Mitsuba's camera frame is x left, y up, z forward; OpenCV's is x right, y down, z forward."""
    return np.asarray(pose, float) @ np.diag([-1.0, -1.0, 1.0, 1.0])


def led_world(s: Setup) -> np.ndarray:
    return s.pose[:3, :3] @ np.asarray(s.led.position_m) + s.pose[:3, 3]


def mitsuba_scene_dict(s: Setup, plys, *, film: dict, integrator: dict, spp: int) -> dict:
    import mitsuba as mi

    cam = s.camera
    hfov = float(np.degrees(2 * np.arctan(0.5 * cam.width / cam.fx)))
    assert abs(cam.fx - cam.fy) < 1e-9 and abs(cam.cx - (cam.width - 1) / 2) < 1e-9 \
        and abs(cam.cy - (cam.height - 1) / 2) < 1e-9, "Mitsuba's perspective: square pixels, centred"
    d = {
        "type": "scene",
        "integrator": integrator,
        "sensor": {
            "type": "perspective", "fov": hfov, "fov_axis": "x",
            # Mitsuba starts camera rays at the near clip plane, so every path is near_clip/cos θ short:
            # 10 µm (≤ 7 µm of radial distance here) instead of the default 1 cm.
            "near_clip": 1e-5, "far_clip": 1e3,
            "to_world": mi.ScalarTransform4f(mitsuba_to_world(s.pose).tolist()),
            "sampler": {"type": "independent", "sample_count": spp},
            "film": dict(film, width=cam.width, height=cam.height, rfilter={"type": "box"}),
        },
        "led": {"type": "point", "position": led_world(s).tolist(), "intensity": {"type": "uniform",
                                                                                  "value": s.led.intensity_w_sr}},
    }
    for i, (path, a) in enumerate(plys):
        d[f"mesh{i}"] = {"type": "ply", "filename": str(path), "face_normals": True,
                         "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse",
                                                                "reflectance": {"type": "uniform", "value": a}}}}
    return d


def phasor_film(freq_indices: tuple[int, int], base_hz: float = BASE_HZ, bins: int = 64) -> dict:
    """A ``phasor_hdr_film`` whose FFT bins k_lo..k_hi are k·base_hz (see the module docstring)."""
    k_lo, k_hi = freq_indices
    span = C / base_hz                     # temporal_bins · bin_width_opl, metres of optical path
    mean_idx = 0.5 * (k_lo + k_hi)
    half = 0.5 * (k_hi - k_lo) - 0.1       # = 3·sigma_idx; floor/ceil of mean ∓ half give k_lo, k_hi
    return {"type": "phasor_hdr_film", "temporal_bins": bins, "bin_width_opl": span / bins, "start_opl": 0.0,
            "wl_mean": span / mean_idx, "wl_sigma": span / (6 * half / 3)}


MITSUBA_VARIANTS = {"cpu": "llvm_ad_mono", "gpu": "cuda_ad_mono"}
DEVICE = "cpu"
"""Where both renderers run: ``cpu`` (mitransient on LLVM, tofcore on the CPU) or ``gpu`` (mitransient on
CUDA, tofcore with ``device="gpu"``); error_vs_time.py's ``--device`` sets it."""


def mitsuba_setup():
    """Select the variant of :data:`DEVICE` (the CPU one needs DRJIT_LIBLLVM_PATH → libLLVM 19) and import
    mitransient."""
    import mitsuba as mi
    mi.set_variant(MITSUBA_VARIANTS[DEVICE])
    import mitransient  # noqa: F401  (registers the transient plugins)
    return mi


class MitransientRenderer:
    """A loaded mitransient scene; ``render(seed, max_depth)`` → ((F, H, W) complex phasors in tofcore's sign, s)."""

    def __init__(self, s: Setup, freqs_hz, spp: int, folder: Path, max_depth: int):
        mi = mitsuba_setup()
        self.mi = mi
        ks = [f / BASE_HZ for f in freqs_hz]
        if not all(abs(k - round(k)) < 1e-9 for k in ks):
            raise ValueError(f"frequencies must be multiples of {BASE_HZ / 1e6} MHz, got {freqs_hz}")
        ks = [int(round(k)) for k in ks]
        self.plys = export_plys(s, folder)
        film = phasor_film((min(ks), max(ks)))
        self.scene = mi.load_dict(mitsuba_scene_dict(
            s, self.plys, film=film, spp=spp,
            integrator={"type": "transient_path", "max_depth": max_depth + 1, "rr_depth": 1000}))
        self.integrators = {max_depth: self.scene.integrator()}
        fr = np.array(self.scene.sensors()[0].film().frequencies, dtype=np.float64).ravel()
        self.film_freqs_hz = fr * C
        self.index = [int(np.argmin(np.abs(self.film_freqs_hz - f))) for f in freqs_hz]
        err = max(abs(self.film_freqs_hz[i] - f) / f for i, f in zip(self.index, freqs_hz))
        if err > 1e-6:
            raise RuntimeError(f"phasor film frequencies {self.film_freqs_hz} do not contain {freqs_hz}")
        self.spp = spp
        self.max_depth = max_depth

    def render(self, seed: int, spp: int | None = None, max_depth: int | None = None):
        """One render: ((F, H, W) complex phasors, (H, W) steady image, seconds)."""
        import drjit as dr
        mi = self.mi
        depth = self.max_depth if max_depth is None else max_depth
        if depth not in self.integrators:
            self.integrators[depth] = mi.load_dict({"type": "transient_path", "max_depth": depth + 1,
                                                    "rr_depth": 1000})
        t0 = time.perf_counter()
        steady, ph = self.integrators[depth].render(self.scene, seed=seed, spp=spp or self.spp)
        dr.eval(steady, ph)
        ph = np.array(ph, dtype=np.float64)      # (H, W, F, 2)
        seconds = time.perf_counter() - t0
        z = ph[..., 0] - 1j * ph[..., 1]          # conj: tofcore's sign convention
        return np.moveaxis(z[:, :, self.index], -1, 0), np.array(steady, dtype=np.float64)[..., 0], seconds


def multipath_error_m(p_full: np.ndarray, p_direct: np.ndarray, freqs_hz) -> np.ndarray:
    """(F, H, W) c/(4πf) · arg(P_full · conj(P_direct)), metres of radial distance."""
    scale = C / (4 * np.pi * np.asarray(freqs_hz, float))[:, None, None]
    return scale * np.angle(p_full * np.conj(p_direct))


def distance_m(p: np.ndarray, freqs_hz) -> np.ndarray:
    """(F, H, W) wrapped radial distance c/(4πf) · arg P in [0, c/2f)."""
    scale = C / (4 * np.pi * np.asarray(freqs_hz, float))[:, None, None]
    return scale * np.mod(np.angle(p), 2 * np.pi)
