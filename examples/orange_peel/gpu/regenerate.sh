#!/usr/bin/env bash
# GPU regeneration of the orange-peel data (simulator 0.2.0), in phases that fit <= 10-minute device calls.
# Run from the repository root on the GPU machine after staging taichi/warp/pydantic into /tmp/gpusite
# (../shared/device/gpu-wheels.sh; pydantic wheels go into .gpu/ti). Results land in $OUT.
#   bash examples/orange_peel/gpu/regenerate.sh paper-bg      # start the paper set in the background (setsid)
#   bash examples/orange_peel/gpu/regenerate.sh quick         # quick set, tiny fixture, identifiability
#   bash examples/orange_peel/gpu/regenerate.sh wait 540      # wait for the paper set; return its parts
#   bash examples/orange_peel/gpu/regenerate.sh final         # noise checks and speed benchmarks
# The stores are written under /tmp/ds (outside the synced working tree, so they survive later calls).
# A committed snapshot of invphys in .gpu/src (git archive HEAD invphys) replaces the working tree's own,
# so that other people's uncommitted work cannot change a long generation.
set -uo pipefail
[ -d .gpu/src/invphys ] && rm -rf invphys && cp -r .gpu/src/invphys invphys
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT" /tmp/ds
ship_paper() { tar -C /tmp/ds -cf "$OUT/paper.tar" --exclude='.*.tmp' orange_peel_paper 2>/dev/null; \
               cp /tmp/paper.log "$OUT/paper.log" 2>/dev/null; true; }
case "$1" in
  paper-bg)
    setsid nohup python3 -m invphys.cli dataset generate datasets/specs/orange_peel_paper.yaml \
      --batch-size 256 --no-progress -o /tmp/ds/orange_peel_paper > /tmp/paper.log 2>&1 < /dev/null &
    echo $! > /tmp/paper.pid; echo "paper generation started (pid $(cat /tmp/paper.pid))";;
  quick)
    t0=$SECONDS
    python3 -m invphys.cli dataset generate datasets/specs/orange_peel_quick.yaml --no-progress \
      -o /tmp/ds/orange_peel_quick 2>&1 | tail -5
    echo "quick: $((SECONDS - t0)) s"; tar -C /tmp/ds -cf "$OUT/quick.tar" orange_peel_quick
    python3 tests/data/make_orange_tiny.py --n 512 --batch 64 --arch cuda --out "$OUT/orange_tiny.npz" | tail -2
    echo "fixture: $((SECONDS - t0)) s"
    python3 benchmarks/bench_identifiability.py --preset quick --arch cuda --points 16 --batch 64 \
      --scales-from /tmp/ds/orange_peel_quick --out "$OUT/identifiability_quick_cuda.json" | tail -30
    echo "identifiability: $((SECONDS - t0)) s"; tail -3 /tmp/paper.log; ship_paper;;
  wait)
    end=$((SECONDS + ${2:-540}))
    while [ $SECONDS -lt $end ] && kill -0 "$(cat /tmp/paper.pid)" 2>/dev/null; do sleep 10; done
    tail -5 /tmp/paper.log; ls /tmp/ds/orange_peel_paper | wc -l; ship_paper;;
  final)
    b=benchmarks
    for ds in paper quick; do
      python3 $b/bench_simulator_noise.py /tmp/ds/orange_peel_$ds --rows 64 --arch cuda --batch 64 \
        --out "$OUT/simulator_noise_$ds.json" | tail -12; done
    for be in taichi warp; do for bs in 64 16; do
      python3 $b/bench_simulator.py --backend $be --preset paper --arch cuda --batch $bs --runs $bs \
        $( [ $bs = 16 ] && echo --spread ) --out "$OUT/simulator_${be}_paper_cuda_random${bs}_b${bs}.json" | grep -E '"(wall_per_run_s|device|max_rel_feature_diff)"'
    done; done
    python3 $b/bench_simulator.py --backend taichi --preset paper --arch cuda --batch 64 --runs 64 \
      --config '{"eta_dt_factor": 1000}' --out "$OUT/simulator_taichi_paper_cuda_random64_b64_noeta.json" \
      | grep -E '"(wall_per_run_s|mean)"';;
esac
