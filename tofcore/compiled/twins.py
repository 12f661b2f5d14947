"""Which NumPy reference function each compiled kernel function mirrors: one registry that names the pair.

:mod:`tofcore.compiled.kernels` is the NumPy tracer written again as scalar functions (DESIGN.md
"Backends"). :data:`TWINS` maps the name of every function defined there (``@fn``, ``@cpu_parallel``,
``@gpu_kernel``) to

* the dotted name (``module.qualname``, as :data:`tofcore.backend.KERNELS` names the CUDA twins' references)
  of the NumPy function it mirrors, or a tuple of them where one kernel function does the work of several
  (:func:`~tofcore.compiled.kernels.correlation` evaluates all four correlation kinds); or
* a short reason, in words, why it has no single NumPy counterpart (a GPU wavefront stage, the traversal's
  stack bookkeeping) and where it is checked instead.

``tests/tofcore/test_kernel_twins.py`` walks the registry: every kernel function has an entry and every
entry a kernel function; every reference resolves (a reference renamed or moved fails there, not in a
reader's head); the names that kernels.py's docstrings point at resolve and agree with the registry; and
each kernel function with a reference is called directly from a jitted loop and compared with it on the
same inputs (the module lists which, and counts them). Plain data: nothing here imports numba or the
modules named; :func:`resolve` imports a name's module when asked.
"""

from __future__ import annotations

import importlib

_GPU_STAGE = ("a CUDA kernel of the GPU wavefront, plain Python on the CPU; the CUDA simulator test in "
              "tests/tofcore/test_compiled.py checks the pass's sums against the NumPy frame")
_GPU_STAGING = ("GPU wavefront staging between kernels (no NumPy counterpart); the store_light/load_light "
                "round trip and the CUDA simulator test in tests/tofcore/test_compiled.py check it")

