"""How far the fine-tuning critics' value on their own replay data drifts from the data's Monte-Carlo
value: a run's dumped online buffer replayed offline, one fresh loss per critic setting and seed.

For a fine-tuning run (``l1flow-rl finetune``) with at least one online checkpoint, the run's latest
``checkpoints/online_buffer_round*`` dump is copied (the run may still be going: it deletes the old dump
when it writes a new one) and loaded into the run's buffers (``RLBuffers``, as the run builds them).
For each ``--config NAME="finetune.x=... finetune.y=..."`` and each seed, a fresh loss of the run's
algorithm is built from the BC start (``cfg.checkpoint``), and ``--updates`` updates of
``l1flow_rl.finetune.base.update`` (Adam at ``finetune.lr``, TorchRL ``SoftUpdate`` at
``finetune.tau``) run on ``RLBuffers.sample_online()`` batches; at update 0 (the fresh loss on the
first batch) and at each ``--report-at`` update the batch's ``q_data_mean`` (the critics' mean value of
the windows they train on), ``target_mean``, ``q_actor_mean``, ``entropy`` and ``alpha`` (where the loss
reports them) and the seconds per update so far are recorded.

The yardstick (:func:`mc_values`): the Monte-Carlo value of those windows, the discounted sum of the
rewards from the window's step to its episode's end (sparse reward: gamma^k for a success k steps
ahead, 0 for an episode that never terminates), over the buffer's anchor rows (chunk starts for DSRL)
whose chunk the critic loss keeps (``chunk_valid``). It is the value of the policies
that collected the data; a truncated episode's tail is unknown and counts 0, a lower bound, so the
fraction of windows in such episodes is reported beside it.

The saved results replayed the retired residual-steering arm's buffers (its code is gone: they stay as
records); the bench replays any run of a registered critic algorithm (DSRL, QC, FQL).

    OMP_NUM_THREADS=1 python -m benchmarks.finetune.bench_critic_bias \\
        --run runs/bench_finetune_online/maniskill_pickcube_dsrl_seed0 \\
        --config preset="" --config redq="finetune.num_critics=10 finetune.target_critics=2" \\
        --seeds 0 1 --updates 1000 --report-at 100 250 500 1000
"""

from __future__ import annotations

import argparse
import copy
import re
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from benchmarks.lib.common import machine_info, parse_args, save_results
from benchmarks.report.finetune import render_critic_bias

__all__ = ["METRICS", "latest_dump", "main", "mc_values", "parse_configs"]

#: the loss outputs recorded at each report point (those the loss has)
METRICS = ("q_data_mean", "target_mean", "q_actor_mean", "entropy", "alpha")
_DUMP = re.compile(r"online_buffer_round(\d+)")


def mc_values(
    episode: np.ndarray,
    step: np.ndarray,
    terminated: np.ndarray,
    truncated: np.ndarray,
    anchor: np.ndarray,
    *,
    gamma: float,
    rl_horizon: int | None = None,
    reward: np.ndarray | None = None,
) -> dict[str, Any]:
    """The Monte-Carlo value of the windows a chunk critic trains on, from per-step arrays [N].

    Args:
        episode, step: each row's episode id and step in its episode (an episode's rows need not be
            contiguous or ordered).
        terminated, truncated: the step's ``("next", "terminated" | "truncated")``.
        anchor: rows where a window starts (the buffer's anchor rows).
        gamma: the per-step discount.
        rl_horizon: h, the critic's executed steps: a window whose chunk runs past the end of an
            episode that did not terminate is left out, as the critic loss leaves it out
            (``chunk_valid``, :mod:`l1flow_rl.data.rl_windows`). None: every anchor counts.
        reward: the per-step reward (default: ``terminated``, the sparse reward).

    Returns ``windows`` (how many), ``mc_mean`` (the mean over them of sum_{k>=0} gamma^k r_{t+k} to the
    episode's end), ``truncated_fraction`` (of windows in episodes that ended without a terminal state:
    their tail is unknown, so their value is a lower bound), ``success_fraction`` (of windows in episodes
    that terminated) and ``episodes`` (those with at least one window).
    """
    episode, step = np.asarray(episode).reshape(-1), np.asarray(step).reshape(-1)
    terminated = np.asarray(terminated, dtype=bool).reshape(-1)
    truncated = np.asarray(truncated, dtype=bool).reshape(-1)
    anchor = np.asarray(anchor, dtype=bool).reshape(-1)
    r = terminated.astype(np.float64) if reward is None else np.asarray(reward, dtype=np.float64).reshape(-1)
    n = episode.shape[0]
    if not all(a.shape[0] == n for a in (step, terminated, truncated, anchor, r)):
        raise ValueError("episode, step, terminated, truncated, anchor and reward need one value per row")
    order = np.lexsort((step, episode))  # by episode, then step
    ep, st = episode[order], step[order]
    same_next = np.zeros(n, dtype=bool)  # the next sorted row continues this row's episode
    same_next[:-1] = ep[1:] == ep[:-1]
    value = np.zeros(n)
    rs = r[order]
    for i in range(n - 1, -1, -1):  # the discounted return to the episode's end, backwards
        value[i] = rs[i] + (gamma ** float(st[i + 1] - st[i]) * value[i + 1] if same_next[i] else 0.0)
    _, group = np.unique(ep, return_inverse=True)
    last = np.flatnonzero(~same_next)  # each episode's last row, in group order
    ended_terminal = terminated[order][last][group]
    ended_cut = (truncated[order][last] | ~terminated[order][last])[group]
    length = (st[last] + 1)[group]
    keep = anchor[order]
    if rl_horizon is not None:
        keep &= (st + int(rl_horizon) <= length) | ended_terminal
    count = int(keep.sum())
    if count == 0:
        raise ValueError("no window: no anchor row (whose chunk the critic keeps)")
    return {
        "windows": count,
        "episodes": int(np.unique(ep[keep]).size),
        "mc_mean": float(value[keep].mean()),
        "truncated_fraction": float(ended_cut[keep].mean()),
        "success_fraction": float(ended_terminal[keep].mean()),
        "gamma": float(gamma),
        "rl_horizon": rl_horizon,
    }


