"""What exists for the GPU alone: CUDA kernels and device-memory handling (CuPy).

The simulator itself is written once (:mod:`tofcore.backend`); this folder and :mod:`tofcore.fused` hold
only the pieces that NumPy's API cannot express fast enough on a GPU. Every kernel is the twin of a NumPy
reference function, listed in the one dispatch table :data:`tofcore.backend.KERNELS` (which
``tests/tofcore/test_kernels.py`` walks, on the GPU machine comparing each kernel with its reference):

==========================  ==============================================  ==================================
module                      kernel                                          NumPy reference
==========================  ==============================================  ==================================
:mod:`.traversal`           closest hit / any hit over the BVH records      ``BVH.intersect`` / ``BVH.occluded``
:mod:`tofcore.fused`        counter-based uniforms (SplitMix64 ×2)          :func:`tofcore.rng.uniform`
:mod:`tofcore.fused`        Owen-scrambled Sobol' points (2-D and 1-D)      :func:`tofcore.tracer.qmc.scrambled_2d`,
                                                                            :func:`~tofcore.tracer.qmc.scrambled_1d`
:mod:`tofcore.fused`        dielectric and conductor Fresnel                ``fresnel.fresnel_dielectric`` /
                                                                            ``fresnel.fresnel_conductor``
:mod:`tofcore.fused`        square-wave correlation g_j(τ)                  ``modulation.square_correlation``
:mod:`tofcore.fused`        Poisson shot-noise counts (inversion / PTRS)    ``noise.poisson``
==========================  ==============================================  ==================================

The BVH traversal twins the scene alone and the compiled GPU tracer (:mod:`tofcore.compiled.cuda`) launches
it, so this folder stands on the tracer's floor; the fused kernels twin the tracer's and the sensor's
functions, so they stand a floor higher, beside it (docs/architecture.md). The kernels take their shared
constants (BVH record layout, hash constants, replicate count) from the Python modules they twin. Nothing
here is imported unless a device array reaches a reference function, so the CPU path never imports CuPy.
"""
