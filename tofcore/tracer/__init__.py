"""Light transport: a wavefront path tracer that buckets light by bounce count and path length.

For every pixel and sample a camera ray leaves the lens; at every surface vertex x_k the tracer connects to
**every LED** with a shadow ray (next-event estimation) and to the sample's light vertex (MIS), then samples
the BSDF for the next direction, until ``max_depth`` vertices or a miss (SPEC §1, thesis §5.1). Each
connection is a contribution with weight w (radiance at the lens, W m⁻² sr⁻¹), optical path length
L = |LED → x_k| + … + |x_1 → lens| (float64, metres) and bounce count k (1 = direct, ≥ 2 = multipath).

The modules, in the order of the data (docs/architecture.md):

* :mod:`~tofcore.tracer.trace` — :func:`trace` / :func:`trace_progressive`: settings → passes of samples, run
  through one :class:`~tofcore.tracer.trace.Tracer` interface and decided there alone (a ``PassPolicy``);
* :mod:`~tofcore.tracer.setup` — the settings checked into one typed :class:`TraceSetup`;
* :mod:`~tofcore.tracer.sampler` — the one table of sample dimensions (:mod:`~tofcore.tracer.qmc`,
  :mod:`~tofcore.rng` below it);
* :mod:`~tofcore.tracer.path` — the path state (structure of arrays), a surface vertex, a contribution;
* :mod:`~tofcore.tracer.stages` — camera rays, intersect, shade, next event, light vertex, scatter
  (:mod:`~tofcore.tracer.surface` and :mod:`~tofcore.tracer.light_paths` below them);
* :mod:`~tofcore.tracer.integrator` — the path loop of one chunk; :mod:`~tofcore.tracer.accumulate` — its sums;
* :mod:`~tofcore.tracer.parallel` — the NumPy ``ReferenceTracer``: chunks, worker processes
  (:mod:`~tofcore.tracer.workers`), GPU chunk sizes (the compiled tracer, :mod:`tofcore.compiled.tracer`, stands above);
* :mod:`~tofcore.tracer.transport` — the result; :mod:`~tofcore.tracer.estimator` — its error estimate and
  the adaptive allocation of samples.

Determinism: every sample is a function of (seed, pixel, sample, dimension); every chunk holds whole pixels
and sums them in sample order, so the frame is the same bit for bit whatever the chunk size or worker count.
Memory is bounded by the chunk size (paths in flight), not by spp. The tracer reads the scene and a bank
of correlation functions; it never imports the sensor or the outputs.
"""
