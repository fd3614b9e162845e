"""What every fine-tuning algorithm stands on: the chunk critic's TD loss, and the protocol the loop
talks to.

* :class:`ChunkCriticLoss`, the TD loss shared by QC, FQL and DSRL (each names its own next-chunk
  actor).
* :class:`FinetuneAlgorithm`: what an algorithm tells the loop (:mod:`l1flow_rl.finetune.loop`): its
  settings block, the loss it trains (whose ``actor`` acts), the BC start in acting form, its target
  networks' update, and the data it needs. :class:`ChunkCriticAlgorithm` adds the critics and their
  Polyak update for the algorithms on :class:`ChunkCriticLoss`.
* :class:`Learner`: one run's trained state built from an algorithm: the loss, Adam, the target
  update, the EMA that acts (``finetune.ema_power``), what it saves and restores; :func:`update` is
  its one step.

The chunk critic's target. For a window at step t with h executed actions, the target is

    y = R_h + gamma^h * (1 - terminated) * Qbar(s_{t+h}, a'),     R_h = sum_{i<h} gamma^i r_{t+i}

with ``a'`` from the algorithm's next-chunk actor and ``Qbar`` the target critics aggregated by
``min`` or ``mean``. With ``per_chunk_discount`` (DSRL: its env wrapper makes one chunk one step of
the MDP) gamma is the discount per chunk decision: ``R_h`` sums the chunk's rewards undiscounted and
the bootstrap is discounted by ``gamma`` once. The windows
(:func:`~l1flow_rl.data.rl_windows.read_rl_targets`) give ``("next", "terminated")`` only where an
episode ended in a terminal state within the chunk; a truncated episode bootstraps from its final
observation. A chunk that crosses a terminal end is
valid: its return is summed to that end and nothing is bootstrapped. A chunk that crosses a
truncated end is not (``chunk_valid`` False) and drops out of the loss, as in QC.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.objectives import LossModule, SoftUpdate

from l1flow_rl.errors import CheckpointMismatchError
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.modules.ema import DPEma, make_ema
from l1flow_rl.modules.policy import ChunkPolicy
from l1flow_rl.networks.critic import ChunkCritic, critic_module
from l1flow_rl.objectives.chunk_loss import required_entry
from l1flow_rl.utils.doc_examples import CRITIC, FLOW, TRAIN_STEP, TRANSITIONS, add_example

__all__ = [
    "ChunkCriticAlgorithm",
    "ChunkCriticLoss",
    "FinetuneAlgorithm",
    "Learner",
    "NoSettings",
    "update",
]

Q_AGGREGATIONS = ("mean", "min")


@add_example(
    FLOW,
    CRITIC,
    """\
