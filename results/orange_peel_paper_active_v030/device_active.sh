#!/usr/bin/env bash
# Device run: the validate (replay only) and active stages of active_from_amortised_paper.yaml on one GPU.
# Staging: benchmarks/device/split_taichi_wheels.sh's folders (first call: `bash .gpu/ti/stage.sh`, carry
# [".gpu/ti"]); this second call carries [".gpu/tb", "runs/protocol_paper_active030"]. Resumable: the active
# stage keeps every finished round in active/progress.npz and every polish batch in active/polish.npz;
# unpack $OUT/run.tgz into runs/protocol_paper_active030 before the next call.
# usage: bash results/orange_peel_paper_active_v030/device_active.sh SECONDS
REPO=$PWD
LIMIT=${1:-540}
RUN=runs/protocol_paper_active030
SPEC=examples/orange_peel/invphys_orange_peel/specs/active_from_amortised_paper.yaml
T0=$(date +%s)
bash benchmarks/device/ensure_staged.sh || exit 1
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/examples/anisompm:$REPO/examples/orange_peel PYTHONUNBUFFERED=1 INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
nvidia-smi --query-gpu=name,memory.used --format=csv,noheader
sed -e 's/^simulator: {type: orange_peel,/simulator: {type: "invphys_orange_peel.simulator:OrangePeelSimulator",/' \
    -e 's/^executor: {type: local}/executor: {type: local}\nfeatures: {type: "invphys_orange_peel.features:OrangePeelFeatures"}/' \
    $SPEC > /tmp/active_gpu.yaml && echo "tracker: none" >> /tmp/active_gpu.yaml
python3 -m invphys.cli run /tmp/active_gpu.yaml --out $RUN --stage validate --no-progress > $OUT/validate.txt 2>&1
echo "validate rc=$?"; tail -4 $OUT/validate.txt
LEFT=$(( LIMIT - ($(date +%s) - T0) ))
echo "active: $LEFT s left"
timeout $LEFT python3 -m invphys.cli run /tmp/active_gpu.yaml --out $RUN --stage active --no-progress > $OUT/active.txt 2>&1
echo "active rc=$? at $(( $(date +%s) - T0 )) s"
grep -v Warning $OUT/active.txt | tail -15
tar -C $RUN -czf $OUT/run.tgz validate active
