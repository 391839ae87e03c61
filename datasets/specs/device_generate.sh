#!/usr/bin/env bash
# Device run: (re)generate the committed datasets with the working tree's simulator, resumable.
# Usage on the device: STEPS="quick paper noise" LIMIT=560 bash datasets/specs/device_generate.sh
# Staging: `bash benchmarks/device/split_taichi_wheels.sh` here; on the device one call `bash .gpu/ti/stage.sh`
# (carry .gpu/ti), then this script with carry .gpu/tb. The stores come back under $OUT/datasets/.
T_START=$(date +%s)
bash benchmarks/device/ensure_staged.sh || exit 1
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . -e examples/anisompm -e examples/orange_peel > $OUT/pip.txt 2>&1 || { echo "pip -e failed"; tail -5 $OUT/pip.txt; }
nvidia-smi --query-gpu=name,memory.used --format=csv,noheader
left() { echo $(( ${LIMIT:-560} - ($(date +%s) - T_START) )); }
echo "staged in $(( $(date +%s) - T_START )) s"
mkdir -p $OUT/datasets
for step in ${STEPS:-quick paper}; do
  L=$(left); [ "$L" -lt 40 ] && { echo "no time for $step"; break; }
  case $step in
    quick|paper)
      M=$(python3 -c "print(max(0.5, ($L - 25) / 60))")
      echo "== $step: limit $M min"
      timeout $L python3 -m invphys.cli dataset generate datasets/specs/orange_peel_$step.yaml --limit-minutes $M \
        > $OUT/gen_$step.txt 2>&1; echo "rc=$? at $(( $(date +%s) - T_START )) s"; tail -12 $OUT/gen_$step.txt
      tar --exclude=.lock -cf $OUT/datasets/$step.tar datasets/orange_peel_$step ;;
    noise)
      echo "== noise"
      timeout $L python3 benchmarks/bench_simulator_noise.py datasets/orange_peel_paper --rows 64 --arch cuda --batch 64 \
        --jitter 0.01 --repeats 4 --out $OUT/simulator_noise_paper.json > $OUT/noise.txt 2>&1
      echo "rc=$? at $(( $(date +%s) - T_START )) s"; tail -40 $OUT/noise.txt ;;
  esac
done
echo "done in $(( $(date +%s) - T_START )) s"
