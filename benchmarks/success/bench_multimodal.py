"""Multi-modality, measured: how each method splits its samples over 2, 4 and 8 demonstrated modes.

Every family of the toy (``l1flow_rl.commands.toy``: opposite sines (2), nested amplitudes (4), phase shifts
(8)) is trained with L1 Flow (and evaluated at 2 NFE, at other t_first, and under x-prediction
Euler-10 without retraining), L1 Flow with uniform t, v-prediction flow matching (10 and 2 Euler
steps) and L1 regression, on the same small UNet and the same data stream. Per evaluation: the share
of samples on each mode, modes hit, off-mode mass and balance, saved as JSON plus one figure per
family.

    python -m benchmarks.success.bench_multimodal [--steps 1500] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from benchmarks.lib.common import format_table, machine_info, parse_args, save_results
from l1flow_rl.commands.toy import MODE_FAMILIES, TOY_METHODS, toy_modes, train_and_evaluate
from l1flow_rl.config import ToyConfig

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/multimodal.json")
    parser.add_argument("--figures", default="benchmarks/results", help="directory for the PNGs")
    parser.add_argument("--families", nargs="+", default=list(MODE_FAMILIES))
    parser.add_argument("--methods", nargs="+", default=list(TOY_METHODS))
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--samples", type=int, default=1024)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not the claim")
    args = parse_args(parser, argv)
    if args.quick:
        args.steps, args.samples = 5, 32
    torch.set_num_threads(1)  # the toy's tiny convolutions only lose to spin-waiting threads
    figures: dict = {"machine": machine_info(), "quick": args.quick, "steps": args.steps, "families": {}}
    start = time.perf_counter()
    for family in args.families:
        modes = toy_modes(family)
        toy = OmegaConf.structured(
            ToyConfig(
                steps=args.steps, samples=args.samples, seed=args.seed, methods=args.methods, modes=family
            )
        )
        report, samples = train_and_evaluate(toy, modes, verbose=False)
        figures["families"][family] = {"num_modes": modes.shape[0], "methods": report["methods"]}
        rows = [
            {
                "evaluation": name,
                "nfe": r["nfe"],
                "modes hit": f"{r['modes_hit']}/{r['num_modes']}",
                "off-mode": r["share_neither"],
                "balance": r["balance"],
            }
            for name, r in report["methods"].items()
        ]
        print(f"\n{family} ({modes.shape[0]} modes), {args.steps} steps per method:")
        print(format_table(rows, ["evaluation", "nfe", "modes hit", "off-mode", "balance"]))
        if not args.quick:
            from l1flow_rl.commands.toy_plot import plot_toy

            plot_toy(modes, samples, report["methods"], Path(args.figures) / f"multimodal_{family}.png")
    figures["seconds"] = round(time.perf_counter() - start, 1)
    save_results(args.out, figures)
    print(f"\nsaved {args.out} ({figures['seconds']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
