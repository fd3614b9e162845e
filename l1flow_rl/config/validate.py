"""Checks of a composed config that the dataclass schema cannot express, run before any work.

The schema (:class:`~l1flow_rl.config.AppConfig`) checks keys and types. This module asks the
registries that define the values (:data:`BUILTIN_CHOICES`: simulators, samplers, losses, encoders,
evaluation protocols, ...) and runs the rules that live beside what they validate
(:data:`BUILTIN_CHECKS`): a simulator's task rules (``SimulatorSpec.task_problems``), a sampler's
and a loss's arguments (``sampler_problems``, ``loss_problems``), an encoder's fit to the
observation (``encoder_problems``), the evaluation seeds (``eval_config_problems``). Every problem
is collected; the error names each field, what it holds and what is allowed. All of it takes well
under a second: no simulator, network or demonstration is touched (the simulator packages'
registrations import no simulator).

A package outside the library that adds an enum-like field or a rule plugs in with one call, e.g.::

    register_choices("my_group.mode", lambda: sorted(MODES))

Example:
    >>> from omegaconf import OmegaConf
    >>> from l1flow_rl.config import AppConfig
    >>> cfg = OmegaConf.structured(AppConfig)
    >>> cfg.policy.sampler = "ddim2"
    >>> try:
    ...     validate_config(cfg)
    ... except ConfigValidationError as err:
    ...     print(str(err).splitlines()[1])  # doctest: +ELLIPSIS
      policy.sampler='ddim2': expected one of ['ddim', 'ddpm', 'direct', ...]
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any, get_args

from omegaconf import DictConfig, ListConfig, OmegaConf

from l1flow_rl.config import finetune
from l1flow_rl.config.app import RESUME_MODES, AppConfig
from l1flow_rl.config.data import PADDING_RULES, quality_problems
from l1flow_rl.config.network import network_problems
from l1flow_rl.config.path_fields import path_problems
from l1flow_rl.config.ranges import range_problems
from l1flow_rl.config.task import CONTROL_KINDS, TaskConfig
from l1flow_rl.config.train import LOGGERS
from l1flow_rl.data.loading import dataset_problem
from l1flow_rl.envs.registry import registered_simulators
from l1flow_rl.evaluation.plan import eval_config_problems
from l1flow_rl.evaluation.protocols import protocol_names
from l1flow_rl.finetune.registry import finetune_problems
from l1flow_rl.finetune.start_check import start_problems
from l1flow_rl.flow.samplers import make_sampler, sampler_names, sampler_problems, samplers_for
from l1flow_rl.modules.normalizer import NormalizerMode
from l1flow_rl.networks.encoders import encoder_names, encoder_problems
from l1flow_rl.networks.encoders.resnet18_gn import WIDTHS
from l1flow_rl.networks.mlp import ACTIVATIONS
from l1flow_rl.networks.registry import network_names
from l1flow_rl.objectives.registry import get_loss, loss_names, loss_problems
from l1flow_rl.workspace.teacher import teacher_problems

__all__ = [
    "BUILTIN_CHECKS",
    "BUILTIN_CHOICES",
    "COMMAND_SCOPES",
    "ConfigValidationError",
    "check_policy",
    "config_problems",
    "register_check",
    "register_choices",
    "validate_config",
]

Check = Callable[[DictConfig, str], list[str]]


class ConfigValidationError(ValueError):
    """One or more config fields hold values that cannot work; the message lists each, and
    ``problems`` holds them, one line each (the CLI prints one line per problem)."""

    def __init__(self, problems: str | list[str]) -> None:
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__(
            f"{len(self.problems)} config value(s) cannot work:\n  " + "\n  ".join(self.problems)
            if len(self.problems) > 1 or not isinstance(problems, str)
            else problems
        )


#: What each sub-command builds from the config, hence what must be checked for it:
#: ``"policy"``: the method (sampler, loss and their options); ``"network"``: the chunk denoiser
#: (``network.*``) and an encoder that must fit the task's observations. ``eval`` and ``export`` take
#: both from the checkpoint (``eval`` checks a swapped sampler itself); a command not listed gets both.
COMMAND_SCOPES: dict[str, frozenset[str]] = {
    "train": frozenset({"policy", "network"}),
    "eval": frozenset(),
    "export": frozenset(),
    "demos": frozenset(),
    "toy": frozenset(),
}

#: Each enum-like field and the registry that answers what it may hold (read at validation time,
#: so that a simulator, sampler, loss, encoder or protocol registered later is seen).
BUILTIN_CHOICES: dict[str, Callable[[], Iterable[str]]] = {
    "task.simulator": lambda: registered_simulators(),
    "task.control": lambda: CONTROL_KINDS,
    "data.padding": lambda: PADDING_RULES,
    "policy.sampler": sampler_names,
    "policy.loss": loss_names,
    "policy.normalizer": lambda: get_args(NormalizerMode),
    "policy.obs_normalizer": lambda: get_args(NormalizerMode),
    "train.logger": lambda: LOGGERS,
    "encoder.name": encoder_names,
    "network.name": network_names,
    "network.activation": lambda: sorted(ACTIVATIONS),
    "eval.protocol": protocol_names,
    "eval.val_sampler": sampler_names,
    **finetune.CHOICES,
}

_CHOICES: dict[str, Callable[[], Iterable[str]]] = dict(BUILTIN_CHOICES)
_CHECKS: list[Check] = []


def register_choices(field: str, choices: Callable[[], Iterable[str]]) -> None:
    """Declare the allowed values of the dotted ``field`` (read when a config is validated, so a
    registry filled later is seen). A field absent from the config is skipped."""
    _CHOICES[field] = choices


def register_check(check: Check) -> None:
    """Add a cross-field check: ``check(cfg, command)`` returns problems, one line each."""
    if check not in _CHECKS:
        _CHECKS.append(check)


def _select(cfg: Any, dotted: str) -> Any:
    return OmegaConf.select(cfg, dotted, default=None) if isinstance(cfg, DictConfig) else None


def _plain(node: Any) -> Any:
    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    return node


# -- checks ------------------------------------------------------------------------------------------


def _check_choices(cfg: DictConfig) -> list[str]:
    problems = []
    for field, provider in _CHOICES.items():
        value = _select(cfg, field)
        if value is None:
            continue
        allowed = sorted(provider())
        if value not in allowed:
            problems.append(f"{field}={value!r}: expected one of {allowed}")
    return problems


def check_policy(
    policy: Mapping[str, Any] | DictConfig, prefix: str = "policy", sampler_field: str | None = None
) -> list[str]:
    """Problems with a method: the sampler's and the loss's arguments (asked of their registries)
    and whether the loss trains what the sampler reads. Messages name ``<prefix>.loss`` and
    ``<sampler_field>`` / ``<sampler_field>_kwargs`` (default ``<prefix>.sampler``), so a sampler set
    elsewhere (``eval.val_sampler``) is checked the same way. Unknown names are left to the choices
    check.

    Example:
        >>> policy = {"sampler": "euler", "sampler_kwargs": {"t_first": 0.5}, "loss": "l1flow"}
        >>> print(*check_policy(policy))  # doctest: +ELLIPSIS
        policy.sampler_kwargs.t_first: sampler 'euler' takes no such argument; it takes ['steps'] ...
    """
    p = _plain(policy)
    sf = sampler_field or f"{prefix}.sampler"
    sampler_name, loss_name = p.get("sampler"), p.get("loss")
    problems: list[str] = []
    sampler = None
    if sampler_name in sampler_names():
        kwargs = p.get("sampler_kwargs") or {}
        problems += sampler_problems(sampler_name, kwargs, sf)
        sampler = None if problems else make_sampler(sampler_name, **kwargs)
    if loss_name in loss_names():
        problems += loss_problems(loss_name, p.get("loss_kwargs"), prefix)
        prediction = getattr(get_loss(loss_name), "prediction", None)
        if sampler is not None and prediction and sampler.prediction != prediction:
            problems.append(
                f"{sf}={sampler_name!r} reads a {sampler.prediction!r}-prediction network, but "
                f"{prefix}.loss={loss_name!r} trains {prediction!r} prediction; samplers that fit: "
                f"{samplers_for(prediction)}"
            )
    return problems


def _check_val_sampler(cfg: DictConfig, command: str) -> list[str]:
    """``eval.val_sampler`` and its arguments, against what ``policy.loss`` trains: the method check
    under the eval field names."""
    ev = cfg.get("eval") if isinstance(cfg, DictConfig) else None
    if ev is None or not ev.get("val_sampler") or cfg.get("policy") is None:
        return []
    method = {
        "sampler": ev.val_sampler,
        "sampler_kwargs": ev.get("val_sampler_kwargs"),
        "loss": cfg.policy.loss,
    }
    return check_policy(method, sampler_field="eval.val_sampler")


def _check_horizons(cfg: DictConfig, command: str) -> list[str]:
    """The executed window [To - 1, To - 1 + K) lies inside the predicted chunk H (what
    :class:`~l1flow_rl.modules.policy.ChunkPolicy` requires), once each horizon is in its range."""
    p = cfg.get("policy") if isinstance(cfg, DictConfig) else None
    if p is None or not all(isinstance(p.get(k), int) and p.get(k) >= 1 for k in _HORIZONS):
        return []
    if p.obs_horizon - 1 + p.action_steps <= p.pred_horizon:
        return []
    return [
        f"policy.pred_horizon={p.pred_horizon}: expected >= policy.obs_horizon - 1 + policy.action_steps = "
        f"{p.obs_horizon - 1 + p.action_steps} (the executed steps must fit the predicted chunk)"
    ]


_HORIZONS = ("obs_horizon", "pred_horizon", "action_steps")


def _check_betas(cfg: DictConfig, command: str) -> list[str]:
    betas = _select(cfg, "train.betas")
    if betas is None or len(betas) == 2:
        return []
    return [f"train.betas={list(betas)}: expected two numbers (Adam's beta1, beta2)"]


def _check_resume(cfg: DictConfig, command: str) -> list[str]:
    """``resume``: false, true or auto (typed loosely in the schema, which has no bool-or-word type)."""
    if "resume" not in cfg:
        return []
    value = cfg.resume
    if isinstance(value, bool) or (isinstance(value, str) and value in RESUME_MODES):
        return []
    return [f"resume={value!r}: expected false, true or auto"]


#: The rules that read more than one field, each defined beside what it validates.
BUILTIN_CHECKS: tuple[Check, ...] = (
    _check_resume,
    _check_horizons,
    _check_betas,
    _check_val_sampler,
    eval_config_problems,
    *finetune.CHECKS,
    finetune_problems,
    start_problems,
    quality_problems,
    teacher_problems,
)


def _check_task(cfg: DictConfig, scopes: frozenset[str]) -> list[str]:
    """The task against its simulator's rules (``SimulatorSpec.task_problems``: obs_mode, env keys);
    an image task needs an encoder that reads images (``encoder_problems``)."""
    spec = registered_simulators().get(_select(cfg, "task.simulator"))
    if spec is None:  # reported by the choices check
        return []
    task = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(TaskConfig), cfg.task))
    problems = spec.task_problems(task)
    encoder = _select(cfg, "encoder.name")
    if problems or "network" not in scopes or encoder not in encoder_names():
        return problems
    images = [k for k, dims in spec.observation_entries(task).items() if dims == 3]
    return [
        f"task {task.name!r} (task.obs_mode={task.obs_mode!r}): {problem}, or a state task "
        "(task.obs_mode=state)"
        for problem in encoder_problems(encoder, images)
    ]


def _check_kernel(cfg: DictConfig) -> list[str]:
    """The UNet's convolutions keep the chunk's length (padding ``kernel_size // 2``) only with an odd
    kernel; an even one fails at the first residual sum."""
    kernel = _select(cfg, "network.kernel_size")
    if _select(cfg, "network.name") != "unet" or not isinstance(kernel, int) or kernel < 1 or kernel % 2:
        return []
    return [f"network.kernel_size={kernel}: expected an odd number (same-length convolutions)"]


def _check_encoder(cfg: DictConfig, scopes: frozenset[str]) -> list[str]:
    """``encoder.group_size`` divides the image trunk's channels (GroupNorm), where the trunk is
    built: ``resnet18_gn`` named, or ``auto`` on a task that observes images."""
    size, name = _select(cfg, "encoder.group_size"), _select(cfg, "encoder.name")
    if (
        "network" not in scopes
        or not isinstance(size, int)
        or size < 1
        or name not in ("resnet18_gn", "auto")
    ):
        return []
    if name == "auto" and _select(cfg, "task.obs_mode") == "state":
        return []
    if all(w % size == 0 for w in WIDTHS):
        return []
    return [
        f"encoder.group_size={size}: expected a divisor of the image trunk's channels {list(WIDTHS)} "
        "(channels per GroupNorm group), e.g. 16"
    ]


def config_problems(cfg: DictConfig, command: str = "train", paths: bool = False) -> list[str]:
    """Every problem :func:`validate_config` would report, one line each (``paths``: the path
    fields too, which looks at the file system)."""
    scopes = COMMAND_SCOPES.get(command, frozenset({"policy", "network"}))
    problems = range_problems(cfg, AppConfig)
    problems += _check_choices(cfg)
    if "policy" in scopes and "policy" in cfg:
        problems += check_policy(cfg.policy)
    problems += _check_encoder(cfg, scopes)
    if "network" in scopes:
        problems += network_problems(cfg) + _check_kernel(cfg)
    if "task" in cfg:
        problems += _check_task(cfg, scopes)
    for check in (*BUILTIN_CHECKS, *_CHECKS):
        problems += check(cfg, command)
    if paths:
        problems += path_problems(cfg, AppConfig, command, dataset_problem)
    return list(dict.fromkeys(problems))  # a rule that two checks share is said once


def validate_config(cfg: DictConfig, command: str = "train", paths: bool = False) -> None:
    """Raise :class:`ConfigValidationError` listing every field of ``cfg`` that cannot work for
    ``command`` (see :data:`COMMAND_SCOPES`): each value outside its declared range
    (:mod:`l1flow_rl.config.ranges`), each unknown choice, each broken relation between fields, and
    with ``paths`` each path field that names nothing usable (:mod:`l1flow_rl.config.path_fields`)."""
    problems = config_problems(cfg, command, paths)
    if problems:
        raise ConfigValidationError(problems)
