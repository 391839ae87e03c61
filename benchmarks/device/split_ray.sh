#!/usr/bin/env bash
# Prepares Ray (for the `ray_actors` executor and benchmarks/bench_multi_gpu.py) to travel to the GPU machine
# in pieces that fit beside the tracked tree under the 64 MiB a `run` call carries, like
# split_taichi_wheels.sh does for taichi. Ray's wheel (~80 MB) is stripped to what actors need: no jars,
# rllib, data, serve, tune, train, llm or dashboard UI; its binaries without symbols (~25 MB as tar.xz).
#   .gpu/r1 .. .gpu/rK: pieces of ray.tar.xz
#   .gpu/rw: Ray's dependency wheels and the stage script that joins the pieces into /tmp/gpusite
# Usage (from the project's root):  bash benchmarks/device/split_ray.sh [VERSION]
# then, on the machine that will run the work (after or before taichi's staging, back to back):
#   bash .gpu/r1/stage.sh carry [".gpu/r1"]; ...; bash .gpu/rK/stage.sh; bash .gpu/rw/stage.sh carry [".gpu/rw"]
set -euo pipefail
RAY=${1:-2.60.0}
root=$(git rev-parse --show-toplevel); cd "$root"
grep -qxF '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
source benchmarks/device/pieces.sh
room_kib=$(carry_room_kib)
rm -rf .gpu/rw .gpu/r[0-9]* && mkdir -p .gpu/rw
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
python3 -m pip download -q --no-deps "${GPU_PLATFORM[@]}" -d "$tmp/whl" "ray==$RAY"
python3 -m pip download -q --no-deps "${GPU_PLATFORM[@]}" -d .gpu/rw click filelock jsonschema attrs referencing \
  rpds-py jsonschema-specifications msgpack packaging protobuf pyyaml requests urllib3 idna certifi \
  charset-normalizer
mkdir -p "$tmp/r" && (cd "$tmp/r" && unzip -q "$tmp"/whl/ray-*.whl)
(cd "$tmp/r/ray" && rm -rf jars rllib data serve tune train llm dashboard/client)
strip --strip-unneeded "$tmp/r/ray/_raylet.so" "$tmp/r/ray/core/src/ray/gcs/gcs_server" \
  "$tmp/r/ray/core/src/ray/raylet/raylet" 2>/dev/null || echo "warning: strip failed; pieces are larger"
echo "compressing ray (a minute)..."
tar -C "$tmp/r" -cJf "$tmp/ray.tar.xz" .
n=$(cut_into_pieces "$tmp/ray.tar.xz" r "$room_kib")
write_join_stage r "$n" ray .gpu/rw 'PYTHONPATH=/tmp/gpusite python3 -c "import ray" && echo "ray staged in /tmp/gpusite"'
du -sh .gpu/r[0-9]* .gpu/rw
echo "$room_kib KiB of room per call; $n staging calls (.gpu/r1 .. .gpu/r$n), then .gpu/rw"
