#!/usr/bin/env bash
# Device run (issue 16): dataset generation end to end (bench_dataset.py: 4 extraction processes, stores
# written, lock-step batches handed over costliest first) with this tree's packages and with the previous
# commit's anisompm engine (.gpu/old, prepared as in old_vs_new.sh), new first, in one call on one GPU.
# Usage: bash benchmarks/device/dataset_old_vs_new.sh <tag> [n] (carry [".gpu/wb", ".gpu/old"] or staged).
# Results: $OUT/dataset_paper_<tag>_{new,old}.json
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
OUTDIR=${OUT:-/tmp/old_vs_new_out}; mkdir -p "$OUTDIR"
TAG=${1:-change}
N=${2:-384}
export INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
NEW=$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel
OLD=$PWD/.gpu/old/examples/anisompm:$NEW
for v in new old; do
  if [ "$v" = old ]; then P=$OLD; else P=$NEW; fi
  PYTHONPATH=/tmp/gpusite:$P python3 benchmarks/bench_dataset.py --preset paper --arch cuda --n "$N" --batch-size 64 \
    --scheduling lockstep --executors local --extract-workers 4 --warmup 2 \
    --simulator-type invphys_orange_peel.simulator:OrangePeelSimulator \
    --features-type invphys_orange_peel.features:OrangePeelFeatures \
    --out "$OUTDIR/dataset_paper_${TAG}_${v}.json" 2>&1 | grep -E "runs/h|s/run|per run|wall|error|Error" | tail -4
done
