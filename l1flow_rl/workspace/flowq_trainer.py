"""The fine-tuning update: a FlowQLoss on an L1 Flow checkpoint, one Adam over critics and actor, and
TorchRL's SoftUpdate for the target critics (FQL's recipe)."""

from __future__ import annotations

import copy
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import unravel_key
from torch import Tensor
from torchrl.objectives import SoftUpdate

from l1flow_rl.actor import L1FlowActor
from l1flow_rl.config.finetune import FINETUNE_MODES
from l1flow_rl.networks.best_of_n import BestOfNActor
from l1flow_rl.networks.critic import build_critics
from l1flow_rl.networks.one_step import ONE_STEP_SAMPLER, make_one_step_actor
from l1flow_rl.objectives import FlowQLoss

__all__ = ["FlowQTrainer", "finetuned_policy_config"]


def finetuned_policy_config(
    bc_policy_cfg: dict[str, Any], mode: str, best_of_n: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The policy config that rebuilds the fine-tuned actor (``load_actor`` / ``l1flow-rl eval``):
    the BC policy's, with the one-step sampler in ``distill`` mode, and in ``best_of_n`` mode a
    ``best_of_n`` block (``num_samples``, ``rl_horizon``, ``num_qvalue_nets``,
    ``critic_hidden_dims``: what rebuilds the critics the actor selects with)."""
    cfg = copy.deepcopy(bc_policy_cfg)
    if mode == "best_of_n":
        cfg["name"] = f"{cfg.get('name', 'l1flow')}_qc"
        cfg["best_of_n"] = dict(best_of_n or {})
    elif mode == "distill":
        cfg["sampler"], cfg["sampler_kwargs"] = ONE_STEP_SAMPLER[0], dict(ONE_STEP_SAMPLER[1])
        cfg["name"] = f"{cfg.get('name', 'l1flow')}_fql"
    else:
        cfg["name"] = f"{cfg.get('name', 'l1flow')}_flowq"
    return cfg


class FlowQTrainer:
    """Builds the fine-tuned actor, the critics and :class:`~l1flow_rl.FlowQLoss` from a BC actor,
    and runs updates.

    Args:
        bc_actor: the L1 Flow actor of the BC checkpoint (normalisers fitted); it is copied, never
            modified.
        cfg: the ``finetune`` config group.
    """

    def __init__(self, bc_actor: L1FlowActor, cfg: DictConfig) -> None:
        if cfg.mode not in FINETUNE_MODES:
            raise ValueError(f"finetune.mode={cfg.mode!r}; expected one of {FINETUNE_MODES}")
        self.cfg = cfg
        policy = bc_actor.policy
        h = int(cfg.rl_horizon) or policy.action_steps
        self.reference = copy.deepcopy(bc_actor).requires_grad_(False)  # the BC policy, for BC distance
        teacher = None
        if cfg.mode == "distill":
            teacher = copy.deepcopy(bc_actor)
            self.actor = make_one_step_actor(teacher, init=cfg.one_step_init)
        else:  # direct: trained; best_of_n: drawn from as it is
            self.actor = copy.deepcopy(bc_actor).requires_grad_(cfg.mode == "direct")
        critics = build_critics(
            policy, num=cfg.num_qvalue_nets, action_horizon=h, hidden_dims=tuple(cfg.critic_hidden_dims)
        )
        self.loss = FlowQLoss(
            self.actor,
            critics,
            teacher_network=teacher,
            mode=cfg.mode,
            num_qvalue_nets=cfg.num_qvalue_nets,
            alpha=cfg.alpha,
            train_teacher=cfg.train_teacher,
            normalize_q_loss=cfg.normalize_q_loss,
            q_agg=cfg.q_agg,
            gamma=cfg.gamma,
            rl_horizon=h,
            num_samples=cfg.num_samples,
            backup=cfg.backup,
            backup_samples=int(cfg.backup_samples) or None,
            critic_input=cfg.critic_input,
        )
        self.rl_horizon = h
        # the actor that acts (evaluation, collection, checkpoints): best_of_n selects among the
        # policy's chunks with the critics being trained, or their Polyak average (finetune.select_with);
        # the parameters are shared, not copied, so selection follows training
        self.policy_actor: TensorDictModuleBase = self.actor
        # best_of_n acts through its critics: a critic-only update changes the acting policy too
        self.critics_act = cfg.mode == "best_of_n"
        self.select_with_target = self.critics_act and cfg.select_with == "target"
        if cfg.mode == "best_of_n":
            selecting = self.loss.qvalue_network_params
            if self.select_with_target:
                selecting = self.loss.target_qvalue_network_params
            self.policy_actor = BestOfNActor(
                self.actor,
                self.loss.qvalue_network,
                selecting,
                num_samples=cfg.num_samples,
                rl_horizon=h,
                critic_input=cfg.critic_input,
            )
        # Valid chunks hold exactly h steps of their episode (chunk_valid), so the per-step affine map
        # r -> scale * r + offset turns a discounted chunk return R_h into scale * R_h + offset * sum_i g^i.
        self.reward_scale = float(cfg.reward_scale)
        self.reward_shift = float(cfg.reward_offset) * sum(cfg.gamma**i for i in range(h))
        self.updater = SoftUpdate(self.loss, tau=cfg.tau)
        params = [p for p in self.loss.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(params, lr=cfg.lr)
        self.updates = 0

    def shape_rewards(self, batch: TensorDictBase) -> TensorDictBase:
        """``batch`` with its chunk returns under ``finetune.reward_scale`` / ``reward_offset`` (in place)."""
        if self.reward_scale != 1.0 or self.reward_shift != 0.0:
            key = unravel_key(("next", self.loss.tensor_keys.reward))
            batch.set(key, batch.get(key) * self.reward_scale + self.reward_shift)
        return batch

    def mc_targets(self, batch: TensorDictBase) -> Tensor:
        """Monte-Carlo values [B, 1] of the batch's chunks under the shaped rewards: the discounted
        return to the episode's end (``("mc", ...)`` entries of the windows); a truncated episode's
        unplayed remainder is valued as its last reward repeated forever (it stopped where it stood),
        a terminated one's is 0."""
        gamma = float(self.cfg.gamma)
        ret, steps = batch.get(("mc", "return")), batch.get(("mc", "steps")).to(torch.float64)
        last, terminated = batch.get(("mc", "last_reward")), batch.get(("mc", "terminated")).bool()
        discount = gamma**steps  # gamma^(L - t)
        geometric = (1.0 - discount) / (1.0 - gamma) if gamma < 1.0 else steps
        value = self.reward_scale * ret.to(torch.float64) + float(self.cfg.reward_offset) * geometric
        if gamma < 1.0:
            tail = discount * (self.reward_scale * last.to(torch.float64) + float(self.cfg.reward_offset))
            value = value + torch.where(terminated, torch.zeros_like(tail), tail / (1.0 - gamma))
        return value.to(ret.dtype)

    def update(self, batch: TensorDictBase, actor: bool = True, critic: str = "td") -> dict[str, float]:
        """One Adam step and one target update. ``actor=False`` trains the critics alone (warm-up:
        the actor waits for a critic that ranks chunks, instead of climbing an untrained one).
        ``critic="mc"`` (critics alone) regresses them onto :meth:`mc_targets` instead of the TD
        target (call :meth:`sync_target_critics` when that pretraining ends)."""
        if critic not in ("td", "mc"):
            raise ValueError(f"critic must be 'td' or 'mc', got {critic!r}")
        actor = actor and self.cfg.mode != "best_of_n"  # nothing to train but the critics
        if critic == "mc" and actor:
            raise ValueError("critic='mc' pretrains the critics alone; pass actor=False")
        batch = self.shape_rewards(batch)
        if critic == "mc":
            loss_q, meta = self.loss.qvalue_regression_loss(batch, self.mc_targets(batch))
            out, total = TensorDict({"loss_qvalue": loss_q, **meta}, batch_size=[]), loss_q
        elif actor:
            out = self.loss(batch)
            total = out["loss_actor"] + out["loss_qvalue"]
        else:
            loss_q, meta = self.loss.qvalue_loss(batch)
            out = TensorDict({"loss_qvalue": loss_q, **meta}, batch_size=[])
            total = loss_q
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        params = [p for group in self.optimizer.param_groups for p in group["params"]]
        clip = self.cfg.grad_clip if self.cfg.grad_clip > 0 else float("inf")
        grad_norm = torch.nn.utils.clip_grad_norm_(params, clip)
        self.optimizer.step()
        # Monte-Carlo regression bootstraps from nothing, so the target critics only track it when
        # they select (finetune.select_with=target)
        if critic == "td" or self.select_with_target:
            self.updater.step()
        self.updates += 1
        metrics = {k: float(v.detach()) for k, v in out.items() if v.numel() == 1}
        metrics["grad_norm"] = float(grad_norm)
        return metrics

    @torch.no_grad()
    def sync_target_critics(self) -> None:
        """Target critics := critics (after Monte-Carlo pretraining, before TD takes over)."""
        self.loss.target_qvalue_network_params.update_(self.loss.qvalue_network_params.detach())

    @torch.no_grad()
    def critic_diagnostics(
        self, batch: TensorDictBase, samples: int = 8, generator: torch.Generator | None = None
    ) -> dict[str, float]:
        """Does the critic rank anything? On the batch's valid chunks: ``q_state_std``, the spread of
        Q(s, data chunk) across states; ``q_chunk_std``, the mean spread of Q over ``samples`` of the
        actor's chunks at the same state (what its gradient can use); ``q_mc_corr``, the correlation
        of Q(s, data chunk) with the chunk's Monte-Carlo value (NaN without ``("mc", ...)`` entries).
        ``batch`` is read as stored (rewards unshaped)."""
        loss, policy = self.loss, self.actor.policy
        obs, chunk, batch_dims = loss._read(batch)
        valid = loss._valid(batch, batch_dims, chunk.device)
        obs, chunk = obs[valid], chunk[valid]
        n = obs.shape[0]
        params = loss.qvalue_network_params
        q_data = loss._q(obs, loss._executed(chunk), params).mean(0).reshape(n)
        shape = (n, policy.pred_horizon, policy.action_dim)
        device = policy.action_normalizer.scale.device
        sampled = []
        for _ in range(samples):
            noise = torch.randn(shape, generator=generator, dtype=policy.dtype).to(device)
            with loss.actor_network_params.to_module(loss.actor_network):
                x = loss._clip(loss._sample(policy, obs, noise), policy)
            action = policy.action_normalizer.unnormalize(loss._executed(x))
            sampled.append(loss._q(obs, action, params).mean(0).reshape(n))
        out = {
            "q_state_std": float(q_data.std()),
            "q_chunk_std": float(torch.stack(sampled, 1).std(1).mean()),
            "q_mc_corr": float("nan"),
        }
        if ("mc", "return") in batch.keys(include_nested=True):
            mc = self.mc_targets(batch).reshape(-1)[valid]
            out["q_mc_corr"] = float(torch.corrcoef(torch.stack([q_data, mc.to(q_data.dtype)]))[0, 1])
        return out

    @torch.no_grad()
    def bc_distance(self, batch: TensorDictBase, generator: torch.Generator | None = None) -> float:
        """Mean |fine-tuned chunk - BC chunk| (normalised units, executed steps) from the same noise;
        ``best_of_n``: the chosen chunk against the first of the N draws (how far selection moves)."""
        loss, policy = self.loss, self.actor.policy
        if isinstance(self.policy_actor, BestOfNActor):
            with torch.random.fork_rng(devices=[]):  # off the training RNG stream
                if generator is not None:
                    torch.manual_seed(int(torch.randint(2**31, (1,), generator=generator)))
                observation = batch.get(loss.tensor_keys.observation)
                chosen, draws, _ = self.policy_actor.select(observation.reshape(-1, *observation.shape[1:]))
            norm = policy.action_normalizer.normalize
            return float((norm(chosen) - norm(draws[:, 0])).abs().mean())
        obs = policy.as_obs_dict(batch.get(loss.tensor_keys.observation))
        shape = (obs.shape[0], policy.pred_horizon, policy.action_dim)
        device = policy.action_normalizer.scale.device
        noise = torch.randn(shape, generator=generator, dtype=policy.dtype).to(device)
        mine = loss._executed(loss._sample(policy, obs, noise))
        ref = loss._executed(loss._sample(self.reference.policy, obs, noise))
        return float((mine - ref).abs().mean())

    def state_dict(self) -> dict[str, Any]:
        return {
            "loss": self.loss.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.loss.load_state_dict(state["loss"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = int(state["updates"])
