#!/usr/bin/env bash
# Device run (issue 16): the previous commit's anisompm engine against this tree's on one GPU, in one call.
#   kind "batch" (default): per-stage kernel times and back-to-back substeps (bench_kernel_forms --skip-runs), then
#     one whole lock-step batch of SIZE random runs (bench_host_share; SIZE 64): old, new, old, new, since one
#     machine's times drift by a few per cent between passes;
#   kind "dataset": dataset generation end to end (bench_dataset.py: SIZE runs, default 384, 4 extraction
#     processes, stores written, 64 slots; SCHED (4th argument) lockstep (default: batches handed over
#     costliest first) or continuous; MIN_CHUNK (5th) for continuous: each version's own default when left
#     out (until stop 42 this kind always passed 16)): new, then old (ORDER="old new" in the environment: old first);
#   kind "stream": SIZE (default 256) random runs through continuous batching on a warm engine
#     (bench_continuous_gpu.py, min_chunk 16, costliest first, no feature check): old, new, old, new.
#
# Prepare here (ignored; only the changed packages, since a call carries at most 64 MiB):
#     rm -rf .gpu/old && mkdir -p .gpu/old && git archive HEAD~1 examples/anisompm | tar -x -C .gpu/old
# (add `invphys examples/orange_peel` to the archive when the change touches them: each old package found
# under .gpu/old comes first on the old path)
# then run `bash benchmarks/device/old_vs_new.sh <tag> [batch|dataset] [size]` with carry [".gpu/wb", ".gpu/old"]
# (or [".gpu/old"] on a machine staged already: ensure_staged.sh). Results under $OUT:
# kernel_times_<tag>_{old,new}_{1,2}.json, host_share_<tag>_{old,new}_{1,2}.json, dataset_paper_<tag>_{new,old}.json,
# stream_<tag>_{old,new}_{1,2}.json.
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
OUTDIR=${OUT:-/tmp/old_vs_new_out}; mkdir -p "$OUTDIR"
TAG=${1:-change}
KIND=${2:-batch}
export INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
NEW=$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel
# the benchmarks put this tree's packages first on sys.path unless they are there already: list them last
OLD=$NEW
for d in examples/orange_peel examples/anisompm; do
  if [ -d "$PWD/.gpu/old/$d" ]; then OLD=$PWD/.gpu/old/$d:$OLD; fi
done
if [ -d "$PWD/.gpu/old/invphys" ]; then OLD=$PWD/.gpu/old:$OLD; fi
path_of() { if [ "$1" = old ]; then echo "/tmp/gpusite:$OLD"; else echo "/tmp/gpusite:$NEW"; fi; }

if [ "$KIND" = dataset ]; then
  N=${3:-384}
  SCHED=${4:-lockstep}
  CHUNK=""; if [ "$SCHED" = continuous ] && [ -n "$5" ]; then CHUNK="--min-chunk $5"; fi
  for v in ${ORDER:-new old}; do
    PYTHONPATH=$(path_of $v) python3 benchmarks/bench_dataset.py --preset paper --arch cuda --n "$N" --batch-size 64 \
      --scheduling "$SCHED" $CHUNK --executors local --extract-workers 4 --warmup 2 \
      --simulator-type invphys_orange_peel.simulator:OrangePeelSimulator \
      --features-type invphys_orange_peel.features:OrangePeelFeatures \
      --out "$OUTDIR/dataset_paper_${TAG}_${v}.json" 2>&1 | grep -E "runs/h|s/run|per run|wall|error|Error" | tail -4
  done
  exit 0
fi
if [ "$KIND" = stream ]; then
  N=${3:-256}
  for pass in 1 2; do
    for v in old new; do
      PYTHONPATH=$(path_of $v) python3 benchmarks/bench_continuous_gpu.py --runs "$N" --batch 64 \
        --cases continuous:16:longest_first --no-features --tag "${TAG}_${v}_${pass}" \
        --out "$OUTDIR/stream_${TAG}_${v}_${pass}.json" 2>&1 | grep -E "seconds_per_run|error|Error" | tail -3
    done
  done
  exit 0
fi
BATCH=${3:-64}
for pass in 1 2; do
  for v in old new; do
    PYTHONPATH=$(path_of $v) python3 -c "import invphys_anisompm.backends.taichi_backend as m; print('$v uses', m.__file__)"
    PYTHONPATH=$(path_of $v) python3 benchmarks/bench_kernel_forms.py --preset paper --runs "$BATCH" --batch "$BATCH" \
      --forms loop --skip-runs --steps 40 --out "$OUTDIR/kernel_times_${TAG}_${v}_${pass}.json"
    PYTHONPATH=$(path_of $v) python3 benchmarks/bench_host_share.py --preset paper --arch cuda --batch "$BATCH" \
      --out "$OUTDIR/host_share_${TAG}_${v}_${pass}.json"
  done
done
