#!/bin/bash
# One whole GPU check in one device call (`run` with: bash bench/gpu/whole_check.sh): cold start with empty caches,
# the GPU tests, the post-trace benches, the CPU tracer on the host's cores. Logs under $OUT (at most 8 files come back).
export PYTHONPATH=$PWD
cd $PWD
nvidia-smi --query-gpu=name,memory.total --format=csv > $OUT/gpu.txt 2>&1
lscpu | head -20 > $OUT/cpu.txt
# 1. cold start first, with empty caches (nothing compiled on this machine yet)
export CUPY_CACHE_DIR=$(mktemp -d) NUMBA_CACHE_DIR=$(mktemp -d)
( time timeout 240 python3 -m tofcore warmup --device gpu ) > $OUT/warmup_cold.log 2>&1
timeout 120 python3 bench/gpu_cupy_compiles.py kinect 64 > $OUT/first_frame_warm_cache.log 2>&1
( time timeout 120 python3 -m tofcore warmup --device gpu ) > $OUT/warmup_warm.log 2>&1
# 2. GPU tests (same caches: warm)
timeout 300 python3 -m pytest -m gpu tests/tofcore/test_camera_decode.py tests/tofcore/test_gpu.py tests/tofcore/test_depth_error.py -q -rs -p no:cacheprovider > $OUT/gpu_tests.log 2>&1
# 3. post-trace benches
timeout 120 python3 bench/bench_camera_decode.py --device gpu --repeat 21 --json $OUT/camera_decode.json > $OUT/bench_camera_decode.log 2>&1
timeout 180 python3 bench/gpu_post_stages.py --repeat 5 --json $OUT/post_stages.json > $OUT/post_stages.log 2>&1
# 4. the CPU tracer on the host's 16 cores (kernels compiled first by the warm-up above? CPU ones: no, compile here)
timeout 400 python3 bench/bench_compiled.py --cpu-threads 16,16,8,2,1 --json $OUT/cpu16.json > $OUT/cpu16.log 2>&1
echo done > $OUT/done.txt
