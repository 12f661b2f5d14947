"""Light transport: the path tracer over a scene (:mod:`tofcore.tracer.transport`), its sampler
(:mod:`~tofcore.tracer.rng`, :mod:`~tofcore.tracer.qmc`), light vertices (:mod:`~tofcore.tracer.light_paths`),
adaptive allocation (:mod:`~tofcore.tracer.adaptive`) and parallel execution (:mod:`~tofcore.tracer.workers`).

It reads the scene and a bank of correlation functions; it never imports the sensor or the outputs.
"""
