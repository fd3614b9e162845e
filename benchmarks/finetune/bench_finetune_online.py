"""Online fine-tuning from one BC checkpoint: each algorithm's preset (``configs/finetune/``), one run each,
then success against env steps (mean and spread over seeds), the control arms' test figures and the
cost figures of every run in one JSON and one figure per task.

    python -m benchmarks.finetune.bench_finetune_online --checkpoint runs/bc/checkpoints/best.pt \\
        --task maniskill_pickcube --algorithms dsrl --seeds 0 1 2 --steps 100000 \\
        --control bc_start=runs/bc --continued-bc-updates 8000

The runs are ``l1flow-rl finetune finetune=<algorithm> ...`` with the preset's defaults, except the
per-algorithm budget overrides in :data:`CPU_BUDGET` (each says why: what the 2-core cost figures of
``bench_finetune_cost.py`` allow); ``--override`` adds more to every run, or replaces a budget
override of the same key. Finished runs (their
``eval.json``) are read back, interrupted ones resume from their last checkpoint, and finished ones
shorter than asked (``--steps``, ``--continued-bc-updates``) are extended to it (``resume=true``: the
run goes on as the longer run would have; its earlier report stays as ``eval_step<N>.json``);
``--collect-only`` only reads. The file's ``start`` block fingerprints the checkpoint (its weights and the
episodes it trained on): seeds and controls compare only against the same start.

``--continued-bc-updates N`` adds the control that separates "online data" from "more updates": per
seed, N updates of the flow's own L1 Flow loss on the demonstrations alone, from the same checkpoint
with the same optimiser and batch (filtered BC's offline phase, no env step), validated 4 times; its
test figure (best-validated, the start competing) is a control arm with mean and spread over seeds.
Beside it, ``continued_bc_last``: the same runs' last weights on the test seeds. A 50-episode
validation swings by up to 0.14 with the sampler's noise alone, so the start can win the selection
on luck (Can: it did in all 3 seeds, so ``continued_bc`` reported the start's 0.09 while the last
weights test 0.16); the two rows together show both readings of "more updates".
Each online algorithm gets the same ``<algorithm>_last`` row: its runs' last weights on the test seeds.

``--offline-only-updates N`` adds the arm that separates "online data" from "TD": per algorithm and
seed, the algorithm's own preset and budget with N updates on the demonstrations alone (its critics
trained by TD, its actor by its own loss; ``online.steps=0``), validated 4 times and tested as the
continued-BC control is (``<algorithm>_offline``). Give N as the online run's updates (its offline
updates plus its online ones; the online runs' ``summary`` records both) to compare at equal updates.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import torch

from benchmarks.lib.common import machine_info, parse_args, save_results
from benchmarks.lib.stats import mean_and_spread, runs_aggregate
from benchmarks.report.finetune import render_finetune_online

#: budget departures from the presets on 2 shared CPU cores, with the cost figure that forces each
CPU_BUDGET: dict[str, list[str]] = {
    # an update with 32 proposals at batch 256 takes 14-34 s here (N=8: 3 s): N=8 and 1 update per 20 steps
    "qc": ["finetune.qc.num_samples=8", "online.updates_per_step=0.05"],
    # an update (BC + the 2-NFE teacher + mu) takes 0.6 s at batch 128, 1.2 s at 256 (Intel Xeon core):
    # 3,000 offline updates, then 1 per 20 env steps, fit 100k env steps in the 2-hour cap (PickCube
    # mixed50c: 102 min; finetune_online_maniskill_pickcube_mixed50c_fql_100k.json)
    "fql": ["offline.steps=3000", "online.updates_per_step=0.05", "finetune.batch_size=128"],
    # an update takes 0.09 s (no flow call): the preset's 0.25 updates per env step (2 per chunk decision)
    "dsrl": [],
    # an update decodes the actor's noise twice (the bootstrap's w' and the distillation's w): 0.7-1.1 s
    # at batch 256 with one decode, 0.16-0.29 s at 128: batch 128 and the 8,000 updates of the
    # filtered-BC and continued-BC arms (AMD EPYC; on an Intel Xeon core ~0.8 s: PickCube mixed50c ran
    # at 0.042 to fit the cap)
    "dsrl_na": ["finetune.batch_size=128", "online.updates_per_step=0.084"],
    "filtered_bc": [],  # an L1 Flow step at batch 64 (~0.1 s), 0.084 per env step
    "filtered_bc_delta": [],  # the same on delta-control tasks
    "flowq": [],  # its preset already makes 0.5 updates per env step, the floor of the anchors'
}


def budget(algorithm: str, override: list[str]) -> list[str]:
    """The algorithm's CPU budget overrides, then ``--override``; an ``--override`` of a key the budget
    sets replaces it (hydra refuses a key given twice)."""
    keys = {item.partition("=")[0] for item in override}
    return [o for o in CPU_BUDGET[algorithm] if o.partition("=")[0] not in keys] + list(override)


def finetune_cmd(
    preset: str, seed: int, args, run_dir: Path, length: list[str], settings: list[str]
) -> list[str]:
    """One ``l1flow-rl finetune`` run from the bench's checkpoint: its preset, its length (env steps or
    offline updates), the bench's validation and test sizes, then ``settings`` (budget, overrides)."""
    return [
        sys.executable,
        "-m",
        "l1flow_rl.commands.cli",
        "finetune",
        f"finetune={preset}",
        f"checkpoint={args.checkpoint}",
        f"task={args.task}",
        f"run_dir={run_dir}",
        *length,
        f"eval.episodes={args.test_episodes}",
        f"eval.val_episodes={args.val_episodes}",
        f"seed={seed}",
        *settings,
    ]


