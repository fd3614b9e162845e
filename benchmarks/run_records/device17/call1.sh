#!/bin/bash
# Wave 3's seventeenth session, one lent GPU (15 device-minutes): issue 30's online QC from the start with
# room, the mixed-30 Can BC start (CPU test 0.40; filtered BC + EMA there: 0.51 mean of 3 seeds at 60k env
# steps). device15 ran QC at this budget from the under-trained 20-demo start (0.14 -> 0.26, one seed);
# this call asks whether QC lifts a trained start, with two seeds:
#   qc_seed0, qc_seed1: the QC preset (best of 32, the flow keeps its BC loss on the replay buffer), learner
#   on the GPU, 8 CPU collector workers each, 2,400 warm-up env steps with the start, then 0.25 updates
#   per env step to 14,400 env steps (~3,000 updates); validation (50 episodes, 10 envs) of the start and
#   at the end on the same seeds, then a 50-episode test of the better of the two.
# Beside them, tests/test_cuda.py (capped at 150 s; the ManiSkill cases skip: no mani_skill there).
# Carried files: build_bundle.sh beside this file. Run as
#   run(command="bash benchmarks/run_records/device17/call1.sh",
#       carry=[".gpu", ".gl"],
#       timeout_s=590)
exec > >(tee -a $OUT/log.txt) 2>&1
set -x
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
[ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] && export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
mkdir -p data/robosuite/PickPlaceCan && xz -dc .gpu/can_mixed30.hdf5.xz > data/robosuite/PickPlaceCan/PickPlaceCan.absolute.state.seed0.n30.mixed.hdf5 || exit 1
mkdir -p /tmp/site && tar xJf .gpu/core312.tar.xz -C /tmp/site || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1 MUJOCO_GL=egl PYOPENGL_PLATFORM=egl
python3 -m pip install -q --no-deps --no-index --no-build-isolation -e . || exit 1
export OMP_NUM_THREADS=1
T=${T:-480}  # timeout_s (590) - setup (~40 s) - timeout's kill grace (20 s) - digest and tar (~10 s)
common="checkpoint=.gpu/can_start.pt task=robosuite_can device=cuda eval.val_episodes=50 eval.episodes=50 eval.num_envs=10 eval.video_episodes=0"
online="online.steps=14400 online.warmup_steps=2000 online.updates_per_step=0.25 online.eval_every=0 online.num_envs=8"
run() { name=$1; shift; timeout -k 20 -s TERM $T python3 -m l1flow_rl.cli finetune $common run_dir=/tmp/r/$name "$@" > /tmp/r_$name.log 2>&1; echo "$name exit $?"; }
mkdir -p /tmp/r
nvidia-smi --query-gpu=name,memory.used --format=csv
# ARM and EXTRA (empty in the call that ran) let a later call run another arm through this script
run qc${ARM}_seed0 finetune=qc $online seed=0 $EXTRA & p0=$!
run qc${ARM}_seed1 finetune=qc $online seed=1 $EXTRA & p1=$!
if [ -z "$ARM" ]; then
  timeout -k 5 150 python3 -m pytest tests/test_cuda.py -q -p no:cacheprovider > /tmp/r_test_cuda.log 2>&1; echo "test_cuda exit $?"
fi
wait $p0 $p1  # a bare wait would also wait for the tee that logs this call (bash >= 5.1): device25
[ -f /tmp/r_test_cuda.log ] && tail -5 /tmp/r_test_cuda.log
for f in /tmp/r_qc*.log; do echo "== $f"; tr '\r' '\n' < $f | grep -a -E "validation|test|success|Error|error|updates/s" | tail -12; done
tar -C /tmp -cf $OUT/runs.tar --exclude=checkpoints --exclude='*.memmap' r $(cd /tmp && ls r_*.log)
ls -la $OUT
