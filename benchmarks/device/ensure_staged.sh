#!/usr/bin/env bash
# Sourced or run by device scripts: taichi and the wheels in /tmp/gpusite, staged by an earlier call on this
# warm machine (marker /tmp/gpusite/.staged) or now from a carried .gpu/tb. Staging in its own calls
# (`bash .gpu/ti/stage.sh` carry [".gpu/ti"], then `bash .gpu/tb/stage.sh` carry [".gpu/tb"]) leaves a
# work call the whole 64 MiB carry minus the tracked tree for run directories.
if [ -f /tmp/gpusite/.staged ]; then
  echo "taichi + wheels already staged in /tmp/gpusite"
elif [ -f .gpu/tb/stage.sh ]; then
  bash .gpu/tb/stage.sh
else
  echo "error: nothing staged on this machine and no .gpu/tb carried (fresh machine? stage .gpu/ti then .gpu/tb)" >&2
  exit 1
fi
