#!/bin/bash
# One device call (`run` with: bash bench/gpu/cold_start_and_profile.sh): the GPU's cold start with empty caches
# (every kernel compiled: numba-cuda's and CuPy's), the GPU tests, the ground truth's kernels against the array
# program (bench/gpu_first_hit.py), cProfile of preview and dataset frames (bench/gpu/profile_frames.py), then the
# frame's stages (bench/gpu_post_stages.py). Each step has its own timeout so that the call fits in 600 s; the logs
# are written as the steps end (at most 8 files come back from $OUT).
export PYTHONPATH=$PWD
{ nvidia-smi --query-gpu=name,memory.total --format=csv; lscpu | head -20; } > $OUT/machine.txt 2>&1
export CUPY_CACHE_DIR=$(mktemp -d) NUMBA_CACHE_DIR=$(mktemp -d)
{ time timeout 150 python3 -m tofcore warmup --device gpu; time timeout 60 python3 -m tofcore warmup --device gpu; } \
    > $OUT/cold_start.log 2>&1
timeout 200 python3 -m pytest -m gpu tests/tofcore/test_camera_decode.py tests/tofcore/test_gpu.py \
    tests/tofcore/test_depth_error.py tests/tofcore/test_kernels.py tests/tofcore/test_compiled.py -q -rs \
    -p no:cacheprovider > $OUT/gpu_tests.log 2>&1
timeout 40 python3 bench/gpu_first_hit.py --repeat 21 > $OUT/first_hit.log 2>&1
timeout 100 python3 bench/gpu/profile_frames.py --out /tmp/profile --frames 16 --preview-frames 30 > $OUT/profile.log 2>&1
cp /tmp/profile/preview.txt /tmp/profile/dataset.txt $OUT/ 2>/dev/null
timeout 60 python3 bench/gpu_post_stages.py --repeat 3 >> $OUT/first_hit.log 2>&1
echo done > $OUT/done.txt
