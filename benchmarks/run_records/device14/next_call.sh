#!/bin/bash
# Prepared for the next lease (not yet run): verifies the CUDA online path fixed after call1 and measures
# online QC/FQL on Can with the learner on the GPU. Build the carried files first (build_bundle.sh), then
#   run(command="bash benchmarks/run_records/device14/next_call.sh",
#       carry=[".gpu", ".gl", "data/robosuite/PickPlaceCan"], timeout_s=560)
# Every run stops itself (SIGTERM at T seconds: checkpoint, no test); the records come back in runs.tar.
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
[ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] && export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1 MUJOCO_GL=egl PYOPENGL_PLATFORM=egl
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
export OMP_NUM_THREADS=1  # after pip: nproc reads it (the machine has 16 cores)
# 1. the online path on CUDA (ManiSkill is not in the bundle: the CUDA test skips without it, so the same
#    check runs on Can below, and the test stays for a lease that carries mani_skill)
T=${T:-400}
common="checkpoint=.gpu/can_start.pt task=robosuite_can device=cuda seed=0 eval.val_episodes=50 eval.episodes=100 eval.num_envs=5 eval.video_episodes=0"
# RLPD-style (QC-RLPD): no offline phase, demonstrations in half of every batch; a 2,000-step warm-up so
# that updates start within the lease (the presets' 5,000 is the anchors')
online="online.steps=30000 online.warmup_steps=2000 online.eval_every=10000 online.num_envs=8"
run() { name=$1; shift; timeout -k 40 -s TERM $T python3 -m l1flow_rl.cli finetune $common run_dir=/tmp/r/$name "$@" > /tmp/r_$name.log 2>&1; echo "$name exit $?"; }
mkdir -p /tmp/r
run qc_online finetune=qc $online &
run fql_online finetune=fql $online &
wait
for f in /tmp/r_*.log; do tr '\r' '\n' < $f | grep -a -E "validation|Error|error" | tail -8; done
tar -C /tmp -cf $OUT/runs.tar --exclude=checkpoints r $(cd /tmp && ls r_*.log)
ls -la $OUT
