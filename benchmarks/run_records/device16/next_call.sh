#!/bin/bash
# Prepared in wave 3's seventh session for the next GPU lease (that session had 284 device-seconds, too
# few to start a machine): issue 30's QC with the flow frozen and its proposals cached (ProposalCache),
# beside device15's QC with the flow training (0.14 -> 0.26 at 16.8k env steps, UTD 0.25; 12k steps here so that
# the final validation fits T=450 s). Carried files:
# ../device14/build_bundle.sh. Run as
#   run(command="bash benchmarks/run_records/device16/next_call.sh",
#       carry=[".gpu", ".gl", "data/robosuite/PickPlaceCan"], timeout_s=570)
# Arms (same start, seed, warm-up, 50 validation episodes as device15): frozen QC at device15's UTD 0.25
# (is training the flow what moved device15's QC?) and at QC's own UTD 1 (what the cache makes
# affordable: a warm update is the critics' pick over 256 x 32 cached chunks, no flow call).
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
[ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] && export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1 MUJOCO_GL=egl PYOPENGL_PLATFORM=egl
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
export OMP_NUM_THREADS=1
T=${T:-450}  # T <= timeout_s - 80 (setup ~30 s, timeout -k 40), so the digest and tar below run
common="checkpoint=.gpu/can_start.pt task=robosuite_can device=cuda seed=0 eval.val_episodes=50 eval.episodes=100 eval.num_envs=10 eval.video_episodes=0"
online="online.steps=12000 online.warmup_steps=2000 online.eval_every=0 online.num_envs=8 finetune.qc.freeze_flow=true"
run() { name=$1; shift; timeout -k 40 -s TERM $T python3 -m l1flow_rl.cli finetune $common run_dir=/tmp/r/$name "$@" > /tmp/r_$name.log 2>&1; echo "$name exit $?"; }
mkdir -p /tmp/r
nvidia-smi --query-gpu=name,memory.used --format=csv
run qc_frozen_utd0p25 finetune=qc $online online.updates_per_step=0.25 &
run qc_frozen_utd1 finetune=qc $online online.updates_per_step=1.0 &
wait
for f in /tmp/r_*.log; do tr '\r' '\n' < $f | grep -a -E "validation|test|Error|error" | tail -8; done
tar -C /tmp -cf $OUT/runs.tar --exclude=checkpoints r $(cd /tmp && ls r_*.log)
ls -la $OUT
