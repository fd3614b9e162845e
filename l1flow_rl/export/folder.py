"""The pretrained folder on disk: its config.json, its safetensors files, and the checks on both.

The low layer of :mod:`l1flow_rl.export.pretrained` (the folder's layout is described there): it reads and
writes folders for :meth:`L1FlowActor.save_pretrained <l1flow_rl.L1FlowActor.save_pretrained>` and
:meth:`L1FlowActor.from_pretrained <l1flow_rl.L1FlowActor.from_pretrained>`, and so imports nothing
that imports the actor; the actor class it builds is passed in.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from tensordict.nn import TensorDictModule  # the actor's base: naming the actor would close a circle

from l1flow_rl.errors import CheckpointMismatchError
from l1flow_rl.export.program import ONNX_FILE, PROGRAM_FILE, export_onnx, export_program, program_description
from l1flow_rl.flow.samplers import sampler_name
from l1flow_rl.networks.registry import LEGACY_POLICY_KEYS, network_name
from l1flow_rl.utils.state_dict import load_state_into

__all__ = [
    "CONFIG_FILE",
    "FORMAT",
    "FORMAT_VERSION",
    "NORMALIZER_FILE",
    "READABLE_VERSIONS",
    "TRAIN_CONFIG_FILE",
    "WEIGHTS_FILE",
    "PretrainedFolderError",
    "build_described",
    "is_pretrained_folder",
    "json_ready",
    "load_weights",
    "read_pretrained_config",
    "read_state",
    "write_folder",
]

FORMAT = "l1flow-rl-pretrained"
#: bumped when a reader of the previous version would misread a new folder (2: the ``network``
#: section; version 1 held the UNet's settings in ``policy``, and still reads as that UNet)
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
NORMALIZER_FILE = "normalizer.safetensors"
TRAIN_CONFIG_FILE = "train_config.json"

#: the policy settings :func:`~l1flow_rl.workspace.build.build_actor` reads, with the defaults of
#: :meth:`L1FlowActor.build` for an actor built by hand (``for_state``) without a config
_POLICY_DEFAULTS: dict[str, Any] = {"obs_horizon": 2, "pred_horizon": 16, "action_steps": 8}
#: what a version-1 folder (from before the ``network`` section) built its UNet with when its policy
#: section left a setting out: :meth:`L1FlowActor.build`'s defaults then
_V1_UNET_DEFAULTS: dict[str, Any] = {
    "down_dims": [256, 512, 1024],
    "timestep_embed_dim": 128,
    "kernel_size": 5,
    "n_groups": 8,
    "timestep_scale": 1.0,
}


class PretrainedFolderError(ValueError):
    """A folder that is not a pretrained policy of this library, or is incomplete; names the file."""


def _library_version() -> str:
    try:
        return metadata.version("l1flow-rl")
    except metadata.PackageNotFoundError:  # a source tree that was never installed
        return "unknown"


def _plain(cfg: Any) -> Any:
    if cfg is None:
        return None
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else json_ready(cfg)


def json_ready(value: Any) -> Any:
    """Mappings, sequences and scalars as JSON values (tuples become lists)."""
    if isinstance(value, Mapping):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    return value


def _policy_description(actor: TensorDictModule, policy: Mapping[str, Any] | None) -> dict[str, Any]:
    """The policy settings as given, completed from the actor itself: horizons and sampler are read
    from the modules, so they can never disagree with the weights."""
    p = actor.policy
    sampler = p.sampler
    given = {k: v for k, v in (_plain(policy) or {}).items() if k not in LEGACY_POLICY_KEYS}
    described = {**_POLICY_DEFAULTS, **given}
    described.update(
        obs_horizon=p.obs_horizon,
        pred_horizon=p.pred_horizon,
        action_steps=p.action_steps,
        sampler=sampler_name(sampler),
        sampler_kwargs=json_ready(sampler.settings()),
    )
    return described


def _split_state(actor: TensorDictModule) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """(network and encoder weights, normaliser buffers) of the actor's state_dict, as contiguous
    tensors that own their memory (safetensors refuses views of shared storage)."""
    weights, norms = {}, {}
    for key, value in actor.state_dict().items():
        target = norms if "_normalizer." in key else weights
        target[key] = value.detach().cpu().contiguous().clone()
    return weights, norms


def _normalizer_modes(actor: TensorDictModule) -> dict[str, str]:
    p = actor.policy
    modes = {f"observation.{k}": n.mode for k, n in p.obs_normalizer.items()}
    modes["action"] = p.action_normalizer.mode
    return modes


def write_folder(
    actor: TensorDictModule,
    path: str | os.PathLike,
    *,
    policy: Mapping[str, Any] | DictConfig | None = None,
    encoder: Mapping[str, Any] | DictConfig | None = None,
    task: Mapping[str, Any] | DictConfig | None = None,
    train_config: Mapping[str, Any] | DictConfig | None = None,
    source: Mapping[str, Any] | None = None,
    program: bool = False,
    onnx: bool = False,
) -> Path:
    """Write ``actor`` as a pretrained folder at ``path`` (see :mod:`l1flow_rl.export.pretrained`).

    Args:
        actor: an :class:`~l1flow_rl.L1FlowActor` (not a best-of-N actor: its critics are not saved).
        policy: the settings it was built with (the ``policy`` config group, or the keyword
            arguments given to :meth:`L1FlowActor.build`); horizons, sampler and the network (its
            name and settings: the ``network`` section) are read from the actor itself. The folder is
            rebuilt before it is published, so settings that do not describe the actor are refused
            here, not at load time.
        encoder: the encoder settings it was built with (the ``encoder`` config group), read as
            ``policy`` is.
        task: the task config it was trained on (``l1flow-rl eval`` on the folder uses it).
        train_config: the whole run config, stored as train_config.json for provenance.
        source: where the weights came from (checkpoint path, step, EMA or raw weights).
        program: also write ``policy.pt2``, the ``torch.export`` program of the 2-NFE call.
        onnx: also write ``policy.onnx``, the same call as an ONNX model (needs the ``export`` extra).

    The folder appears under its final name only once complete; an existing folder of this format
    at ``path`` is replaced, anything else there is refused.
    """
    target = Path(path)
    if target.exists() and not (
        target.is_dir() and (is_pretrained_folder(target) or not any(target.iterdir()))
    ):
        raise PretrainedFolderError(
            f"{target}: exists and is not a pretrained folder of l1flow-rl; choose another path or remove it"
        )
    p = actor.policy
    config = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "library_version": _library_version(),
        "policy": _policy_description(actor, policy),
        # read from the network itself, so it always rebuilds these weights
        "network": {"name": network_name(p.net), **json_ready(p.net.settings())},
        "encoder": _plain(encoder) or {"name": "auto"},
        "observation": {
            "key": json_ready(actor.in_keys[0]),
            "entries": {
                k: {
                    "shape": list(s),
                    "dtype": "uint8" if len(s) == 3 else str(p.dtype).removeprefix("torch."),
                }
                for k, s in p.encoder.obs_shapes.items()
            },
        },
        "action": {
            "key": json_ready(actor.out_keys[0]),
            "shape": [p.action_dim],
            "dtype": str(p.dtype).removeprefix("torch."),
            "executed_window": [p.action_steps, p.action_dim],
            "predicted_chunk": [p.pred_horizon, p.action_dim],
        },
        "sampler": {
            "name": sampler_name(p.sampler),
            "kwargs": json_ready(p.sampler.settings()),
            "nfe": p.sampler.nfe,
            "prediction": p.sampler.prediction,
        },
        "normalizers": {"file": NORMALIZER_FILE, "modes": _normalizer_modes(actor)},
        "weights": {"file": WEIGHTS_FILE, **(json_ready(source) or {})},
        "task": _plain(task),
    }
    weights, norms = _split_state(actor)
    check = build_described(type(actor), config, target)  # the description must rebuild this very network
    load_weights(check, {**weights, **norms}, target)

    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{target.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        save_file(weights, str(tmp / WEIGHTS_FILE), metadata={"format": FORMAT})
        save_file(norms, str(tmp / NORMALIZER_FILE), metadata={"format": FORMAT})
        if train_config is not None:
            (tmp / TRAIN_CONFIG_FILE).write_text(json.dumps(_plain(train_config), indent=2))
        if program:
            export_program(actor, tmp / PROGRAM_FILE)
            config["program"] = program_description(actor)
        if onnx:
            export_onnx(actor, tmp / ONNX_FILE)
            config["onnx"] = {**program_description(actor), "file": ONNX_FILE}
        (tmp / CONFIG_FILE).write_text(json.dumps(config, indent=2))
        old = target.parent / f".{target.name}.old-{os.getpid()}"
        if target.exists():
            os.replace(target, old)
        os.replace(tmp, target)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def is_pretrained_folder(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder with a config.json of this format (complete or not)."""
    config = Path(path) / CONFIG_FILE
    if not config.is_file():
        return False
    try:
        return json.loads(config.read_text()).get("format") == FORMAT
    except (json.JSONDecodeError, AttributeError, OSError):
        return False


