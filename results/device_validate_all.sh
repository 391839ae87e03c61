#!/usr/bin/env bash
# Device run: the validate + report stages of several prepared runs in ONE call, in order, within SECONDS.
# BUNDLE is a tarball of the runs' files the validate stage reads (made on the CPU by
# `bash results/pack_for_gpu.sh runs/next_gpu.tgz RUN ...`, carried as one path, unpacked here); each run's validate/ + report/ come back as $OUT/<run name>.tgz (unpack with
# `tar -C runs/<run name> -xzf`). A run cut short by the time limit resumes in the next call on the same warm
# machine (device_validate.sh keeps the memo in /tmp/keep). Stage taichi first (ensure_staged.sh).
# usage: bash results/device_validate_all.sh SECONDS BUNDLE SPEC RUN [SPEC RUN ...]
SECONDS_ALL=$1; BUNDLE=$2; shift 2
[ -n "$SECONDS_ALL" ] && [ -f "$BUNDLE" ] && [ $# -ge 2 ] || { echo "usage: device_validate_all.sh SECONDS BUNDLE SPEC RUN [SPEC RUN ...]"; exit 2; }
tar -xzf "$BUNDLE" || exit 1
DEADLINE=$(( $(date +%s) + SECONDS_ALL ))
while [ $# -ge 2 ]; do
  SPEC=$1; RUN=$2; shift 2
  LEFT=$(( DEADLINE - $(date +%s) - 40 ))   # report + tar after the validate stage
  [ $LEFT -gt 30 ] || { echo "no time left for $RUN"; break; }
  echo "=== $RUN ($LEFT s)"
  bash results/orange_peel_paper_protocol_amortised/device_validate.sh $LEFT $SPEC $RUN
done
ls -la ${OUT:-/tmp/validate_out}
