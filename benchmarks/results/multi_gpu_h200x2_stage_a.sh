#!/usr/bin/env bash
# Device call A (H2): Ray 2.60 (stripped: no jars/rllib/data/serve/tune/train/llm/dashboard UI; binaries
# stripped of symbols) + jsonschema & deps into /tmp/gpusite, then a 2-GPU Ray smoke test.
set -e
mkdir -p /tmp/gpusite && tar -C /tmp/gpusite -xJf .gpu/h2/a/ray.tar.xz
python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/gpusite .gpu/h2/a/*.whl
export PYTHONPATH=/tmp/gpusite PYTHONUNBUFFERED=1
python3 --version; nvidia-smi --query-gpu=name,memory.total --format=csv,noheader; df -h /dev/shm | tail -1
timeout 120 python3 - <<'P'
import subprocess, time, ray
t = time.time()
n = len(subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout.split("GPU ")) - 1
ray.init(num_gpus=n, include_dashboard=False, configure_logging=False)   # as the benchmark does
print("ray", ray.__version__, "resources", {k: v for k, v in ray.cluster_resources().items() if k in ("CPU", "GPU")},
      "init %.1fs" % (time.time() - t))
@ray.remote(num_gpus=1)
class A:
    def f(self):
        import os
        return os.environ.get("CUDA_VISIBLE_DEVICES"), [str(g) for g in ray.get_gpu_ids()]
if ray.cluster_resources().get("GPU", 0) < 2:
    raise SystemExit("Ray sees fewer than 2 GPUs")
xs = [A.remote() for _ in range(2)]
print("actors", ray.get([x.f.remote() for x in xs], timeout=60), "%.1fs" % (time.time() - t))
ray.shutdown()
P
echo "stage A ok"
