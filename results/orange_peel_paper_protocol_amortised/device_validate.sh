#!/usr/bin/env bash
# Device run (H2): the protocol_paper_amortised validate + report stages (memo carried in runs/protocol_paper_amortised/validate).
# usage: bash .gpu/h2b/run.sh SECONDS
REPO=$PWD
LIMIT=${1:-420}
if [ ! -d /tmp/gpusite/taichi ]; then
  mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite \
    .gpu/tix/*.whl .gpu/h5/*.whl || exit 1
fi
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/examples/anisompm:$REPO/examples/orange_peel PYTHONUNBUFFERED=1 INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
nvidia-smi --query-gpu=name,memory.used --format=csv
sed -e 's/^simulator: {type: orange_peel,/simulator: {type: "invphys_orange_peel.simulator:OrangePeelSimulator",/' \
    -e 's/^executor: {type: local}/executor: {type: local}\nfeatures: {type: "invphys_orange_peel.features:OrangePeelFeatures"}/' \
    examples/orange_peel/invphys_orange_peel/specs/amortised_vs_lookup_paper.yaml > /tmp/amortised_gpu.yaml && echo "tracker: none" >> /tmp/amortised_gpu.yaml
wc -l runs/protocol_paper_amortised/validate/simulated.jsonl
T0=$(date +%s)
timeout $LIMIT python3 -m invphys.cli run /tmp/amortised_gpu.yaml --out runs/protocol_paper_amortised --stage validate --no-progress \
  > $OUT/validate_stdout.txt 2> $OUT/validate_stderr.txt
echo "validate rc=$? in $(( $(date +%s) - T0 )) s"
tail -c 2500 $OUT/validate_stderr.txt; tail -c 2500 $OUT/validate_stdout.txt
timeout 60 python3 -m invphys.cli run /tmp/amortised_gpu.yaml --out runs/protocol_paper_amortised --stage report --no-progress > $OUT/report_stdout.txt 2>&1
echo "report rc=$?"; tail -c 800 $OUT/report_stdout.txt
wc -l runs/protocol_paper_amortised/validate/simulated.jsonl
tar -C runs/protocol_paper_amortised -czf $OUT/run.tgz validate report
ls -la $OUT
