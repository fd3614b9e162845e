"""Checks of a composed config that the dataclass schema cannot express, run before any work.

The schema (:class:`~l1flow_rl.config.AppConfig`) checks keys and types. This module checks
values against the registries that define them (samplers, losses, simulators, normalisers,
loggers, padding rules, and the protocols and encoders other packages register), the keys of
``policy.sampler_kwargs`` / ``policy.loss_kwargs`` against what their constructors take, and that
the task and the policy fit each other. Every problem is collected; the error names each field,
what it holds and what is allowed. All of it takes well under a second: no simulator, network or
demonstration is touched.

A package that adds an enum-like field plugs in with one call, e.g.::

    register_choices("eval.protocol", lambda: sorted(PROTOCOLS))

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

import inspect
from collections.abc import Callable, Iterable, Mapping
from typing import Any, get_args

from omegaconf import DictConfig, ListConfig, OmegaConf

__all__ = [
    "COMMAND_SCOPES",
    "ConfigValidationError",
    "check_policy",
    "register_check",
    "register_choices",
    "validate_config",
]


class ConfigValidationError(ValueError):
    """One or more config fields hold values that cannot work; the message lists each."""


#: What each sub-command builds from the config, hence what must be checked for it:
#: ``"policy"``: the method (sampler, loss and their options); ``"network"``: an encoder that must
#: fit the task's observations. ``eval`` takes both from its checkpoint (and checks a swapped
#: sampler itself); a command not listed gets both.
COMMAND_SCOPES: dict[str, frozenset[str]] = {
    "train": frozenset({"policy", "network"}),
    "eval": frozenset(),
    "demos": frozenset(),
    "toy": frozenset(),
}

_CHOICES: dict[str, Callable[[], Iterable[str]]] = {}
_CHECKS: list[Callable[[DictConfig, str], list[str]]] = []


def register_choices(field: str, choices: Callable[[], Iterable[str]]) -> None:
    """Declare the allowed values of the dotted ``field`` (read when a config is validated, so a
    registry filled later is seen). A field absent from the config is skipped."""
    _CHOICES[field] = choices


def register_check(check: Callable[[DictConfig, str], list[str]]) -> None:
    """Add a cross-field check: ``check(cfg, command)`` returns problems, one line each."""
    if check not in _CHECKS:
        _CHECKS.append(check)


def _select(cfg: Any, dotted: str) -> Any:
    return OmegaConf.select(cfg, dotted, default=None) if isinstance(cfg, DictConfig) else None


def _plain(node: Any) -> Any:
    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    return node


# -- registries of the built-in fields ---------------------------------------------------------------


def _simulators() -> list[str]:
    from l1flow_rl.envs.registry import registered_simulators

    return sorted(registered_simulators())


def _normalizer_modes() -> list[str]:
    from l1flow_rl.normalizer import NormalizerMode

    return list(get_args(NormalizerMode))


def _samplers() -> list[str]:
    from l1flow_rl.flow.samplers import sampler_names

    return sampler_names()


def _losses() -> list[str]:
    from l1flow_rl.workspace.build import LOSSES

    return sorted(LOSSES)


def _control_kinds() -> list[str]:
    from l1flow_rl.config.task import CONTROL_KINDS

    return list(CONTROL_KINDS)


def _padding_rules() -> list[str]:
    from l1flow_rl.config.data import PADDING_RULES

    return list(PADDING_RULES)


def _encoders() -> list[str]:
    from l1flow_rl.networks.encoders import encoder_names

    return encoder_names()


def _loggers() -> list[str]:
    from l1flow_rl.config.train import LOGGERS

    return list(LOGGERS)


for _field, _provider in {
    "task.simulator": _simulators,
    "task.control": _control_kinds,
    "data.padding": _padding_rules,
    "policy.sampler": _samplers,
    "policy.loss": _losses,
    "policy.normalizer": _normalizer_modes,
    "policy.obs_normalizer": _normalizer_modes,
    "train.logger": _loggers,
    "encoder.name": _encoders,
}.items():
    register_choices(_field, _provider)


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


def _accepted_kwargs(cls: type) -> list[str]:
    params = inspect.signature(cls.__init__).parameters.values()
    skip = {"self", "actor_network"}
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return [p.name for p in params if p.name not in skip and p.kind in kinds]


def check_policy(
    policy: Mapping[str, Any] | DictConfig, prefix: str = "policy", sampler_field: str | None = None
) -> list[str]:
    """Problems with a method: the sampler's and the loss's names and keyword arguments, the
    values the sampler refuses, and whether the loss trains what the sampler reads. Messages name
    ``<prefix>.loss`` and ``<sampler_field>`` / ``<sampler_field>_kwargs`` (default
    ``<prefix>.sampler``), so a sampler set elsewhere (``eval.val_sampler``) is checked the same way.

    Example:
        >>> policy = {"sampler": "euler", "sampler_kwargs": {"t_first": 0.5}, "loss": "l1flow"}
        >>> print(*check_policy(policy))  # doctest: +ELLIPSIS
        policy.sampler_kwargs.t_first: sampler 'euler' takes no such argument; it takes ['steps'] ...
    """
    from l1flow_rl.flow.samplers import make_sampler, sampler_names, sampler_parameters, samplers_for
    from l1flow_rl.workspace.build import LOSSES

    p = _plain(policy)
    sf = sampler_field or f"{prefix}.sampler"
    problems: list[str] = []
    sampler_name, loss_name = p.get("sampler"), p.get("loss")
    sampler = None
    if sampler_name in sampler_names():
        kwargs = dict(p.get("sampler_kwargs") or {})
        accepted = sampler_parameters(sampler_name)
        unknown = sorted(set(kwargs) - set(accepted))
        problems += [
            f"{sf}_kwargs.{k}: sampler {sampler_name!r} takes no such argument; it takes "
            f"{accepted} (drop it with ~{sf}_kwargs.{k})"
            for k in unknown
        ]
        if not unknown:
            try:
                sampler = make_sampler(sampler_name, **kwargs)
            except (TypeError, ValueError) as err:
                problems.append(f"{sf}_kwargs={kwargs}: {err}")
    if loss_name in LOSSES:
        cls = LOSSES[loss_name]
        accepted = _accepted_kwargs(cls)
        kwargs = dict(p.get("loss_kwargs") or {})
        problems += [
            f"{prefix}.loss_kwargs.{k}: loss {loss_name!r} ({cls.__name__}) takes no such argument; "
            f"it takes {accepted}"
            for k in sorted(set(kwargs) - set(accepted))
        ]
        if isinstance(kwargs.get("timesteps"), str):
            from l1flow_rl.flow.timesteps import make_timesteps

            try:
                make_timesteps(kwargs["timesteps"])
            except ValueError as err:
                problems.append(f"{prefix}.loss_kwargs.timesteps: {err}")
        prediction = getattr(cls, "prediction", None)
        if sampler is not None and prediction and sampler.prediction != prediction:
            problems.append(
                f"{sf}={sampler_name!r} reads a {sampler.prediction!r}-prediction network, but "
                f"{prefix}.loss={loss_name!r} trains {prediction!r} prediction; samplers that fit: "
                f"{samplers_for(prediction)}"
            )
    return problems


def _encoder_reads_images(name: str) -> bool:
    from l1flow_rl.networks.encoders import get_encoder, resolve_encoder_name

    try:
        return get_encoder(resolve_encoder_name(name, has_images=True)).images
    except ValueError:  # an unknown name: reported by the choices check
        return True


def _check_task(cfg: DictConfig, scopes: frozenset[str]) -> list[str]:
    """obs_mode and env options against the simulator's spec; an image task needs an image encoder."""
    from l1flow_rl.config.task import TaskConfig
    from l1flow_rl.envs.registry import registered_simulators

    spec = registered_simulators().get(_select(cfg, "task.simulator"))
    if spec is None:  # reported by the choices check
        return []
    problems = []
    obs_mode = cfg.task.obs_mode
    if obs_mode not in spec.obs_modes:
        problems.append(
            f"task.obs_mode={obs_mode!r}: simulator {spec.name!r} supports {sorted(spec.obs_modes)}"
        )
        return problems
    # task.env keys: checked where the simulator lists them (SimulatorSpec.env_keys); ManiSkill and
    # robosuite pass the block on to gym.make / robosuite.make, which name a key they do not take.
    if spec.env_keys is not None:
        unknown = sorted(set(cfg.task.env or {}) - set(spec.env_keys))
        if unknown:
            problems.append(
                f"task.env: simulator {spec.name!r} takes no key(s) {unknown}; "
                f"it takes {sorted(spec.env_keys)}"
            )
    if "network" in scopes:
        task = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(TaskConfig), cfg.task))
        images = [k for k, dims in spec.observation_entries(task).items() if dims == 3]
        encoder = _select(cfg, "encoder.name")
        if images and encoder is not None and not _encoder_reads_images(encoder):
            problems.append(
                f"task {cfg.task.name!r} observes images (task.obs_mode={obs_mode!r}, entries {images}), but "
                f"encoder.name={encoder!r} reads flat vectors only; use an image encoder (encoder=auto or "
                "encoder=resnet18_gn) or a state task (task.obs_mode=state)"
            )
    return problems


def validate_config(cfg: DictConfig, command: str = "train") -> None:
    """Raise :class:`ConfigValidationError` listing every field of ``cfg`` that cannot work for
    ``command`` (see :data:`COMMAND_SCOPES`)."""
    scopes = COMMAND_SCOPES.get(command, frozenset({"policy", "network"}))
    problems = _check_choices(cfg)
    if "policy" in scopes and "policy" in cfg:
        problems += check_policy(cfg.policy)
    if "task" in cfg:
        problems += _check_task(cfg, scopes)
    for check in _CHECKS:
        problems += check(cfg, command)
    if problems:
        raise ConfigValidationError(
            f"{len(problems)} config value(s) cannot work:\n  " + "\n  ".join(problems)
        )
