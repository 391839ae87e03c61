#!/usr/bin/env bash
# Device run (lead): Nsight Compute profile of the orange peel's Taichi substep kernels (paper preset, 64 runs).
if [ ! -d /tmp/gpusite/taichi ]; then
  mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite .gpu/h5/*.whl || exit 1
fi
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel PYTHONUNBUFFERED=1
which ncu || ls /opt/nvidia/nsight-compute/
timeout 500 python3 benchmarks/bench_kernel_profile.py --preset paper --batch 64 --out $OUT/kernel_profile_paper_h200.json > $OUT/stdout.txt 2> $OUT/stderr.txt
echo rc=$?; tail -12 $OUT/stdout.txt; tail -20 $OUT/stderr.txt
