#!/bin/bash
# Device call 2: bf16 graph test, latency with cuDNN autotuning, every sampler on CUDA, training throughput.
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
date
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site MUJOCO_GL=disable PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
timeout 90 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py -k captured
timeout 120 python3 benchmarks/bench_latency_cuda.py --cudnn-benchmark --rounds 30 --out $OUT/latency_cuda_cudnn_benchmark.json
timeout 45 python3 -m benchmarks.bench_latency --device cuda --threads 0 --network state --no-train --out $OUT/latency_sampler_cuda_state.json
timeout 60 python3 -m benchmarks.bench_latency --device cuda --threads 0 --network image --no-train --out $OUT/latency_sampler_cuda_image.json
date
timeout 250 python3 benchmarks/bench_train_throughput.py --device cuda --rounds 5 --networks image state --out $OUT/train_throughput_cuda.json
date
