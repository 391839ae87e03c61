#!/usr/bin/env bash
# Device run (H1): the active stage of results/orange_peel_paper_active_polish/spec.yaml on the GPU
# (a copy of .gpu/lead/active.sh: stages taichi, names the plugins by module path; the orange peel
# package is the committed one (snapshot of 99ebd5d in .gpu/h1/polish/op), not the working tree's).
# Resumes: the rounds from active/progress.npz, the polish from active/polish.npz.
T_START=$(date +%s)
REPO=$PWD
if [ ! -d /tmp/gpusite/taichi ]; then
  mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite \
    .gpu/tix/*.whl .gpu/h5/*.whl || exit 1
fi
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/.gpu/h1/polish/op/examples/orange_peel PYTHONUNBUFFERED=1 INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
nvidia-smi --query-gpu=name,memory.used --format=csv
SPEC=${SPEC:-results/orange_peel_paper_active_polish/spec.yaml}
sed -e 's/^simulator: {type: orange_peel,/simulator: {type: "invphys_orange_peel.simulator:OrangePeelSimulator",/' \
    -e 's/^executor: {type: local}/executor: {type: local}\nfeatures: {type: "invphys_orange_peel.features:OrangePeelFeatures"}/' \
    $SPEC > /tmp/polish_gpu.yaml && echo "tracker: none" >> /tmp/polish_gpu.yaml
[ -n "$BUDGET" ] && sed -i "s/polish: {budget: [0-9]*,/polish: {budget: $BUDGET,/" /tmp/polish_gpu.yaml
grep -n "polish:" /tmp/polish_gpu.yaml
python3 -c "import invphys_orange_peel, sys; print('orange peel from', invphys_orange_peel.__file__)"
LEFT=$(( ${LIMIT:-570} - ($(date +%s) - T_START) ))
echo "staged in $(( $(date +%s) - T_START )) s; stage limit $LEFT s"
T0=$(date +%s)
timeout $LEFT python3 -m invphys.cli run /tmp/polish_gpu.yaml --out runs/protocol_paper_active --stage active --no-progress \
  > $OUT/active_stdout.txt 2> $OUT/active_stderr.txt
RC=$?
echo "active rc=$RC in $(( $(date +%s) - T0 )) s"
tail -c 2500 $OUT/active_stderr.txt; tail -c 1500 $OUT/active_stdout.txt
LEFT=$(( ${LIMIT:-570} - ($(date +%s) - T_START) ))
if [ $RC = 0 ] && [ -n "$RECHECK" ] && [ $LEFT -gt 60 ]; then
  timeout $(( LEFT - 15 )) python3 .gpu/h1/polish/recheck.py /tmp/polish_gpu.yaml runs/protocol_paper_active $OUT/recheck.json \
    > $OUT/recheck.txt 2>&1; echo "recheck rc=$?"; tail -5 $OUT/recheck.txt
fi
cp /tmp/polish_gpu.yaml $OUT/
tar -C runs/protocol_paper_active -czf $OUT/active.tgz --exclude=surrogate_round4 active
ls -la $OUT; echo "total $(( $(date +%s) - T_START )) s"
