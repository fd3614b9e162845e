#!/bin/bash
# Prepared in wave 3's twenty-fourth session for the next GPU lease (see ../device24/README.md). device24:
# QC + the flow's EMA from the mixed30c Can start collected 0 of 8 successes in the first learning round
# of both seeds (warm-up 3/8, 2/8): the fresh online critics' pick over 32 proposals, not the flow. This
# call trains the critics (and the flow's BC loss) offline on the 30 demonstrations first, as QC does
# before its online phase, then runs device24's online budget shortened to fit one call: 2,000 offline
# updates (~170 s at ~12/s), a 2,400-step warm-up round, two learning rounds (7,200 env steps in all).
# Compare the first learning round's first-episode success (online/first_episode_success.csv, 8 per
# seed) with device24's 0/8, 0/8. Build the bundle here first: bash benchmarks/run_records/device17/build_bundle.sh
#   run(command="bash benchmarks/run_records/device25/next_call.sh", carry=[".gpu", ".gl"], timeout_s=590)
ARM=_ema_off2k EXTRA="finetune.ema_power=0.75 offline.steps=2000 online.steps=7200 eval.val_episodes=20 eval.episodes=20" \
    T=430 exec bash "$(dirname "$0")/../device17/call1.sh"