def offline_length(updates: int) -> list[str]:
    """An offline-only run: ``updates`` on the demonstrations, no env step, validated 4 times."""
    return ["online.steps=0", f"offline.steps={updates}", f"offline.eval_every={max(updates // 4, 1)}"]


def run_one(algorithm: str, seed: int, args, run_dir: Path) -> list[str]:
    length = [f"online.steps={args.steps}", f"online.eval_every={args.eval_every}"]
    return finetune_cmd(algorithm, seed, args, run_dir, length, budget(algorithm, args.override))


def continued_bc_cmd(seed: int, args, run_dir: Path) -> list[str]:
    """The continued-BC control: filtered BC's offline phase only (demonstrations, no env step)."""
    length = offline_length(args.continued_bc_updates)
    return finetune_cmd("filtered_bc", seed, args, run_dir, length, list(args.override))


def offline_only_cmd(algorithm: str, seed: int, args, run_dir: Path) -> list[str]:
    """The algorithm's TD-only arm: its preset and CPU budget, ``--offline-only-updates`` updates on the
    demonstrations, no env step (its offline phase alone). Its length replaces an ``--override`` of the
    same keys: the online runs' ``offline.steps`` (their offline phase) is part of its N."""
    length = offline_length(args.offline_only_updates)
    return finetune_cmd(algorithm, seed, args, run_dir, length, offline_only_settings(algorithm, args))


def offline_only_settings(algorithm: str, args) -> list[str]:
    """The TD-only arm's budget and overrides, less the keys its own length sets, with its actor
    learning: a preset (flow-Q's) or ``--override`` whose offline phase trains the critics alone
    would leave the arm's acting flow exactly at the start."""
    keys = {item.partition("=")[0] for item in offline_length(1)} | {"offline.critic_only"}
    kept = [o for o in budget(algorithm, args.override) if o.partition("=")[0] not in keys]
    return [*kept, "offline.critic_only=false"]


def offline_arm(name: str) -> bool:
    """Whether an arm is measured in updates on the demonstrations (no env step)."""
    return name == "continued_bc" or name.endswith("_offline")


