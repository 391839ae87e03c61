#!/usr/bin/env bash
# Device run (issues 11 and 16): what the damage-resolved time step (dt <= 0.1 min(eta)) costs and what it buys.
# The same 64 stored rows of datasets/orange_peel_paper (seed 0) are re-simulated twice on one GPU: as stored
# (a plain re-run: the noise) and without the eta bound (eta_dt_factor 1000); each reports R_gt against the
# stored features, the per-feature ceilings and the seconds per run (kernels compiled first, untimed).
# Staging: benchmarks/device/split_taichi_wheels.sh's pieces (`bash .gpu/cN/stage.sh` carry [".gpu/cN"] for each,
# then `bash .gpu/wb/stage.sh` carry [".gpu/wb"]); then this script. Results: $OUT/eta_plain.json, $OUT/eta_off.json.
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
OUTDIR=${OUT:-/tmp/eta_out}; mkdir -p "$OUTDIR"
ROWS=${1:-64}
python3 benchmarks/bench_simulator_noise.py datasets/orange_peel_paper --rows "$ROWS" --arch cuda --batch 64 --warmup 1 \
  --out "$OUTDIR/eta_plain.json"
python3 benchmarks/bench_simulator_noise.py datasets/orange_peel_paper --rows "$ROWS" --arch cuda --batch 64 --warmup 1 \
  --config '{"eta_dt_factor": 1000}' --out "$OUTDIR/eta_off.json"
