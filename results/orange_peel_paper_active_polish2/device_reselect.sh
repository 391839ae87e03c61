#!/usr/bin/env bash
# Device run (lead): bench_robust_reselect on one GPU from the working tree.
# Carry: .gpu/tix (taichi without its C API library), .gpu/h5 (pure-Python wheels + pydantic_core).
T_START=$(date +%s)
if [ ! -d /tmp/gpusite/taichi ]; then
  mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/tix/taichi.tar.xz || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite .gpu/h5/*.whl || exit 1
fi
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . -e examples/anisompm -e examples/orange_peel > $OUT/pip.txt 2>&1 || { echo "pip -e failed"; tail -5 $OUT/pip.txt; }
nvidia-smi --query-gpu=name,memory.used --format=csv
LEFT=$(( ${LIMIT:-560} - ($(date +%s) - T_START) ))
echo "staged in $(( $(date +%s) - T_START )) s; limit $LEFT s"
timeout $LEFT python3 benchmarks/bench_robust_reselect.py \
  --polish results/orange_peel_paper_active_polish2/polish_active_again_paper_h100.json \
  --log results/orange_peel_paper_active_polish2/log.npz --arch cuda --sim-batch 64 --scheduling continuous --min-chunk 16 \
  --candidates ${CANDS:-8} --k ${K:-2} --out $OUT/robust_reselect_h100.json > $OUT/stdout.txt 2> $OUT/stderr.txt
echo "rc=$? in $(( $(date +%s) - T_START )) s"
tail -5 $OUT/stdout.txt; tail -15 $OUT/stderr.txt
