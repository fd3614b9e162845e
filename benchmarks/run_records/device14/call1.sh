#!/bin/bash
# Device call 1 (session 14's lease): issue 30's QC and FQL arms on robosuite Can from the 20-demo BC start
# (runs/ft_bc_can_n20 best.pt, EMA weights only: .gpu/can_start.pt), learners on the GPU, MuJoCo in CPU
# workers. Four runs at once, each stopped (SIGTERM: checkpoint, no test) at its time limit.
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
[ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] && export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1 MUJOCO_GL=egl PYOPENGL_PLATFORM=egl OMP_NUM_THREADS=1
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
nvidia-smi -L; nproc
timeout 120 python3 -c "
import torch; print(torch.__version__, torch.cuda.is_available())
from l1flow_rl.envs.factory import make_env
env = make_env('robosuite_can', num_envs=1)
print(env.rollout(3)['next', 'reward'].shape)
env.close()
" || { echo PREFLIGHT FAILED; exit 3; }
T=${T:-420}
common="checkpoint=.gpu/can_start.pt task=robosuite_can device=cuda seed=0 eval.val_episodes=50 eval.episodes=100 eval.num_envs=5 eval.video_episodes=0"
offline="offline.steps=8000 offline.eval_every=2000"
# RLPD-style (QC-RLPD): no offline phase, demonstrations in half of every batch, 5,000 warm-up steps
online="online.steps=30000 online.eval_every=5000 online.num_envs=4"
run() { name=$1; shift; timeout -k 40 -s TERM $T python3 -m l1flow_rl.cli finetune $common run_dir=/tmp/r/$name "$@" > /tmp/r_$name.log 2>&1; echo "$name exit $?"; }
mkdir -p /tmp/r
run qc_offline finetune=qc $offline &
run fql_offline finetune=fql $offline &
run fql_online finetune=fql $online &
run qc_online finetune=qc $online &
sleep 60; nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv; uptime
wait
for f in /tmp/r_*.log; do tr '\r' '\n' < $f | grep -a -v "it/s\]$" | tail -25; done
tar -C /tmp -cJf $OUT/runs.tar.xz --exclude=checkpoints r $(cd /tmp && ls r_*.log)
ls -la $OUT
