"""The teacher of a distillation run (``teacher=``), checked when the config is composed, and the
run's training ledger.

A distillation loss (a :class:`~l1flow_rl.objectives.distillation.DistillationLossBase`) needs a
teacher checkpoint; any other loss refuses one. :func:`teacher_problems` reads the checkpoint's
recorded config without reading its tensors (they are memory-mapped) and names, one line each, what
keeps it from teaching this run: another task, another network shape, a method that cannot teach this
loss, a student sampler that reads the network as another teacher's.

The teacher is loaded with the safe checkpoint loader (EMA weights, frozen). The ledger lists every
training stage a policy's weights went through, the teacher's first: what convergence figures count
(the paper counts a distilled student's epochs with its teacher's). A checkpoint, ``history.json``,
``eval.json`` and ``summary.json`` carry it.

Example:
    >>> from omegaconf import OmegaConf
    >>> cfg = OmegaConf.create({"policy": {"loss": "consistency"}, "teacher": None})
    >>> print(*teacher_problems(cfg, "train"))  # doctest: +ELLIPSIS
    teacher: policy.loss='consistency' distils a teacher; pass teacher=<checkpoint of a policy=edm run> ...
    >>> ledger = [{"stage": "teacher", "policy": "edm", "steps": 3000, "checkpoint": "t.pt"}]
    >>> own = own_stage("consistency", 500, batch_size=256)
    >>> total_steps([*ledger, own])
    3500
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModule

from l1flow_rl.errors import CheckpointReadError
from l1flow_rl.flow.samplers import make_sampler, sampler_names
from l1flow_rl.objectives.distillation import DistillationLossBase
from l1flow_rl.objectives.registry import get_loss, loss_names
from l1flow_rl.workspace.checkpoint import _select, load_actor, load_checkpoint

__all__ = [
    "NETWORK_FIELDS",
    "TASK_FIELDS",
    "load_teacher",
    "own_stage",
    "teacher_ledger",
    "teacher_problems",
    "total_steps",
]

#: what the teacher must share with the student: the task it acts in ...
TASK_FIELDS = ("task.env_id", "task.obs_mode", "task.control_mode")
#: ... and the network the student starts from (its weights are loaded into the student)
NETWORK_FIELDS = (
    "policy.obs_horizon",
    "policy.pred_horizon",
    "network.name",
    "network.timestep_embed_dim",
    "network.timestep_scale",
    "network.down_dims",
    "network.kernel_size",
    "network.n_groups",
    "network.hidden_dims",
    "network.activation",
    "network.layer_norm",
    "network.residual",
    "encoder.name",
)
#: the methods whose checkpoint can teach, by the prediction type of their sampler
_TEACHER_POLICY = {"karras": "edm", "epsilon": "ddpm"}


def _plain(cfg: Any) -> dict[str, Any]:
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)  # type: ignore[return-value]


def _prediction(sampler: str | None, kwargs: Mapping[str, Any] | None) -> str | None:
    """The prediction type a checkpoint's sampler reads (None: a sampler this install does not know)."""
    if sampler not in sampler_names():
        return None
    return make_sampler(sampler, **dict(kwargs or {})).prediction


def _reads_teacher(sampler: str | None) -> str | None:
    """The teacher prediction type a student sampler reads its network as (None: any, or unknown)."""
    return getattr(make_sampler(sampler), "teacher_prediction", None) if sampler in sampler_names() else None


def _student_sampler_problems(loss: type, plain: Mapping[str, Any]) -> list[str]:
    """The loss's own objection to the student's sampler (e.g. OneDP-S's stochastic generator)."""
    policy = plain["policy"]
    if policy.get("sampler") not in sampler_names():
        return []
    try:
        sampler = make_sampler(policy["sampler"], **dict(policy.get("sampler_kwargs") or {}))
    except (TypeError, ValueError):  # the sampler check reports it
        return []
    problem = loss.student_sampler_problem(sampler, dict(policy.get("loss_kwargs") or {}))
    return [problem] if problem else []


def _student_loss(cfg: Mapping[str, Any]) -> type | None:
    name = _select(cfg, "policy.loss")
    return get_loss(name) if name in loss_names() else None


