"""Evaluation settings (``eval``): protocol, validation and test seeds, envs, videos.

Checkpoints are chosen on the validation seeds (``val_seed``, ``val_episodes``); the reported
figures come from the test seeds (``seed``, ``episodes``), which the two ranges keep apart.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from omegaconf import DictConfig

__all__ = ["EvalConfig"]


@dataclass
class EvalConfig:
    # How figures are measured (l1flow_rl.evaluation.protocol_names()): default | maniskill | ...
    protocol: str = "default"
    episodes: int = 50  # test episodes: the reported figures
    seed: int = 100_000  # test seeds: seed, seed + 1, ... (Diffusion Policy's convention)
    val_episodes: int = 0  # episodes of each validation (checkpoint choice); 0: as many as the test
    val_seed: int = 10_000  # validation seeds, disjoint from the test seeds and from demo seeds
    # Validation under another sampler of the same network (None: policy.sampler), e.g. ddim with
    # {steps: 16} for a DDPM-100 run: its curve and checkpoint choice at a sixth of the cost; the
    # test figures keep policy.sampler.
    val_sampler: str | None = None
    val_sampler_kwargs: dict = field(default_factory=dict)
    num_envs: int = 2
    # Episodes filmed (mp4 in run_dir/videos, and to the logger); None: 1 on a GPU, 0 on the CPU,
    # where the first rendered frame costs seconds.
    video_episodes: int | None = None
    video_fps: int = 20
    deterministic: bool = False


def _protocols() -> list[str]:
    from l1flow_rl.evaluation.protocols import protocol_names

    return protocol_names()


def _check_seeds(cfg: DictConfig, command: str) -> list[str]:
    ev = cfg.get("eval") if isinstance(cfg, DictConfig) else None
    if ev is None:
        return []
    from l1flow_rl.evaluation.plan import check_seed_ranges

    problems = []
    if ev.episodes < 1 and command == "eval":
        problems.append(f"eval.episodes={ev.episodes}: expected >= 1")
    if ev.val_episodes < 0:
        problems.append(f"eval.val_episodes={ev.val_episodes}: expected >= 0 (0: as many as eval.episodes)")
    try:
        check_seed_ranges(ev.val_seed, ev.val_episodes or ev.episodes, ev.seed, ev.episodes)
    except ValueError as err:
        problems.append(str(err))
    return problems


def _check_val_sampler(cfg: DictConfig, command: str) -> list[str]:
    """``eval.val_sampler``: a known sampler, arguments it takes, and one that reads what the loss trains."""
    ev = cfg.get("eval") if isinstance(cfg, DictConfig) else None
    name = ev.get("val_sampler") if ev is not None else None
    if not name:
        return []
    from l1flow_rl.flow.samplers import make_sampler, sampler_names, sampler_parameters, samplers_for
    from l1flow_rl.workspace.build import LOSSES

    if name not in sampler_names():
        return [f"eval.val_sampler={name!r}: expected one of {sorted(sampler_names())}"]
    kwargs = dict(ev.get("val_sampler_kwargs") or {})
    unknown = sorted(set(kwargs) - set(sampler_parameters(name)))
    if unknown:
        return [
            f"eval.val_sampler_kwargs.{k}: sampler {name!r} takes no such argument; it takes "
            f"{sampler_parameters(name)}"
            for k in unknown
        ]
    try:
        sampler = make_sampler(name, **kwargs)
    except (TypeError, ValueError) as err:
        return [f"eval.val_sampler_kwargs={kwargs}: {err}"]
    loss = LOSSES.get(cfg.policy.loss) if cfg.get("policy") is not None else None
    prediction = getattr(loss, "prediction", None)
    if prediction and sampler.prediction != prediction:
        return [
            f"eval.val_sampler={name!r} reads a {sampler.prediction!r}-prediction network, but "
            f"policy.loss={cfg.policy.loss!r} trains {prediction!r} prediction; samplers that fit: "
            f"{samplers_for(prediction)}"
        ]
    return []


def _register_checks() -> None:
    from l1flow_rl.config.validate import register_check, register_choices

    register_choices("eval.protocol", _protocols)
    register_check(_check_seeds)
    register_check(_check_val_sampler)


_register_checks()