def parse_configs(items: list[str]) -> dict[str, list[str]] | str:
    """``NAME="finetune.a=1 finetune.b=2"`` items as {name: overrides}, each override checked against
    ``finetune``'s schema; or the one-line reason the first bad item is refused."""
    from l1flow_rl.commands.cli import compose_config

    found: dict[str, list[str]] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            return (
                f'argument --config: {item!r} is not NAME="OVERRIDES" (e.g. redq="finetune.num_critics=10")'
            )
        if name in found:
            return f"argument --config: the name {name!r} is given twice"
        try:
            overrides = [o for o in shlex.split(text) if o]  # preset="" outside a shell: no override
        except ValueError as err:
            return f"argument --config: {item!r}: {err}"
        for o in overrides:
            if not o.startswith("finetune.") or "=" not in o:
                return f"argument --config: {item!r}: {o!r} is not finetune.KEY=VALUE"
        try:  # composed and validated as l1flow-rl finetune would (keys, types, ranges)
            compose_config(overrides, command="finetune")
        except Exception as err:  # hydra's, omegaconf's or the validator's: one line
            return f"argument --config: {item!r}: {str(err).splitlines()[0]}"
        found[name] = overrides
    return found


def _finetune_overrides(overrides: list[str]) -> DictConfig:
    return OmegaConf.from_dotlist(overrides).get("finetune") or OmegaConf.create({})


def latest_dump(run: Path) -> Path | None:
    """The run's online buffer dump of the highest round (round100 after round99), or None."""
    dumps = [
        (int(m.group(1)), p)
        for p in (run / "checkpoints").glob("online_buffer_round*")
        if (m := _DUMP.fullmatch(p.name))
    ]
    return max(dumps)[1] if dumps else None


def _copy_latest(run: Path, into: Path) -> Path:
    """Copy the latest dump; a running job may delete it mid-copy when it writes the next one: retry."""
    for _ in range(5):
        src = latest_dump(run)
        if src is None:
            break
        dst = into / src.name
        shutil.rmtree(dst, ignore_errors=True)
        try:
            shutil.copytree(src, dst)
            return dst
        except (FileNotFoundError, shutil.Error):
            time.sleep(2.0)
    raise RuntimeError(f"{run}: could not copy an online buffer dump (each vanished while copied)")


def load_run(run: Path) -> tuple[DictConfig, Any, Any]:
    """(config with the current schema's defaults for keys the run predates, BC actor, demonstrations)."""
    from l1flow_rl.config.finetune import FinetuneConfig, OnlineConfig
    from l1flow_rl.config.network import upgrade_saved_config
    from l1flow_rl.config.task import TaskConfig
    from l1flow_rl.finetune.loop import start_dataset
    from l1flow_rl.workspace.checkpoint import load_actor, load_checkpoint
    from l1flow_rl.workspace.dataset import load_task_episodes

    # a run from before the network group: its policy block's UNet settings move to a network block
    cfg = OmegaConf.create(upgrade_saved_config(OmegaConf.to_container(OmegaConf.load(run / "config.yaml"))))
    schema = OmegaConf.structured(FinetuneConfig)
    OmegaConf.set_struct(schema, False)  # the algorithms' own blocks are not in the common schema
    cfg.finetune = OmegaConf.merge(schema, cfg.finetune)
    cfg.online = OmegaConf.merge(OmegaConf.structured(OnlineConfig), cfg.online)
    # typed as the job types it: a simulator's reader options read it by attribute (robosuite: state_keys)
    cfg.task = OmegaConf.merge(OmegaConf.structured(TaskConfig), cfg.task)
    bc_state = load_checkpoint(cfg.checkpoint)
    bc_actor, bc_cfg = load_actor(cfg.checkpoint)  # EMA weights, as the fine-tuning job loads them
    # the network is the checkpoint's, as the fine-tuning job takes it (policy, network, encoder)
    cfg.policy = OmegaConf.merge(cfg.policy, bc_cfg.policy)
    for group in ("network", "encoder"):
        if bc_cfg.get(group) is not None:
            cfg[group] = (
                bc_cfg[group] if cfg.get(group) is None else OmegaConf.merge(cfg[group], bc_cfg[group])
            )
    return cfg, bc_actor, load_task_episodes(cfg, start_dataset(cfg, bc_state, given=[]))