def last_weights_eval_cmd(args, control_dir: Path, out_dir: Path) -> list[str]:
    """A run's last weights (``latest.pt``, not the validated choice) on the test seeds."""
    return [
        sys.executable,
        "-m",
        "l1flow_rl.commands.cli",
        "eval",
        f"checkpoint={control_dir / 'checkpoints' / 'latest.pt'}",
        f"task={args.task}",
        f"run_dir={out_dir}",
        f"eval.episodes={args.test_episodes}",
    ]


def last_weights_control(finished: dict[int, Path], args) -> dict | None:
    """Each finished run's last weights on the test seeds (``<run>_last``, tested unless
    ``--collect-only``): the validated choice can miss a gain that 50 fixed validation starts do not
    show (PickCube mixed-50: filtered BC kept its start in two seeds; its last weights tested +5)."""
    last = {s: d.with_name(f"{d.name}_last") for s, d in finished.items()}
    for s, out_dir in last.items():
        if not (out_dir / "eval.json").is_file() and not args.collect_only:
            if not (finished[s] / "checkpoints" / "latest.pt").is_file():
                # a run copied without its checkpoints (its records only) has no last weights to test
                print(
                    f"{finished[s]} has no checkpoints/latest.pt (a restored record?): "
                    "its last weights are not tested"
                )
                continue
            cmd = last_weights_eval_cmd(args, finished[s], out_dir)
            with open(out_dir.parent / f"{out_dir.name}.log", "a") as log:
                if subprocess.run(cmd, stdout=log, stderr=log).returncode != 0:
                    print(f"the last-weights test of {finished[s]} failed; see {out_dir}.log")
    done = {s: d for s, d in last.items() if (d / "eval.json").is_file()}
    return seeded_control({s: read_control(d) for s, d in done.items()}) if done else None


def at_asked_length(run_dir: Path, name: str, args) -> bool:
    """The run has its report (``eval.json``) at the length asked: ``--steps`` env steps, for the
    continued-BC control ``--continued-bc-updates`` updates, for a TD-only arm (``<algorithm>_offline``)
    ``--offline-only-updates``."""
    if not (run_dir / "eval.json").is_file():
        return False
    summary = json.loads((run_dir / "summary.json").read_text())
    if offline_arm(name):
        asked = args.continued_bc_updates if name == "continued_bc" else args.offline_only_updates
        return summary["offline_updates"] >= asked
    return summary["env_steps"] >= args.steps


def seeded_control(per_seed: dict[int, dict]) -> dict:
    """A control arm run once per seed: each seed's figures and the mean and spread of their tests."""
    spread = mean_and_spread([c["test"]["success_once"] for c in per_seed.values()])
    return {
        "seeds": {str(s): c for s, c in per_seed.items()},
        "test": {
            "success_once": spread["mean"],
            "min": spread["min"],
            "max": spread["max"],
            "episodes": next(iter(per_seed.values()))["test"]["episodes"],
        },
    }


def data_cost(dataset: str | None) -> dict | None:
    """What making the run's data cost in the simulator beyond the start's demonstrations: a robomimic
    file grown by ``demos.shifted_replays`` records its attempts and env steps; None for other data."""
    if not dataset or not str(dataset).endswith(".hdf5") or not Path(dataset).is_file():
        return None
    import h5py

    with h5py.File(dataset, "r") as f:
        raw = f["data"].attrs.get("shifted_replays")
    return json.loads(raw) if raw else None


def read_control(run_dir: Path) -> dict:
    """A control arm's test figure: a ``l1flow-rl train`` run (the BC start, continued BC) or a finished
    fine-tuning run, read from its ``eval.json``."""
    test = json.loads((run_dir / "eval.json").read_text())
    summary_file = run_dir / "summary.json"  # an ``l1flow-rl eval`` run writes none
    summary = json.loads(summary_file.read_text()) if summary_file.is_file() else {}
    return {
        "run_dir": str(run_dir),
        "test": {k: test.get(k) for k in ("success_once", "success_at_end", "episodes", "ci95", "selection")},
        "steps": summary.get("steps"),
        "cpu_seconds": summary.get("cpu_seconds"),
        "data_cost": data_cost(summary.get("dataset")),
    }


