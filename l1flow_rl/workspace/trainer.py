"""One optimisation step, as Diffusion Policy trains: AdamW, warm-up + cosine LR, EMA, optional
gradient clipping, AMP and torch.compile, and DDP when launched under ``torchrun``.

A step never waits for the device: its metrics come back as tensors (read them when you log), the
EMA's decay is computed on the host, and with ``check_values=False`` the loss skips the NaN/Inf
checks that would read the batch back (for batches whose values the data loader already checked).
"""

from __future__ import annotations

import contextlib
import math
from typing import Any

import torch
import torch.distributed as dist
from tensordict import TensorDictBase
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel
from torchrl.objectives import LossModule

from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.modules.ema import make_ema
from l1flow_rl.utils.value_checks import skip_value_checks
from l1flow_rl.workspace.checkpoint import load_state_into

__all__ = ["Trainer", "warmup_cosine"]


def warmup_cosine(warmup_steps: int, total_steps: int):
    """LR multiplier: linear from 0 over ``warmup_steps``, then a half cosine to 0 at ``total_steps``."""

    def factor(step: int) -> float:
        if step < warmup_steps:
            return step / max(1, warmup_steps)
        progress = (step - warmup_steps) / max(1, total_steps - warmup_steps)
        return 0.5 * (1.0 + math.cos(math.pi * min(progress, 1.0)))

    return factor


class _SummedLoss(nn.Module):
    """Sum of a loss module's ``loss_*`` entries, plus each term (detached, so that a non-finite
    sum can be traced to its term) and the loss's diagnostics.

    DDP needs a module whose forward returns the tensors backward starts from; it cannot look
    inside a TensorDict, so this returns (scalar, dict).
    """

    def __init__(self, loss_fn: LossModule) -> None:
        super().__init__()
        self.loss_fn = loss_fn

    def forward(self, batch: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        out = self.loss_fn(batch)
        loss = sum(v for k, v in out.items() if k.startswith("loss_"))
        return loss, {k: v.detach() for k, v in out.items()}


class Trainer:
    """Owns the optimiser, scheduler and EMA for one actor and its loss.

    Args:
        actor: the trained actor; its normalisers must already be fitted (the EMA copies them).
        loss_fn: a loss built on ``actor``.
        total_steps: length of the cosine schedule.
        check_values: run the loss's NaN/Inf checks on each batch. They read values back from the
            device (a host synchronisation per check); turn them off for batches from a buffer of
            episodes the loader checked, as ``l1flow-rl train`` does.
    """

    def __init__(
        self,
        actor: L1FlowActor,
        loss_fn: LossModule,
        *,
        total_steps: int,
        lr: float = 1e-4,
        betas: tuple[float, float] = (0.95, 0.999),
        weight_decay: float = 1e-6,
        warmup_steps: int = 500,
        ema_power: float = 0.75,
        grad_clip: float = 0.0,
        amp: bool = False,
        compile: bool = False,
        check_values: bool = True,
    ) -> None:
        self.actor, self.loss_fn = actor, loss_fn
        self.grad_clip, self.amp, self.check_values = grad_clip, amp, check_values
        if compile:
            # In place (the state_dict keys stay the same), with static shapes: a second batch size
            # (evaluation's) then compiles its own kernels instead of dynamic-shape ones; on torch
            # 2.11 / H100 a dynamic GroupNorm-backward kernel failed with "misaligned address".
            actor.policy.net.compile(dynamic=False)
        params = [p for p in actor.parameters() if p.requires_grad]
        # A loss may train networks of its own beside the actor (OneDP-S's score network), at its own
        # multiple of the learning rate (a second parameter group only when that multiple is not 1).
        extra = [p for p in getattr(loss_fn, "extra_parameters", list)() if p.requires_grad]
        scale = float(getattr(loss_fn, "extra_lr_scale", 1.0))
        self._params = params + extra
        groups: list[Any] = params + extra
        if extra and scale != 1.0:
            groups = [{"params": params}, {"params": extra, "lr": lr * scale}]
        # The fused kernel (one launch for all parameters) where it is the fast path; elsewhere
        # torch's default, so CPU runs stay bit-for-bit what they were.
        fused = True if self._params and self._params[0].device.type == "cuda" else None
        self.optimizer = torch.optim.AdamW(
            groups, lr=lr, betas=tuple(betas), weight_decay=weight_decay, fused=fused
        )
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, warmup_cosine(warmup_steps, total_steps)
        )
        self.ema = make_ema(actor, power=ema_power)
        self.step = 0
        summed = _SummedLoss(loss_fn)
        self.distributed = dist.is_available() and dist.is_initialized()
        self._forward: nn.Module = DistributedDataParallel(summed) if self.distributed else summed

    @property
    def ema_actor(self) -> L1FlowActor:
        return self.ema.module  # type: ignore[return-value]

    def train_step(self, batch: TensorDictBase) -> dict[str, Tensor | float]:
        """One update on ``batch``; returns its metrics without waiting for the device.

        ``loss`` (the sum of the ``loss_*`` terms, also returned one by one), ``grad_norm`` (before
        clipping) and the loss's scalar diagnostics are detached 0-dim tensors on the training
        device, ``lr`` (the scheduler's rate after this step) a float: call ``float()`` on them only
        when they are logged, since each read waits for the device.
        """
        device_type = next(self.actor.parameters()).device.type
        autocast = torch.autocast(device_type, dtype=torch.bfloat16) if self.amp else contextlib.nullcontext()
        checks = contextlib.nullcontext() if self.check_values else skip_value_checks()
        with autocast, checks:
            loss, diagnostics = self._forward(batch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.grad_clip > 0:
            grad_norm = torch.nn.utils.clip_grad_norm_(self._params, self.grad_clip)
        else:  # the norm only: scaling every gradient by 1.0 would be a wasted pass
            grads = [p.grad for p in self._params if p.grad is not None]
            grad_norm = torch.nn.utils.get_total_norm(grads)
        self.optimizer.step()
        self.scheduler.step()
        lr = self.scheduler.get_last_lr()[0]  # the rate of the next step, as logged before
        self.ema.update_parameters(self.actor)
        self.step += 1
        metrics: dict[str, Tensor | float] = {
            "loss": loss.detach(),
            "lr": lr,
            "grad_norm": grad_norm.detach(),
        }
        metrics.update({k: v.detach() for k, v in diagnostics.items() if v.numel() == 1})
        return metrics

    def state_dict(self) -> dict[str, Any]:
        state = {
            "model": self.actor.state_dict(),
            "ema": self.ema_actor.state_dict(),
            "ema_n_averaged": self.ema.n_averaged.clone(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "step": self.step,
        }
        loss_state = getattr(self.loss_fn, "training_state", dict)()
        if loss_state:  # a distillation loss's target or score network
            state["loss_state"] = loss_state
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        load_state_into(self.actor, state["model"])
        load_state_into(self.ema_actor, state["ema"])
        self.ema.n_averaged.copy_(state["ema_n_averaged"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.step = int(state["step"])
        if "loss_state" in state:
            self.loss_fn.load_training_state(state["loss_state"])
