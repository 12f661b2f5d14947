#!/bin/bash
# The per-GPU dataset rate on a 1-GPU machine in one device call (`run` with: bash bench/gpu/one_gpu_rate.sh):
# bench_multigpu's 1-GPU runs of a 48- and a 200-frame Kinect v2 set (64 spp, PNG + JSON), one warm kernel cache.
export PYTHONPATH=$PWD
for frames in 48 200; do
    timeout 280 python3 bench/bench_multigpu.py --gpus 0 --out-dir /tmp/rate$frames --frames $frames --rounds 1 \
        --cold-rounds 0 --warm-cache /tmp/rate-cache --budget 270 > $OUT/rate$frames.log 2>&1
    cp /tmp/rate$frames/bench_multigpu.md $OUT/rate$frames.md 2>/dev/null
done
