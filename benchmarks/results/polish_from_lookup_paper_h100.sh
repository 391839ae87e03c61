#!/usr/bin/env bash
# Device run (lead): bench_polish_from_lookup on one GPU from a git-archive snapshot (src.tgz) of main.
# Carry: .gpu/tix (taichi), .gpu/h5 (pure-Python wheels), .gpu/lead/snap (src.tgz, this script, log.npz if resuming).
T_START=$(date +%s)
REPO=$PWD; SNAP=$REPO/.gpu/lead/snap
if [ ! -d /tmp/gpusite/taichi ]; then
  mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite .gpu/tix/*.whl .gpu/h5/*.whl || exit 1
fi
rm -rf /tmp/src && mkdir -p /tmp/src && tar -C /tmp/src -xzf $SNAP/src.tgz || exit 1
cd /tmp/src
export PYTHONPATH=/tmp/gpusite:/tmp/src:/tmp/src/examples/anisompm:/tmp/src/examples/orange_peel PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . -e examples/anisompm -e examples/orange_peel > $OUT/pip.txt 2>&1 || { echo "pip -e failed"; tail -5 $OUT/pip.txt; }
nvidia-smi --query-gpu=name,memory.used --format=csv
mkdir -p /tmp/pl && [ -f $SNAP/log.npz ] && cp $SNAP/log.npz /tmp/pl/log.npz
LEFT=$(( ${LIMIT:-570} - ($(date +%s) - T_START) ))
echo "staged in $(( $(date +%s) - T_START )) s; limit $LEFT s"
( while sleep 20; do [ -f /tmp/pl/log.npz ] && cp /tmp/pl/log.npz $OUT/log.npz; done ) &
timeout $LEFT python3 benchmarks/bench_polish_from_lookup.py --report results/orange_peel_paper_protocol/report.json \
  --bundle inverters/orange_peel_paper --arch cuda --sim-batch 64 --scheduling continuous --min-chunk 16 --chunk 200 --budget ${BUDGET:-24} --below ${BELOW:-0.9} \
  --log /tmp/pl/log.npz --compare results/orange_peel_paper_active_polish/report.json \
  --out $OUT/polish_from_lookup_paper_h100.json > $OUT/stdout.txt 2> $OUT/stderr.txt
echo "rc=$? in $(( $(date +%s) - T_START )) s"
[ -f /tmp/pl/log.npz ] && cp /tmp/pl/log.npz $OUT/log.npz
tail -20 $OUT/stdout.txt; tail -5 $OUT/stderr.txt
