#!/usr/bin/env bash
# Prepares taichi (and the pure-Python wheels a pipeline stage needs: pydantic, cma, zuko, dill) to travel to
# the GPU machine in several carried folders: a `run` call carries at most 64 MiB, counted on disk (du -k), and
# the tracked tree (committed datasets, bundles and results) takes most of it, so taichi's compressed files
# (~37 MB) are cut into pieces that fit beside it.
#   .gpu/c1 .. .gpu/cN: taichi's files as pieces of one tar.xz (piece size = the room the tracked tree leaves)
#   .gpu/wb: the wheels, and the stage script that joins the pieces into /tmp/gpusite
# Usage (from the project's root):  bash benchmarks/device/split_taichi_wheels.sh   (prints the N calls to make)
# then `run` calls back to back (the machine is released after ~30 s idle):
#   bash .gpu/c1/stage.sh  carry [".gpu/c1"];  ...;  bash .gpu/cN/stage.sh  carry [".gpu/cN"]
#   bash .gpu/wb/stage.sh  carry [".gpu/wb"]
# then work calls that carry only run data and call benchmarks/device/ensure_staged.sh (the staged site stays
# while the machine is warm). Re-run this script when the tracked tree has grown (pieces must still fit).
# results/orange_peel_paper_protocol_amortised/device_validate.sh is an example of a work call.
set -euo pipefail
TI=${1:-1.7.4}
root=$(git rev-parse --show-toplevel); cd "$root"
grep -qxF '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
source benchmarks/device/pieces.sh
room_kib=$(carry_room_kib)
rm -rf .gpu/ti .gpu/tb .gpu/wb .gpu/c[0-9]* && mkdir -p .gpu/wb
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
python3 -m pip download -q --no-deps "${GPU_PLATFORM[@]}" -d "$tmp/whl" "taichi==$TI"
python3 -m pip download -q --no-deps "${GPU_PLATFORM[@]}" -d .gpu/wb dill pydantic pydantic-core annotated-types \
  typing-inspection cma zuko
mkdir -p "$tmp/t" && (cd "$tmp/t" && unzip -q "$tmp"/whl/taichi-*.whl)
echo "compressing taichi (a few minutes)..."
tar -C "$tmp/t" -cJf "$tmp/taichi.tar.xz" .
n=$(cut_into_pieces "$tmp/taichi.tar.xz" c "$room_kib")
write_join_stage c "$n" taichi .gpu/wb 'touch /tmp/gpusite/.staged; echo "taichi + wheels staged in /tmp/gpusite"'
du -sh .gpu/c* .gpu/wb
echo "$room_kib KiB of room per call; $n staging calls (.gpu/c1 .. .gpu/c$n), then .gpu/wb"
