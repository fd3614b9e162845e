"""The fine-tuning algorithms by name: each is its loss class, the builder of that loss (and with it the
acting module, ``loss.actor``) from a BC actor and the ``finetune`` config, and its settings block.

A new algorithm is one loss file plus one :func:`register_finetune_algorithm` call; the config
validator (``finetune.algorithm``) and ``l1flow-rl finetune`` read this table.

Example:
    >>> import torch
    >>> from omegaconf import OmegaConf
    >>> from l1flow_rl import L1FlowActor
    >>> from l1flow_rl.config.finetune import FinetuneConfig
    >>> cfg = OmegaConf.structured(FinetuneConfig(algorithm="fql", critic_hidden_dims=[32]))
    >>> flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
    >>> loss = FINETUNE_ALGORITHMS["fql"].build(flow, cfg)
    >>> type(loss).__name__, type(loss.actor).__name__
    ('FQLLoss', 'OneStepActor')
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from omegaconf import DictConfig
from torch import nn
from torchrl.objectives import LossModule

from l1flow_rl.config.finetune import (
    DSRLNASettings,
    DSRLSettings,
    FilteredBCSettings,
    FQLSettings,
    QCSettings,
)
from l1flow_rl.finetune.best_of_n_actor import BestOfNActor
from l1flow_rl.finetune.noise_actor import NoiseActor
from l1flow_rl.finetune.one_step_actor import OneStepActor
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.networks.critic import ChunkCritic
from l1flow_rl.objectives.dsrl import DSRLLoss
from l1flow_rl.objectives.dsrl_na import DSRLNALoss
from l1flow_rl.objectives.filtered_bc import FilteredBCLoss
from l1flow_rl.objectives.fql import FQLLoss
from l1flow_rl.objectives.qc import QCLoss

__all__ = [
    "FINETUNE_ALGORITHMS",
    "FinetuneAlgorithm",
    "finetune_algorithm_names",
    "finetune_algorithm_problems",
    "register_finetune_algorithm",
]


@dataclass(frozen=True)
class FinetuneAlgorithm:
    """``build(flow, finetune_cfg)`` -> the loss (its ``actor`` acts); ``start_actor(loss)``: the BC
    policy in the form that writes what the online buffer stores (the warm-up steps' actor);
    ``settings``: the dataclass of the algorithm's own block ``finetune.<name>``; ``online_keys``:
    per-step entries the online buffer keeps beside the core ones; ``online_anchor_key``: where set,
    online windows start only at rows where that entry is 1 (DSRL: chunk starts, the only windows
    its critic can value); ``successful_episodes_only``: windows only in episodes that ended in
    success, demonstrations and online episodes alike (filtered BC); ``uses_offline_data``: False
    where the batches need entries demonstrations lack (DSRL's noise); ``with_flow(loss, flow)``:
    the acting module with ``flow`` in place of the loss's trained BC flow (so that the flow's EMA
    acts, ``finetune.ema_power``), for algorithms whose acting module wraps that flow; None where it
    acts through networks of its own (its EMA then averages the whole acting module). The loss is a
    :class:`~l1flow_rl.ChunkCriticLoss`, or a plain TorchRL ``LossModule`` with ``actor`` and
    ``rl_horizon`` where there is no critic (filtered BC)."""

    name: str
    loss_cls: type[LossModule]
    settings: type
    build: Callable[[L1FlowActor, DictConfig], LossModule]
    start_actor: Callable[[LossModule], nn.Module]
    online_keys: tuple[str, ...] = ()
    online_anchor_key: str | None = None
    successful_episodes_only: bool = False
    uses_offline_data: bool = True
    with_flow: Callable[[LossModule, L1FlowActor], nn.Module] | None = None

    def check(self, cfg: DictConfig) -> list[str]:
        """Problems of a composed run config for this algorithm, one line each."""
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
        if self.online_keys and cfg.online.get("action_noise", 0.0) > 0:
            problems.append(
                f"online.action_noise={cfg.online.action_noise}: finetune.algorithm={self.name} learns from "
                f"the stored {list(self.online_keys)}, which noise on the executed action would not match; "
                "use online.action_noise=0 (it explores through its own actor)"
            )
        return problems


FINETUNE_ALGORITHMS: dict[str, FinetuneAlgorithm] = {}


def register_finetune_algorithm(algorithm: FinetuneAlgorithm) -> None:
    FINETUNE_ALGORITHMS[algorithm.name] = algorithm


def finetune_algorithm_names() -> list[str]:
    """The allowed values of ``finetune.algorithm`` (read by the config validator)."""
    return sorted(FINETUNE_ALGORITHMS)


def finetune_algorithm_problems(cfg: DictConfig, command: str) -> list[str]:
    """The chosen algorithm's own rules (it says what data it can use), for ``l1flow-rl finetune``."""
    ft = cfg.get("finetune")
    if command != "finetune" or ft is None:
        return []
    algorithm = FINETUNE_ALGORITHMS.get(ft.algorithm)
    return [] if algorithm is None else algorithm.check(cfg)


def _critic(flow: L1FlowActor, cfg: DictConfig, input_shape, normalize_input: bool = True) -> ChunkCritic:
    return ChunkCritic.from_policy(
        flow,
        input_shape=input_shape,
        num_critics=int(cfg.num_critics),
        hidden_dims=tuple(cfg.critic_hidden_dims),
        normalize_input=normalize_input,
    )


def _horizon(flow: L1FlowActor, cfg: DictConfig) -> int:
    return int(cfg.rl_horizon) or flow.policy.action_steps


def _common(cfg: DictConfig) -> dict:
    return {
        "gamma": float(cfg.gamma),
        "q_agg": str(cfg.q_agg),
        "rl_horizon": int(cfg.rl_horizon) or None,
        "target_critics": int(cfg.target_critics) or None,
    }


def _build_qc(flow: L1FlowActor, cfg: DictConfig) -> QCLoss:
    critic = _critic(flow, cfg, (_horizon(flow, cfg), flow.policy.action_dim))
    return QCLoss(
        flow,
        critic,
        num_samples=int(cfg.qc.num_samples),
        freeze_flow=bool(cfg.qc.freeze_flow),
        **_common(cfg),
    )


def _build_fql(flow: L1FlowActor, cfg: DictConfig) -> FQLLoss:
    mu = OneStepActor.from_flow(flow, hidden_dims=tuple(cfg.fql.actor_hidden_dims))
    critic = _critic(flow, cfg, (_horizon(flow, cfg), flow.policy.action_dim))
    return FQLLoss(
        mu,
        flow,
        critic,
        alpha=float(cfg.fql.alpha),
        normalize_q_loss=bool(cfg.fql.normalize_q_loss),
        **_common(cfg),
    )


def _build_dsrl(flow: L1FlowActor, cfg: DictConfig) -> DSRLLoss:
    s = cfg.dsrl
    steer = NoiseActor.from_flow(flow, bound=float(s.noise_bound), hidden_dims=tuple(s.actor_hidden_dims))
    critic = _critic(flow, cfg, steer.noise_policy.noise_shape, normalize_input=False)
    return DSRLLoss(
        steer,
        critic,
        target_entropy=float(s.target_entropy),
        init_alpha=float(s.init_alpha),
        **_common(cfg),
    )


def _build_dsrl_na(flow: L1FlowActor, cfg: DictConfig) -> DSRLNALoss:
    s = cfg.dsrl_na
    steer = NoiseActor.from_flow(flow, bound=float(s.noise_bound), hidden_dims=tuple(s.actor_hidden_dims))
    return DSRLNALoss(
        steer,
        _critic(flow, cfg, (_horizon(flow, cfg), flow.policy.action_dim)),
        _critic(flow, cfg, steer.noise_policy.noise_shape, normalize_input=False),
        target_entropy=float(s.target_entropy),
        init_alpha=float(s.init_alpha),
        distill_samples=int(s.distill_samples),
        **_common(cfg),
    )


def _build_filtered_bc(flow: L1FlowActor, cfg: DictConfig) -> FilteredBCLoss:
    return FilteredBCLoss(
        flow, rl_horizon=int(cfg.rl_horizon) or None, mask_padding=bool(cfg.filtered_bc.mask_padding)
    )


def _flow(loss) -> L1FlowActor:
    return loss.flow


def _qc_with_flow(loss: QCLoss, flow: L1FlowActor) -> BestOfNActor:
    # another flow proposes, the online critics still pick
    return BestOfNActor(flow, loss.critic, num_samples=loss.actor.num_samples, rl_horizon=loss.rl_horizon)


register_finetune_algorithm(
    FinetuneAlgorithm("qc", QCLoss, QCSettings, _build_qc, _flow, with_flow=_qc_with_flow)
)
register_finetune_algorithm(FinetuneAlgorithm("fql", FQLLoss, FQLSettings, _build_fql, _flow))


_STEERING = {
    "start_actor": lambda loss: loss.actor.prior(),
    # the chunk's steering input at each step, and the wrapper's step count (1 where a chunk starts)
    "online_keys": ("noise", "counter"),
    # sampling every step gave 1 valid window in 8 (valid_fraction 0.10-0.12 on PushCube)
    "online_anchor_key": "counter",
    "uses_offline_data": False,
}
register_finetune_algorithm(FinetuneAlgorithm("dsrl", DSRLLoss, DSRLSettings, _build_dsrl, **_STEERING))
# DSRL-NA's action critic values the executed actions of any window, demonstrations included: it
# stores nothing beyond the core entries and reads every window
register_finetune_algorithm(
    FinetuneAlgorithm("dsrl_na", DSRLNALoss, DSRLNASettings, _build_dsrl_na, _STEERING["start_actor"])
)
register_finetune_algorithm(
    FinetuneAlgorithm(
        "filtered_bc",
        FilteredBCLoss,
        FilteredBCSettings,
        _build_filtered_bc,
        _flow,
        successful_episodes_only=True,
        with_flow=lambda loss, flow: flow,  # the flow is the acting module
    )
)
