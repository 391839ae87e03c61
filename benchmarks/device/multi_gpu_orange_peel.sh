#!/usr/bin/env bash
# Device run (a 2-GPU machine, e.g. nvidia-h200-x2): one GPU against two through the `ray_actors` executor on
# the orange peel's paper preset (benchmarks/bench_multi_gpu.py --scene orange_peel). Stage taichi first
# (split_taichi_wheels.sh's .gpu/cN and .gpu/wb calls) and Ray (split_ray.sh's .gpu/rN and .gpu/rw calls).
# usage: bash benchmarks/device/multi_gpu_orange_peel.sh [RUNS] [CHUNK] [EXTRACT_WORKERS]   -> $OUT/multi_gpu_orange_peel.json
REPO=$PWD; RUNS=${1:-256}; CHUNK=${2:-128}; EW=${3:-0}
bash benchmarks/device/ensure_staged.sh || exit 1
[ -d /tmp/gpusite/ray ] || { echo "error: no Ray in /tmp/gpusite (stage .gpu/r1 .. rK, then .gpu/rw)" >&2; exit 1; }
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/examples/anisompm:$REPO/examples/orange_peel:$REPO/examples/cheese_cut:$REPO/benchmarks
export PYTHONUNBUFFERED=1 INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
OUTDIR=${OUT:-/tmp/multi_gpu_out}; mkdir -p "$OUTDIR"
nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader
timeout ${BENCH_TIMEOUT:-540} python3 benchmarks/bench_multi_gpu.py --scene orange_peel --gpus 2 --runs "$RUNS" \
  --chunk "$CHUNK" --min-chunk 16 --extract-workers "$EW" --out "$OUTDIR/multi_gpu_orange_peel.json" 2> "$OUTDIR/bench_stderr.txt"
echo "bench rc=$?"
grep -v "^\s*$" "$OUTDIR/bench_stderr.txt" | grep -iv "token auth" | tail -c 2500
