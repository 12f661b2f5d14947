#!/bin/bash
# The 2-GPU dataset check in one device call on nvidia-h200-x2 (`run` with: bash bench/gpu/multigpu_check.sh):
# bench_multigpu's cold and warm rounds of a 48-frame Kinect v2 set; its JSON, table and logs come back in $OUT.
export PYTHONPATH=$PWD
timeout 560 python3 bench/bench_multigpu.py --out-dir /tmp/mg48 --frames 48 --rounds 1 --cold-rounds 1 --budget 520 \
    > $OUT/multigpu.log 2>&1
cp /tmp/mg48/bench_multigpu.json /tmp/mg48/bench_multigpu.md $OUT/ 2>/dev/null
grep -h "kernel warm-up" /tmp/mg48/*.log > $OUT/warmup_lines.txt 2>/dev/null
tar czf $OUT/mg48_logs.tgz -C /tmp/mg48 --exclude work . 2>/dev/null
