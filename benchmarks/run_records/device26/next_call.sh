#!/bin/bash
# Prepared in wave 3's twenty-fifth session for the next GPU lease (see ../device25/README.md). device25:
# 2,000 offline critic updates before acting removed QC's first-round collapse (8 of 16 first episodes
# succeed against 0 of 16 without), but its end policy was read on 20 episodes only (test 0.15 / 0.15,
# start validation 0.25 on the same 20). This call asks what the end policy is: the qc preset (now with
# offline.steps 2000) + the flow's EMA from the mixed30c Can start, two seeds at once, 9,600 env steps
# (2,400 warm-up, three learning rounds), tested on 100 episodes. Expected wall: setup ~85 s, start
# validation (20) ~35 s, offline ~165 s, online ~180 s, end validation ~35 s, test (100) ~150 s: ~650 s,
# above one call; T=440 stops the runs after their online phase with a checkpoint (the harness's design)
# and a second call on the warm machine finishes them:
#   bash benchmarks/run_records/device17/build_bundle.sh   # here, first (~1 min)
#   run(command="bash benchmarks/run_records/device26/next_call.sh", carry=[".gpu", ".gl"], timeout_s=590)
#   run(command="RESUME=1 bash benchmarks/run_records/device26/next_call.sh", carry=[".gpu", ".gl"], timeout_s=590)
EXTRA="finetune.ema_power=0.75 online.steps=9600 eval.val_episodes=20 eval.episodes=100"
[ -n "$RESUME" ] && EXTRA="$EXTRA resume=true"
ARM=_off2k_t100 EXTRA="$EXTRA" T=440 exec bash "$(dirname "$0")/../device17/call1.sh"
