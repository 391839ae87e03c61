#!/usr/bin/env bash
# Device call B (H2), right after call A on the same warm machine: taichi (.gpu/tix) + the benchmark.
REPO=$PWD
[ -d /tmp/gpusite/ray ] || { echo "no Ray in /tmp/gpusite: a fresh machine, run call A first"; exit 3; }
tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz && python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite .gpu/tix/*.whl || exit 1
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/examples/anisompm:$REPO/examples/cheese_cut:$REPO/benchmarks PYTHONUNBUFFERED=1 INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
python3 -c "import ray, taichi, pydantic; print('ray', ray.__version__, 'taichi', taichi.__version__)" 2>&1 | tail -1
timeout ${BENCH_TIMEOUT:-480} python3 benchmarks/bench_multi_gpu.py --gpus 2 --runs ${RUNS:-256} --chunk ${CHUNK:-128} \
  --out $OUT/multi_gpu_h200x2.json 2> $OUT/bench_stderr.txt
echo "bench rc=$?"
grep -v "^\s*$" $OUT/bench_stderr.txt | grep -iv "token auth" | tail -c 2500
