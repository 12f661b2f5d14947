"""What exists for the GPU alone: CUDA kernels and device-memory handling (CuPy).

The simulator itself is written once (:mod:`tofcore.backend`); this folder
holds only the pieces that NumPy's API cannot express fast enough on a GPU.
Every kernel has a NumPy twin that ``tests/tofcore/test_gpu.py`` compares it
with on the GPU machine:

==========================  ==============================================  ==================================
module                      kernel                                          NumPy twin
==========================  ==============================================  ==================================
:mod:`.traversal`           closest hit / any hit over the BVH records      ``BVH.intersect`` / ``BVH.occluded``
:mod:`.fused`               counter-based uniforms (SplitMix64 ×2)          :func:`tofcore.tracer.rng.uniform`
:mod:`.fused`               dielectric and conductor Fresnel                :mod:`tofcore.scene.fresnel`
:mod:`.fused`               square-wave correlation g_j(τ)                  ``modulation.square_correlation``
==========================  ==============================================  ==================================

Nothing here is imported unless a device array reaches a dispatching function,
so the CPU path never imports CuPy.
"""
