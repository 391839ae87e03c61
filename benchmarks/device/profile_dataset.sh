#!/usr/bin/env bash
# Device run (issue 16): the dataset pipeline's main thread sampled (benchmarks/sample_main_thread.py) over a
# SIZE-run paper dataset (continuous, 64 slots, 4 extraction processes, stores written) for each min_chunk in
# CHUNKS, then a bare stream of the same runs (bench_continuous_gpu, no caller work) at the first min_chunk.
# Usage: bash benchmarks/device/profile_dataset.sh [size] [chunks, comma list]; carry [".gpu/wb"] on a fresh
# machine staged with .gpu/c1..c9 (ensure_staged.sh). Results under $OUT: dataset_mc<K>.json, prof_dataset_mc<K>.json,
# stream_mc<K>.json, prof_stream_mc<K>.json.
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
OUTDIR=${OUT:-/tmp/profile_dataset_out}; mkdir -p "$OUTDIR"
N=${1:-512}
CHUNKS=${2:-64,16}
export INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel
for K in ${CHUNKS//,/ }; do
  python3 benchmarks/sample_main_thread.py --out "$OUTDIR/prof_dataset_mc$K.json" -- benchmarks/bench_dataset.py \
    --preset paper --arch cuda --n "$N" --batch-size 64 --scheduling continuous --min-chunk "$K" --executors local \
    --extract-workers 4 --warmup 2 --simulator-type invphys_orange_peel.simulator:OrangePeelSimulator \
    --features-type invphys_orange_peel.features:OrangePeelFeatures --out "$OUTDIR/dataset_mc$K.json" 2>&1 \
    | grep -E "\"wall_s\"|rror" | tail -3
done
K=${CHUNKS%%,*}
python3 benchmarks/sample_main_thread.py --out "$OUTDIR/prof_stream_mc$K.json" -- benchmarks/bench_continuous_gpu.py \
  --runs "$N" --batch 64 --cases "continuous:$K:longest_first" --no-features --out "$OUTDIR/stream_mc$K.json" 2>&1 \
  | grep -E "seconds_per_run|rror" | tail -3