def read_pretrained_config(path: str | os.PathLike) -> dict[str, Any]:
    """config.json of a pretrained folder, checked: the format, its version, the sections it needs."""
    folder = Path(path)
    if not folder.is_dir():
        raise PretrainedFolderError(
            f"{folder}: not a folder (a pretrained policy is a folder with {CONFIG_FILE})"
        )
    config_path = folder / CONFIG_FILE
    if not config_path.is_file():
        raise PretrainedFolderError(
            f"{config_path}: missing; {folder} is not a pretrained policy folder (expected {CONFIG_FILE}, "
            f"{WEIGHTS_FILE}, {NORMALIZER_FILE}: write one with l1flow-rl export checkpoint=CKPT out=DIR)"
        )
    try:
        config = json.loads(config_path.read_text())
    except json.JSONDecodeError as err:
        raise PretrainedFolderError(f"{config_path}: not valid JSON ({err})") from err
    if not isinstance(config, dict) or config.get("format") != FORMAT:
        found = config.get("format") if isinstance(config, dict) else type(config).__name__
        raise PretrainedFolderError(
            f"{config_path}: format is {found!r}, not {FORMAT!r}; this folder was not written by l1flow-rl "
            "(a LeRobot policy folder, for instance, cannot be loaded here)"
        )
    version = config.get("format_version")
    if version not in READABLE_VERSIONS:
        raise PretrainedFolderError(
            f"{config_path}: format_version {version!r}, but this l1flow-rl ({_library_version()}) reads "
            f"version {' or '.join(map(str, READABLE_VERSIONS))}; export the checkpoint again with this "
            "version"
        )
    for section in ("policy", "encoder", "observation", "action", *(("network",) if version >= 2 else ())):
        if not isinstance(config.get(section), dict):
            raise PretrainedFolderError(f"{config_path}: section {section!r} is missing")
    if version == 1:  # before the network section: the policy section's UNet, as version 1 read it
        policy = config["policy"]
        unet = {k: policy.get(k, default) for k, default in _V1_UNET_DEFAULTS.items()}
        config["policy"] = {k: v for k, v in policy.items() if k not in unet}
        config["network"] = {"name": "unet", **unet}
    for name in (WEIGHTS_FILE, NORMALIZER_FILE):
        if not (folder / name).is_file():
            raise PretrainedFolderError(f"{folder / name}: missing; the folder is incomplete")
    return config


