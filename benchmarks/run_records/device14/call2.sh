#!/bin/bash
# Device call 2 (the lease's last ~4 minutes): the fixed CUDA online path, smallest end-to-end run on Can
# (QC, 2 collector workers, 2 rounds of 300 env steps, 8 updates), learner on the GPU.
exec > >(tee -a $OUT/log.txt) 2>&1
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1 MUJOCO_GL=egl PYOPENGL_PLATFORM=egl
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
export OMP_NUM_THREADS=1
python3 -m l1flow_rl.cli finetune finetune=qc checkpoint=.gpu/can_start.pt task=robosuite_can device=cuda \
    seed=0 run_dir=/tmp/r online.steps=600 online.warmup_steps=300 online.frames_per_round=300 \
    online.num_envs=2 online.updates_per_step=0.0267 eval.val_episodes=2 eval.episodes=2 eval.num_envs=2 \
    eval.video_episodes=0 finetune.qc.num_samples=4 finetune.batch_size=16 2>&1 | tr '\r' '\n' | grep -a -v "it/s\]$"
echo "finetune exit ${PIPESTATUS[0]}"
python3 -c "import json; h=json.load(open('/tmp/r/history.json')); print([(r['env_steps'], r['policy'], r['updates'], round(r['env_steps_per_s'],1)) for r in h['rounds']])"
