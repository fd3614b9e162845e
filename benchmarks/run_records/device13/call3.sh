#!/bin/bash
# Device call 3: static-shape compile fix (test + the state network's compiled settings), every sampler on CUDA.
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
date
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site MUJOCO_GL=disable PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
timeout 100 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py -k "compiled_trainer or bf16_autocast or host_syncs"
timeout 210 python3 benchmarks/bench_train_throughput.py --device cuda --rounds 5 --networks state --out $OUT/train_throughput_cuda_state.json
date
timeout 90 python3 -m benchmarks.bench_latency --device cuda --threads 0 --network state --no-train --rounds 6 --out $OUT/latency_sampler_cuda_state.json
timeout 110 python3 -m benchmarks.bench_latency --device cuda --threads 0 --network image --no-train --rounds 5 --out $OUT/latency_sampler_cuda_image.json
date
