#!/usr/bin/env bash
# Device run (issue 16): the previous commit's packages against this tree's on one GPU, alternating in one call
# (one machine's times drift by a few per cent between passes): per-stage kernel times and back-to-back
# substeps (bench_kernel_forms --skip-runs), then a whole lock-step batch (bench_host_share); old, new, old, new.
#
# Prepare here (ignored; only the changed package, since a call carries at most 64 MiB):
#     rm -rf .gpu/old && mkdir -p .gpu/old && git archive HEAD~1 examples/anisompm | tar -x -C .gpu/old
# then run `bash benchmarks/device/old_vs_new.sh <tag> [batch]` with carry [".gpu/wb", ".gpu/old"] after staging
# (ensure_staged.sh). Results: $OUT/kernel_times_<tag>_{old,new}_{1,2}.json, $OUT/host_share_<tag>_{old,new}_{1,2}.json.
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
OUTDIR=${OUT:-/tmp/old_vs_new_out}; mkdir -p "$OUTDIR"
TAG=${1:-change}
BATCH=${2:-64}
export INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
NEW=$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel
# the benchmarks put this tree's packages first on sys.path unless they are there already: list them last
OLD=$PWD/.gpu/old/examples/anisompm:$NEW
for pass in 1 2; do
  for v in old new; do
    if [ "$v" = old ]; then P=$OLD; else P=$NEW; fi
    PYTHONPATH=/tmp/gpusite:$P python3 -c "import invphys_anisompm.backends.taichi_backend as m; print('$v uses', m.__file__)"
    PYTHONPATH=/tmp/gpusite:$P python3 benchmarks/bench_kernel_forms.py --preset paper --runs "$BATCH" --batch "$BATCH" \
      --forms loop --skip-runs --steps 40 --out "$OUTDIR/kernel_times_${TAG}_${v}_${pass}.json"
    PYTHONPATH=/tmp/gpusite:$P python3 benchmarks/bench_host_share.py --preset paper --arch cuda --batch "$BATCH" \
      --out "$OUTDIR/host_share_${TAG}_${v}_${pass}.json"
  done
done
