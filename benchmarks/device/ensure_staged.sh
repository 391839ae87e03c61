#!/usr/bin/env bash
# Sourced or run by device scripts: taichi and the wheels in /tmp/gpusite, staged by an earlier call on this
# warm machine (marker /tmp/gpusite/.staged) or now from a carried .gpu/wb. Staging in its own calls
# (benchmarks/device/split_taichi_wheels.sh: `bash .gpu/cN/stage.sh` carry [".gpu/cN"] for each piece, then
# `bash .gpu/wb/stage.sh` carry [".gpu/wb"]) leaves a
# work call the whole 64 MiB carry minus the tracked tree for run directories.
if [ -f /tmp/gpusite/.staged ]; then
  echo "taichi + wheels already staged in /tmp/gpusite"
elif [ -f .gpu/wb/stage.sh ]; then
  bash .gpu/wb/stage.sh
else
  echo "error: nothing staged on this machine and no .gpu/wb carried (fresh machine? stage .gpu/c1 .. .gpu/cN, then .gpu/wb)" >&2
  exit 1
fi
