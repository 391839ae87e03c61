#!/usr/bin/env bash
# Device run (issue 16): where a dataset's wall goes against a bare stream of the same runs, in one call.
#   1. bench_dataset.py --time-split: SIZE (default 512) random paper runs end to end (continuous, 64 slots, the
#      simulator's default min_chunk, 4 extraction processes, stores written): the stream's production against its
#      consumer (the pipeline), the Taichi backend's synchronising reads (the GPU wait), launches, uploads, the
#      hand-off and the store's appends;
#   2. bench_continuous_gpu.py: the same runs (seed 0) through a warm engine with no caller work.
# Usage on a machine staged with .gpu/c1..c9 (see ensure_staged.sh): `bash benchmarks/device/dataset_split.sh [size]`
# with carry [".gpu/wb"]. Results under $OUT: dataset_split_<size>.json, stream_<size>.json.
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
OUTDIR=${OUT:-/tmp/dataset_split_out}; mkdir -p "$OUTDIR"
N=${1:-512}
export INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel
python3 benchmarks/bench_dataset.py --preset paper --arch cuda --n "$N" --batch-size 64 --scheduling continuous \
  --executors local --extract-workers 4 --warmup 2 --time-split \
  --simulator-type invphys_orange_peel.simulator:OrangePeelSimulator \
  --features-type invphys_orange_peel.features:OrangePeelFeatures --out "$OUTDIR/dataset_split_$N.json" 2>&1 \
  | grep -E "\"wall_s\"|rror" | cut -c1-400 | tail -3
python3 benchmarks/bench_continuous_gpu.py --runs "$N" --batch 64 --cases continuous:64:longest_first --no-features \
  --out "$OUTDIR/stream_$N.json" 2>&1 | grep -E "seconds_per_run|rror" | tail -3
