#!/usr/bin/env bash
# Device run: grow dataset stores for MINUTES, one spec per GPU (CUDA_VISIBLE_DEVICES), feature extraction in
# EW worker processes each, then pack every store into one file, $OUT/stores.tgz (a device call returns
# only a few files, and a later call replaces the device tree's untracked files with this machine's).
# Staging: benchmarks/device/split_taichi_wheels.sh's folders (`bash .gpu/cN/stage.sh` carry [".gpu/cN"] for
# each piece, then `bash .gpu/wb/stage.sh` carry [".gpu/wb"]); the stores travel as files of the tree. Resumable: run
# `tar -xzf stores.tgz` in the repository root here before the next call (generation skips stored rows).
# usage: bash datasets/device/grow.sh MINUTES EW SPEC [SPEC ...]   (SPEC i runs on GPU i)
#   one H100:  bash datasets/device/grow.sh 8 4 datasets/specs/orange_peel_paper_seed1.yaml
#   two GPUs:  bash datasets/device/grow.sh 8 4 datasets/specs/orange_peel_paper_seed1.yaml datasets/specs/orange_peel_paper_seed2.yaml
MIN=$1; EW=$2; shift 2
[ -n "$MIN" ] && [ -n "$EW" ] && [ $# -ge 1 ] || { echo "usage: grow.sh MINUTES EW SPEC [SPEC ...]"; exit 2; }
REPO=$PWD
if command -v nvidia-smi >/dev/null; then bash benchmarks/device/ensure_staged.sh >/dev/null || exit 1; fi
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/examples/anisompm:$REPO/examples/orange_peel:$PYTHONPATH
export PYTHONUNBUFFERED=1 INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
OUTDIR=${OUT:-/tmp/grow_out}; mkdir -p "$OUTDIR"
T0=$(date +%s); stores=(); gpu=0
for spec in "$@"; do
  name=$(basename "$spec" .yaml)
  store=$(python3 -c "import sys, yaml; print(yaml.safe_load(open(sys.argv[1]))['dataset']['path'])" "$spec") || exit 2
  stores+=("$store")
  sed -e "s/^executor: {type: local.*}/executor: {type: local, extract_workers: $EW}/" "$spec" > "/tmp/$name.gpu.yaml"
  grep -q "extract_workers: $EW" "/tmp/$name.gpu.yaml" || { echo "$spec: executor line not found"; exit 2; }
  CUDA_VISIBLE_DEVICES=$gpu python3 -m invphys.cli dataset generate "/tmp/$name.gpu.yaml" --limit-minutes "$MIN" \
    --no-progress > "$OUTDIR/$name.txt" 2>&1 &
  gpu=$((gpu + 1))
done
wait
echo "generated in $(( $(date +%s) - T0 )) s"
for spec in "$@"; do grep -v Warning "$OUTDIR/$(basename "$spec" .yaml).txt" | grep -E "this run|store |adaptive round" ; done
tar --exclude=.lock --exclude=.design.lock -czf "$OUTDIR/stores.tgz" "${stores[@]}"
