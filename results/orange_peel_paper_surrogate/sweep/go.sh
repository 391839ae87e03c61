#!/bin/bash
# one GPU call: all sweep configs in parallel processes + sklearn peers on the CPU cores
cd "$(dirname "$0")"
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
python -c "import torch, numpy; print('torch', torch.__version__, torch.cuda.is_available())"
python -c "import sklearn, scipy, joblib; print('sklearn', sklearn.__version__, scipy.__version__)" || echo NO_SKLEARN
mkdir -p $OUT/s
names=$(python -c "import sys; sys.argv=['x','data.npz','/tmp']; import sweep; print(' '.join(sweep.configs()))")
for n in $names; do timeout 320 python sweep.py data.npz $OUT/s $n > $OUT/s/log_$n.txt 2>&1 & done
for n in paper modern_yj modern_none; do timeout 320 python sweep.py data.npz $OUT/s $n 250,500,1000 > $OUT/s/log_lc_$n.txt 2>&1 & done
(timeout 320 python gp.py data.npz $OUT/s > $OUT/s/log_peers.txt 2>&1) &
wait
cat $OUT/s/log_*.txt
cd $OUT && tar czf sweep.tgz s && rm -rf s
