"""L1 Flow's training objective: sample prediction, L1, mixed logit-normal time."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import Tensor

from l1flow_rl.flow.objectives import LossSpace, LossType, check_loss_type, sample_prediction_error
from l1flow_rl.flow.samplers import TwoStepSampler
from l1flow_rl.flow.time import interpolate
from l1flow_rl.flow.timesteps import TimestepDistribution, make_timesteps
from l1flow_rl.objectives.chunk_loss import ChunkLossBase

__all__ = ["L1FlowLoss"]


class L1FlowLoss(ChunkLossBase):
    """The network f(x_t, t, obs) is trained to predict the clean chunk x1.

    ``x_t = (1 - t) x0 + t x1`` with ``x0 ~ N(0, I)`` and ``t`` from ``timesteps``; the loss is
    ``|f(x_t, t) - x1|`` (``loss_type="l1"``) averaged over valid chunk steps. Every ablation of the
    paper is an option: ``timesteps`` (``"mixed"``, ``"uniform"``, ``"beta"`` or a
    :class:`~l1flow_rl.flow.TimestepDistribution`), ``loss_type`` (``"l1"``/``"mse"``),
    ``loss_space`` (``"x"``, or ``"v"``: the same error weighted by 1/(1 - t), (1 - t) >= 0.05),
    and ``t_first`` (when given, the actor samples with ``TwoStepSampler(t_first)``).

    Args:
        actor_network: an :class:`~l1flow_rl.L1FlowActor` with a sample-prediction sampler
            (``TwoStepSampler``, the default, or ``EulerSampler``).

    Returns a TensorDict with ``"loss_l1flow"`` and detached diagnostics ``"t_mean"`` and
    ``"x_error_l1"`` (mean |f - x1| in normalised units, whatever the loss type).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from l1flow_rl import L1FlowActor, L1FlowLoss
        >>> actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, obs_horizon=2, pred_horizon=16,
        ...                               action_steps=8, down_dims=(32, 64))
        >>> loss_fn = L1FlowLoss(actor)
        >>> td = TensorDict({"observation": torch.randn(4, 2, 5),
        ...                  "action_chunk": torch.rand(4, 16, 2) * 2 - 1}, batch_size=[4])
        >>> out = loss_fn(td)
        >>> out["loss_l1flow"].backward()
        >>> actor(TensorDict({"observation": torch.randn(4, 2, 5)}, batch_size=[4]))["action_chunk"].shape
        torch.Size([4, 8, 2])
    """

    loss_name = "loss_l1flow"
    prediction = "sample"
    sampler_hint = "L1FlowActor.for_state(..., sampler=TwoStepSampler(0.5)) (the default)"
    diagnostic_keys = ("t_mean", "x_error_l1")

    def __init__(
        self,
        actor_network: TensorDictModule,
        *,
        timesteps: str | TimestepDistribution = "mixed",
        loss_type: LossType = "l1",
        loss_space: LossSpace = "x",
        t_first: float | None = None,
        reduction: str = "mean",
        mask_padding: bool = False,
    ) -> None:
        super().__init__(actor_network, reduction=reduction, mask_padding=mask_padding)
        self.loss_type = check_loss_type(loss_type)
        if loss_space not in ("x", "v"):
            raise ValueError(f"loss_space must be 'x' or 'v', got {loss_space!r}")
        self.timesteps = make_timesteps(timesteps)
        self.loss_space = loss_space
        if t_first is not None:
            self.policy.sampler = TwoStepSampler(t_first)

    def _elementwise_loss(
        self, cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        t = self.timesteps.sample(x1.shape[0], device=x1.device).to(x1.dtype)
        x0 = torch.randn_like(x1)
        x_t = interpolate(x0, x1, t)
        x1_hat = self.policy.denoise(x_t, t, cond)
        err = sample_prediction_error(x1_hat, x1, t, self.loss_type, self.loss_space)
        return err, {"t_mean": t.mean(), "x_error_l1": self._valid_mean((x1_hat - x1).abs(), valid)}