def teacher_problems(cfg: DictConfig | Mapping[str, Any], command: str) -> list[str]:
    """One line per reason ``teacher=`` cannot serve this ``train`` run (none for other commands)."""
    if command != "train":
        return []
    plain = _plain(cfg)
    loss = _student_loss(plain)
    if loss is None:  # an unknown loss is the choices check's
        return []
    path, name = plain.get("teacher"), plain["policy"]["loss"]
    distils = issubclass(loss, DistillationLossBase)
    if not distils:
        if path:
            return [f"teacher={path!r}: policy.loss={name!r} trains from demonstrations alone; drop teacher="]
        return []
    methods = [_TEACHER_POLICY.get(p, p) for p in loss.teacher_predictions]
    problems = _student_sampler_problems(loss, plain)
    if not path:
        return [
            *problems,
            f"teacher: policy.loss={name!r} distils a teacher; pass teacher=<checkpoint of a "
            f"{' or '.join(f'policy={m}' for m in methods)} run> (its checkpoints/best.pt)",
        ]
    try:  # the recorded config only: the tensors are mapped, not read
        saved = _plain(load_checkpoint(path, mmap=True)["config"])
    except CheckpointReadError as err:
        return [*problems, f"teacher={path!r}: {err}"]
    checks = (("was trained on another task", TASK_FIELDS), ("has another network", NETWORK_FIELDS))
    for what, fields in checks:
        diffs = [
            f"{f} {_select(saved, f)!r} (run: {_select(plain, f)!r})"
            for f in fields
            if _select(saved, f) != _select(plain, f)
        ]
        if diffs:
            problems.append(f"teacher={path!r} {what}: {', '.join(diffs)}")
    prediction = _prediction(_select(saved, "policy.sampler"), _select(saved, "policy.sampler_kwargs"))
    if prediction is None:
        return problems
    if prediction not in loss.teacher_predictions:
        problems.append(
            f"teacher={path!r} is a policy={_select(saved, 'policy.name')!r} checkpoint ({prediction!r} "
            f"prediction), which cannot teach policy.loss={name!r}; it distils "
            f"{' or '.join(f'policy={m}' for m in methods)}"
        )
        return problems
    student = _select(plain, "policy.sampler")
    wants = _reads_teacher(student)
    if wants not in (None, prediction):
        fit = [n for n in sampler_names() if _reads_teacher(n) == prediction]
        problems.append(
            f"teacher={path!r} is a {prediction!r}-prediction network, but policy.sampler={student!r} reads "
            f"its network like a {wants!r} one; use policy.sampler={fit[0]!r}"
        )
    return problems


def own_stage(policy: str, steps: int, batch_size: int | None = None) -> dict[str, Any]:
    """This run's entry of the ledger (with its batch size, so that steps convert to epochs)."""
    return {"stage": "own", "policy": policy, "steps": int(steps), "batch_size": batch_size}


def total_steps(ledger: list[dict[str, Any]]) -> int:
    """Training steps over every stage."""
    return sum(int(entry["steps"]) for entry in ledger)


def teacher_ledger(state: dict[str, Any], path: str) -> list[dict[str, Any]]:
    """The stages a teacher checkpoint's weights went through, each marked as the teacher's: its own
    ledger (a distilled teacher lists its own teacher too), or for a checkpoint written before ledgers,
    its step count."""
    stages = state.get("ledger")
    if not stages:
        cfg = state["config"]
        stages = [own_stage(cfg["policy"]["name"], state["step"], cfg["train"]["batch_size"])]
    return [
        {**entry, "stage": "teacher", "checkpoint": str(path)} if entry["stage"] == "own" else entry
        for entry in stages
    ]


def load_teacher(path: str | Path, device: torch.device) -> tuple[TensorDictModule, list[dict[str, Any]]]:
    """The teacher actor (EMA weights, frozen, in eval mode) and its ledger."""
    actor, _ = load_actor(path, use_ema=True, map_location=device)
    actor.requires_grad_(False)
    return actor, teacher_ledger(load_checkpoint(path, mmap=True), str(path))  # its config and counters
