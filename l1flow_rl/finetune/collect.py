"""Online data for fine-tuning: a TorchRL ``Collector`` (0.14's name for ``SyncDataCollector``)
running the chunk actor (through ``MultiStepActorWrapper``) in the task's env, in rounds that start
from freshly seeded resets.

Each round resets every env (``reset_at_each_iter``) from seeds fixed by the round number, so a
resumed run collects exactly what an uninterrupted one would: no episode spans two rounds (the
buffer stores a round's unfinished episodes as truncated). Episodes end on success or failure
(``ignore_terminations=False``), which gives the critic its terminal states, or at the time limit.
"""

from __future__ import annotations

from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType
from torchrl.modules import AdditiveGaussianModule, MultiStepActorWrapper

from l1flow_rl.config import TaskConfig
from l1flow_rl.config.finetune import round_frames
from l1flow_rl.envs import make_env
from l1flow_rl.envs.registry import get_simulator

__all__ = ["OnlineCollector", "round_stats", "single_frames"]

#: seeds reserved per round: every env reset of a round draws consecutive seeds from the round's base
SEEDS_PER_ROUND = 100_000


def single_frames(batch: TensorDictBase, entries: dict, obs_horizon: int) -> TensorDictBase:
    """Keep the current frame of each history-stacked observation entry (and its ``"next"`` twin):
    the buffers store one frame per step and stack histories when they cut windows."""
    out = batch.clone(False)
    for key, frame_dims in entries.items():
        dim = -(int(frame_dims) + 1)
        for k in (key, ("next", *((key,) if isinstance(key, str) else key))):
            value = out.get(k, default=None)
            if value is None:
                continue
            if value.shape[dim] != obs_horizon:
                raise ValueError(
                    f"collector entry {k!r} has shape {tuple(value.shape)}; expected {obs_horizon} stacked "
                    f"frames at dim {dim}"
                )
            out.set(k, value.select(dim, obs_horizon - 1))
    return out


def round_stats(batch: TensorDictBase) -> dict[str, float | None]:
    """Episodes a round finished (by success, failure or the time limit; not those the round's end
    cuts), how many succeeded (None when none finished), and the mean reward per step."""
    done = batch.get(("next", "done")).bool().reshape(-1)
    success = batch.get(("next", "success"), default=None)
    ended = int(done.sum())
    out = {"episodes_ended": float(ended), "reward_mean": float(batch.get(("next", "reward")).float().mean())}
    if success is not None:
        succeeded = int((done & success.bool().reshape(-1)).sum())
        out["episodes_succeeded"] = float(succeeded)
        out["episode_success"] = succeeded / ended if ended else None
        if batch.batch_dims == 2:  # [envs, steps]: each env's first episode of the round
            # episode_success is biased upward: an episode started after an early success ends
            # within the round only if it succeeds too (the cut ones are not counted). Each env's
            # first episode ends whatever its outcome when a round is one full episode per env
            # (online.frames_per_round=0), so its share is the unbiased one.
            done_2d = batch.get(("next", "done")).bool().reshape(batch.shape)
            success_2d = success.bool().reshape(batch.shape)
            ends = done_2d.any(dim=1)
            first_end = done_2d.float().argmax(dim=1)
            first_ok = success_2d[torch.arange(batch.shape[0]), first_end] & ends
            n_first = int(ends.sum())
            out["first_episodes"] = float(n_first)
            out["first_episode_success"] = int(first_ok.sum()) / n_first if n_first else None
    return out


class OnlineCollector:
    """Collects one round of environment steps (``online.frames_per_round``; see
    :func:`~l1flow_rl.config.finetune.round_frames`) per :meth:`collect` with the given actor.

    Args:
        cfg: the composed run config (``task``, ``policy``, ``online``).
        actor: the chunk actor (its parameters are read live: updates between rounds take effect).
        device: where the actor runs. The envs step in CPU worker processes and the collector moves
            each step's data to the actor's device and back (TorchRL's ``env_device``/``policy_device``),
            so the rounds and the replay buffers stay on the CPU.
    """

    def __init__(self, cfg: DictConfig, actor: TensorDictModuleBase, device: torch.device) -> None:
        ocfg = cfg.online
        frames = round_frames(cfg)
        if frames % ocfg.num_envs:
            raise ValueError(
                f"online.frames_per_round={ocfg.frames_per_round} must be a multiple of online.num_envs="
                f"{ocfg.num_envs} (every env steps the same number of times per round)"
            )
        task: TaskConfig = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(TaskConfig), cfg.task))
        self.entries = dict(get_simulator(task.simulator).observation_entries(task))
        self.obs_horizon = int(cfg.policy.obs_horizon)
        self.env_seed = int(ocfg.env_seed)
        self.env = make_env(
            task,
            num_envs=ocfg.num_envs,
            device="cpu",
            obs_horizon=self.obs_horizon,
            ignore_terminations=False,
            render=False,
        )
        policy = MultiStepActorWrapper(actor, n_steps=int(cfg.policy.action_steps), init_key="is_init")
        sigma = float(ocfg.get("action_noise", 0.0))
        if sigma > 0:  # exploration noise on each executed (and stored) action, projected into the bounds
            spec = self.env.action_spec.clone().to(device)  # the noise is added where the policy runs
            noise = AdditiveGaussianModule(
                spec, sigma_init=sigma, sigma_end=sigma, annealing_num_steps=1, device=device
            )
            policy = TensorDictSequential(policy, noise)
        # building the collector may run the policy once; keep that off the training RNG stream
        with torch.random.fork_rng(devices=[]):
            self.collector = Collector(
                self.env,
                policy,
                frames_per_batch=frames,
                total_frames=-1,
                reset_at_each_iter=True,
                exploration_type=ExplorationType.RANDOM,
                # an env made on the GPU fails the collector's first call ("indices should be either
                # on cpu or on the same device"): the envs step on the CPU, the policy where it runs
                env_device="cpu",
                policy_device=device,
                storing_device="cpu",
            )
        self._iter = iter(self.collector)

    def collect(self, round_index: int) -> TensorDictBase:
        """One round: every env reset from the round's seeds, then ``frames_per_round`` steps."""
        self.env.set_seed(self.env_seed + round_index * SEEDS_PER_ROUND)
        with torch.no_grad():
            batch = next(self._iter)
        return single_frames(batch, self.entries, self.obs_horizon)

    def close(self) -> None:
        self.collector.shutdown()
        self.env.close(raise_if_closed=False)  # not gated on is_closed (see PeriodicEvaluator.close)

    def __enter__(self) -> OnlineCollector:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
