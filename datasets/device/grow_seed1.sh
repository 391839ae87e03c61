#!/usr/bin/env bash
# Device run: grow datasets/orange_peel_paper_seed1_v030 (datasets/specs/orange_peel_paper_seed1.yaml) for
# MINUTES on one GPU, extraction in EW worker processes, then pack the store into $OUT/seed1_store.tgz.
# Staging: benchmarks/device/split_taichi_wheels.sh's folders (first call `bash .gpu/ti/stage.sh`, carry
# [".gpu/ti"]); this call carries [".gpu/tb"] (the store travels as untracked/tracked files of the tree).
# Resumable: unpack $OUT/seed1_store.tgz here before the next call (generation skips stored rows).
# usage: bash datasets/device/grow_seed1.sh MINUTES [EW]
MIN=${1:-8}
EW=${2:-4}
REPO=$PWD
STORE=datasets/orange_peel_paper_seed1_v030
bash .gpu/tb/stage.sh >/dev/null || exit 1
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/examples/anisompm:$REPO/examples/orange_peel PYTHONUNBUFFERED=1 INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
sed -e "s/^executor: {type: local.*}/executor: {type: local, extract_workers: $EW}/" \
    datasets/specs/orange_peel_paper_seed1.yaml > /tmp/seed1_gpu.yaml
grep -q "extract_workers: $EW" /tmp/seed1_gpu.yaml || { echo "spec edit failed"; exit 1; }
T0=$(date +%s)
python3 -m invphys.cli dataset generate /tmp/seed1_gpu.yaml --limit-minutes "$MIN" --no-progress > $OUT/grow.txt 2>&1
echo "generate rc=$? in $(( $(date +%s) - T0 )) s"
grep -v Warning $OUT/grow.txt | tail -6
tar -czf $OUT/seed1_store.tgz $STORE   # one file: a run returns a limited number of files
