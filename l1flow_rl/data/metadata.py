"""What a dataset knows about itself (format, source file, env id, control), carried inside the episodes.

The facts ride in the episodes' TensorDict as one non-tensor entry (``METADATA_KEY``, a JSON string),
so they survive what TensorDicts do to steps: indexing, slicing, ``.to()``, ``clone()``,
``torch.cat`` and memory-mapping (``memmap`` / ``load_memmap``). :func:`episodes_metadata` reads them
back as a frozen :class:`EpisodeMetadata`.

    eps = load_episodes("PushCube-v1.h5")
    episodes_metadata(eps[eps["episode"] < 3]).control   # 'delta'
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from tensordict import NonTensorData, NonTensorStack, TensorDictBase

from l1flow_rl.data.episodes import EpisodeDataError

__all__ = [
    "METADATA_KEY",
    "EpisodeMetadata",
    "attach_metadata",
    "control_of",
    "episodes_metadata",
    "merge_metadata",
    "strip_metadata",
]

#: The non-tensor entry holding the metadata (a JSON string, the same on every row).
METADATA_KEY = "episodes_metadata"


@dataclass(frozen=True)
class EpisodeMetadata:
    """Facts about a set of episodes; ``None`` where nobody recorded them.

    Args:
        format: the reader that made them (``maniskill``, ``robomimic``, ``diffusion_policy_zarr``,
            ``lerobot``, ``collector``), None for episodes built by hand.
        source: the file or directory they came from (several joined by ``" + "`` after ``cat``).
        env_id: the environment the data were recorded in.
        control_mode: the simulator's controller name (ManiSkill ``pd_ee_delta_pos``, ...).
        control: ``"delta"`` (a change from the current pose) or ``"absolute"`` (a target); decides how
            chunks are padded past an episode's end.
        has_rewards: whether ``("next", "reward")`` holds recorded rewards (False: a placeholder that
            RL must not use).
        has_final_observation: whether ``("next", "observation")`` at an episode's last step is the
            observation recorded after its last action (False: the last observation repeated).
        extra: anything else a reader knows (``obs_mode``, ``memmap_dir``, ...); JSON values only.
    """

    format: str | None = None
    source: str | None = None
    env_id: str | None = None
    control_mode: str | None = None
    control: str | None = None
    has_rewards: bool | None = None
    has_final_observation: bool | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.control not in (None, "delta", "absolute"):
            raise ValueError(f"control must be 'delta', 'absolute' or None, got {self.control!r}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EpisodeMetadata:
        """Known keys become fields, the rest goes to ``extra``."""
        names = {f.name for f in fields(cls)} - {"extra"}
        extra = {**dict(data.get("extra") or {}), **{k: v for k, v in data.items() if k not in names}}
        extra.pop("extra", None)
        return cls(**{k: v for k, v in data.items() if k in names}, extra=extra)

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> EpisodeMetadata:
        return cls.from_dict(json.loads(text))

    def describe(self) -> str:
        """The source for error messages."""
        return self.source or "episodes"


def control_of(control_mode: str | None) -> str | None:
    """``"delta"`` or ``"absolute"`` from a controller name, None when the name does not say.

    ManiSkill names its delta controllers ``*_delta_*``; velocity controllers are neither.
    """
    if not control_mode:
        return None
    name = str(control_mode).lower()
    if "delta" in name:
        return "delta"
    if "vel" in name:
        return None
    return "absolute"


def attach_metadata(
    episodes: TensorDictBase, metadata: EpisodeMetadata | Mapping[str, Any]
) -> TensorDictBase:
    """Store ``metadata`` in ``episodes`` (in place) and return them."""
    if not isinstance(metadata, EpisodeMetadata):
        metadata = EpisodeMetadata.from_dict(metadata)
    was_locked = episodes.is_locked
    if was_locked:
        episodes.unlock_()
    try:
        episodes.set_non_tensor(METADATA_KEY, metadata.to_json())
    finally:
        if was_locked:
            episodes.lock_()
    return episodes


def strip_metadata(episodes: TensorDictBase) -> tuple[TensorDictBase, EpisodeMetadata | None]:
    """(the episodes without the metadata entry, their metadata or None); a shallow copy, no data moved.

    Storages keep the metadata once, not per row (a memory-mapped storage would write one string per step).
    """
    if METADATA_KEY not in episodes.keys():  # noqa: SIM118 (TensorDict has no __contains__)
        return episodes, None
    return episodes.exclude(METADATA_KEY), episodes_metadata(episodes)


def _values(entry) -> list[str]:
    if isinstance(entry, NonTensorData):
        return [entry.data]
    if isinstance(entry, NonTensorStack):
        seen: list[str] = []
        for value in entry.tolist():
            for v in value if isinstance(value, list) else [value]:
                if v not in seen:
                    seen.append(v)
        return seen
    if isinstance(entry, str):
        return [entry]
    raise TypeError(f"the {METADATA_KEY!r} entry is not metadata: {type(entry).__name__}")


def merge_metadata(parts: list[EpisodeMetadata]) -> EpisodeMetadata:
    """One description of episodes from several sources (after ``torch.cat``).

    Sources are joined; fields all parts agree on are kept, unknown ones are left out. Parts recorded
    with different control (delta vs absolute) cannot be padded by one rule, so that is an error.
    """
    parts = [p for p in parts if p is not None]
    if not parts:
        return EpisodeMetadata()
    if len(parts) == 1:
        return parts[0]
    controls = {p.control for p in parts if p.control is not None}
    if len(controls) > 1:
        detail = ", ".join(f"{p.describe()}: {p.control}" for p in parts)
        raise EpisodeDataError(
            f"episodes recorded with different control ({detail}) cannot share one chunk padding rule"
        )

    def common(name: str):
        values = {getattr(p, name) for p in parts}
        return values.pop() if len(values) == 1 else None

    def all_true(name: str):
        values = [getattr(p, name) for p in parts]
        if any(v is False for v in values):
            return False
        return True if all(v is True for v in values) else None

    sources = []
    for p in parts:
        for s in (p.source or "").split(" + "):
            if s and s not in sources:
                sources.append(s)
    return EpisodeMetadata(
        format=common("format"),
        source=" + ".join(sources) or None,
        env_id=common("env_id"),
        control_mode=common("control_mode"),
        control=controls.pop() if controls else None,
        has_rewards=all_true("has_rewards"),
        has_final_observation=all_true("has_final_observation"),
        extra={k: v for k, v in parts[0].extra.items() if all(p.extra.get(k) == v for p in parts[1:])},
    )


def episodes_metadata(episodes: TensorDictBase) -> EpisodeMetadata:
    """What the episodes carry about themselves; an empty :class:`EpisodeMetadata` (every field None)
    for episodes without any (built by hand). Episodes concatenated from several sources give the
    merged description (see :func:`merge_metadata`)."""
    if not isinstance(episodes, TensorDictBase):
        raise TypeError(f"expected episodes (a TensorDict of steps), got {type(episodes).__name__}")
    if METADATA_KEY not in episodes.keys():  # noqa: SIM118
        return EpisodeMetadata()
    values = _values(episodes.get(METADATA_KEY))
    return merge_metadata([EpisodeMetadata.from_json(v) for v in values])
