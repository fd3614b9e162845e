"""Metadata travels inside the episodes: through slicing, cat, clone, .to(), memory-mapping and storage."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from tensordict import TensorDict
from test_data_formats import write_maniskill, write_robomimic

from l1flow_rl.data import (
    EpisodeDataError,
    EpisodeMetadata,
    attach_metadata,
    episodes_metadata,
    load_episodes,
    make_chunk_buffer,
)


@pytest.fixture
def eps(tmp_path):
    path = tmp_path / "demo.h5"
    write_maniskill(path, lengths=(5, 8))
    return load_episodes(path)


def test_loaded_metadata_is_typed_and_frozen(eps, tmp_path):
    meta = episodes_metadata(eps)
    assert isinstance(meta, EpisodeMetadata)
    assert meta == EpisodeMetadata(
        format="maniskill",
        source=str(tmp_path / "demo.h5"),
        env_id="PushCube-v1",
        control_mode="pd_ee_delta_pos",
        control="delta",
        has_rewards=True,
        has_final_observation=True,
        extra={"obs_mode": "state"},
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        meta.control = "absolute"
    assert episodes_metadata(TensorDict({"x": torch.zeros(3)}, [3])) == EpisodeMetadata()


def test_metadata_survives_tensordict_operations(eps, tmp_path):
    meta = episodes_metadata(eps)
    views = {
        "mask": eps[eps["episode"] == 1],
        "slice": eps[2:7],
        "index": eps[torch.tensor([0, 3, 12])],
        "clone": eps.clone(),
        "to": eps.to("cpu").to(torch.float64),
        "cat": torch.cat([eps[:5], eps[5:]]),
        "select": eps.select("observation", "action", "episodes_metadata"),
    }
    for name, view in views.items():
        assert episodes_metadata(view) == meta, name
    eps.memmap(tmp_path / "copy")
    assert episodes_metadata(TensorDict.load_memmap(tmp_path / "copy")) == meta


def test_memory_mapped_copies_keep_metadata(tmp_path):
    path = tmp_path / "lift.hdf5"
    write_robomimic(path, image=False)
    stored = load_episodes(path, memmap_dir=tmp_path / "mm")
    again = load_episodes(path, memmap_dir=tmp_path / "mm")  # reopened, not rewritten
    for eps in (stored, again):
        meta = episodes_metadata(eps)
        assert (meta.format, meta.env_id, meta.source) == ("robomimic", "Lift", str(path))
        assert meta.extra["memmap_dir"] == str((tmp_path / "mm").resolve())
        assert episodes_metadata(eps[3:]) == meta
    rb = make_chunk_buffer(stored, obs_horizon=2, pred_horizon=4, batch_size=4)
    assert rb.storage.metadata == episodes_metadata(stored)
    # the storage keeps it once, not as a per-row string entry
    assert "episodes_metadata" not in rb.storage.get(slice(None)).keys()  # noqa: SIM118


def test_cat_of_two_sources_merges_and_refuses_mixed_control(eps, tmp_path):
    other_path = tmp_path / "other.h5"
    write_maniskill(other_path, lengths=(4,))
    other = load_episodes(other_path)
    other["episode"] += 10
    both = episodes_metadata(torch.cat([eps, other]))
    assert both.source == f"{tmp_path / 'demo.h5'} + {other_path}"
    assert (both.control, both.env_id, both.has_rewards) == ("delta", "PushCube-v1", True)
    absolute = attach_metadata(other.clone(), {"source": "abs.h5", "control": "absolute"})
    with pytest.raises(EpisodeDataError, match=r"different control \(.*demo\.h5: delta, abs\.h5: absolute\)"):
        episodes_metadata(torch.cat([eps, absolute]))


def test_padding_follows_the_recorded_control(tmp_path):
    # the same actions padded past the end: zero arm motion under delta control, repeated under absolute
    path = tmp_path / "demo.h5"
    write_maniskill(path, lengths=(6,), control_mode="pd_ee_delta_pos")
    delta = load_episodes(path)
    absolute = attach_metadata(delta.clone(), {**episodes_metadata(delta).__dict__, "control": "absolute"})
    last = delta["action"][-1]
    for eps, expected in ((delta, torch.cat([torch.zeros(3), last[3:]])), (absolute, last)):
        batch = make_chunk_buffer(eps, obs_horizon=2, pred_horizon=8, batch_size=200, seed=0).sample()
        after = batch["action_is_pad"] & (torch.arange(8) > 1)
        assert after.any()
        assert torch.equal(batch["action_chunk"][after], expected.expand(int(after.sum()), 4))
