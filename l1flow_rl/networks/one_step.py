"""The one-step policy mu(s, z) of flow Q-learning (FQL), built from an L1 Flow actor.

FQL trains a one-step network that maps noise z straight to an action, distilled from the multi-step
flow policy and pushed up the critic. L1 Flow's network already predicts the clean chunk from any
(x_t, t), so mu(s, z) = f(z, t=0 | s) is the same network read at t = 0: one Euler step of the
sample-prediction flow (``EulerSampler(1)``). That makes mu an ordinary :class:`~l1flow_rl.L1FlowActor`
(saved, loaded and evaluated like any other) and lets it start from the teacher's weights, where
f(z, 0 | s) is already the teacher's one-step estimate of the chunk.
"""

from __future__ import annotations

import copy

from l1flow_rl.actor import L1FlowActor
from l1flow_rl.flow.samplers import EulerSampler

__all__ = ["ONE_STEP_SAMPLER", "make_one_step_actor"]

#: How a one-step actor's config names its sampler (``make_sampler(name, **kwargs)``).
ONE_STEP_SAMPLER: tuple[str, dict[str, int]] = ("euler", {"steps": 1})


def make_one_step_actor(teacher: L1FlowActor, *, init: str = "teacher") -> L1FlowActor:
    """A new actor mu(s, z) = f_phi(z, 0 | s) with the teacher's architecture and normalisers.

    Args:
        teacher: an L1 Flow actor (sample prediction); it is not modified and shares no tensors
            with the result.
        init: ``"teacher"`` copies the teacher's weights (FQL trains mu from scratch; starting at
            the teacher's one-step estimate saves most of the distillation), ``"scratch"``
            re-initialises the network (the normalisers are kept).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from l1flow_rl import L1FlowActor
        >>> from l1flow_rl.networks.one_step import make_one_step_actor
        >>> teacher = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
        >>> mu = make_one_step_actor(teacher)
        >>> mu.sampler.nfe, mu(TensorDict({"observation": torch.randn(3, 2, 5)}, [3]))["action_chunk"].shape
        (1, torch.Size([3, 8, 2]))
    """
    if init not in ("teacher", "scratch"):
        raise ValueError(f"init must be 'teacher' or 'scratch', got {init!r}")
    if teacher.policy.sampler.prediction != "sample":
        raise ValueError(
            f"a one-step policy reads a sample-prediction network at t=0; the teacher's sampler "
            f"{teacher.policy.sampler!r} expects {teacher.policy.sampler.prediction!r} prediction"
        )
    actor = copy.deepcopy(teacher)
    actor.policy.sampler = EulerSampler(ONE_STEP_SAMPLER[1]["steps"])
    if init == "scratch":
        for module in actor.policy.net.modules():
            if hasattr(module, "reset_parameters"):
                module.reset_parameters()
    for p in actor.parameters():
        p.requires_grad_(True)
    return actor
