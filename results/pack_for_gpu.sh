#!/usr/bin/env bash
# Packs what the validate and report stages of prepared runs read (train/ without figures, invert/'s JSON,
# validate/ without renders: the memo and baselines.json) into one tarball to carry to the GPU machine;
# results/device_validate_all.sh unpacks it there. Prints its size: the carry limit is 64 MiB minus the
# tracked tree (git ls-files), with taichi staged by earlier calls.
# usage: bash results/pack_for_gpu.sh OUT.tgz RUN [RUN ...]
set -euo pipefail
out=$1; shift
[ $# -ge 1 ] || { echo "usage: pack_for_gpu.sh OUT.tgz RUN [RUN ...]"; exit 2; }
paths=()
for run in "$@"; do
  [ -d "$run/train" ] && [ -d "$run/invert" ] || { echo "error: $run has no train/ and invert/ (run them on the CPU first)" >&2; exit 2; }
  [ -f "$run/validate/baselines.json" ] || echo "warning: $run/validate/baselines.json missing: the GPU machine would fit the baselines (sbi is not there)" >&2
  paths+=("$run/train" "$run"/invert/*.json)
  [ -d "$run/validate" ] && paths+=("$run/validate")
  [ -f "$run/spec.yaml" ] && paths+=("$run/spec.yaml")
done
tar -czf "$out" --exclude='*.png' --exclude='validate/renders' "${paths[@]}"
tracked=$(git ls-files -z | xargs -0 du -ck 2>/dev/null | tail -1 | cut -f1)   # the carry counts disk use
echo "$out: $(du -k "$out" | cut -f1) KiB; tracked tree $tracked KiB; limit $((64 * 1024)) KiB"
