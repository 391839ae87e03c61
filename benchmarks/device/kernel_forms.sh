#!/usr/bin/env bash
# Device run (issue 16): the lower-register kernel forms (split P2G, looped g2p) against the fused, unrolled
# ones on one GPU: kernel times of every form, whole runs of the fastest against the baseline (twice).
# Staging as in eta_bound_whatif.sh; then this script. Results: $OUT/kernel_forms_<preset>.json.
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
OUTDIR=${OUT:-/tmp/forms_out}; mkdir -p "$OUTDIR"
PRESET=${1:-paper}
RUNS=${2:-128}
python3 benchmarks/bench_kernel_forms.py --preset "$PRESET" --runs "$RUNS" --batch 64 \
  --out "$OUTDIR/kernel_forms_${PRESET}.json"
