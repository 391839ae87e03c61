#!/usr/bin/env bash
# Device run (lead): the active stage of results/orange_peel_paper_active/spec.yaml on the GPU.
REPO=$PWD
if [ ! -d /tmp/gpusite/taichi ]; then
  mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite \
    .gpu/tix/*.whl .gpu/h5/*.whl || exit 1
fi
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/examples/anisompm:$REPO/examples/orange_peel PYTHONUNBUFFERED=1 INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
nvidia-smi --query-gpu=name,memory.used --format=csv
sed -e 's/^simulator: {type: orange_peel,/simulator: {type: "invphys_orange_peel.simulator:OrangePeelSimulator",/' \
    -e 's/^executor: {type: local}/executor: {type: local}\nfeatures: {type: "invphys_orange_peel.features:OrangePeelFeatures"}/' \
    results/orange_peel_paper_active/spec.yaml > /tmp/active_gpu.yaml && echo "tracker: none" >> /tmp/active_gpu.yaml
[ -n "$SEED" ] && python3 .gpu/lead/seed_checkpoint.py /tmp/active_gpu.yaml runs/protocol_paper_active
T0=$(date +%s)
timeout ${LIMIT:-560} python3 -m invphys.cli run /tmp/active_gpu.yaml --out runs/protocol_paper_active --stage active --no-progress \
  > $OUT/active_stdout.txt 2> $OUT/active_stderr.txt
echo "active rc=$? in $(( $(date +%s) - T0 )) s"
tail -c 3000 $OUT/active_stderr.txt; tail -c 1500 $OUT/active_stdout.txt
tar -C runs/protocol_paper_active -czf $OUT/active.tgz active
ls -la $OUT
