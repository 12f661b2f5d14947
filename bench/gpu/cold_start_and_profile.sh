#!/bin/bash
# One device call (`run` with: bash bench/gpu/cold_start_and_profile.sh): the GPU's cold start with empty caches
# (the CUDA build of kernels.py after 2026-12-02's compile changes: constants as np.int64, no literal overloads),
# the GPU tests, then cProfile of preview and dataset frames (bench/gpu/profile_frames.py). At most 8 files
# come back from $OUT: the logs are joined into a few.
export PYTHONPATH=$PWD
{ nvidia-smi --query-gpu=name,memory.total --format=csv; lscpu | head -20; } > $OUT/machine.txt 2>&1
export CUPY_CACHE_DIR=$(mktemp -d) NUMBA_CACHE_DIR=$(mktemp -d)
{ time timeout 240 python3 -m tofcore warmup --device gpu; time timeout 120 python3 -m tofcore warmup --device gpu
  timeout 120 python3 bench/gpu_cupy_compiles.py kinect 64; } > $OUT/cold_start.log 2>&1
timeout 300 python3 -m pytest -m gpu tests/tofcore/test_camera_decode.py tests/tofcore/test_gpu.py \
    tests/tofcore/test_depth_error.py tests/tofcore/test_kernels.py tests/tofcore/test_compiled.py -q -rs \
    -p no:cacheprovider > $OUT/gpu_tests.log 2>&1
timeout 240 python3 bench/gpu/profile_frames.py --out /tmp/profile > $OUT/profile.log 2>&1
cp /tmp/profile/preview.txt /tmp/profile/dataset.txt $OUT/ 2>/dev/null
echo done > $OUT/done.txt