def _digest(tensors: dict) -> str:
    """sha256 over named tensors in key order: names, dtypes, shapes and bytes."""
    h = hashlib.sha256()
    for key in sorted(tensors, key=str):
        t = tensors[key].detach().cpu().contiguous()
        h.update(f"{key}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.view(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def start_fingerprint(checkpoint: str | Path) -> dict:
    """What tells a start from one remade by its own command: sha256 of its weights (model and EMA)
    and of the episodes it trained on as training loads them (their content: an HDF5 file's bytes
    change with its write times). A remake on another machine or commit can differ in either; the
    file's controls and seeds compare only against the same start."""
    from omegaconf import OmegaConf

    from l1flow_rl.workspace.checkpoint import load_checkpoint
    from l1flow_rl.workspace.dataset import load_task_episodes

    state = load_checkpoint(checkpoint)
    weights = {f"model.{k}": v for k, v in state["model"].items()}
    weights.update({f"ema.{k}": v for k, v in (state.get("ema") or {}).items()})
    dataset = state.get("dataset")
    episodes = None
    if dataset and Path(dataset).exists():
        data = load_task_episodes(OmegaConf.create(state["config"]), Path(dataset))
        episodes = _digest({k: data.get(k) for k in data.keys(True, True)})
    return {"weights_sha256": _digest(weights), "dataset": dataset, "episodes_sha256": episodes}


def read_run(run_dir: Path) -> dict:
    """A finished run's figures; a run stopped early (no eval.json) is read from its last checkpoint."""
    stopped = not (run_dir / "eval.json").is_file()
    if stopped:
        from l1flow_rl.workspace.checkpoint import load_checkpoint

        state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
        history = {"evals": state["evals"], "rounds": state["records"].get("rounds", [])}
        summary = {**state["progress"], "machine": None}
        test = {}
    else:
        history = json.loads((run_dir / "history.json").read_text())
        summary = json.loads((run_dir / "summary.json").read_text())
        test = json.loads((run_dir / "eval.json").read_text())
    val = [e for e in history["evals"] if e.get("split", "val") == "val"]

    # the harness's closing validation carries no phase and no env-step count: its step (offline
    # updates + env steps) tells them; a run extended after it finished has one in the middle too
    def closing(e: dict) -> dict:
        if "step" not in e:
            return {**e, "phase": "final", "env_steps": summary.get("env_steps")}
        return {**e, "phase": "final", "env_steps": int(e["step"]) - int(summary.get("offline_updates") or 0)}

    val = [e if e.get("phase") else closing(e) for e in val]
    rounds = history.get("rounds", [])
    trained = [r for r in rounds if r.get("policy") == "actor"]

    def mean(key, rows):
        values = [r[key] for r in rows if r.get(key) is not None]
        return sum(values) / len(values) if values else None

    return {
        "stopped_early": stopped,
        "validation": [
            {
                "env_steps": e.get("env_steps", 0),
                "phase": e.get("phase", "final"),
                "success_once": e["success_once"],
            }
            for e in val
        ],
        "collected_success": [[r["env_steps"], r.get("episode_success")] for r in rounds],
        # unbiased (collect.round_stats): each env's first episode per round; absent in older runs
        "collected_first_episode_success": [[r["env_steps"], r.get("first_episode_success")] for r in rounds],
        "test": {k: test.get(k) for k in ("success_once", "success_at_end", "episodes", "ci95", "selection")},
        "start_validation": val[0]["success_once"] if val else None,
        "env_steps_per_s_warmup": mean("env_steps_per_s", [r for r in rounds if r.get("policy") == "start"]),
        "env_steps_per_s_actor": mean("env_steps_per_s", trained),
        "updates_per_s": mean("updates_per_s", trained),
        "summary": {
            k: summary.get(k)
            for k in (
                "offline_updates",
                "online_updates",
                "env_steps",
                "wall_seconds",
                "cpu_seconds",
                "online_seconds",
            )
        },
        "machine": summary.get("machine"),
        "data_cost": data_cost(summary.get("dataset")),
    }


def plot(data: dict, out: Path) -> None:
    """Validation success against env steps per algorithm (mean over seeds, min-max band), the control
    arms' test figures as horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for name, algo in data["algorithms"].items():
        curve = algo["aggregate"]["curve"]
        x = [c["env_steps"] for c in curve]
        (line,) = ax.plot(x, [c["mean"] for c in curve], "o-", label=f"{name} ({len(algo['runs'])} seeds)")
        ax.fill_between(
            x, [c["min"] for c in curve], [c["max"] for c in curve], alpha=0.2, color=line.get_color()
        )
    for k, (name, control) in enumerate(data["controls"].items()):
        test = control["test"]
        seeds = f", {len(control['seeds'])} seeds" if "seeds" in control else ""
        label = f"{name} (test {test['success_once']:.2f}{seeds})"
        ax.axhline(test["success_once"], ls="--", lw=1, color=f"C{k + 5}", label=label)
        if "seeds" in control:  # its tests' min-max
            ax.axhspan(test["min"], test["max"], alpha=0.1, color=f"C{k + 5}")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("validation success_once")
    ax.set_ylim(-0.05, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"online fine-tuning from one BC start, {data['task']}")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--task", default="maniskill_pickcube")
    parser.add_argument("--algorithms", nargs="*", default=list(CPU_BUDGET), help="none: the controls only")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--eval-every", type=int, default=20_000)
    parser.add_argument("--val-episodes", type=int, default=50)
    parser.add_argument("--test-episodes", type=int, default=100)
    parser.add_argument(
        "--control",
        nargs="*",
        default=[],
        metavar="NAME=RUN_DIR",
        help="control arms read from finished runs' eval.json (the BC start, continued BC, ...)",
    )
    parser.add_argument(
        "--continued-bc-updates",
        type=int,
        default=0,
        help="per seed, a continued-BC control of this many demonstration-only updates from the checkpoint",
    )
    parser.add_argument(
        "--offline-only-updates",
        type=int,
        default=0,
        help="per algorithm and seed, its TD-only arm: this many updates on the demonstrations alone",
    )
    parser.add_argument("--jobs", type=int, default=1, help="runs at once")
    parser.add_argument("--root", default="runs/bench_finetune_online")
    parser.add_argument("--override", nargs="*", default=[])
    parser.add_argument("--collect-only", action="store_true")
    parser.add_argument("--out", default=None)
    parser.add_argument(
        "--plot",
        default=None,
        help="also draw this file's curves there (a PNG; RESULTS.md draws one figure per start instead)",
    )
    args = parse_args(parser, argv)
    controls = {}
    for item in args.control:
        name, sep, run_dir = item.partition("=")
        if not sep or not (Path(run_dir) / "eval.json").is_file():
            parser.error(f"--control {item!r}: expected NAME=RUN_DIR of a finished run (with eval.json)")
        controls[name] = read_control(Path(run_dir))
    root = Path(args.root)
    dirs = {(a, s): root / f"{args.task}_{a}_seed{s}" for a in args.algorithms for s in args.seeds}
    control_dirs = {s: root / f"{args.task}_continued_bc_seed{s}" for s in args.seeds}
    commands = {key: run_one(key[0], key[1], args, d) for key, d in dirs.items()}
    if args.continued_bc_updates:
        commands.update({("continued_bc", s): continued_bc_cmd(s, args, d) for s, d in control_dirs.items()})
        dirs.update({("continued_bc", s): d for s, d in control_dirs.items()})
    for a in args.algorithms if args.offline_only_updates else []:
        for seed in args.seeds:
            key = (f"{a}_offline", seed)
            dirs[key] = root / f"{args.task}_{a}_offline_seed{seed}"
            commands[key] = offline_only_cmd(a, seed, args, dirs[key])
    if not args.collect_only:
        pending = [(key, dirs[key]) for key in commands if not at_asked_length(dirs[key], key[0], args)]
        for (name, _), run_dir in pending:
            last = run_dir.with_name(f"{run_dir.name}_last")
            if (last / "eval.json").is_file():  # a finished run is extended: its last weights change
                length = "offline_updates" if offline_arm(name) else "env_steps"
                done = json.loads((run_dir / "summary.json").read_text())[length]
                last.rename(last.with_name(f"{last.name}_{done}"))  # its old last weights' test is kept
        running: list[tuple[tuple[str, int], subprocess.Popen]] = []
        while pending or running:
            while pending and len(running) < args.jobs:
                (name, seed), run_dir = pending.pop(0)
                run_dir.parent.mkdir(parents=True, exist_ok=True)
                log = open(run_dir.parent / f"{run_dir.name}.log", "a")  # noqa: SIM115 (closed with the process)
                cmd = commands[(name, seed)]
                if (run_dir / "checkpoints" / "latest.pt").is_file():  # an interrupted run continues exactly
                    cmd = [*cmd, "resume=true"]
                running.append(((name, seed), subprocess.Popen(cmd, stdout=log, stderr=log)))
            key, proc = running.pop(0)
            if proc.wait() != 0:
                print(f"{key} failed (exit {proc.returncode}); see {dirs[key]}.log")
    if args.continued_bc_updates:
        finished = {s: d for s, d in control_dirs.items() if (d / "eval.json").is_file()}
        if finished:
            controls["continued_bc"] = {
                **seeded_control({s: read_control(d) for s, d in finished.items()}),
                "updates": args.continued_bc_updates,
                "overrides": list(args.override),  # --override reaches the control too (e.g. an EMA)
            }
            last = last_weights_control(finished, args)
            if last:
                controls["continued_bc_last"] = {
                    **last,
                    "updates": args.continued_bc_updates,
                    "overrides": list(args.override),
                }
    for a in args.algorithms if args.offline_only_updates else []:
        finished = {
            s: dirs[(f"{a}_offline", s)]
            for s in args.seeds
            if at_asked_length(dirs[(f"{a}_offline", s)], f"{a}_offline", args)
        }
        if finished:
            controls[f"{a}_offline"] = {
                **seeded_control({s: read_control(d) for s, d in finished.items()}),
                "updates": args.offline_only_updates,
                "overrides": offline_only_settings(a, args),
            }
    for a in args.algorithms:  # each online run's last weights too, beside its validated choice
        finished = {s: dirs[(a, s)] for s in args.seeds if at_asked_length(dirs[(a, s)], a, args)}
        last = last_weights_control(finished, args)
        if last:
            controls[f"{a}_last"] = {**last, "overrides": budget(a, args.override)}
    readable = lambda d: (d / "eval.json").is_file() or (d / "checkpoints" / "latest.pt").is_file()  # noqa: E731
    algorithms = {}
    for a in args.algorithms:
        runs = {s: read_run(dirs[(a, s)]) for s in args.seeds if readable(dirs[(a, s)])}
        if runs:
            algorithms[a] = {
                "budget_overrides": budget(a, args.override),
                "runs": {str(s): r for s, r in runs.items()},
                "aggregate": runs_aggregate(runs),
            }
    out = Path(args.out or f"benchmarks/results/finetune_online_{args.task}.json")
    data = {
        "task": args.task,
        "checkpoint": str(args.checkpoint),
        "online_steps": args.steps,
        "offline_only_updates": args.offline_only_updates,
        "eval_every": args.eval_every,
        "val_episodes": args.val_episodes,
        "test_episodes": args.test_episodes,
        "start": start_fingerprint(args.checkpoint),
        "machine": machine_info("cpu"),
        "controls": controls,
        "algorithms": algorithms,
    }
    from benchmarks.finetune.rechoose import rechoose  # it imports this module: imported here

    rechoose(data)  # runs measured under the earlier checkpoint rule are read under today's
    save_results(out, data)
    if args.plot:
        plot(data, Path(args.plot))
    print(render_finetune_online(data))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
