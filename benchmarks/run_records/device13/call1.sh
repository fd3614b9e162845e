#!/bin/bash
# Device call 1: CUDA tests, captured latency vs diffusers, every sampler's CUDA latency, training throughput.
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
date; nvidia-smi -L; nproc; python3 -V
ls ~/.sapien 2>&1; find / -xdev -name 'libPhysXGpu*' 2>/dev/null | head -3
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site MUJOCO_GL=disable PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
python3 -c "import torch, torchrl, tensordict, numpy; print(torch.__version__, torchrl.__version__, tensordict.__version__, numpy.__version__, torch.cuda.get_device_name())"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py
timeout 170 python3 benchmarks/bench_latency_cuda.py --out $OUT/latency_cuda.json
timeout 200 python3 benchmarks/bench_train_throughput.py --device cuda --out $OUT/train_throughput_cuda.json
timeout 50 python3 benchmarks/bench_latency.py --device cuda --threads 0 --network state --no-train --out $OUT/latency_sampler_cuda_state.json
timeout 50 python3 benchmarks/bench_latency.py --device cuda --threads 0 --network image --no-train --out $OUT/latency_sampler_cuda_image.json
date
