"""QC's actor: N chunks from the L1 Flow policy's 2-NFE sampler, the one the critics value most executed.

The flow is the behaviour-cloned policy (kept training by :class:`~l1flow_rl.QCLoss`'s BC term), so
every executed chunk is one the data make likely, and the critics only rank the flow's own samples.
N proposals cost two batched network evaluations. The proposals are clipped to the action range
before the critics value them (ColinQiyangLi/qc clips its samples before the pick): a critic ranks
the chunk that would be executed, never a value it extrapolates past the bounds.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor

from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.modules.normalizer import clip_actions
from l1flow_rl.modules.policy import ChunkPolicy, ExecutesChunks
from l1flow_rl.networks.critic import ChunkCritic
from l1flow_rl.utils.doc_examples import CRITIC, FLOW, add_example

__all__ = ["BestOfNActor"]


@add_example(
    FLOW,
    CRITIC,
    """\
>>> from torchrl.modules import MultiStepActorWrapper
>>> from l1flow_rl import BestOfNActor
>>> best = BestOfNActor(flow, critic, num_samples=16, rl_horizon=8)
>>> best(TensorDict({"observation": torch.randn(3, 2, 5)}, [3]))["action_chunk"].shape
torch.Size([3, 8, 2])
>>> acting = MultiStepActorWrapper(best, n_steps=8)
>>> is_init = torch.ones(3, 1, dtype=torch.bool)
>>> acting(TensorDict({"observation": torch.randn(3, 2, 5), "is_init": is_init}, [3]))["action"].shape
torch.Size([3, 2])
""",
)
class BestOfNActor(ExecutesChunks, TensorDictModuleBase):
    """Reads the observation history and writes the best of ``num_samples`` executable windows.

    Args:
        actor: the L1 Flow actor whose chunks are proposed.
        critic: the chunk critic that picks (its ensemble mean); pass the critic a
            :class:`~l1flow_rl.QCLoss` trains, whose parameters it shares, so picking follows training.
        num_samples: N proposals per observation (QC: 32).
        rl_horizon: h, the executed steps the critic reads (the first h of the window).

    Proposals always start from random noise: under a deterministic exploration type the N draws
    from zero noise would coincide.
    """

    def __init__(self, actor: L1FlowActor, critic: ChunkCritic, *, num_samples: int, rl_horizon: int) -> None:
        super().__init__()
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if not 1 <= rl_horizon <= actor.policy.action_steps:
            raise ValueError(
                f"rl_horizon={rl_horizon} must lie in [1, action_steps={actor.policy.action_steps}]"
            )
        if critic.input_shape != (rl_horizon, actor.policy.action_dim):
            raise ValueError(
                f"the critic values inputs of shape {list(critic.input_shape)}, but best-of-N proposes "
                f"executed chunks of shape {[rl_horizon, actor.policy.action_dim]}"
            )
        self.actor, self.critic = actor, critic
        self.num_samples, self.rl_horizon = int(num_samples), int(rl_horizon)
        self.in_keys: list[NestedKey] = list(actor.in_keys)
        self.out_keys: list[NestedKey] = list(actor.out_keys)

    @property
    def policy(self) -> ChunkPolicy:
        return self.actor.policy

    def propose(
        self, obs: TensorDictBase, num_samples: int | None = None, noise: Tensor | None = None
    ) -> Tensor:
        """N full chunks per read observation [B, To]: [B, N, H, A] in environment units, clipped to
        the action range (the encoder runs once per observation, the network twice per chunk).
        ``noise`` [B, N, H, A]: the sampler's starting noise (default: fresh standard-normal draws)."""
        policy, n = self.policy, int(num_samples or self.num_samples)
        cond = policy.encode(obs).repeat_interleave(n, 0)
        shape = (cond.shape[0], policy.pred_horizon, policy.action_dim)
        if noise is None:
            noise = torch.randn(shape, dtype=cond.dtype, device=cond.device)
        elif noise.shape != (obs.shape[0], n, *shape[1:]):
            raise ValueError(
                f"noise must have shape {[obs.shape[0], n, *shape[1:]]} (observations, proposals, "
                f"pred_horizon, action_dim), got {list(noise.shape)}"
            )
        x1 = policy.sampler(lambda x, t: policy.denoise(x, t, cond), noise.reshape(shape).to(cond))
        x1 = clip_actions(x1)
        return policy.action_normalizer.unnormalize(x1).reshape(obs.shape[0], n, *x1.shape[1:])

    def executed(self, chunks: Tensor) -> Tensor:
        """The critic's steps [..., h, A] of full chunks [..., H, A]."""
        start = self.policy.obs_horizon - 1
        return chunks[..., start : start + self.rl_horizon, :]

    def pick(self, obs: TensorDictBase, chunks: Tensor) -> Tensor:
        """Index [B] of the proposal [B, N, H, A] with the highest mean value under ``self.critic``."""
        return self.pick_executed(obs, self.executed(chunks))

    def pick_executed(self, obs: TensorDictBase, executed: Tensor) -> Tensor:
        """Index [B] of the proposal's executed steps [B, N, h, A] that ``self.critic`` values most."""
        b, n = executed.shape[:2]
        q = self.critic(obs.repeat_interleave(n, 0), executed.reshape(b * n, self.rl_horizon, -1)).mean(-1)
        return q.reshape(b, n).argmax(1)

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation = tensordict.get(self.in_keys[0], None)
        if observation is None:
            raise KeyError(f"{type(self).__name__} reads {self.in_keys[0]!r}, which the input lacks")
        batch = tuple(self.policy.batch_dims(observation))
        obs = self.policy.as_obs_dict(observation, key=str(self.in_keys[0]))
        chunks = self.propose(obs)
        chosen = chunks[torch.arange(chunks.shape[0]), self.pick(obs, chunks)]
        window = self.policy.executable(chosen)
        tensordict.set(self.out_keys[0], window.reshape(*batch, *window.shape[1:]))
        return tensordict
