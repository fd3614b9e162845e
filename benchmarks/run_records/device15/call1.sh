#!/bin/bash
# Wave 3's sixth session, one lent H200: issue 30's first online QC and FQL measurement with a validation
# after the updates (device14's call stopped before any online validation). Carried files: device14's
# build_bundle.sh. Run as
#   run(command="bash benchmarks/run_records/device15/call1.sh",
#       carry=[".gpu", ".gl", "data/robosuite/PickPlaceCan"], timeout_s=570)
# Design for one call: learner on the GPU (~15 updates/s each, device14), 8 collector workers each,
# 0.25 updates per env step so that 16k env steps (2k of warm-up with the start) and ~3,500 updates fit;
# validation (50 episodes, 10 envs) of the start and at the end; each run stops itself at T seconds.
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
[ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] && export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1 MUJOCO_GL=egl PYOPENGL_PLATFORM=egl
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
export OMP_NUM_THREADS=1
T=${T:-500}  # too long for timeout_s=570 with ~30 s of setup and timeout -k 40: the digest and tar below never ran (README)
common="checkpoint=.gpu/can_start.pt task=robosuite_can device=cuda seed=0 eval.val_episodes=50 eval.episodes=100 eval.num_envs=10 eval.video_episodes=0"
online="online.steps=16000 online.warmup_steps=2000 online.updates_per_step=0.25 online.eval_every=0 online.num_envs=8"
run() { name=$1; shift; timeout -k 40 -s TERM $T python3 -m l1flow_rl.cli finetune $common run_dir=/tmp/r/$name "$@" > /tmp/r_$name.log 2>&1; echo "$name exit $?"; }
mkdir -p /tmp/r
nvidia-smi --query-gpu=name,memory.used --format=csv
run qc_online finetune=qc $online &
run fql_online finetune=fql $online &
wait
for f in /tmp/r_*.log; do tr '\r' '\n' < $f | grep -a -E "validation|test|Error|error" | tail -8; done
tar -C /tmp -cf $OUT/runs.tar --exclude=checkpoints r $(cd /tmp && ls r_*.log)
ls -la $OUT
