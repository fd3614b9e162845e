"""Flow-Q fine-tuning against continued behaviour cloning, at an equal number of gradient updates.

One BC checkpoint (``--demos`` demonstrations, ``--bc-steps`` L1 Flow steps) is the start of three
arms, all on the same demonstrations, scored on the same test seeds (``eval.json`` of each run):

* ``bc``: the checkpoint itself (success before fine-tuning);
* ``flowq_offline``: ``--offline-steps`` FlowQ updates on the demonstrations' rewards;
* ``flowq_online``: the same offline updates, then ``--online-steps`` environment steps collected by
  the fine-tuned policy with ``--updates-per-step`` updates per step (success against environment
  steps on the validation seeds every ``--online-eval-every`` steps);
* ``bc_continued``: BC trained for ``--bc-steps`` + the online arm's update count, from scratch on the
  same data with the same schedule settings: continued imitation at the same number of updates.

Saved: ``benchmarks/results/flow_q_<tag>.json`` (every arm's success_once with its 95 % interval,
wall time, updates, env steps; the online curve) and ``flow_q_<tag>.png``. Runs resume: finished
ones are read back. On 2 CPU cores the default budget (PickCube, 10 demos, 1500 BC steps, 500 offline
updates, 6000 env steps at 0.25 updates per step, 50 test episodes) is several hours;
``--quick`` checks the script on tiny budgets (PushCube, 3 demos).

    .venv/bin/python -m benchmarks.bench_flow_q --task maniskill_pickcube --demos 10

``--data FILE`` trains every arm on one dataset instead, e.g. noisy rollouts from
``benchmarks.make_noisy_demos`` (the run of ``benchmarks/results/flow_q_*noise0_1*.json``)::

    .venv/bin/python -m benchmarks.make_noisy_demos --episodes 100 --noise 0.1 \
        --checkpoint runs/bench_success/maniskill_pushcube/l1flow/seed0/checkpoints/best.pt \
        --out runs/bench_flow_q/data/noisy/PushCube-v1.noise0.1.n100.h5
    .venv/bin/python -m benchmarks.bench_flow_q --task maniskill_pushcube \
        --data runs/bench_flow_q/data/noisy/PushCube-v1.noise0.1.n100.h5 --bc-steps 1500 \
        --offline-steps 1000 --online-steps 2000 --updates-per-step 0.5 --online-eval-every 1000 \
        --alpha 10 --jobs 2 --data-dir runs/bench_flow_q/data eval.val_episodes=20

``--extra-test-episodes N`` also scores every arm's model on the N test seeds after the first
``--episodes`` (``rescore_extra<N>`` in each run folder) and reports the pooled rate beside the first:
a 100-episode rate has a 95 % interval of about +-0.09, wider than the gains measured here. A finished
invocation re-run with it only adds those evaluations.

Runs live under ``--root``/<task>_<data>_seed<seed>/, one folder per arm named by what sets it apart
(``bc_<steps>``, ``flowq_<mode>_alpha<a>[_gamma<g>]_off<n>[_on<m>x<u>]``), so invocations that change
only the flow-Q settings share the BC arms; hydra overrides given as ``extra`` are not part of the
names: change ``--root`` with them.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from benchmarks.common import format_table, machine_info, save_results
from benchmarks.sweep import Run, _cli, _threads, rescore, train  # _cli: the shared subprocess runner
from l1flow_rl.config.evaluation import EvalConfig
from l1flow_rl.evaluation.metrics import wilson_interval

#: the distill arm's actor samples in one network evaluation; on noisy data that alone changes success
#: (a one-step chunk is the network's estimate from pure noise, which averages the demonstrated noise
#: away), so the BC arms are also scored under it: the gain credited to Q is over the better of the two
ONE_STEP = ["policy.sampler=euler", "policy.sampler_kwargs.steps=1"]

#: finetune.reward_<part> options the flow-Q arms may override -> their tag in run names
REWARD_MAP = {"scale": "rs", "offset": "ro"}

#: every imitation arm: the BC start and continued BC, each under its own and the one-step sampler
BC_ARMS = ("bc", "bc_one_step", "bc_continued", "bc_continued_one_step")

#: the arms that start from the BC checkpoint (independent of each other: --jobs runs them side by side)
ARMS = ("flowq_offline", "flowq_online", "bc_continued")


def finetune(run: Run, data_dir: Path, checkpoint: Path, threads: int | None = None) -> dict[str, Any]:
    """Fine-tune (or resume, or just read) ``run`` from ``checkpoint``; returns its eval.json.
    ``threads``: torch's intra-op threads (set when arms share the machine)."""
    if not run.done:
        resume = ["resume=true"] if (run.run_dir / "checkpoints" / "latest.pt").is_file() else []
        args = [
            "finetune",
            f"checkpoint={checkpoint}",
            *run.overrides,
            f"run_dir={run.run_dir}",
            f"data_dir={data_dir}",
            *resume,
        ]
        code = _cli(args, run.log, {"OMP_NUM_THREADS": str(threads)} if threads else None)
        if code != 0:
            raise RuntimeError(f"{run.name}: l1flow-rl finetune exited with {code}; see {run.log}")
    return json.loads((run.run_dir / "eval.json").read_text())