>>> from l1flow_rl import ChunkCriticLoss
>>> bc_chunk = lambda obs: flow.policy(obs)  # the BC policy's next chunk: TD-only
>>> loss_fn = ChunkCriticLoss(critic, flow, next_actor=bc_chunk)
""",
    TRANSITIONS,
    TRAIN_STEP,
)
class ChunkCriticLoss(LossModule):
    """TD loss of an ensemble of chunk critics; usable alone with any next-chunk actor.

    Args:
        critic: a :class:`~l1flow_rl.networks.critic.ChunkCritic` (E members) or a
            TensorDictModule around one. Its target copy is made here (update it with TorchRL's
            ``SoftUpdate``).
        policy: the :class:`~l1flow_rl.modules.policy.ChunkPolicy` (or an actor holding one) whose reader
            validates observations and whose horizons locate the executed chunk; it is not trained here.

    Keyword Args:
        next_actor: ``read next observation [N, To] -> critic input [N, ...]``, the chunk valued at
            s_{t+h} (e.g. the BC policy's own chunk: a TD-only arm). Subclasses name their own
            actor in :meth:`next_value` instead.
        gamma: per-step discount; the bootstrap is discounted by ``gamma ** rl_horizon``. The
            windows' chunk returns must be discounted with the same gamma.
        per_chunk_discount: ``gamma`` is the discount per chunk decision instead (DSRL): the
            bootstrap is discounted by ``gamma``; the windows' chunk returns must then be the
            undiscounted sums of the chunks' rewards (the buffers' return discount 1).
        q_agg: ``"mean"`` (QC, FQL) or ``"min"`` over the target critics.
        rl_horizon: h, executed actions per chunk (default: the policy's ``action_steps``).

    The input holds ``"observation"`` [*B, To, ...], ``"action_chunk"`` [*B, H, A] (its steps
    [To-1, To-1+h) are the executed ones), ``("next", "reward")`` [*B, 1] (the discounted chunk
    return), ``("next", "terminated")`` [*B, 1], ``("next", "observation")`` and ``"chunk_valid"``
    [*B, 1] (absent: all valid). Returns ``"loss_qvalue"`` and detached ``"q_data_mean"``,
    ``"target_mean"``, ``"td_error_abs"``, ``"valid_fraction"``.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            observation (NestedKey): observation history [*B, To, ...]. Defaults to ``"observation"``.
            action_chunk (NestedKey): the stored chunk [*B, H, A] in environment units.
                Defaults to ``"action_chunk"``.
            reward (NestedKey): read under ``"next"``: the discounted chunk return [*B, 1].
                Defaults to ``"reward"``.
            terminated (NestedKey): read under ``"next"``: no bootstrap where True.
                Defaults to ``"terminated"``.
            next_observation (NestedKey): the history h steps later. Defaults to ``("next", "observation")``.
            chunk_valid (NestedKey): [*B, 1] bool, False for windows left out of the critic loss.
                Defaults to ``"chunk_valid"``.
        """

        observation: NestedKey = "observation"
        action_chunk: NestedKey = "action_chunk"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"
        next_observation: NestedKey = ("next", "observation")
        chunk_valid: NestedKey = "chunk_valid"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    qvalue_network: TensorDictModule
    qvalue_network_params: TensorDictBase
    target_qvalue_network_params: TensorDictBase
    critic_diagnostics = ("q_data_mean", "target_mean", "td_error_abs", "valid_fraction")

    def __init__(
        self,
        critic: ChunkCritic | TensorDictModule,
        policy: torch.nn.Module,
        *,
        next_actor: Callable[[TensorDictBase], Tensor] | None = None,
        gamma: float = 0.99,
        q_agg: str = "mean",
        rl_horizon: int | None = None,
        target_critics: int | None = None,
        per_chunk_discount: bool = False,
    ) -> None:
        if q_agg not in Q_AGGREGATIONS:
            raise ValueError(f"q_agg must be one of {Q_AGGREGATIONS}, got {q_agg!r}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must lie in [0, 1], got {gamma}")
        super().__init__()
        reader = getattr(policy, "policy", policy)
        if not isinstance(reader, ChunkPolicy):
            raise TypeError(
                f"policy must be a ChunkPolicy or an actor holding one, got {type(policy).__name__}"
            )
        # not a submodule: the policy is read (observations, horizons), never trained by this loss
        self.__dict__["reader"] = reader
        module = critic if isinstance(critic, TensorDictModule) else critic_module(critic)
        if not isinstance(module.module, ChunkCritic):
            raise TypeError(f"critic must be a ChunkCritic, got {type(module.module).__name__}")
        self.convert_to_functional(module, "qvalue_network", create_target_params=True)
        self.rl_horizon = int(rl_horizon or reader.action_steps)
        if not 1 <= self.rl_horizon <= reader.action_steps:
            raise ValueError(
                f"rl_horizon={self.rl_horizon} must lie in [1, action_steps={reader.action_steps}]"
            )
        self.gamma, self.q_agg = float(gamma), q_agg
        self.per_chunk_discount = bool(per_chunk_discount)
        members = self.critic.num_critics
        if target_critics is not None and not 1 <= target_critics <= members:
            raise ValueError(f"target_critics={target_critics} must lie in [1, num_critics={members}]")
        self.target_critics = target_critics
        self._next_actor = next_actor

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass  # the target is computed here (one line, see td_target); no TorchRL value estimator

    @property
    def critic(self) -> ChunkCritic:
        return self.qvalue_network.module  # type: ignore[return-value]

    # -- reading the batch -------------------------------------------------------------------------
    def _get(self, td: TensorDictBase, key: NestedKey, what: str):
        return required_entry(td, key, what, type(self).__name__)

    def read_observation(self, td: TensorDictBase, key: NestedKey) -> TensorDictBase:
        """The observation under ``key`` through the policy's reader: a flat TensorDict [N, To]."""
        return self.reader.as_obs_dict(self._get(td, key, "an observation history"), key=str(key))

    def executed(self, chunk: Tensor) -> Tensor:
        """The executed steps [..., h, A] of stored or predicted chunks [..., H, A]."""
        start = self.reader.obs_horizon - 1
        return chunk[..., start : start + self.rl_horizon, :]

    def critic_input(self, td: TensorDictBase) -> Tensor:
        """What the critics value for the batch's windows: the executed actions (environment units)."""
        policy = self.reader
        chunk = self._get(td, self.tensor_keys.action_chunk, "the stored chunk [*B, H, A]")
        return self.executed(chunk.reshape(-1, policy.pred_horizon, policy.action_dim))

    def _column(self, td: TensorDictBase, key: NestedKey, n: int, what: str) -> Tensor:
        value = self._get(td, key, what)
        if value.numel() != n:
            raise ValueError(
                f"{key!r} ({what}) must hold one value per window ({n}), got {tuple(value.shape)}"
            )
        return value.reshape(n)

    def valid(self, td: TensorDictBase, n: int) -> Tensor:
        key = self.tensor_keys.chunk_valid
        if td.get(key, default=None) is None:
            return torch.ones(n, dtype=torch.bool)
        return self._column(td, key, n, "chunk validity").bool()

    # -- values ------------------------------------------------------------------------------------
    def q(
        self, observation: TensorDictBase, value_input: Tensor, *, target: bool = False, detach: bool = False
    ) -> Tensor:
        """Every critic's value [N, E]: online or ``target`` critics; ``detach``: no gradient reaches
        the critics' parameters (an actor's objective)."""
        if target:  # .data: a swap-in must not write the module's Parameter wrappers back into the targets
            params = self.target_qvalue_network_params.data
        else:
            params = self.qvalue_network_params.detach() if detach else self.qvalue_network_params
        with params.to_module(self.qvalue_network):
            return self.critic(observation, value_input)

    def aggregate(self, q: Tensor) -> Tensor:
        """[N, E] -> [N] by ``q_agg``."""
        return q.min(-1).values if self.q_agg == "min" else q.mean(-1)

    def aggregate_target(self, q: Tensor) -> Tensor:
        """The bootstrap's [N, E] -> [N]: ``q_agg`` over ``target_critics`` members drawn at random for
        the batch (RLPD/REDQ: min over 2 of 10), or over all of them."""
        if self.target_critics is not None:
            q = q[:, torch.randperm(q.shape[-1], device=q.device)[: self.target_critics]]
        return self.aggregate(q)

    def next_value(self, td: TensorDictBase, next_obs: TensorDictBase) -> Tensor:
        """Qbar(s_{t+h}, a') [N] with a' from the next-chunk actor (called under no_grad)."""
        if self._next_actor is None:
            raise NotImplementedError(
                f"{type(self).__name__} needs next_actor= (the chunk valued at the next observation)"
            )
        return self.aggregate_target(self.q(next_obs, self._next_actor(next_obs), target=True))

    @property
    def bootstrap_discount(self) -> float:
        """What the next value is discounted by: ``gamma ** rl_horizon``, or ``gamma`` per chunk."""
        return self.gamma if self.per_chunk_discount else self.gamma**self.rl_horizon

    @torch.no_grad()
    def td_target(self, td: TensorDictBase) -> Tensor:
        """y [N]: R_h + bootstrap_discount * (1 - terminated) * next value."""
        keys = self.tensor_keys
        next_obs = self.read_observation(td, keys.next_observation)
        n = next_obs.shape[0]
        reward = self._column(td, ("next", keys.reward), n, "the discounted chunk return")
        terminated = self._column(td, ("next", keys.terminated), n, "terminal end within the chunk").bool()
        bootstrap = self.next_value(td, next_obs)
        return reward.to(bootstrap.dtype) + self.bootstrap_discount * (~terminated) * bootstrap

    def qvalue_loss(self, td: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """Mean squared TD error of every critic over the valid windows, and its diagnostics."""
        obs = self.read_observation(td, self.tensor_keys.observation)
        n = obs.shape[0]
        target = self.td_target(td)
        valid = self.valid(td, n).to(target.device)
        q = self.q(obs, self.critic_input(td))  # [N, E]
        w = valid.to(q.dtype)
        count = w.sum().clamp_min(1)
        err = q - target.unsqueeze(-1)
        loss = (err.square().mean(-1) * w).sum() / count
        diagnostics = {
            "q_data_mean": (q.mean(-1) * w).sum() / count,
            "target_mean": (target * w).sum() / count,
            "td_error_abs": (err.abs().mean(-1) * w).sum() / count,
            "valid_fraction": w.mean(),
        }
        return loss, {k: v.detach() for k, v in diagnostics.items()}

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        loss, diagnostics = self.qvalue_loss(tensordict)
        return TensorDict({"loss_qvalue": loss, **diagnostics}, batch_size=[])


# -- the algorithm protocol ----------------------------------------------------------------------------


@dataclass
class NoSettings:
    """The settings of an algorithm without a block of its own."""


class FinetuneAlgorithm:
    """What the fine-tuning loop asks of an algorithm. An algorithm's package (a folder under
    ``l1flow_rl/finetune/``, or a user's module that ``finetune.algorithm`` names by its import path)
    defines one instance as ``ALGORITHM``; :mod:`l1flow_rl.finetune.registry` imports it by name.

    Class attributes:
        name: the key of its settings block, ``finetune.<name>``.
        settings: the dataclass of that block; its numeric fields declare their ranges with
            :func:`~l1flow_rl.config.ranges.bounded`. The config validator checks the block's keys,
            types and ranges before any work; :meth:`settings_of` fills the defaults.
        online_keys: per-step entries the online buffer keeps beside the core ones (DSRL: the noise).
        online_anchor_key: where set, online windows start only at rows where that entry is 1 (DSRL:
            chunk starts, the only windows its critic can value).
        successful_episodes_only: windows only in episodes that ended in success, demonstrations and
            online episodes alike (filtered BC).
        uses_offline_data: False where the batches need entries demonstrations lack (DSRL's noise).
        actor_is_start: the actor is the BC start until online updates move it (flow-Q: a copy of the
            flow; QC: the flow's proposals), so an offline phase may train the critics alone
            (``offline.critic_only``) and the TD targets still come from a meaningful actor.
        with_flow: None, or a method ``with_flow(loss, flow)``: the acting module with ``flow`` in place
            of the loss's trained BC flow, for an algorithm whose acting module wraps that flow, so that
            the flow's EMA acts (``finetune.ema_power``). With None, the EMA averages the whole acting
            module.

    Implement :meth:`build`; :meth:`start_actor` and :meth:`target_update` have defaults.
    """

    name: ClassVar[str] = ""
    settings: ClassVar[type] = NoSettings
    online_keys: ClassVar[tuple[str, ...]] = ()
    online_anchor_key: ClassVar[str | None] = None
    successful_episodes_only: ClassVar[bool] = False
    uses_offline_data: ClassVar[bool] = True
    actor_is_start: ClassVar[bool] = False
    with_flow: Callable[[LossModule, L1FlowActor], nn.Module] | None = None

    def build(self, flow: L1FlowActor, cfg: DictConfig, *, seed: int = 0) -> LossModule:
        """The loss from the BC flow (a copy the run may train) and the ``finetune`` block ``cfg``.
        Its ``actor`` is the acting module, its ``rl_horizon`` the executed actions per window;
        ``seed``: the run's, for anything the loss draws on its own (cached proposals)."""
        raise NotImplementedError(f"{type(self).__name__} must implement build(flow, cfg, seed=...)")

    def start_actor(self, loss: LossModule) -> nn.Module:
        """The BC start in the form that writes what the online buffer stores: it acts for the
        warm-up steps. Default: the loss's BC flow (``loss.flow``)."""
        return loss.flow

    def target_update(self, loss: LossModule, tau: float) -> SoftUpdate | None:
        """The update of the loss's target networks after each optimiser step (None: it has none)."""
        return None

    def settings_of(self, cfg: DictConfig | dict) -> DictConfig:
        """The algorithm's block of the ``finetune`` config ``cfg``, over its settings' defaults."""
        block = cfg.get(self.name) if self.name else None
        return OmegaConf.merge(OmegaConf.structured(self.settings), block or {})

    def buffer_options(self, cfg: DictConfig | None = None) -> dict[str, Any]:
        """What the replay buffers keep and draw for this algorithm (the keyword arguments of
        :class:`~l1flow_rl.finetune.buffers.RLBuffers`); ``cfg``: the ``finetune`` block, where its
        settings change them (None: the settings' defaults)."""
        return {
            "online_keys": self.online_keys,
            "online_anchor_key": self.online_anchor_key,
            "successful_episodes_only": self.successful_episodes_only,
        }

    def check(self, cfg: DictConfig) -> list[str]:
        """Problems of a composed run config for this algorithm's data needs, one line each."""
        problems = []
        if not self.uses_offline_data:
            if cfg.offline.steps > 0:
                problems.append(
                    f"offline.steps={cfg.offline.steps}: finetune.algorithm={self.name} trains only on "
                    "data its own actor collected (the demonstrations carry no steering noise); use "
                    "offline.steps=0"
                )
            if cfg.online.offline_fraction > 0 or cfg.online.seed_with_offline:
                problems.append(
                    f"online.offline_fraction={cfg.online.offline_fraction}, online.seed_with_offline="
                    f"{cfg.online.seed_with_offline}: finetune.algorithm={self.name} cannot use "
                    "demonstrations; use online.offline_fraction=0 online.seed_with_offline=false"
                )
        if cfg.offline.get("critic_only") and not (
            self.actor_is_start and isinstance(self, ChunkCriticAlgorithm)
        ):
            problems.append(
                f"offline.critic_only=true: finetune.algorithm={self.name} has no critic, or an actor that "
                "must learn in the offline phase (its TD targets come from it); use offline.critic_only=false"
            )
        if self.online_keys and cfg.online.get("action_noise", 0.0) > 0:
            problems.append(
                f"online.action_noise={cfg.online.action_noise}: finetune.algorithm={self.name} learns from "
                f"the stored {list(self.online_keys)}, which noise on the executed action would not match; "
                "use online.action_noise=0 (it explores through its own actor)"
            )
        return problems


class ChunkCriticAlgorithm(FinetuneAlgorithm):
    """An algorithm on :class:`ChunkCriticLoss`: critics built from the ``finetune`` block, the TD
    options it sets, and TorchRL's ``SoftUpdate`` of the target critics at ``finetune.tau``."""

    def critic(
        self, flow: L1FlowActor, cfg: DictConfig, input_shape: Sequence[int], normalize_input: bool = True
    ) -> ChunkCritic:
        """An ensemble of ``finetune.num_critics`` critics of ``finetune.critic_hidden_dims``."""
        return ChunkCritic.from_policy(
            flow,
            input_shape=tuple(input_shape),
            num_critics=int(cfg.num_critics),
            hidden_dims=tuple(cfg.critic_hidden_dims),
            normalize_input=normalize_input,
        )

    def executed_shape(self, flow: L1FlowActor, cfg: DictConfig) -> tuple[int, int]:
        """The executed chunk a critic values, [h, A] (``finetune.rl_horizon``, 0: ``action_steps``)."""
        return int(cfg.rl_horizon) or flow.policy.action_steps, flow.policy.action_dim

    def td_options(self, cfg: DictConfig) -> dict[str, Any]:
        """``gamma``, ``q_agg``, ``rl_horizon`` and ``target_critics`` of :class:`ChunkCriticLoss`."""
        return {
            "gamma": float(cfg.gamma),
            "q_agg": str(cfg.q_agg),
            "rl_horizon": int(cfg.rl_horizon) or None,
            "target_critics": int(cfg.target_critics) or None,
        }

    def target_update(self, loss: LossModule, tau: float) -> SoftUpdate:
        return SoftUpdate(loss, tau=tau)


def update(
    loss: LossModule,
    optimizer: torch.optim.Optimizer,
    target_update: SoftUpdate | None,
    batch: TensorDictBase,
    ema: DPEma | None = None,
    averaged: nn.Module | None = None,
    *,
    critic_only: bool = False,
) -> dict[str, Tensor]:
    """One update: every ``loss_*`` term summed, one Adam step, one Polyak step of the target networks,
    one step of the EMA (``finetune.ema_power``) of ``averaged`` (default: the loss's acting actor).
    ``critic_only``: the critics' TD term alone (a :class:`ChunkCriticLoss`); the actor and its EMA
    stay as they are. Returns the loss's outputs (tensors: read to the host only when logged)."""
    if critic_only:
        loss_q, diagnostics = loss.qvalue_loss(batch)
        out = {"loss_qvalue": loss_q, **diagnostics}
    else:
        out = loss(batch)
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    optimizer.step()
    if target_update is not None:
        target_update.step()
    if ema is not None and not critic_only:
        ema.update_parameters(loss.actor if averaged is None else averaged)
    return {k: v.detach() for k, v in out.items()}


class Learner:
    """One run's trained state, built from an algorithm: what the loop updates, acts with and saves.

    Args:
        algorithm: the :class:`FinetuneAlgorithm`.
        flow: the BC flow the run starts from (a copy: the algorithm may train it).
        cfg: the ``finetune`` block (``lr``, ``tau``, ``ema_power`` and the algorithm's settings).

    Keyword Args:
        seed: the run's seed (for what the loss draws on its own).
        device: where the loss lives.
        ema_n_averaged: the BC run's EMA counter: an EMA of the trained BC flow goes on from it.

    Attributes: ``loss``; ``start``, the BC start that acts during the warm-up; ``acting``, what acts,
    is validated, tested and saved (the EMA where ``finetune.ema_power`` > 0, else ``loss.actor``);
    ``optimizer`` (Adam over the loss's trainable parameters); ``target_update``; ``ema``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from tensordict import TensorDict
        >>> from l1flow_rl import L1FlowActor
        >>> from l1flow_rl.config.finetune import FinetuneConfig
        >>> from l1flow_rl.finetune.registry import get_algorithm
        >>> flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
        >>> cfg = OmegaConf.structured(FinetuneConfig(algorithm="filtered_bc"))
        >>> learner = Learner(get_algorithm("filtered_bc"), flow, cfg)
        >>> batch = TensorDict({"observation": torch.randn(4, 2, 5),
        ...                     "action_chunk": torch.rand(4, 16, 2) * 2 - 1}, batch_size=[4])
        >>> sorted(k for k in learner.update(batch) if k.startswith("loss_"))
        ['loss_bc']
        >>> learner.acting is flow, learner.target_update is None  # the flow acts; no critic, no target
        (True, True)
        >>> sorted(learner.state_dict())
        ['ema', 'ema_n_averaged', 'loss', 'model', 'optimizer']
    """

    def __init__(
        self,
        algorithm: FinetuneAlgorithm,
        flow: L1FlowActor,
        cfg: DictConfig,
        *,
        seed: int = 0,
        device: torch.device | str = "cpu",
        ema_n_averaged: Tensor | None = None,
    ) -> None:
        self.loss = loss = algorithm.build(flow, cfg, seed=seed).to(device)
        self.start = algorithm.start_actor(loss)
        # With finetune.ema_power the averaged actor acts, is validated, tested and saved (the raw one
        # trains): constant-LR iterates swing from one validation to the next. Where the acting module
        # wraps the trained BC flow (filtered BC: is it; QC: proposes with it), the EMA averages that
        # flow, whose weights are the BC run's EMA: the average goes on from the BC run's counter, as if
        # BC had gone on; from 0 it copied the first, shocked iterates
        # (benchmarks/results/finetune_shock_*.json). Otherwise (new networks act: a noise or one-step
        # actor; a frozen flow) the EMA averages the acting module from 0.
        flow_trains = any(p.requires_grad for p in flow.parameters())
        through_flow = algorithm.with_flow is not None and flow_trains
        self.averaged = flow if through_flow else loss.actor
        power = float(cfg.ema_power)
        self.ema = make_ema(self.averaged, power=power) if power > 0 else None
        if self.ema is not None and through_flow and ema_n_averaged is not None:
            self.ema.n_averaged.copy_(ema_n_averaged)
        if self.ema is None:
            self.acting = loss.actor
        else:
            self.acting = algorithm.with_flow(loss, self.ema.module) if through_flow else self.ema.module
        trainable = [p for p in loss.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(trainable, lr=float(cfg.lr))
        self.target_update = algorithm.target_update(loss, float(cfg.tau))

    def update(self, batch: TensorDictBase, *, critic_only: bool = False) -> dict[str, Tensor]:
        """One update on ``batch`` (:func:`update`)."""
        return update(
            self.loss,
            self.optimizer,
            self.target_update,
            batch,
            self.ema,
            self.averaged,
            critic_only=critic_only,
        )

    def state_dict(self) -> dict[str, Any]:
        """The checkpoint's entries: ``model`` (the acting module's raw weights), ``ema`` (the acting
        module with the averaged weights, what ``load_actor(use_ema=True)`` rebuilds), the EMA's
        counter, the loss and the optimiser."""
        return {
            "model": self.loss.actor.state_dict(),
            "ema": None if self.ema is None else self.acting.state_dict(),
            "ema_n_averaged": None if self.ema is None else self.ema.n_averaged.clone(),
            "loss": self.loss.state_dict(),
            "optimizer": self.optimizer.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any], path: str = "the checkpoint") -> None:
        self.loss.load_state_dict(state["loss"])
        if self.ema is not None:
            if state.get("ema_n_averaged") is None:
                raise CheckpointMismatchError(  # a checkpoint from before the field
                    f"{path} holds no EMA: resume it with finetune.ema_power=0"
                )
            self.acting.load_state_dict(state["ema"])
            self.ema.n_averaged.copy_(state["ema_n_averaged"])
        self.optimizer.load_state_dict(state["optimizer"])
