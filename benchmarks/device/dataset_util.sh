#!/usr/bin/env bash
# Device run (issue 16): dataset generation end to end (bench_dataset.py, continuous, 64 slots, 4 extraction
# processes, stores written, --time-split) for each version given, in that order, with the GPU's utilisation
# sampled every 100 ms by nvidia-smi meanwhile (the share of time some kernel ran: the GPU idle between chunks
# is 100 % minus it).
#   bash benchmarks/device/dataset_util.sh <tag> <runs> name[=dir] ...
# ``dir`` holds a copy of examples/anisompm (e.g. .gpu/old from `git archive HEAD examples/anisompm`); ``new``
# (no dir) is this tree. Results under $OUT: dataset_<tag>_<name>.json, util_<tag>_<name>.csv (timestamp,
# utilisation %), util_<tag>_<name>.window (start and end, seconds since the epoch) and log_<tag>_<name>.txt
# (the benchmark's output: a direct copy or upload that fell back says so there). DATASET_ARGS adds options to
# every pass (e.g. DATASET_ARGS=--host-profile: the main thread sampled, gc pauses timed).
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
OUTDIR=${OUT:-/tmp/dataset_util_out}; mkdir -p "$OUTDIR"
TAG=$1; N=$2; shift 2
export INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
NEW=$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel
for spec in "$@"; do
  name=${spec%%=*}; dir=${spec#*=}
  if [ "$name" = "$spec" ]; then path=/tmp/gpusite:$NEW; else path=/tmp/gpusite:$PWD/$dir/examples/anisompm:$NEW; fi
  nvidia-smi --query-gpu=timestamp,utilization.gpu --format=csv,noheader,nounits -lms 100 \
    > "$OUTDIR/util_${TAG}_${name}.csv" &
  sampler=$!
  date +%s.%N > "$OUTDIR/util_${TAG}_${name}.window"
  PYTHONPATH=$path python3 benchmarks/bench_dataset.py --preset paper --arch cuda --n "$N" --batch-size 64 \
    --scheduling continuous --executors local --extract-workers 4 --warmup 2 --time-split \
    --simulator-type invphys_orange_peel.simulator:OrangePeelSimulator \
    --features-type invphys_orange_peel.features:OrangePeelFeatures $DATASET_ARGS \
    --out "$OUTDIR/dataset_${TAG}_${name}.json" > "$OUTDIR/log_${TAG}_${name}.txt" 2>&1 || true
  grep -oE '"wall_s": [0-9.]+, "ok": [0-9]+|sim_s_per_run": [0-9.]+' "$OUTDIR/log_${TAG}_${name}.txt" | head -2
  grep -E "falls back|Error|error:" "$OUTDIR/log_${TAG}_${name}.txt" | head -3 || true
  date +%s.%N >> "$OUTDIR/util_${TAG}_${name}.window"
  kill $sampler
done