def _test_seed(extra: list[str]) -> int:
    """The first test seed the runs use: ``eval.seed`` from the hydra overrides, else the config's."""
    given = [o.split("=", 1)[1] for o in extra if o.startswith("eval.seed=")]
    return int(given[-1]) if given else EvalConfig.seed


def _eval_overrides(shared: list[str]) -> list[str]:
    """The overrides a re-scoring must share with the runs (seed, test episodes, task, eval fields)."""
    return [o for o in shared if o.startswith(("seed=", "eval.", "task."))]


def _record(result: dict[str, Any], run_dir: Path) -> dict[str, Any]:
    summary = (
        json.loads((run_dir / "summary.json").read_text()) if (run_dir / "summary.json").is_file() else {}
    )
    return {
        "success_once": result["success_once"],
        "ci95": result.get("ci95", {}).get("success_once"),
        "episodes": result.get("episodes"),
        "split": result.get("split"),
        "updates": result.get("updates", result.get("step")),
        "env_steps": result.get("env_steps", 0),
        "wall_seconds": summary.get("wall_seconds"),
    }


def _pooled(first: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """One arm's success_once over its test episodes and the extra ones together, with its Wilson
    interval (both are rates of whole episodes on disjoint seeds, so their counts add)."""
    n = int(first["episodes"]) + int(extra["episodes"])
    wins = round(first["success_once"] * first["episodes"]) + round(extra["success_once"] * extra["episodes"])
    return {"success_once": wins / n, "episodes": n, "ci95": list(wilson_interval(wins, n))}


def _gains(score: dict[str, float]) -> dict[str, float]:
    """FlowQ's gains over the imitation arms, from one score per arm."""
    best_continued = max(score["bc_continued"], score["bc_continued_one_step"])
    return {
        "gain_over_continued_bc": score["flowq_online"] - score["bc_continued"],
        "gain_over_best_continued_bc": score["flowq_online"] - best_continued,
        # offline FlowQ (no more updates than continued BC) against continued BC under either sampler
        "gain_offline_over_best_continued_bc": score["flowq_offline"] - best_continued,
        # offline FlowQ against the best any BC arm scored, under either sampler (the start included)
        "gain_offline_over_best_bc": score["flowq_offline"] - max(score[a] for a in BC_ARMS),
    }


def _data_summary(path: Path | None) -> dict[str, Any] | None:
    """What ``benchmarks.make_noisy_demos`` recorded about a dataset (None for expert demos)."""
    if path is None:
        return None
    summary = path.with_suffix(".summary.json")
    return {"path": str(path), **(json.loads(summary.read_text()) if summary.is_file() else {})}


def _online_curve(run_dir: Path) -> list[dict[str, Any]]:
    path = run_dir / "history.json"
    if not path.is_file():
        return []
    data = json.loads(path.read_text())
    evals = [
        {
            "env_steps": e["env_steps"],
            "success_once": e["success_once"],
            "split": e.get("split"),
            "phase": e["phase"],
        }
        for e in data.get("evals", [])
    ]
    collected = [
        {"env_steps": r["env_steps"], "episode_success": r.get("episode_success")}
        for r in data.get("rounds", [])
    ]
    return [{"evaluations": evals, "collected": collected}]


def _plot(figures: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_bar, ax_curve) = plt.subplots(1, 2, figsize=(10, 3.8))
    arms = list(figures["arms"])
    values = [figures["arms"][a]["success_once"] for a in arms]
    errs = []
    for a in arms:
        ci = figures["arms"][a].get("ci95")
        v = figures["arms"][a]["success_once"]
        # a Wilson bound can sit a rounding error past the value (0 successes: low ~ 1e-18)
        errs.append((max(v - ci[0], 0.0), max(ci[1] - v, 0.0)) if ci else (0.0, 0.0))
    ax_bar.bar(
        arms, values, yerr=list(zip(*errs)), capsize=4, color=["grey", "tab:blue", "tab:green", "tab:orange"]
    )
    ax_bar.set_ylim(0, 1.05)
    ax_bar.set_ylabel("success_once (test seeds)")
    ax_bar.tick_params(axis="x", labelrotation=15)
    curve = figures.get("online_curve") or [{}]
    evals = [e for e in curve[0].get("evaluations", []) if e["phase"] != "final"]
    if evals:
        ax_curve.plot(
            [e["env_steps"] for e in evals], [e["success_once"] for e in evals], "o-", label="validation"
        )
    rounds = [r for r in curve[0].get("collected", []) if r["episode_success"] is not None]
    if rounds:
        ax_curve.plot(
            [r["env_steps"] for r in rounds],
            [r["episode_success"] for r in rounds],
            ".--",
            alpha=0.6,
            label="collected",
        )
    ax_curve.axhline(figures["arms"]["bc"]["success_once"], color="grey", ls=":", label="BC (test)")
    ax_curve.set_xlabel("environment steps (online)")
    ax_curve.set_ylim(-0.05, 1.05)
    ax_curve.grid(alpha=0.3)
    ax_curve.legend(fontsize=8)
    fig.suptitle(figures["setting"], fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="maniskill_pickcube")
    parser.add_argument("--demos", type=int, default=10)
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help="a dataset file for every arm instead of --demos expert demos (benchmarks.make_noisy_demos)",
    )
    parser.add_argument("--bc-steps", type=int, default=1500)
    parser.add_argument("--offline-steps", type=int, default=500)
    parser.add_argument("--online-steps", type=int, default=6000)
    parser.add_argument("--updates-per-step", type=float, default=0.25)
    parser.add_argument("--online-eval-every", type=int, default=2000)
    parser.add_argument("--mode", default="distill", choices=("distill", "direct", "best_of_n"))
    parser.add_argument("--num-samples", type=int, default=32, help="best_of_n: chunks drawn per decision")
    parser.add_argument(
        "--backup",
        default="max",
        choices=("max", "mean", "one_step"),
        help="the TD target's value of the next state: max or mean over drawn chunks, or the one-step chunk",
    )
    parser.add_argument(
        "--backup-samples", type=int, default=0, help="chunks drawn per TD target (0: the mode's default)"
    )
    parser.add_argument(
        "--reward",
        default="recorded",
        choices=("recorded", "sparse"),
        help="the critic's per-step reward: the data's recorded one, or 1 at terminal (success) steps",
    )
    for part in REWARD_MAP:
        parser.add_argument(
            f"--reward-{part}",
            type=float,
            default=None,
            help=f"finetune.reward_{part} for the flow-Q arms (the config's default when not given)",
        )
    parser.add_argument(
        "--critic-target",
        default="td",
        choices=("td", "mc"),
        help="best_of_n: after the Monte-Carlo pretraining, TD targets or Monte-Carlo returns",
    )
    parser.add_argument(
        "--critic-input",
        default="action",
        choices=("action", "residual"),
        help="best_of_n: the critics read the chunk, or the chunk minus the BC policy's zero-noise chunk",
    )
    parser.add_argument("--alpha", type=float, default=100.0)
    parser.add_argument("--gamma", type=float, default=0.99, help="the critic's per-step discount")
    parser.add_argument(
        "--critic-warmup",
        type=int,
        default=0,
        help="critic-only updates before the actor moves, in addition to --offline-steps",
    )
    parser.add_argument(
        "--critic-pretrain",
        type=int,
        default=0,
        help="critic updates on the demonstrations' Monte-Carlo returns before those (cheap: no actor call)",
    )
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--episodes", type=int, default=50, help="test (and validation) episodes")
    parser.add_argument(
        "--extra-test-episodes",
        type=int,
        default=0,
        help="also score every arm's final policy on this many further test seeds (after --episodes "
        "ones) and report the pooled success beside the first",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--jobs", type=int, default=1, help="after BC, the other arms side by side (cores/jobs threads each)"
    )
    parser.add_argument("--root", type=Path, default=Path("runs/bench_flow_q"))
    parser.add_argument("--data-dir", type=Path, default=Path("data"))
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--quick", action="store_true", help="tiny budgets on PushCube (checks the script)")
    parser.add_argument(
        "extra", nargs="*", help="hydra overrides for every run, e.g. task.max_episode_steps=80"
    )
    args = parser.parse_args(argv)
    if args.critic_input == "residual" and args.mode != "best_of_n":
        parser.error(f"--critic-input residual needs --mode best_of_n (got --mode {args.mode})")
    if args.critic_target == "mc" and args.mode != "best_of_n":
        parser.error(f"--critic-target mc needs --mode best_of_n (got --mode {args.mode})")
    if args.extra_test_episodes < 0:
        parser.error(f"--extra-test-episodes must be >= 0, got {args.extra_test_episodes}")
    test_seed = _test_seed(args.extra)

    shared = [f"task={args.task}", f"seed={args.seed}", f"eval.episodes={args.episodes}", *args.extra]
    ft_over = [
        f"finetune.mode={args.mode}",
        f"finetune.num_samples={args.num_samples}",
        f"finetune.backup={args.backup}",
        f"finetune.backup_samples={args.backup_samples}",
        f"finetune.alpha={args.alpha}",
        f"finetune.gamma={args.gamma}",
        f"finetune.batch_size={args.batch_size}",
        f"offline.steps={args.offline_steps + args.critic_warmup + args.critic_pretrain}",
        f"offline.critic_warmup={args.critic_warmup}",
        f"offline.critic_pretrain={args.critic_pretrain}",
    ]
    if args.quick:
        args.task, args.demos, args.bc_steps = "maniskill_pushcube", 3, 20
        args.offline_steps, args.online_steps, args.online_eval_every = 4, 40, 20
        args.updates_per_step, args.episodes = 0.1, 2
        args.extra_test_episodes = min(args.extra_test_episodes, 2)
        shared = [
            "task=maniskill_pushcube",
            f"seed={args.seed}",
            "eval.episodes=2",
            "eval.num_envs=1",
            "task.max_episode_steps=20",
            "policy.down_dims=[16,32]",
            "policy.timestep_embed_dim=16",
            *args.extra,
        ]
        ft_over = [
            f"finetune.mode={args.mode}",
            "finetune.batch_size=16",
            "finetune.critic_hidden_dims=[32,32]",
            "offline.steps=7",
            "offline.critic_pretrain=1",  # the quick run goes through both critic-only paths too
            "offline.critic_warmup=2",
        ]
        args.critic_warmup, args.critic_pretrain = 2, 1
    ft_over += [f"finetune.reward={args.reward}", f"finetune.critic_input={args.critic_input}"]
    ft_over += [f"finetune.critic_target={args.critic_target}"]
    reward_map = {p: v for p in REWARD_MAP if (v := getattr(args, f"reward_{p}")) is not None}
    ft_over += [f"finetune.reward_{p}={v}" for p, v in reward_map.items()]
    bc_over = [f"data.path={args.data}"] if args.data else [f"demos.num={args.demos}"]
    source = args.data.stem.replace(".", "_") if args.data else f"{args.demos}demos"
    gamma = "" if args.gamma == 0.99 else f"_gamma{args.gamma:g}".replace(".", "p")
    # what sets the method's strength: the regulariser's weight, or best_of_n's number of draws
    knob = f"n{args.num_samples}" if args.mode == "best_of_n" else f"alpha{args.alpha:g}"
    if args.backup != "max" or args.backup_samples:  # the default (QC's max backup) keeps its old names
        knob += f"_{args.backup}" + (f"{args.backup_samples}" if args.backup_samples else "")
    knob += ("_sparse" if args.reward == "sparse" else "") + (
        "_residual" if args.critic_input == "residual" else ""
    )
    knob += "_mctarget" if args.critic_target == "mc" else ""
    knob += "".join(f"_{REWARD_MAP[p]}{v:g}".replace(".", "p") for p, v in reward_map.items())
    warm = (f"_mc{args.critic_pretrain}" if args.critic_pretrain else "") + (
        f"_warm{args.critic_warmup}" if args.critic_warmup else ""
    )
    tag = "quick" if args.quick else f"{args.task}_{source}_{args.mode}_{knob}{gamma}{warm}_seed{args.seed}"
    # one folder per data set and seed: arms with the same settings (BC, continued BC) are shared by
    # invocations that differ in the flow-Q settings; each run's folder names what sets it apart
    root = args.root / (f"quick_{source}" if args.quick else f"{args.task}_{source}_seed{args.seed}")
    fq_name = f"flowq_{args.mode}_{knob}{gamma}{warm}_off{args.offline_steps}".replace(".", "p")
    # every flow-Q update counts, critic-only ones included (the Monte-Carlo ones cost far less than
    # a BC step, so this favours continued BC): continued BC gets as many steps
    critic_only = args.critic_pretrain + args.critic_warmup
    online_updates = critic_only + args.offline_steps + round(args.updates_per_step * args.online_steps)
    online_over = [
        f"online.steps={args.online_steps}",
        f"online.updates_per_step={args.updates_per_step}",
        f"online.eval_every={args.online_eval_every}",
        # rounds of one full-length episode per env (online.frames_per_round=0); quick: 2 rounds of 20
        f"online.num_envs={1 if args.quick else 2}",
    ]

    bc_run = Run("bc", [*bc_over, *shared, f"train.steps={args.bc_steps}"], root / f"bc_{args.bc_steps}")
    continued = args.bc_steps + online_updates
    # no dot in a folder name: Run.log replaces the suffix after the last dot
    online_name = f"{fq_name}_on{args.online_steps}x{args.updates_per_step:g}".replace(".", "p")
    runs = {
        "bc": bc_run,
        "flowq_offline": Run("flowq_offline", [*ft_over, *shared, "online.steps=0"], root / fq_name),
        "flowq_online": Run("flowq_online", [*ft_over, *shared, *online_over], root / online_name),
        "bc_continued": Run(
            "bc_continued", [*bc_over, *shared, f"train.steps={continued}"], root / f"bc_{continued}"
        ),
    }
    results: dict[str, dict[str, Any]] = {}
    results["bc"] = _record(train(bc_run, args.data_dir), bc_run.run_dir)
    checkpoint = bc_run.run_dir / "checkpoints" / "latest.pt"
    threads = _threads(args.jobs) if args.jobs > 1 else None

    def arm(name: str) -> dict[str, Any]:
        run = runs[name]
        if name == "bc_continued":
            return _record(train(run, args.data_dir, threads), run.run_dir)
        return _record(finetune(run, args.data_dir, checkpoint, threads), run.run_dir)

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        done = dict(zip(ARMS, pool.map(arm, ARMS)))
    results.update(done)
    for name in ("bc", "bc_continued"):
        scored = rescore(runs[name], "one_step", [*ONE_STEP, *_eval_overrides(shared)])
        results[f"{name}_one_step"] = _record(scored, runs[name].run_dir / "rescore_one_step")
    if args.extra_test_episodes:
        n_extra = args.extra_test_episodes
        # the seeds right after the arms' own test seeds: disjoint from them and the same for every arm
        seeds = [f"eval.seed={test_seed + args.episodes}", f"eval.episodes={n_extra}"]
        kept = [o for o in _eval_overrides(shared) if not o.startswith(("eval.seed=", "eval.episodes="))]
        for name in list(results):
            base = name.removesuffix("_one_step")
            sampler = ONE_STEP if name != base else []
            # the arm's own model: BC runs report best.pt (chosen on validation seeds), FlowQ runs
            # their final fine-tuned policy
            ckpt = "latest.pt" if base.startswith("flowq") else None
            label = f"extra{n_extra}" + ("_one_step" if sampler else "")
            scored = rescore(runs[base], label, [*sampler, *kept, *seeds], ckpt)
            results[name]["extra"] = _record(scored, runs[base].run_dir / f"rescore_{label}")
            results[name]["pooled"] = _pooled(results[name], results[name]["extra"])

    data_summary = _data_summary(args.data)
    data = f"{args.demos} demos" if args.data is None else args.data.name
    if data_summary and "noise" in data_summary:
        data += f" (rollouts with action noise {data_summary['noise']}, see 'data')"
    setting = (
        f"{args.task}, {data}, BC {args.bc_steps} steps; "
        f"FlowQ ({args.mode}, "
        + (f"N {args.num_samples}" if args.mode == "best_of_n" else f"alpha {args.alpha}")
        + (f", {args.backup} backup" if args.backup != "max" else "")
        + (f" over {args.backup_samples} draws" if args.backup_samples else "")
        + (", sparse reward" if args.reward == "sparse" else "")
        + (", residual critic input" if args.critic_input == "residual" else "")
        + (", Monte-Carlo critic targets throughout" if args.critic_target == "mc" else "")
        + (f", reward x {args.reward_scale:g}" if args.reward_scale is not None else "")
        + (f" {args.reward_offset:+g} per step" if args.reward_offset is not None else "")
        + f", gamma {args.gamma}) "
        + (f"{args.critic_pretrain} Monte-Carlo critic updates + " if args.critic_pretrain else "")
        + (f"{args.critic_warmup} critic-only updates + " if args.critic_warmup else "")
        + f"{args.offline_steps} offline updates + {args.online_steps} env steps x {args.updates_per_step} "
        f"updates/step; continued BC {args.bc_steps + online_updates} steps; {args.episodes} test episodes"
        + (f" (+ {args.extra_test_episodes} more, pooled)" if args.extra_test_episodes else "")
    )
    if args.extra:  # hydra overrides are not in the run names: the setting line says which ones ran
        setting += f"; overrides: {' '.join(args.extra)}"
    figures = {
        "quick": args.quick,
        "setting": setting,
        "overrides": list(args.extra),
        "budget": {
            "bc_steps": args.bc_steps,
            "offline_updates": args.offline_steps,
            "online_env_steps": args.online_steps,
            "critic_pretrain_updates": args.critic_pretrain,
            "critic_warmup_updates": args.critic_warmup,
            "online_updates": online_updates - args.offline_steps - critic_only,
            "bc_continued_steps": args.bc_steps + online_updates,
            "flowq_batch_size": args.batch_size,
        },
        "arms": results,
        **_gains({name: r["success_once"] for name, r in results.items()}),
        "extra_test_episodes": args.extra_test_episodes,
        # the same gains on every arm's test and extra episodes together (None without extra ones)
        "pooled_gains": _gains({name: r["pooled"]["success_once"] for name, r in results.items()})
        if args.extra_test_episodes
        else None,
        "online_curve": _online_curve(runs["flowq_online"].run_dir),
        "runs": {name: str(run.run_dir) for name, run in runs.items()},
        "data": data_summary,
        "machine": machine_info(),
    }
    out = args.out or Path("benchmarks/results") / f"flow_q_{tag}.json"
    save_results(out, figures)
    _plot(figures, out.with_suffix(".png"))
    rows = [
        {"arm": name, **r, "pooled_success": r.get("pooled", {}).get("success_once")}
        for name, r in results.items()
    ]
    columns = ["arm", "success_once", "episodes", "updates", "env_steps", "wall_seconds"]
    print(setting)
    print(format_table(rows, columns + (["pooled_success"] if args.extra_test_episodes else [])))
    if figures["pooled_gains"]:
        pooled = figures["pooled_gains"]
        print(
            f"pooled over {args.episodes + args.extra_test_episodes} episodes: offline FlowQ over the better "
            f"continued BC {pooled['gain_offline_over_best_continued_bc']:+.3f}, online FlowQ "
            f"{pooled['gain_over_best_continued_bc']:+.3f}"
        )
    print(
        f"gain of online FlowQ over continued BC: {figures['gain_over_continued_bc']:+.3f} (2-NFE), "
        f"{figures['gain_over_best_continued_bc']:+.3f} (the better of 2-NFE and one-step); saved {out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