def _buffers(cfg: DictConfig, episodes, loss, dump: Path, seed: int):
    from l1flow_rl.finetune.buffers import RLBuffers
    from l1flow_rl.finetune.registry import get_algorithm

    alg = get_algorithm(cfg.finetune.algorithm)
    bufs = RLBuffers(cfg, episodes, loss.rl_horizon, seed=seed, **alg.buffer_options(cfg.finetune))
    bufs.load_online(dump)
    bufs.online.set_rng(torch.Generator().manual_seed(seed + 1))  # the dump's generator: seeded anew
    return bufs


def buffer_yardstick(bufs, gamma: float, rl_horizon: int) -> dict[str, Any]:
    """:func:`mc_values` of the online buffer's stored steps at its sampler's anchor rows."""
    from l1flow_rl.config.finetune import REWARD_KEYS

    storage = bufs.online.storage
    data = storage.get(slice(0, len(storage)))
    # the sampler's own anchor rows: chunk starts, complete (alive) episodes, the padding cap
    _, _, anchors = bufs.online.sampler._episode_table(storage)
    anchor = np.zeros(len(storage), dtype=bool)
    anchor[anchors.numpy()] = True
    reward_key = tuple(bufs.online.sampler.layout.reward_key)
    out = mc_values(
        data.get("episode").numpy(),
        data.get("step").numpy(),
        data.get(("next", "terminated")).numpy(),
        data.get(("next", "truncated")).numpy(),
        anchor,
        gamma=gamma,
        rl_horizon=rl_horizon,
        reward=data.get(reward_key).numpy().astype(np.float64),
    )
    reward = {tuple(v): k for k, v in REWARD_KEYS.items()}.get(reward_key, "/".join(reward_key))
    return {**out, "reward": reward, "steps_stored": len(storage)}


def replay(cfg, bc_actor, episodes, dump: Path, seed: int, updates: int, report_at: list[int]):
    """One fresh loss trained ``updates`` times on the dumped buffer: (curve, yardstick, loss settings)."""
    from torchrl.objectives import SoftUpdate

    from l1flow_rl.finetune.base import update
    from l1flow_rl.finetune.registry import get_algorithm

    torch.manual_seed(seed)
    alg = get_algorithm(cfg.finetune.algorithm)
    with open_dict(cfg):  # the algorithm's block over its defaults, as the fine-tuning job fills it
        cfg.finetune[alg.name] = alg.settings_of(cfg.finetune)
    loss = alg.build(copy.deepcopy(bc_actor), cfg.finetune)
    optimizer = torch.optim.Adam([p for p in loss.parameters() if p.requires_grad], lr=float(cfg.finetune.lr))
    target_update = SoftUpdate(loss, tau=float(cfg.finetune.tau))
    bufs = _buffers(cfg, episodes, loss, dump, seed)
    yardstick = buffer_yardstick(bufs, float(loss.gamma), int(loss.rl_horizon))
    batch = bufs.sample_online()
    with torch.no_grad():  # update 0: the fresh critics on the first batch
        out = loss(batch)
    curve = []
    wall, cpu = time.perf_counter(), time.process_time()
    for i in range(updates + 1):
        if i > 0:
            out = update(loss, optimizer, target_update, batch if i == 1 else bufs.sample_online())
        if i in report_at:
            point = {"update": i, **{k: round(float(out[k]), 5) for k in METRICS if k in out}}
            if i > 0:
                point["s_per_update"] = round((time.perf_counter() - wall) / i, 4)
                point["cpu_s_per_update"] = round((time.process_time() - cpu) / i, 4)
            curve.append(point)
            print(f"  seed {seed} update {i}: " + ", ".join(f"{k} {v}" for k, v in point.items()), flush=True)
    critics = dict(
        num_critics=int(cfg.finetune.num_critics),
        target_critics=int(cfg.finetune.target_critics),
        critic_hidden_dims=list(cfg.finetune.critic_hidden_dims),
        q_agg=str(cfg.finetune.q_agg),
        rl_horizon=int(loss.rl_horizon),
        gamma=float(loss.gamma),
        mixing=bufs.mixing,
        parameters=sum(p.numel() for p in loss.qvalue_network_params.values(True, True)),
    )
    return curve, yardstick, critics