def build_described(
    actor_cls: type[TensorDictModule], config: Mapping[str, Any], folder: Path
) -> TensorDictModule:
    """The untrained ``actor_cls`` that ``config`` (a checked config.json) describes."""
    obs = config["observation"]
    shapes = {k: tuple(v["shape"]) for k, v in obs["entries"].items()}
    key = obs.get("key", "observation")
    out = config["action"].get("key", "action_chunk")
    try:
        return actor_cls.from_config(
            config["policy"],
            shapes,
            int(config["action"]["shape"][0]),
            config["encoder"],
            config["network"],
            in_keys=[tuple(key) if isinstance(key, list) else key],
            out_keys=[tuple(out) if isinstance(out, list) else out],
        )
    except (KeyError, TypeError, ValueError) as err:
        raise PretrainedFolderError(
            f"{folder / CONFIG_FILE}: cannot build the policy it describes: {err}"
        ) from err


def load_weights(actor: TensorDictModule, state: Mapping[str, torch.Tensor], folder: Path) -> None:
    """``state`` into ``actor``; a mismatch is a :class:`PretrainedFolderError` naming the folder."""
    try:
        load_state_into(actor, state, str(folder))
    except CheckpointMismatchError as err:
        raise PretrainedFolderError(str(err)) from err


def read_state(folder: Path) -> dict[str, torch.Tensor]:
    """The weights and normaliser buffers of a folder, as one state_dict."""
    state: dict[str, torch.Tensor] = {}
    for name in (WEIGHTS_FILE, NORMALIZER_FILE):
        try:
            state.update(load_file(str(folder / name)))
        except (SafetensorError, OSError) as err:
            raise PretrainedFolderError(f"{folder / name}: cannot be read as safetensors ({err})") from err
    return state
