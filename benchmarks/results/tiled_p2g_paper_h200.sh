#!/usr/bin/env bash
# Device run (lead): tiled vs atomic Taichi P2G on one GPU (grid parity, kernel profile, whole runs).
if [ ! -d /tmp/gpusite/taichi ]; then
  mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite .gpu/h5/*.whl || exit 1
fi
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name --format=csv,noheader
timeout ${LIMIT:-540} python3 benchmarks/bench_tiled_p2g.py --preset paper --runs ${RUNS:-64} --batch 64 ${EXTRA:-} \
  --out $OUT/tiled_p2g_paper.json > $OUT/stdout.txt 2> $OUT/stderr.txt
echo rc=$?; cat $OUT/stdout.txt; grep -v "^\[Taichi\]" $OUT/stderr.txt | tail -40
[ -n "$PROF" ] && timeout 200 python3 benchmarks/bench_kernel_profile.py --preset paper --batch 64 --p2g tiled --out $OUT/kernel_profile_tiled.json > $OUT/prof_stdout.txt 2> $OUT/prof_stderr.txt
echo prof rc=$?; cat $OUT/prof_stdout.txt | cut -c1-400; tail -5 $OUT/prof_stderr.txt
