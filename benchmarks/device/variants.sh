#!/usr/bin/env bash
# Device run (issue 16): several versions of the anisompm engine on one GPU, in one call: per-stage kernel times
# and back-to-back substeps of 64 random runs (bench_kernel_forms --skip-runs) for each, in the order given.
#   bash benchmarks/device/variants.sh <tag> name=dir [name=dir ...]
# ``dir`` holds a copy of examples/anisompm (e.g. .gpu/old from `git archive HEAD examples/anisompm`, or a
# variant a trial patched); ``new`` (no dir) is this tree. Carry the dirs (a call carries at most 64 MiB).
# Results under $OUT: kernel_times_<tag>_<name>.json.
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
OUTDIR=${OUT:-/tmp/variants_out}; mkdir -p "$OUTDIR"
TAG=$1; shift
export INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
NEW=$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel
for spec in "$@"; do
  name=${spec%%=*}; dir=${spec#*=}
  if [ "$name" = "$spec" ]; then path=/tmp/gpusite:$NEW; else path=/tmp/gpusite:$PWD/$dir/examples/anisompm:$NEW; fi
  PYTHONPATH=$path python3 -c "import invphys_anisompm.backends.taichi_backend as m; print('$name uses', m.__file__)"
  PYTHONPATH=$path python3 benchmarks/bench_kernel_forms.py --preset paper --runs 64 --batch 64 --forms loop \
    --skip-runs --steps 40 --out "$OUTDIR/kernel_times_${TAG}_${name}.json" | grep -E "streamed|ms'" || true
done
