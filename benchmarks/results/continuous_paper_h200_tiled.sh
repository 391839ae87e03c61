#!/usr/bin/env bash
# Device run (lead): continuous batching vs lock-step with the tiled P2G, 256 random paper runs, one GPU.
if [ ! -d /tmp/gpusite/taichi ]; then
  mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite .gpu/h5/*.whl || exit 1
fi
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name --format=csv,noheader
timeout 540 python3 benchmarks/bench_continuous_gpu.py --preset paper --runs 256 --batch 64 --p2g tiled \
  --cases continuous:16:longest_first lockstep --budget 470 --out $OUT/continuous_paper_tiled.json > $OUT/stdout.txt 2> $OUT/stderr.txt
echo rc=$?; tail -15 $OUT/stdout.txt; grep -v "^\[Taichi\]" $OUT/stderr.txt | tail -15
