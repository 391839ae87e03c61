#!/usr/bin/env bash
# Device run: the validate + report stages of amortised_vs_lookup_paper.yaml on one GPU (simulator 0.3.0).
# Staging: taichi in carried pieces (benchmarks/device/split_taichi_wheels.sh: one call per .gpu/cN, then .gpu/wb),
# and
# RUN (train + first report made on the CPU; report/baselines.json copied into
# validate/) as carried paths (or inside a carried tarball: results/device_validate_all.sh). Resumable: a call stopped by LIMIT keeps validate/simulated.jsonl.
# usage (a work call after staging, carry [RUN]): bash results/orange_peel_paper_protocol_amortised/device_validate.sh SECONDS [SPEC RUN]
# (defaults: amortised_vs_lookup_paper.yaml, runs/protocol_paper_amortised; the extra-data spec is
# amortised_vs_lookup_paper_extra.yaml with runs/protocol_paper_amortised_extra)
REPO=$PWD
OUT=${OUT:-/tmp/validate_out}; mkdir -p $OUT
LIMIT=${1:-420}
SPEC=${2:-examples/orange_peel/invphys_orange_peel/specs/amortised_vs_lookup_paper.yaml}
RUN=${3:-runs/protocol_paper_amortised}
bash benchmarks/device/ensure_staged.sh || exit 1
export PYTHONPATH=/tmp/gpusite:$REPO:$REPO/examples/anisompm:$REPO/examples/orange_peel PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.used --format=csv
# The packages installed (editable, their entry points registered) make the stage keys the CPU computes: the
# spec runs as written, and the CPU's report finds validate current. Where the install fails, the spec's
# plugins are named by module path with autoload off (it runs, but the CPU then sees validate as stale).
if python3 -m pip install -q --no-deps --no-build-isolation -e . -e examples/anisompm -e examples/orange_peel \
     > /tmp/pip_install.txt 2>&1 && python3 -m invphys.cli validate $SPEC > /tmp/validate_spec.txt 2>&1; then
  echo "packages installed: the spec runs as written"; cp $SPEC /tmp/amortised_gpu.yaml
  echo "tracker: none" >> /tmp/amortised_gpu.yaml   # no TensorBoard there; the tracker is in no stage key
else
  echo "packages not installed ($(tail -c 300 /tmp/pip_install.txt /tmp/validate_spec.txt 2>/dev/null | tr '\n' ' ')): module paths, autoload off"
  export INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
  sed -e 's/^simulator: {type: orange_peel,/simulator: {type: "invphys_orange_peel.simulator:OrangePeelSimulator",/' \
      -e 's/^executor: {type: local}/executor: {type: local}\nfeatures: {type: "invphys_orange_peel.features:OrangePeelFeatures"}/' \
      $SPEC > /tmp/amortised_gpu.yaml && echo "tracker: none" >> /tmp/amortised_gpu.yaml
fi
NAME=$(basename $RUN); LOGS=$RUN/device_logs; mkdir -p $LOGS   # inside the returned tarball (a call returns few files)
# a warm machine keeps the previous call's memo in /tmp (a later call's carry replaces the tree's copy)
KEEP=/tmp/keep/$RUN
if [ -f $KEEP/validate/simulated.jsonl ] && [ $(wc -l < $KEEP/validate/simulated.jsonl) -gt $(cat $RUN/validate/simulated.jsonl 2>/dev/null | wc -l) ]; then
  cp -r $KEEP/validate/. $RUN/validate/ && echo "memo taken from the previous call on this machine"
fi
wc -l $RUN/validate/simulated.jsonl 2>/dev/null
T0=$(date +%s)
timeout $LIMIT python3 -m invphys.cli run /tmp/amortised_gpu.yaml --out $RUN --stage validate --no-progress \
  > $LOGS/validate_stdout.txt 2> $LOGS/validate_stderr.txt
echo "validate rc=$? in $(( $(date +%s) - T0 )) s"
tail -c 2500 $LOGS/validate_stderr.txt; tail -c 1500 $LOGS/validate_stdout.txt
timeout 60 python3 -m invphys.cli run /tmp/amortised_gpu.yaml --out $RUN --stage report --no-progress > $LOGS/report_stdout.txt 2>&1
echo "report rc=$?"; tail -c 800 $LOGS/report_stdout.txt
wc -l $RUN/validate/simulated.jsonl
mkdir -p $KEEP && cp -r $RUN/validate $KEEP/
tar -C $RUN -czf $OUT/$NAME.tgz --exclude=validate/renders validate report device_logs
ls -la $OUT