TWINS: dict[str, str | tuple[str, ...]] = {
    # vectors: one IEEE operation per component, as the reference's array expressions
    "dot": "tofcore.tracer.surface.dot",
    "norm": "numpy.linalg.norm",
    "sub": "numpy.subtract",
    "scale": "numpy.multiply",
    "divide": "numpy.divide",
    "neg": "numpy.negative",
    "to_f32": "numpy.ndarray.astype",
    "rotate": "tofcore.tracer.surface.rotate",
    # random numbers
    "splitmix": "tofcore.rng._splitmix",
    "hash_bits": "tofcore.rng.bits",
    "uniform": "tofcore.rng.uniform",
    "reverse_bits": "tofcore.tracer.qmc.reverse_bits",
    "owen_scramble": "tofcore.tracer.qmc.owen_scramble",
    "sobol_dim1_lookup": "tofcore.tracer.qmc.sobol_2d",
    "sobol_dim1_bits": ("tofcore.tracer.qmc.sobol_2d", "tofcore.tracer.qmc._sobol_dim1_tables"),
    "qmc_seeds": "tofcore.tracer.qmc._seeds",
    "sample_2d": "tofcore.tracer.qmc.sample_2d",
    "sample_1d": "tofcore.tracer.qmc.sample_1d",
    # warps
    "concentric_disk": "tofcore.scene.sampling.sample_concentric_disk",
    "cosine_hemisphere": "tofcore.scene.sampling.sample_cosine_hemisphere",
    # camera
    "distort_with_jacobian": "tofcore.scene.camera.Camera._distort_with_jacobian",
    "undistort_near": "tofcore.scene.camera.Camera._undistort_near",
    "camera_ray": "tofcore.scene.camera.Camera._ray_block",
    # BVH traversal
    "ray_frame": "tofcore.scene.bvh._ray_frame",
    "inverse_direction": "tofcore.scene.bvh._ray_records",
    "push_child": ("traversal bookkeeping: the order a closest-hit ray visits children (the NumPy traversal "
                   "goes breadth first); checked through traverse's hits"),
    "traverse": "tofcore.scene.bvh.BVH._trace",
    "intersect": ("tofcore.scene.bvh.BVH.intersect", "tofcore.scene.bvh.BVH.occluded"),
    # surfaces and ray offsets
    "point_offset": "tofcore.tracer.surface.point_offset",
    "spawn_offset": "tofcore.tracer.surface.spawn_offset",
    "shadow_ray": "tofcore.tracer.surface.shadow_ray",
    "orthonormal_basis": "tofcore.tracer.surface.orthonormal_basis",
    "surface_at": "tofcore.tracer.surface.surface_at",
    "hit_point": "tofcore.tracer.surface.surface_geometry",
    "surface_params": "tofcore.scene.bsdf.SurfaceParams",
    "texture_sample": "tofcore.scene.material.Texture.sample",
    "perturb_normal": "tofcore.tracer.surface._perturb",
    "ambient_radiance": "tofcore.scene.ambient.Ambient.radiance",
    "add_transient": "tofcore.tracer.accumulate.Tally._add_transient",
    "to_local": "tofcore.tracer.surface.Surface.to_local",
    "to_world": "tofcore.tracer.surface.Surface.to_world",
    # reflection
    "fresnel_dielectric": "tofcore.scene.fresnel.fresnel_dielectric",
    "fresnel_conductor": "tofcore.scene.fresnel.fresnel_conductor",
    "specular_fresnel": "tofcore.scene.bsdf.specular_fresnel",
    "outgoing": "tofcore.scene.bsdf._outgoing",
    "rough_alpha": "tofcore.scene.bsdf._rough_alpha",
    "specular_density": "tofcore.scene.sampling.pdf_vcavity_visible_normal",
    "coat_fresnel": "tofcore.scene.fresnel.fresnel_dielectric",
    "reflect_visible_normal": ("tofcore.scene.sampling.sample_vcavity_visible_normal", "tofcore.scene.bsdf._reflect"),
    "beckmann_distribution": "tofcore.scene.sampling.beckmann_distribution",
    "half_vector": "tofcore.scene.bsdf._half_vector",
    "oren_nayar": "tofcore.scene.bsdf.oren_nayar",
    "cos_azimuth_difference": "tofcore.scene.bsdf.cos_azimuth_difference",
    "eval_terms": ("tofcore.scene.bsdf._pair", "tofcore.scene.bsdf._eval"),
    "pdf_terms": "tofcore.scene.bsdf._pdf",
    "eval_bsdf": "tofcore.scene.bsdf.eval_bsdf",
    "eval_pdf_bsdf": "tofcore.scene.bsdf.eval_pdf_bsdf",
    "sample_bsdf": "tofcore.scene.bsdf.sample_bsdf",
    # LEDs and correlations
    "led_intensity": "tofcore.scene.led.LED.intensity",
    "emission_pdf": "tofcore.scene.led.LED.emission_pdf",
    "sample_emission": "tofcore.scene.led.LED.sample_emission",
    "correlation": ("tofcore.sensor.modulation.phasor_component", "tofcore.sensor.modulation.sine_correlation",
                    "tofcore.sensor.modulation.square_correlation", "tofcore.sensor.modulation.pulsed_correlation",
                    "tofcore.sensor.modulation.harmonic_correlation",
                    "tofcore.sensor.modulation.tabulated_correlation"),
    "channel_value": ("tofcore.sensor.modulation.phasor_component", "tofcore.sensor.modulation.sine_correlation",
                      "tofcore.sensor.modulation.square_correlation", "tofcore.sensor.modulation.pulsed_correlation",
                      "tofcore.sensor.modulation.harmonic_correlation",
                      "tofcore.sensor.modulation.tabulated_correlation"),
    # one path: the stages of tofcore.tracer.stages, per path
    "led_estimate": "tofcore.tracer.stages._to_led",
    "connect_led": "tofcore.tracer.stages._to_led",
    "light_ray": "tofcore.tracer.light_paths.trace_light_vertices",
    "light_vertex_at": "tofcore.tracer.light_paths.trace_light_vertices",
    "light_vertex": "tofcore.tracer.light_paths.trace_light_vertices",
    "light_estimate": "tofcore.tracer.light_paths.connect",
    "connect_light": "tofcore.tracer.light_paths.connect",
    "camera_start": "tofcore.tracer.stages.camera_rays",
    "ray_query": "tofcore.tracer.surface.leaving",
    "next_hit": "tofcore.tracer.stages.intersect",
    "camera_vertex": "tofcore.tracer.stages.shade",
    "add_next_events": "tofcore.tracer.stages.next_event",
    "add_connection": "tofcore.tracer.stages.light_vertex",
    "next_direction": "tofcore.tracer.stages.scatter",
    "trace_path": "tofcore.tracer.integrator.trace_chunk",
    "trace_pixels": "tofcore.tracer.integrator.trace_chunk",
    "first_hits": "tofcore.tracer.stages.first_hit",  # tests/tofcore/test_compiled.py: every field equal
    # the GPU wavefront (tofcore.compiled.cuda drives it)
    "store_vec": _GPU_STAGING,
    "load_vec": _GPU_STAGING,
    "store_xyz": _GPU_STAGING,
    "store_light": _GPU_STAGING,
    "load_light": _GPU_STAGING,
    "store_ray": _GPU_STAGING,
    "wf_start": _GPU_STAGE,
    "wf_light": _GPU_STAGE,
    "queue_next_events": "tofcore.tracer.stages._to_led",  # the estimates, and the shadow rays it traces
    "queue_connection": "tofcore.tracer.light_paths.connect",  # the connection, and the shadow ray it traces
    "continue_path": "tofcore.tracer.stages.scatter",  # the next state and ray of the paths that go on
    "wf_shade": _GPU_STAGE,
    "wf_resolve": _GPU_STAGE,
    "gather_outputs": ("GPU wavefront bookkeeping (threads per pixel and sum of wf_gather); the CUDA simulator "
                       "test in tests/tofcore/test_compiled.py checks the sums"),
    "in_sample_order": ("GPU wavefront bookkeeping (a pixel's addends in sample order, as trace_pixels adds "
                        "them); the CUDA simulator test in tests/tofcore/test_compiled.py checks the sums"),
    "wf_gather": _GPU_STAGE,
    "wf_transient": _GPU_STAGE,
    "pixel_centre_direction": "tofcore.tracer.surface.rotate",
    "wf_first_rays": "tofcore.tracer.stages.first_hit",  # the rays; the CUDA simulator test checks the record
    "wf_first_hit": "tofcore.tracer.stages.first_hit_record",
}
"""Kernel function name → its NumPy reference (``module.qualname``, or a tuple of them), or why it has none."""


def references(name: str) -> tuple[str, ...]:
    """The reference names of kernel function ``name`` (empty where :data:`TWINS` gives a reason instead)."""
    value = TWINS[name]
    names = value if isinstance(value, tuple) else (value,)
    return () if any(is_reason(v) for v in names) else names


def is_reason(value: str) -> bool:
    """True for a reason in words, False for a dotted name (which never contains a space)."""
    return " " in value


def resolve(dotted: str):
    """The object a dotted name ``module.qualname`` names: the longest importable prefix, then attributes.

    Raises ImportError (no prefix imports) or AttributeError (an attribute is missing): a stale name.
    """
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for attribute in parts[cut:]:
            obj = getattr(obj, attribute)
        return obj
    raise ImportError(f"no module of {dotted!r} imports")
