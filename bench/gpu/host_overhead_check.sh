#!/bin/bash
# One device call (`run` with: bash bench/gpu/host_overhead_check.sh, carry ["_base"]): a GPU frame's host costs
# before and after, side by side on one machine. `_base/` holds the earlier commit's tree (git archive REV | tar -x -C
# _base); both trees share one warm kernel cache each. GPU tests first, then gpu_post_stages and the preview/dataset
# profile in the base tree and in this one, in turn, then the first frame of a fresh process with a warm cache.
export CUPY_CACHE_DIR=/tmp/cupy-cache
here=$PWD
{ nvidia-smi --query-gpu=name --format=csv,noheader; lscpu | grep "Model name"; } > $OUT/warmup.log 2>&1
NUMBA_CACHE_DIR=/tmp/nb-new PYTHONPATH=$here timeout 120 python3 -m tofcore warmup --device gpu >> $OUT/warmup.log 2>&1
(cd _base && NUMBA_CACHE_DIR=/tmp/nb-base PYTHONPATH=$PWD timeout 120 python3 -m tofcore warmup --device gpu) >> $OUT/warmup.log 2>&1
NUMBA_CACHE_DIR=/tmp/nb-new PYTHONPATH=$here timeout 150 python3 -m pytest -m gpu tests/tofcore/test_camera_decode.py \
    tests/tofcore/test_gpu.py tests/tofcore/test_depth_error.py tests/tofcore/test_compiled.py -q -rs \
    -p no:cacheprovider > $OUT/gpu_tests.log 2>&1
for round in 1 2; do
  for tree in base new; do
    dir=$here; [ $tree = base ] && dir=$here/_base
    (cd $dir && NUMBA_CACHE_DIR=/tmp/nb-$tree PYTHONPATH=$dir timeout 45 python3 bench/gpu_post_stages.py --repeat 5) \
        > $OUT/stages_${tree}_$round.log 2>&1
  done
done
for tree in base new; do
  dir=$here; [ $tree = base ] && dir=$here/_base
  (cd $dir && NUMBA_CACHE_DIR=/tmp/nb-$tree PYTHONPATH=$dir timeout 60 python3 bench/gpu/profile_frames.py \
      --out /tmp/prof-$tree --frames 24 --preview-frames 40 --top 40) > $OUT/profile_$tree.log 2>&1
  cat /tmp/prof-$tree/preview.txt >> $OUT/profile_$tree.log 2>/dev/null
done

# the first frame of a fresh process with warm caches, and one GPU's dataset rate (48 frames), this tree only
NUMBA_CACHE_DIR=/tmp/nb-new PYTHONPATH=$here timeout 40 python3 bench/gpu_cupy_compiles.py kinect 64 >> $OUT/warmup.log 2>&1
NUMBA_CACHE_DIR=/tmp/nb-new PYTHONPATH=$here timeout 100 python3 bench/bench_multigpu.py --gpus 0 --out-dir /tmp/rate48 \
    --frames 48 --rounds 1 --cold-rounds 0 --warm-cache /tmp/nb-new --budget 90 >> $OUT/gpu_tests.log 2>&1
cat /tmp/rate48/bench_multigpu.md >> $OUT/gpu_tests.log 2>/dev/null
echo done >> $OUT/gpu_tests.log
