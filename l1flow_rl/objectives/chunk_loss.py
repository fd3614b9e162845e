"""What every chunk-policy loss shares: key handling, input checks, masking and reduction."""

from __future__ import annotations

import abc
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives import LossModule

from l1flow_rl.modules.policy import ChunkPolicy
from l1flow_rl.utils.value_checks import value_checks_enabled

__all__ = ["ChunkLossBase"]


def required_entry(td: TensorDictBase, key: NestedKey, what: str, owner: str):
    """``td[key]``, or a KeyError that names the loss, the key, what it should hold and the keys present."""
    value = td.get(key, default=None)
    if value is None:
        raise KeyError(
            f"{owner}: the input has no {key!r} entry ({what}); present keys: "
            f"{sorted(map(str, td.keys(True, True)))}. Use set_keys(...) to point at another key."
        )
    return value


class ChunkLossBase(LossModule):
    """Base for losses that train a :class:`~l1flow_rl.modules.actor.L1FlowActor`'s network on action chunks.

    Subclasses set ``loss_name``, ``prediction`` (the sampler target they train for) and implement
    :meth:`_elementwise_loss`.

    ``mask_padding=False`` (the default) trains on padded steps too, as Diffusion Policy and
    ManiSkill's baseline do, so the policy learns to hold still past an episode's end;
    ``mask_padding=True`` leaves steps flagged by ``action_is_pad`` out of the loss.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            observation (NestedKey): observation history, [*B, To, D] or a TensorDict of entries.
                Defaults to ``"observation"``.
            action_chunk (NestedKey): demonstrated chunk, [*B, H, A], in environment units.
                Defaults to ``"action_chunk"``.
            action_is_pad (NestedKey): optional [*B, H] bool, True where the chunk step is edge
                padding. Its shape is always checked; with ``mask_padding=True`` those steps are
                left out of the loss. Defaults to ``"action_is_pad"``.
        """

        observation: NestedKey = "observation"
        action_chunk: NestedKey = "action_chunk"
        action_is_pad: NestedKey = "action_is_pad"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    actor_network: TensorDictModule
    actor_network_params: TensorDictBase
    target_actor_network_params: TensorDictBase

    loss_name: str = "loss"
    prediction: str = ""
    sampler_hint: str = ""

    def __init__(
        self, actor_network: TensorDictModule, *, reduction: str = "mean", mask_padding: bool = False
    ):
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}")
        self._in_keys = None
        self._out_keys = None
        super().__init__()
        policy = getattr(actor_network, "module", None)
        if not isinstance(policy, ChunkPolicy):
            raise TypeError(
                f"{type(self).__name__} needs an L1FlowActor (a TensorDictModule around a ChunkPolicy), "
                f"got {type(actor_network).__name__}"
            )
        if policy.sampler.prediction != self.prediction:
            raise ValueError(
                f"{type(self).__name__} trains a network that predicts {self.prediction!r}, but the actor's "
                f"sampler {policy.sampler!r} expects {policy.sampler.prediction!r}; build the actor with "
                f"{self.sampler_hint}"
            )
        self.convert_to_functional(actor_network, "actor_network")
        self.reduction = reduction
        self.mask_padding = mask_padding

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # No value estimator (a behaviour-cloning loss); set_keys lands here, so drop cached key lists.
        self._in_keys = None
        self._out_keys = None

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            keys = self.tensor_keys
            self._in_keys = [keys.observation, keys.action_chunk, keys.action_is_pad]
        return self._in_keys

    @in_keys.setter
    def in_keys(self, value: list[NestedKey]) -> None:
        self._in_keys = value

    @property
    def out_keys(self) -> list[NestedKey]:
        if self._out_keys is None:
            self._out_keys = [self.loss_name, *self.diagnostic_keys]
        return self._out_keys

    @out_keys.setter
    def out_keys(self, value: list[NestedKey]) -> None:
        self._out_keys = value

    diagnostic_keys: tuple[str, ...] = ()

    @property
    def policy(self) -> ChunkPolicy:
        return self.actor_network.module  # type: ignore[return-value]

    # -- input handling -----------------------------------------------------------------------
    def _get(self, td: TensorDictBase, key: NestedKey, what: str):
        return required_entry(td, key, what, type(self).__name__)

    def _read_batch(self, td: TensorDictBase) -> tuple[TensorDictBase, Tensor, Tensor | None, torch.Size]:
        """Validated (flat observation TD [N, To], normalised chunk [N, H, A], valid mask [N, H] or None)."""
        policy, keys = self.policy, self.tensor_keys
        H, A = policy.pred_horizon, policy.action_dim
        action = self._get(td, keys.action_chunk, f"the demonstrated chunk, [*B, {H}, {A}]")
        if action.dim() < 2 or tuple(action.shape[-2:]) != (H, A):
            raise ValueError(
                f"{keys.action_chunk!r} must have shape [*B, {H}, {A}] (pred_horizon, action_dim), "
                f"got {tuple(action.shape)}"
            )
        if value_checks_enabled() and not torch.isfinite(action).all():
            bad = (~torch.isfinite(action)).reshape(-1, H * A).any(-1).nonzero()[:5, 0].tolist()
            raise ValueError(f"{keys.action_chunk!r} contains NaN or Inf (flat batch rows {bad})")
        batch = action.shape[:-2]
        observation = self._get(
            td, keys.observation, f"the observation history, [*B, {policy.obs_horizon}, ...]"
        )
        obs = policy.as_obs_dict(observation, key=str(keys.observation))
        obs_batch = policy.batch_dims(observation)
        if tuple(obs_batch) != tuple(batch):
            raise ValueError(
                f"{keys.observation!r} has batch dims {list(obs_batch)} but {keys.action_chunk!r} has "
                f"{list(batch)}; expected [*B, {policy.obs_horizon}, ...] and [*B, {H}, {A}] with the same *B"
            )
        n = obs.shape[0]
        valid = None
        is_pad = td.get(keys.action_is_pad, default=None)
        if is_pad is not None:
            if tuple(is_pad.shape) != (*batch, H):
                raise ValueError(
                    f"{keys.action_is_pad!r} must have shape {[*batch, H]}, got {tuple(is_pad.shape)}"
                )
            if self.mask_padding:
                valid = ~is_pad.reshape(n, H).bool()
        x1 = policy.action_normalizer.normalize(action.reshape(n, H, A).to(policy.dtype))
        return obs, x1, valid, batch

    # -- the loss ------------------------------------------------------------------------------
    @abc.abstractmethod
    def _elementwise_loss(
        self, cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Element-wise loss [N, H, A] for normalised chunks ``x1`` and diagnostics.

        ``valid`` ([N, H] bool or None) is only for diagnostics; :meth:`forward` masks the loss.
        """

    @staticmethod
    def _valid_mean(value: Tensor, valid: Tensor | None) -> Tensor:
        """Mean of ``value`` [N, H, A] over the valid chunk steps (all steps when ``valid`` is None)."""
        if valid is None:
            return value.mean()
        mask = valid.unsqueeze(-1).expand_as(value)
        return torch.where(mask, value, torch.zeros_like(value)).sum() / mask.sum().clamp_min(1)

    def _chunk_loss(
        self, obs: TensorDictBase, cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """The element-wise loss with the flat observation at hand too (a teacher encodes it itself)."""
        return self._elementwise_loss(cond, x1, valid)

    # -- what a loss trains and keeps beyond the actor (distillation: a score network, a target) --
    #: the learning rate of :meth:`extra_parameters` as a multiple of the actor's
    extra_lr_scale: float = 1.0

    def extra_parameters(self) -> list[torch.nn.Parameter]:
        """Parameters the optimiser trains beside the actor's (none for behaviour cloning), at
        ``extra_lr_scale`` times the actor's learning rate."""
        return []

    def training_state(self) -> dict[str, Tensor]:
        """What a resumed run needs of this loss beyond the actor and the optimiser (tensors only)."""
        return {}

    def load_training_state(self, state: dict[str, Tensor]) -> None:
        """Restore :meth:`training_state`."""

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        obs, x1, valid, batch = self._read_batch(tensordict)
        with self.actor_network_params.to_module(self.actor_network):
            cond = self.policy.encode(obs)
            err, diagnostics = self._chunk_loss(obs, cond, x1, valid)
        mask = None if valid is None else valid.unsqueeze(-1).expand_as(err)
        if self.reduction == "none":
            loss = err if mask is None else torch.where(mask, err, torch.zeros_like(err))
            loss = loss.reshape(*batch, *err.shape[1:])
        else:
            loss = self._reduce_loss(err, mask=mask)
        out = {self.loss_name: loss}
        out.update({k: v.detach() for k, v in diagnostics.items()})
        return TensorDict(out, batch_size=[])
