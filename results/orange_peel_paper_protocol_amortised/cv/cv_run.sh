#!/usr/bin/env bash
# Device run (H2): simulate the leave-one-out answers for training pseudo-targets (hyper-parameter choice).
REPO=$PWD
if [ ! -d /tmp/gpusite/taichi ]; then
  mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite \
    .gpu/tix/*.whl .gpu/h5/*.whl || exit 1
fi
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/examples/orange_peel PYTHONUNBUFFERED=1 INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
nvidia-smi --query-gpu=name,memory.used --format=csv
T0=$(date +%s)
timeout ${1:-540} python3 .gpu/h2b/cvsim.py simulate .gpu/h2b/cv_answers.json $OUT/cv_sim.json 2>&1 | grep -v "^\[Taichi\]" | tail -40
echo "rc=$? in $(( $(date +%s) - T0 )) s"