def aggregate(curves: dict[str, list[dict]]) -> list[dict]:
    """Per report point, each metric's mean, min and max over seeds."""
    runs = list(curves.values())
    out = []
    for j, point in enumerate(runs[0]):
        row: dict[str, Any] = {"update": point["update"]}
        for k in point:
            if k != "update":
                vals = [r[j][k] for r in runs]
                row[k] = {"mean": round(sum(vals) / len(vals), 5), "min": min(vals), "max": max(vals)}
        out.append(row)
    return out


def _fail(parser: argparse.ArgumentParser, message: str) -> None:
    parser.exit(2, f"{parser.prog}: error: {message}\n")


def _check_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict[str, list[str]]:
    configs = parse_configs(args.config)
    if isinstance(configs, str):
        _fail(parser, configs)
    if args.updates < 1:
        _fail(parser, f"argument --updates: must be >= 1, got {args.updates}")
    bad = [u for u in args.report_at if not 1 <= u <= args.updates]
    if bad:
        _fail(parser, f"argument --report-at: {bad} outside 1..--updates ({args.updates})")
    run = Path(args.run)
    if not (run / "config.yaml").is_file():
        _fail(parser, f"argument --run: {run} has no config.yaml (not a fine-tuning run directory)")
    if latest_dump(run) is None:
        _fail(
            parser,
            f"argument --run: {run}/checkpoints holds no online_buffer_round* dump (no online round saved)",
        )
    return configs  # type: ignore[return-value]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="a fine-tuning run directory with an online buffer dump")
    parser.add_argument(
        "--config",
        action="append",
        required=True,
        metavar='NAME="OVERRIDES"',
        help="a critic setting; repeat",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--updates", type=int, default=1000)
    parser.add_argument("--report-at", nargs="+", type=int, default=[100, 250, 500, 1000])
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the machine is shared)")
    parser.add_argument(
        "--out", default=None, help="default: benchmarks/results/critic_bias_<task>_<algorithm>.json"
    )
    args = parse_args(parser, argv)
    configs = _check_args(parser, args)
    torch.set_num_threads(args.threads)
    run = Path(args.run)
    points = [0, *sorted(set(args.report_at))]  # 0: the fresh critics, before any update
    base, bc_actor, episodes = load_run(run)
    out = Path(args.out or f"benchmarks/results/critic_bias_{base.task.name}_{base.finetune.algorithm}.json")
    with tempfile.TemporaryDirectory(prefix="critic_bias_") as tmp:
        dump = _copy_latest(run, Path(tmp))
        rnd = int(_DUMP.fullmatch(dump.name).group(1))  # type: ignore[union-attr]
        from l1flow_rl.config.finetune import round_frames

        data: dict[str, Any] = {
            "machine": machine_info("cpu"),
            "run": str(run),
            "task": base.task.name,
            "algorithm": base.finetune.algorithm,
            "checkpoint": str(base.checkpoint),
            "dump": dump.name,
            "env_steps": rnd * round_frames(base),
            "batch_size": int(base.finetune.batch_size),
            "updates": args.updates,
            "report_at": points,
            "seeds": args.seeds,
            "yardstick": None,
            "configs": {},
            "finished": False,
        }
        for name, overrides in configs.items():
            cfg = copy.deepcopy(base)
            cfg.finetune = OmegaConf.merge(cfg.finetune, _finetune_overrides(overrides))
            print(f"{name}: {' '.join(overrides) or '(the run preset)'}", flush=True)
            entry: dict[str, Any] = {"overrides": overrides, "seeds": {}}
            for seed in args.seeds:
                curve, yardstick, critics = replay(cfg, bc_actor, episodes, dump, seed, args.updates, points)
                entry["seeds"][str(seed)] = curve
                entry["settings"] = critics
                if data["yardstick"] is None:
                    data["yardstick"] = yardstick
                if yardstick != data["yardstick"]:  # another gamma or horizon: its own windows
                    entry["yardstick"] = yardstick
                entry["mean"] = aggregate(entry["seeds"])
                data["configs"][name] = entry
                save_results(out, data)  # a long run keeps what it measured so far
        data["load_average_1min_end"] = machine_info("cpu")["load_average_1min"]
        data["finished"] = True
        save_results(out, data)
    print(render_critic_bias(data))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
