#!/bin/bash
# Prepared in wave 3's seventeenth session for the next GPU lease. device17 ran the QC preset (no EMA) from
# the mixed-30 Can start: validation 0.46 -> 0.46 / 0.50 at 14.4k env steps, and the collected success fell
# 0.625 -> 0.125 in the first learning round of both seeds (the constant-LR shock that the EMA removed for
# filtered BC on the CPU). This call runs the same two seeds with the flow's EMA (finetune.ema_power=0.75:
# the averaged flow proposes, the online critics pick, and the average goes on from the BC run's counter,
# as filtered BC's preset does); everything else is device17's call, with T shortened (its setup took ~70 s).
# Carried files: ../device17/build_bundle.sh (run it here first, ~2 minutes). Run as
#   run(command="bash benchmarks/run_records/device18/next_call.sh", carry=[".gpu", ".gl"], timeout_s=590)
ARM=_ema EXTRA="finetune.ema_power=0.75" T=450 exec bash "$(dirname "$0")/../device17/call1.sh"
