#!/bin/bash
# Wave 3's twenty-fourth session, one lent GPU (15 device-minutes): device18's prepared call, from the
# re-made mixed-30 Can start "mixed30c" (runs/ft_bc_can_mixed30 re-made in the twenty-third session:
# CPU test 0.37, 50-episode validation 0.38). QC preset with the flow's EMA (finetune.ema_power=0.75: the
# averaged flow proposes, the online critics pick), two seeds, device17's budget: 2,000 warm-up env steps,
# then 0.25 updates per env step to 14,400 env steps. The question: does the EMA remove the first-round
# collapse of collected success (device17, no EMA: 0.625 -> 0.125 in both seeds)?
# Carried files: ../device17/build_bundle.sh (which now leaves out zarr/numcodecs, imported lazily by the
# DP zarr format only, so that the tree (22.4 MB now) plus the bundle stay under 64 MiB).
#   run(command="bash benchmarks/run_records/device24/call.sh", carry=[".gpu", ".gl"], timeout_s=590)
ARM=_ema EXTRA="finetune.ema_power=0.75" T=440 exec bash "$(dirname "$0")/../device17/call1.sh"
