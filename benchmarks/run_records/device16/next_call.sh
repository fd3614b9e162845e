#!/bin/bash
# Prepared in wave 3's seventh session for the next GPU lease (that session had 284 device-seconds, too
# few to start a machine). Issue 30: device15's online QC on Can rose 0.14 -> 0.26 (one seed); on the
# CPU, QC with the flow frozen and its proposals cached (N=8, 0.1 updates per env step) fell 0.22 ->
# 0.06/0.10 at 25k/50k env steps. This call separates the two questions at device15's exact budget:
#   qc_frozen_seed0: the flow frozen (ProposalCache), everything else as device15 (N=32, UTD 0.25, seed 0);
#   qc_seed1: device15's run with another seed (does the rise replicate?).
# Carried files: ../device14/build_bundle.sh. Run as
#   run(command="bash benchmarks/run_records/device16/next_call.sh",
#       carry=[".gpu", ".gl", "data/robosuite/PickPlaceCan"], timeout_s=590)
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
[ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] && export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1 MUJOCO_GL=egl PYOPENGL_PLATFORM=egl
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
export OMP_NUM_THREADS=1
T=${T:-500}  # T <= timeout_s - 80 (setup ~30 s, timeout -k 40), so the digest and tar below run
common="checkpoint=.gpu/can_start.pt task=robosuite_can device=cuda eval.val_episodes=50 eval.episodes=100 eval.num_envs=10 eval.video_episodes=0"
online="online.steps=16000 online.warmup_steps=2000 online.updates_per_step=0.25 online.eval_every=0 online.num_envs=8"
run() { name=$1; shift; timeout -k 40 -s TERM $T python3 -m l1flow_rl.cli finetune $common run_dir=/tmp/r/$name "$@" > /tmp/r_$name.log 2>&1; echo "$name exit $?"; }
mkdir -p /tmp/r
nvidia-smi --query-gpu=name,memory.used --format=csv
run qc_frozen_seed0 finetune=qc $online seed=0 finetune.qc.freeze_flow=true &
run qc_seed1 finetune=qc $online seed=1 &
wait
for f in /tmp/r_*.log; do tr '\r' '\n' < $f | grep -a -E "validation|test|Error|error" | tail -8; done
tar -C /tmp -cf $OUT/runs.tar --exclude=checkpoints r $(cd /tmp && ls r_*.log)
ls -la $OUT
