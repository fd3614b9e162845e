"""Flow Q-learning on action chunks (FQL / QC-FQL) for L1 Flow policies.

The critic is an ensemble of Q(s, a_{t:t+h}) networks on executed action chunks, trained towards the
chunked TD target ``R_h + gamma^h * (1 - terminated) * Qbar(s_{t+h}, a')`` with ``R_h`` the
discounted chunk return and ``a'`` the actor's chunk at ``s_{t+h}``; chunks that cross an episode's
end (``chunk_valid`` False) drop out of the critic loss. The actor objective has two modes:

* ``"distill"`` (FQL): a one-step policy mu(s, z) maximises Q while staying close, with weight
  ``alpha``, to the L1 Flow policy's 2-NFE chunk from the same noise z (clipped to the action range).
  The L1 Flow teacher is frozen (``train_teacher=False``: no gradient reaches it) or co-trained with
  its BC loss (the distillation target is always detached).
* ``"direct"``: the L1 Flow policy itself is the actor; Q's gradient flows back through both of its
  network evaluations, and ``alpha`` weighs its L1 Flow BC loss on the batch.
* ``"best_of_n"`` (Q-chunking's QC): the L1 Flow policy stays as trained (no actor loss); the deployed
  actor executes the best of ``num_samples`` of its chunks under the critic
  (:class:`~l1flow_rl.networks.best_of_n.BestOfNActor`), and the TD target backs up that choice:
  the max over N drawn next chunks of the target critics' value (``backup="max"``), or the mean
  over the draws (``backup="mean"``: the value of the policy as it samples, a SARSA-like critic that
  the selection then improves on once, as in one-step offline RL), or the policy network's one-step
  chunk (``backup="one_step"``: a chunk valued as if the policy's averaged behaviour followed it).

``normalize_q_loss`` scales the Q term by ``lambda = 1 / mean|Q|`` (no gradient through lambda),
as FQL does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey, unravel_key
from torch import Tensor
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators, _vmap_func, dispatch_value_estimator
from torchrl.objectives.value import ValueEstimatorBase

from l1flow_rl.flow.samplers import ChunkSampler, make_sampler
from l1flow_rl.networks.one_step import ONE_STEP_SAMPLER
from l1flow_rl.objectives.chunk_loss import required_entry
from l1flow_rl.objectives.l1flow import L1FlowLoss
from l1flow_rl.policy import ChunkPolicy

__all__ = ["FlowQLoss"]

_MODES = ("distill", "direct", "best_of_n")
_BACKUPS = ("max", "mean", "one_step")
#: the backup's one-step sampler: the sample-prediction network read once, at t = 0 (FQL's mu)
_ONE_STEP = make_sampler(ONE_STEP_SAMPLER[0], **ONE_STEP_SAMPLER[1])


def _chunk_policy(module: TensorDictModule, what: str) -> ChunkPolicy:
    policy = getattr(module, "module", None)
    if not isinstance(policy, ChunkPolicy):
        raise TypeError(
            f"FlowQLoss: {what} must be an L1FlowActor (a TensorDictModule around a ChunkPolicy), "
            f"got {type(module).__name__}"
        )
    if policy.sampler.prediction != "sample":
        raise ValueError(
            f"FlowQLoss: {what}'s sampler {policy.sampler!r} reads a {policy.sampler.prediction!r}-"
            "prediction network; flow Q-learning here fine-tunes sample-prediction (L1 Flow) networks"
        )
    return policy


class FlowQLoss(LossModule):
    """Chunked flow Q-learning: separate :meth:`qvalue_loss` and :meth:`actor_loss` (the TD3+BC pattern).

    Args:
        actor_network: the fine-tuned actor, an :class:`~l1flow_rl.L1FlowActor`. In ``"distill"`` mode
            the one-step policy mu(s, z) (see :func:`~l1flow_rl.networks.one_step.make_one_step_actor`);
            in ``"direct"`` mode the L1 Flow actor itself.
        qvalue_network: a critic TensorDictModule reading (observation, executed chunk [*B, h, A] in
            environment units) from its two in_keys and writing Q [*B, 1] to ``state_action_value``
            (see :func:`~l1flow_rl.networks.critic.chunk_critic_module`), or a list of
            ``num_qvalue_nets`` of them (independently initialised; preferred).

    Keyword Args:
        teacher_network: ``"distill"`` mode only: the L1 Flow actor whose 2-NFE chunks mu distils.
        mode: ``"distill"`` (FQL, default), ``"direct"`` or ``"best_of_n"`` (QC).
        num_qvalue_nets: critics in the ensemble (2).
        alpha: ``"distill"``: weight of the distillation loss (FQL uses 3-1000 by task family, QC-FQL
            100); ``"direct"``: weight of the BC loss.
        train_teacher: ``"distill"``: co-train the teacher with its BC loss (else it is frozen).
        normalize_q_loss: scale the Q term by ``1 / mean|Q|`` (stop-gradient).
        q_agg: ``"mean"`` or ``"min"`` over the ensemble's target values.
        gamma: per-step discount; the target uses ``gamma ** h`` (TorchRL's ``steps_to_next_obs``).
            The chunk returns in the data must be discounted with the same gamma.
        rl_horizon: h, executed actions per chunk (default: the actor's ``action_steps``).
        num_samples: ``"best_of_n"``: N, chunks drawn per decision and by default per TD target
            (QC: 32).
        backup: how the TD target values the next state from its drawn chunks: ``"max"`` (QC's
            expected-max backup; with one draw, the actor's own chunk), ``"mean"`` (the expected
            value of the actor's draws: Q of the policy as it samples, no maximisation bias) or
            ``"one_step"`` (the mean value of the actor network's one-step chunks f(z, 0 | s'), its
            estimate of the chunk from pure noise, which lies near the mean of its chunks: on noisy
            demonstrations, the value of a chunk followed by the policy with the noise averaged out).
        backup_samples: chunks drawn per TD target (default: ``num_samples`` in ``"best_of_n"``
            mode with the ``"max"`` or ``"mean"`` backup, 1 otherwise).
        critic_input: what the critics read besides the observation: ``"action"`` (the executed
            chunk) or ``"residual"`` (``"best_of_n"`` only: the chunk minus the frozen policy's own
            chunk from zero noise at that state). Both can represent any Q; the residual removes
            the part of the action that the state predicts, so that on single-policy data the
            critic's action ranking rests on the demonstrated deviations (e.g. injected noise)
            instead of on actions that merely co-occur with good states.
        clip_actions: clip the actor's and the teacher's chunks to ``action_bounds``.
        action_bounds: (low, high) in environment units; None clips to the normalised [-1, 1], i.e.
            the demonstrated action range under the default ``"limits"`` normaliser.
        bc_loss_kwargs: options of the :class:`~l1flow_rl.L1FlowLoss` used as the BC term
            (``timesteps``, ``loss_type``, ``loss_space``).
        mask_padding: leave padded chunk steps out of the BC loss (as :class:`~l1flow_rl.L1FlowLoss`).
        reduction: ``"mean"``, ``"sum"`` or ``"none"`` (per-sample losses [*B]; invalid chunks are 0 in
            the critic loss).

    The input TensorDict holds, besides ``"observation"`` [*B, To, ...], ``"action_chunk"`` [*B, H, A]
    and optional ``"action_is_pad"`` [*B, H]: ``("next", "reward")`` [*B, 1] (the discounted chunk
    return), ``("next", "done")``/``("next", "terminated")`` [*B, 1], ``("next", "observation")``
    (the observation history h steps later) and ``"chunk_valid"`` [*B, 1] (absent: every chunk is
    valid). The executed chunk is ``action_chunk[..., To-1 : To-1+h, :]``.

    Returns ``"loss_actor"``, ``"loss_qvalue"`` and detached diagnostics: ``"q_mean"`` (Q of the
    actor's chunks), ``"q_data_mean"`` (Q of the batch's chunks), ``"target_mean"``, ``"bc_loss"``,
    ``"distill_loss"`` (mean squared distance to the teacher's chunk; ``"direct"``: NaN), ``"lambda"``
    and ``"valid_fraction"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.objectives import SoftUpdate
        >>> from l1flow_rl import FlowQLoss, L1FlowActor
        >>> from l1flow_rl.networks.critic import ChunkCritic, chunk_critic_module
        >>> from l1flow_rl.networks.one_step import make_one_step_actor
        >>> teacher = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
        >>> critics = [
        ...     chunk_critic_module(ChunkCritic.from_policy(teacher, action_horizon=8, hidden_dims=(32,)))
        ...     for _ in range(2)
        ... ]
        >>> loss_fn = FlowQLoss(make_one_step_actor(teacher), critics, teacher_network=teacher, alpha=10.0)
        >>> target_update = SoftUpdate(loss_fn, tau=0.005)
        >>> B = 4
        >>> td = TensorDict({"observation": torch.randn(B, 2, 5),
        ...                  "action_chunk": torch.rand(B, 16, 2) * 2 - 1,
        ...                  "chunk_valid": torch.ones(B, 1, dtype=torch.bool),
        ...                  "next": {"observation": torch.randn(B, 2, 5), "reward": torch.rand(B, 1),
        ...                           "done": torch.zeros(B, 1, dtype=torch.bool),
        ...                           "terminated": torch.zeros(B, 1, dtype=torch.bool)}}, batch_size=[B])
        >>> out = loss_fn(td)
        >>> (out["loss_actor"] + out["loss_qvalue"]).backward()
        >>> target_update.step()
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_qvalue']
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            observation (NestedKey): observation history [*B, To, ...]. Defaults to ``"observation"``.
            action_chunk (NestedKey): the stored chunk [*B, H, A] in environment units; its steps
                [To-1, To-1+h) are the executed ones. Defaults to ``"action_chunk"``.
            action_is_pad (NestedKey): optional [*B, H] padding flags (BC loss).
                Defaults to ``"action_is_pad"``.
            reward (NestedKey): read as ``("next", reward)``, the discounted chunk return [*B, 1].
                Defaults to ``"reward"``.
            done (NestedKey): read as ``("next", done)``. Defaults to ``"done"``.
            terminated (NestedKey): read as ``("next", terminated)``; no bootstrap where True.
                Defaults to ``"terminated"``.
            next_observation (NestedKey): the observation history h steps later.
                Defaults to ``("next", "observation")``.
            chunk_valid (NestedKey): [*B, 1] bool, False for chunks that run past their episode's
                end (left out of the critic loss). Defaults to ``"chunk_valid"``.
            state_action_value (NestedKey): the critic's output key. Defaults to ``"state_action_value"``.
            steps_to_next_obs (NestedKey): steps between the observation and the next one (the
                discount exponent); absent, it is h. Defaults to ``"steps_to_next_obs"``.
        """

        observation: NestedKey = "observation"
        action_chunk: NestedKey = "action_chunk"
        action_is_pad: NestedKey = "action_is_pad"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        next_observation: NestedKey = ("next", "observation")
        chunk_valid: NestedKey = "chunk_valid"
        state_action_value: NestedKey = "state_action_value"
        steps_to_next_obs: NestedKey = "steps_to_next_obs"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    diagnostic_keys = (
        "q_mean",
        "q_data_mean",
        "target_mean",
        "bc_loss",
        "distill_loss",
        "lambda",
        "valid_fraction",
    )

    actor_network: TensorDictModule
    actor_network_params: TensorDictBase
    target_actor_network_params: TensorDictBase
    qvalue_network: TensorDictModule
    qvalue_network_params: TensorDictBase
    target_qvalue_network_params: TensorDictBase
    teacher_network: TensorDictModule
    teacher_network_params: TensorDictBase
    target_teacher_network_params: TensorDictBase

    def __init__(
        self,
        actor_network: TensorDictModule,
        qvalue_network: TensorDictModule | list[TensorDictModule],
        *,
        teacher_network: TensorDictModule | None = None,
        mode: str = "distill",
        num_qvalue_nets: int = 2,
        alpha: float = 100.0,
        train_teacher: bool = False,
        normalize_q_loss: bool = True,
        q_agg: str = "mean",
        gamma: float = 0.99,
        rl_horizon: int | None = None,
        num_samples: int = 32,
        backup: str = "max",
        backup_samples: int | None = None,
        critic_input: str = "action",
        clip_actions: bool = True,
        action_bounds: tuple[Tensor, Tensor] | None = None,
        bc_loss_kwargs: dict | None = None,
        mask_padding: bool = False,
        reduction: str = "mean",
    ) -> None:
        if mode not in _MODES:
            raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
        if q_agg not in ("mean", "min"):
            raise ValueError(f"q_agg must be 'mean' or 'min', got {q_agg!r}")
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must lie in [0, 1], got {gamma}")
        if alpha < 0:
            raise ValueError(f"alpha must be >= 0, got {alpha}")
        if isinstance(qvalue_network, (list, tuple)) and len(qvalue_network) != num_qvalue_nets:
            raise ValueError(
                f"got {len(qvalue_network)} critics but num_qvalue_nets={num_qvalue_nets}; pass as many "
                "critics as the ensemble has members, or one to be copied"
            )
        self._in_keys = None
        super().__init__()
        policy = _chunk_policy(actor_network, "actor_network")
        if mode == "distill":
            if teacher_network is None:
                raise ValueError("mode='distill' needs teacher_network (the L1 Flow actor that mu distils)")
            teacher = _chunk_policy(teacher_network, "teacher_network")
            for attr in ("action_dim", "obs_horizon", "pred_horizon", "action_steps"):
                if getattr(teacher, attr) != getattr(policy, attr):
                    raise ValueError(
                        f"teacher_network.{attr}={getattr(teacher, attr)} differs from actor_network's "
                        f"{getattr(policy, attr)}"
                    )
            shared = {id(p) for p in actor_network.parameters()} & {
                id(p) for p in teacher_network.parameters()
            }
            if shared:
                raise ValueError(
                    "actor_network and teacher_network share parameters; build the one-step actor as a "
                    "copy (make_one_step_actor(teacher))"
                )
        elif teacher_network is not None:
            raise ValueError(f"mode={mode!r} uses the L1 Flow actor itself; teacher_network must be None")
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if backup not in _BACKUPS:
            raise ValueError(f"backup must be one of {_BACKUPS}, got {backup!r}")
        if backup_samples is None:
            backup_samples = num_samples if mode == "best_of_n" and backup != "one_step" else 1
        if backup_samples < 1:
            raise ValueError(f"backup_samples must be >= 1, got {backup_samples}")
        if critic_input not in ("action", "residual"):
            raise ValueError(f"critic_input must be 'action' or 'residual', got {critic_input!r}")
        if critic_input == "residual" and mode != "best_of_n":
            raise ValueError(
                f"critic_input='residual' needs mode='best_of_n' (a frozen policy to subtract); "
                f"mode={mode!r} trains the actor, which would move the critics' input under them"
            )
        if mode == "best_of_n":
            actor_network.requires_grad_(False)  # selected from, never trained
        if train_teacher and mode != "distill":
            raise ValueError("train_teacher applies to mode='distill' only")

        h = policy.action_steps if rl_horizon is None else int(rl_horizon)
        if not 1 <= h <= policy.pred_horizon - policy.obs_horizon + 1:
            raise ValueError(
                f"rl_horizon={h} must lie in [1, pred_horizon - obs_horizon + 1 = "
                f"{policy.pred_horizon - policy.obs_horizon + 1}]: the executed chunk is "
                "action_chunk[To-1 : To-1+h]"
            )
        self.mode, self.alpha, self.train_teacher = mode, float(alpha), bool(train_teacher)
        self.normalize_q_loss, self.q_agg, self.rl_horizon = normalize_q_loss, q_agg, h
        self.num_qvalue_nets, self.clip_actions, self.reduction = num_qvalue_nets, clip_actions, reduction
        self.mask_padding, self.num_samples = mask_padding, int(num_samples)
        self.backup, self.backup_samples = backup, int(backup_samples)
        self.critic_input = critic_input

        self.convert_to_functional(actor_network, "actor_network")
        self.convert_to_functional(
            qvalue_network, "qvalue_network", num_qvalue_nets, create_target_params=True
        )
        bc_network = actor_network
        if mode == "distill":
            if not train_teacher:
                teacher_network.requires_grad_(False)
            self.convert_to_functional(teacher_network, "teacher_network")
            bc_network = teacher_network
        # The BC term is the L1 Flow loss itself (same options as the BC training), on the same
        # parameters: a child loss module that registers no new tensors.
        self.bc_loss_module = L1FlowLoss(
            bc_network, reduction="none", mask_padding=mask_padding, **(bc_loss_kwargs or {})
        )
        if action_bounds is not None:
            low, high = (torch.as_tensor(b, dtype=torch.float32) for b in action_bounds)
            if low.shape != (policy.action_dim,) or high.shape != (policy.action_dim,) or (low > high).any():
                raise ValueError(
                    f"action_bounds must be two [{policy.action_dim}] tensors with low <= high, got "
                    f"{tuple(low.shape)} and {tuple(high.shape)}"
                )
            self.register_buffer("action_low", low)
            self.register_buffer("action_high", high)
        else:
            self.action_low = self.action_high = None
        self._vmap_qvalue = _vmap_func(self.qvalue_network, randomness=self.vmap_randomness)
        self.make_value_estimator(gamma=gamma)

    # -- keys ------------------------------------------------------------------------------------
    def _forward_value_estimator_keys(self, **kwargs) -> None:
        keys = self.tensor_keys
        if self._value_estimator is not None:
            self._value_estimator.set_keys(
                value=keys.state_action_value,
                reward=keys.reward,
                done=keys.done,
                terminated=keys.terminated,
                steps_to_next_obs=keys.steps_to_next_obs,
            )
        if getattr(self, "bc_loss_module", None) is not None:
            self.bc_loss_module.set_keys(
                observation=keys.observation, action_chunk=keys.action_chunk, action_is_pad=keys.action_is_pad
            )
        self._in_keys = None

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            k = self.tensor_keys
            self._in_keys = [
                k.observation,
                k.action_chunk,
                k.action_is_pad,
                unravel_key(("next", k.reward)),
                unravel_key(("next", k.done)),
                unravel_key(("next", k.terminated)),
                k.next_observation,
                k.chunk_valid,
            ]
        return self._in_keys

    @in_keys.setter
    def in_keys(self, value: list[NestedKey]) -> None:
        self._in_keys = value

    @property
    def out_keys(self) -> list[str]:
        return ["loss_actor", "loss_qvalue", *self.diagnostic_keys]

    @out_keys.setter
    def out_keys(self, value) -> None:
        raise AttributeError("FlowQLoss.out_keys are fixed")

    # -- value estimator ----------------------------------------------------------------------------
    def make_value_estimator(self, value_type: ValueEstimators | None = None, **hyperparams) -> None:
        """The chunk TD target: TorchRL's TD(0) estimator with ``gamma ** steps_to_next_obs`` (= h)."""
        if value_type is None:
            value_type = self.default_value_estimator
        if isinstance(value_type, ValueEstimatorBase) or (
            isinstance(value_type, type) and issubclass(value_type, ValueEstimatorBase)
        ):
            return LossModule.make_value_estimator(self, value_type, **hyperparams)
        k = self.tensor_keys
        dispatch_value_estimator(
            self,
            value_type,
            supported=(ValueEstimators.TD0,),
            tensor_keys={
                "value": k.state_action_value,
                "reward": k.reward,
                "done": k.done,
                "terminated": k.terminated,
                "steps_to_next_obs": k.steps_to_next_obs,
            },
            value_network=None,
            **hyperparams,
        )

    # -- helpers -----------------------------------------------------------------------------------
    @property
    def policy(self) -> ChunkPolicy:
        return self.actor_network.module  # type: ignore[return-value]

    def _get(self, td: TensorDictBase, key: NestedKey, what: str):
        return required_entry(td, key, what, "FlowQLoss")

    def _flag(self, td: TensorDictBase, key: NestedKey, batch: tuple[int, ...], what: str) -> Tensor:
        value = self._get(td, key, what)
        if tuple(value.shape) != (*batch, 1):
            raise ValueError(f"{key!r} must have shape {[*batch, 1]} ({what}), got {tuple(value.shape)}")
        return value.reshape(-1, 1)

    def _valid(self, td: TensorDictBase, batch: tuple[int, ...], device: torch.device) -> Tensor:
        """``chunk_valid`` flattened to [N] (absent: every chunk is valid)."""
        key = self.tensor_keys.chunk_valid
        if td.get(key, default=None) is None:
            return torch.ones(math.prod(batch), dtype=torch.bool, device=device)
        return self._flag(td, key, batch, "chunk validity").reshape(-1).bool()

    def _clip(self, x: Tensor, policy: ChunkPolicy) -> Tensor:
        """Clip a normalised chunk to the action range (identity when ``clip_actions`` is off)."""
        if not self.clip_actions:
            return x
        if self.action_low is None:
            return x.clamp(-1.0, 1.0)
        norm = policy.action_normalizer
        low, high = norm.normalize(self.action_low), norm.normalize(self.action_high)
        return torch.maximum(torch.minimum(x, torch.maximum(low, high)), torch.minimum(low, high))

    def _executed(self, chunk: Tensor) -> Tensor:
        start = self.policy.obs_horizon - 1
        return chunk[:, start : start + self.rl_horizon]

    def _sample(
        self, policy: ChunkPolicy, obs: TensorDictBase, noise: Tensor, sampler: ChunkSampler | None = None
    ) -> Tensor:
        """The normalised chunk [N, H, A] from ``noise`` under ``sampler`` (default: the policy's own);
        every network evaluation is in the graph."""
        cond = policy.encode(obs)
        return (sampler or policy.sampler)(lambda x, t: policy.denoise(x, t, cond), noise)

    @torch.no_grad()
    def reference_chunk(self, obs: TensorDictBase) -> Tensor:
        """The frozen policy's executed chunk [N, h, A] from zero noise (environment units): what
        ``critic_input="residual"`` subtracts."""
        with self.actor_network_params.to_module(self.actor_network):
            return self.policy(obs, deterministic=True)[:, : self.rl_horizon]

    def _q(
        self,
        obs: TensorDictBase,
        chunk_env: Tensor,
        params: TensorDictBase,
        reference: Tensor | None = None,
    ) -> Tensor:
        """Ensemble values [Q, N, 1] of executed chunks in environment units (``reference``: the
        residual critics' :meth:`reference_chunk` of ``obs``, when already computed)."""
        if self.critic_input == "residual":
            chunk_env = chunk_env - (self.reference_chunk(obs) if reference is None else reference)
        net = self.qvalue_network
        td = TensorDict({}, batch_size=[chunk_env.shape[0]])
        td.set(net.in_keys[0], obs)
        td.set(net.in_keys[1], chunk_env)
        out = self._vmap_qvalue(td.expand(self.num_qvalue_nets, *td.batch_size), params)
        return out.get(net.out_keys[0])

    def _read(self, td: TensorDictBase) -> tuple[TensorDictBase, Tensor, tuple[int, ...]]:
        """(flattened validated observation [N, To], stored chunk [N, H, A] in env units, batch dims)."""
        policy, keys = self.policy, self.tensor_keys
        H, A = policy.pred_horizon, policy.action_dim
        chunk = self._get(td, keys.action_chunk, f"the stored chunk, [*B, {H}, {A}]")
        if chunk.dim() < 2 or tuple(chunk.shape[-2:]) != (H, A):
            raise ValueError(
                f"{keys.action_chunk!r} must have shape [*B, {H}, {A}], got {tuple(chunk.shape)}"
            )
        batch = tuple(chunk.shape[:-2])
        observation = self._get(
            td, keys.observation, f"the observation history, [*B, {policy.obs_horizon}, ...]"
        )
        if tuple(policy.batch_dims(observation)) != batch:
            raise ValueError(
                f"{keys.observation!r} has batch dims {list(policy.batch_dims(observation))} but "
                f"{keys.action_chunk!r} has {list(batch)}"
            )
        obs = policy.as_obs_dict(observation, key=str(keys.observation))
        return obs, chunk.reshape(-1, H, A).to(policy.dtype), batch

    def _reduce(self, per_sample: Tensor, batch: tuple[int, ...], valid: Tensor | None = None) -> Tensor:
        if self.reduction == "none":
            out = (
                per_sample if valid is None else torch.where(valid, per_sample, torch.zeros_like(per_sample))
            )
            return out.reshape(batch)
        if valid is None:
            return per_sample.mean() if self.reduction == "mean" else per_sample.sum()
        masked = torch.where(valid, per_sample, torch.zeros_like(per_sample)).sum()
        return masked / valid.sum().clamp_min(1) if self.reduction == "mean" else masked

    # -- losses ------------------------------------------------------------------------------------
    def qvalue_loss(self, tensordict: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """Critic loss: squared TD error of every ensemble member (summed), over valid chunks."""
        keys, policy = self.tensor_keys, self.policy
        obs, chunk, batch = self._read(tensordict)
        n = obs.shape[0]
        next_obs = policy.as_obs_dict(
            self._get(tensordict, keys.next_observation, "the observation history h steps later"),
            key=str(keys.next_observation),
        )
        if next_obs.shape[0] != n:
            raise ValueError(f"{keys.next_observation!r} has {next_obs.shape[0]} rows, expected {n}")
        valid = self._valid(tensordict, batch, chunk.device)
        reward = self._flag(
            tensordict, unravel_key(("next", keys.reward)), batch, "the discounted chunk return"
        )
        done = self._flag(tensordict, unravel_key(("next", keys.done)), batch, "done").bool()
        terminated_key = unravel_key(("next", keys.terminated))
        terminated = (
            done
            if tensordict.get(terminated_key, default=None) is None
            else self._flag(tensordict, terminated_key, batch, "terminated").bool()
        )
        with torch.no_grad():
            # the next state's value over `draws` drawn chunks (their max or mean); draw 0 uses the
            # noise a single draw would
            draws = self.backup_samples
            drawn_obs = torch.cat([next_obs] * draws) if draws > 1 else next_obs
            with self.actor_network_params.to_module(self.actor_network):
                noise = torch.randn(
                    draws * n, policy.pred_horizon, policy.action_dim, dtype=chunk.dtype, device=chunk.device
                )
                sampler = _ONE_STEP if self.backup == "one_step" else None
                next_x = self._clip(self._sample(policy, drawn_obs, noise, sampler), policy)
            next_chunk = policy.action_normalizer.unnormalize(self._executed(next_x))
            reference = None
            if self.critic_input == "residual":  # once per state, not once per draw
                reference = torch.cat([self.reference_chunk(next_obs)] * draws)
            next_q = self._q(drawn_obs, next_chunk, self.target_qvalue_network_params, reference)
            next_value = next_q.min(0).values if self.q_agg == "min" else next_q.mean(0)
            next_value = next_value.reshape(draws, n, 1)
            next_value = next_value.max(0).values if self.backup == "max" else next_value.mean(0)
            steps = tensordict.get(keys.steps_to_next_obs, default=None)
            steps = (
                torch.full((n, 1), self.rl_horizon, dtype=reward.dtype, device=reward.device)
                if steps is None
                else steps.reshape(n, 1).to(reward.dtype)
            )
            target_td = TensorDict({}, batch_size=[n])
            target_td.set(keys.steps_to_next_obs, steps)
            target_td.set(unravel_key(("next", keys.reward)), reward.to(next_value.dtype))
            target_td.set(unravel_key(("next", keys.done)), done)
            target_td.set(unravel_key(("next", keys.terminated)), terminated)
            target_td.set(unravel_key(("next", keys.state_action_value)), next_value)
            target = self.value_estimator.value_estimate(target_td)  # [N, 1]
        return self._fit(obs, chunk, batch, valid, target)

    def qvalue_regression_loss(
        self, tensordict: TensorDictBase, target: Tensor
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Critic loss against given values ``target`` [*B, 1] (e.g. Monte-Carlo returns): squared
        error of every ensemble member on the batch's chunks (summed), over valid chunks. No actor
        call and no target critic: a cheap way to give the critics the data's values before TD."""
        obs, chunk, batch = self._read(tensordict)
        n = obs.shape[0]
        if tuple(target.shape) != (*batch, 1):
            raise ValueError(f"target must have shape {[*batch, 1]}, got {tuple(target.shape)}")
        valid = self._valid(tensordict, batch, chunk.device)
        return self._fit(obs, chunk, batch, valid, target.reshape(n, 1).to(chunk.dtype).detach())

    def _fit(
        self, obs: TensorDictBase, chunk: Tensor, batch: tuple[int, ...], valid: Tensor, target: Tensor
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Squared error of every critic's Q(s, executed chunk) against ``target`` [N, 1] (summed over
        the ensemble), reduced over the valid chunks, with the critic diagnostics."""
        n = obs.shape[0]
        q = self._q(obs, self._executed(chunk), self.qvalue_network_params)  # [Q, N, 1]
        loss = self._reduce((q - target.unsqueeze(0)).square().sum(0).reshape(n), batch, valid)
        w = valid.to(q.dtype)
        diagnostics = {
            "q_data_mean": (q.mean(0).reshape(n) * w).sum() / w.sum().clamp_min(1),
            "target_mean": (target.reshape(n) * w).sum() / w.sum().clamp_min(1),
            "valid_fraction": w.mean(),
        }
        return loss, {k: v.detach() for k, v in diagnostics.items()}

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """Actor loss: ``-lambda * Q(s, actor chunk)`` plus the BC / distillation regulariser
        (``"best_of_n"``: 0, nothing to train; the diagnostics describe one draw of the policy)."""
        if self.mode == "best_of_n":
            with torch.no_grad():
                _, meta = self._actor_terms(tensordict)
            zero = torch.zeros((), device=meta["q_mean"].device)
            return zero, {**meta, "distill_loss": zero * float("nan"), "lambda": zero * float("nan")}
        return self._actor_terms(tensordict)

    def _actor_terms(self, tensordict: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        policy = self.policy
        obs, chunk, batch = self._read(tensordict)
        n = obs.shape[0]
        noise = torch.randn(n, policy.pred_horizon, policy.action_dim, dtype=chunk.dtype, device=chunk.device)
        with self.actor_network_params.to_module(self.actor_network):
            x = self._sample(policy, obs, noise)
        # the BC term needs gradients only where it is trained; elsewhere it is a diagnostic
        bc_grad = (self.mode == "direct" and self.alpha > 0) or self.train_teacher
        with torch.set_grad_enabled(bc_grad and torch.is_grad_enabled()):
            bc_per_sample = self._bc_per_sample(tensordict, n)
        distill = torch.full((n,), float("nan"), dtype=x.dtype, device=x.device)
        if self.mode == "distill":
            teacher = self.teacher_network.module
            with torch.no_grad(), self.teacher_network_params.to_module(self.teacher_network):
                target = self._clip(self._sample(teacher, obs, noise), teacher)
            distill = (x - target).square().reshape(n, -1).mean(-1)
        action = policy.action_normalizer.unnormalize(self._executed(self._clip(x, policy)))
        q = self._q(obs, action, self.qvalue_network_params.detach()).mean(0).reshape(n)
        lam = (
            1.0 / q.abs().mean().detach().clamp_min(1e-6)
            if self.normalize_q_loss
            else torch.ones((), device=q.device)
        )
        if self.mode == "distill":
            per_sample = self.alpha * distill - lam * q
            if self.train_teacher:
                per_sample = per_sample + bc_per_sample
        else:
            per_sample = self.alpha * bc_per_sample - lam * q
        loss = self._reduce(per_sample, batch)
        diagnostics = {
            "q_mean": q.mean(),
            "bc_loss": bc_per_sample.mean(),
            "distill_loss": distill.mean(),
            "lambda": lam,
        }
        return loss, {k: v.detach() for k, v in diagnostics.items()}

    def _bc_per_sample(self, tensordict: TensorDictBase, n: int) -> Tensor:
        """The L1 Flow loss per sample [N] (mean over the chunk's valid steps)."""
        bc = self.bc_loss_module
        err = bc(tensordict)[bc.loss_name].reshape(n, -1)  # [N, H*A]; masked steps are 0
        if not self.mask_padding:
            return err.mean(-1)
        is_pad = tensordict.get(self.tensor_keys.action_is_pad, default=None)
        if is_pad is None:
            return err.mean(-1)
        counts = (~is_pad.reshape(n, -1).bool()).sum(-1) * self.policy.action_dim
        return err.sum(-1) / counts.clamp_min(1)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        """Both losses and the diagnostics; the critic's is computed first (as in TD3+BC's order of use)."""
        loss_q, meta_q = self.qvalue_loss(tensordict)
        loss_actor, meta_actor = self.actor_loss(tensordict)
        return TensorDict(
            {"loss_actor": loss_actor, "loss_qvalue": loss_q, **meta_actor, **meta_q}, batch_size=[]
        )
