#!/usr/bin/env bash
# Device run (issue 16): a dataset (bench_dataset.py, continuous, 64 slots, 4 extraction processes) under Nsight
# Systems' CUDA trace, then where the GPU waits (benchmarks/gpu_timeline_gaps.py): its busy share and idle gaps
# in the steady state, and the gaps after each synchronising read (the host's work between a frame end and the
# next launch). Needs .gpu/nsys (benchmarks/device/prepare_nsys.sh) staged: carry [".gpu/wb", ".gpu/nsys"].
#   bash benchmarks/device/nsys_dataset.sh <tag> [runs (256)]
# Results under $OUT: dataset_nsys_<tag>.json, gaps_<tag>_steady.json (30 s ending 12 s before the last
# kernel), gaps_<tag>_all.json, api_<tag>_top.txt (CUDA API calls by total time).
set -e
bash benchmarks/device/ensure_staged.sh >/dev/null
bash .gpu/nsys/stage.sh
OUTDIR=${OUT:-/tmp/nsys_out}; mkdir -p "$OUTDIR"
TAG=$1; N=${2:-256}
D=$(dirname "$(find /opt/nvidia -path "*target-linux-x64/nsys" -type f | head -1)")
Q=$(find /opt/nvidia -name QdstrmImporter -type f | head -1)
export INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1
export PYTHONPATH=/tmp/gpusite:$PWD:$PWD/examples/anisompm:$PWD/examples/orange_peel
"$D/nsys" profile -t cuda --sample=none --cpuctxsw=none -o /tmp/tr_$TAG python3 benchmarks/bench_dataset.py \
  --preset paper --arch cuda --n "$N" --batch-size 64 --scheduling continuous --executors local --extract-workers 4 \
  --warmup 2 --time-split --simulator-type invphys_orange_peel.simulator:OrangePeelSimulator \
  --features-type invphys_orange_peel.features:OrangePeelFeatures --out "$OUTDIR/dataset_nsys_$TAG.json" \
  2>&1 | grep -oE '"wall_s": [0-9.]+, "ok": [0-9]+' | head -1 || true
[ -f /tmp/tr_$TAG.nsys-rep ] || LD_LIBRARY_PATH=/tmp/nsyslib "$Q" -i /tmp/tr_$TAG.qdstrm | tail -2
LD_LIBRARY_PATH=/tmp/nsyslib "$D/nsys" stats -r cuda_gpu_trace,cuda_api_trace --format csv -o /tmp/tr_$TAG \
  /tmp/tr_$TAG.nsys-rep > /dev/null
python3 benchmarks/gpu_timeline_gaps.py /tmp/tr_${TAG}_cuda_gpu_trace.csv /tmp/tr_${TAG}_cuda_api_trace.csv \
  --last-s 30 --skip-last-s 12 --out "$OUTDIR/gaps_${TAG}_steady.json" | head -30
python3 benchmarks/gpu_timeline_gaps.py /tmp/tr_${TAG}_cuda_gpu_trace.csv /tmp/tr_${TAG}_cuda_api_trace.csv \
  --out "$OUTDIR/gaps_${TAG}_all.json" > /dev/null
python3 - "$TAG" > "$OUTDIR/api_${TAG}_top.txt" <<'EOP'
import collections, csv, sys
count, total = collections.Counter(), collections.Counter()
for r in csv.DictReader(open(f"/tmp/tr_{sys.argv[1]}_cuda_api_trace.csv")):
    count[r["Name"]] += 1
    total[r["Name"]] += float(r["Duration (ns)"])
for name, ns in total.most_common(20):
    print(f"{name}\t{count[name]}\t{ns / 1e9:.3f} s")
EOP
cat "$OUTDIR/api_${TAG}_top.txt"
