#!/bin/bash
# Device call 4: the train job on CUDA end to end (point-mass double), its checkpoint re-scored on the CPU.
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site MUJOCO_GL=disable PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py -k "train_job"
