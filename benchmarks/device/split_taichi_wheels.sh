#!/usr/bin/env bash
# Prepares taichi (and the pure-Python wheels a pipeline stage needs: pydantic, cma) to travel to the GPU
# machine in TWO carried folders, because the working tree (~33 MB with the committed datasets, bundles and
# results) plus the whole taichi wheel (56 MB) exceeds the 64 MiB a `run` call carries.
#   .gpu/ti: part a of taichi's files as tar.xz (~19 MB)
#   .gpu/tb: part b (~18 MB) + pydantic, pydantic-core, annotated-types, typing-inspection, cma, zuko, dill wheels
# Usage (from the project's root):  bash benchmarks/device/split_taichi_wheels.sh
# then two `run` calls back to back (the machine is released after ~30 s idle):
#   1. bash .gpu/ti/stage.sh                      carry [".gpu/ti"]
#   2. bash .gpu/tb/stage.sh && YOUR_COMMAND      carry [".gpu/tb", ...]  (PYTHONPATH=/tmp/gpusite:$PWD:...)
# or, when run directories need the carry's room: 2. `bash .gpu/tb/stage.sh` alone, then work calls that
# carry only run data and call benchmarks/device/ensure_staged.sh (the staged site stays while warm).
# results/orange_peel_paper_protocol_amortised/device_validate.sh is an example of call 2.
set -euo pipefail
TI=${1:-1.7.4}
root=$(git rev-parse --show-toplevel); cd "$root"
grep -qxF '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
rm -rf .gpu/ti .gpu/tb && mkdir -p .gpu/ti .gpu/tb
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
plat=(--only-binary=:all: --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64
      --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64)
python3 -m pip download -q --no-deps "${plat[@]}" -d "$tmp/whl" "taichi==$TI"
python3 -m pip download -q --no-deps "${plat[@]}" -d .gpu/tb dill pydantic pydantic-core annotated-types \
  typing-inspection cma zuko
mkdir -p "$tmp/t" && (cd "$tmp/t" && unzip -q "$tmp"/whl/taichi-*.whl)
echo "compressing taichi (a few minutes)..."
tar -C "$tmp/t" -cJf "$tmp/taichi.tar.xz" .
(cd "$tmp" && split -b 19000000 taichi.tar.xz part.)
mv "$tmp/part.aa" .gpu/ti/ && mv "$tmp"/part.a[b-z] .gpu/tb/
cat > .gpu/ti/stage.sh <<'S'
set -e; mkdir -p /tmp/gpuparts && cp .gpu/ti/part.* /tmp/gpuparts/ && echo "taichi part a staged"
S
cat > .gpu/tb/stage.sh <<'S'
set -e; if [ ! -d /tmp/gpusite/taichi ]; then cp .gpu/tb/part.* /tmp/gpuparts/ && mkdir -p /tmp/gpusite && cat /tmp/gpuparts/part.* | tar -C /tmp/gpusite -xJf - ; fi
python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite .gpu/tb/*.whl
touch /tmp/gpusite/.staged; echo "taichi + wheels staged in /tmp/gpusite"
S
du -sh .gpu/ti .gpu/tb
