"""``online.start_rarity_k``: windows drawn in proportion to 1 / p(success | start), p from the k
collected episodes whose starts lie nearest; the demonstrations weighted by the same estimate."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from l1flow_rl.cli import compose_config
from l1flow_rl.config.validate import ConfigValidationError
from l1flow_rl.data.episodes import EpisodeDataError, assemble_episode
from l1flow_rl.data.metadata import attach_metadata
from l1flow_rl.data.start_rarity import StartRarity
from l1flow_rl.workspace.rl_data import RLBuffers


def episodes_at(starts, succeeded, length=20) -> TensorDict:
    """One episode per start x: observation [x + t / 1000, -t]; succeeded ones end terminated."""
    parts = []
    for e, (x, ok) in enumerate(zip(starts, succeeded)):
        t = torch.arange(length + 1, dtype=torch.float32)
        obs = torch.stack([x + t / 1000, -t], -1)
        parts.append(
            assemble_episode(
                e,
                obs[:length],
                torch.randn(length, 3),
                reward=torch.zeros(length),
                terminated=ok,
                final_observation=obs[length],
            )
        )
    return attach_metadata(
        torch.cat(parts), {"source": "hand.h5", "has_rewards": True, "has_final_observation": True}
    )


def _cfg(*extra):
    return compose_config(
        [
            "finetune=filtered_bc",
            "checkpoint=bc.pt",
            "finetune.batch_size=16",
            "online.steps=1000",
            "task.start_dims=[0]",
            *extra,
        ],
        command="finetune",
    )


def _share(batch_episodes, episode) -> float:
    return float((batch_episodes == episode).double().mean())


def test_rare_successes_and_the_demonstrations_near_them_are_drawn_in_proportion_to_their_weight():
    demos = episodes_at(starts=[0.0, 1000.0], succeeded=[True, True])
    buffers = RLBuffers(_cfg("online.start_rarity_k=2"), demos, 8, seed=0, successful_episodes_only=True)
    # nothing collected yet (fewer than k episodes): the demonstrations are drawn uniformly
    assert abs(_share(buffers.offline.sample(4000)["episode"], 1) - 0.5) < 0.03
    # collected: both starts near x=0 succeeded, one of the two near x=1000 did
    buffers.online.extend(episodes_at(starts=[0.0, 1.0, 1000.0, 1001.0], succeeded=[True, True, True, False]))
    # weights by hand: p(x~0) = 2/2 -> 1, p(x~1000) = 1/2 -> 2 (k = 2 nearest collected starts)
    assert abs(_share(buffers.offline.sample(6000)["episode"], 1) - 2 / 3) < 0.03
    online = buffers.online.sample(6000)["observation"][:, -1, 0]
    # the lone success near x=1000 weighs as much as the two near x=0 together
    assert abs(float((online > 500).double().mean()) - 0.5) < 0.03
    assert not bool(((online > 1000.5) & (online < 1002)).any())  # the failure gives no window


def test_without_the_setting_windows_are_drawn_uniformly():
    demos = episodes_at(starts=[0.0, 1000.0], succeeded=[True, True])
    buffers = RLBuffers(_cfg(), demos, 8, seed=0, successful_episodes_only=True)
    buffers.online.extend(episodes_at(starts=[0.0, 1.0, 1000.0, 1001.0], succeeded=[True, True, True, False]))
    assert buffers.offline.sampler.weighting is None
    assert abs(_share(buffers.offline.sample(6000)["episode"], 1) - 0.5) < 0.03


def test_a_start_with_no_success_nearby_weighs_at_most_k():
    collected = episodes_at(starts=[0.0, 1.0, 2.0, 1000.0], succeeded=[False, False, False, True])
    from torchrl.data import LazyTensorStorage

    storage = LazyTensorStorage(len(collected))
    storage.set(range(len(collected)), collected)
    rarity = StartRarity(storage, dims=[0], k=3)
    starts = episodes_at(starts=[0.5, 999.0], succeeded=[True, True], length=1)
    assert rarity.weights(starts, source="demo").tolist() == [3.0, 3.0]  # 0/3 -> floored at 1/3; 1/3
    assert StartRarity(storage, dims=[0], k=2).weights(starts, source="demo").tolist() == [2.0, 2.0]


def test_start_dimensions_outside_the_observation_are_named():
    collected = episodes_at(starts=[0.0, 1.0], succeeded=[True, False])
    from torchrl.data import LazyTensorStorage

    storage = LazyTensorStorage(len(collected))
    storage.set(range(len(collected)), collected)
    with pytest.raises(EpisodeDataError, match=r"task\.start_dims \[5\] name dimensions \[5\] outside .* 2"):
        StartRarity(storage, dims=[5], k=1).weights(collected[:1], source="demo")


def test_the_setting_is_checked_at_config_time_naming_the_fields():
    with pytest.raises(ConfigValidationError, match=r"online\.start_rarity_k=-1: expected 0"):
        compose_config(
            ["finetune=filtered_bc", "online.steps=100", "online.start_rarity_k=-1"], command="finetune"
        )
    # the default task (PushCube) names no start dimensions; Can names its can's x, y
    with pytest.raises(ConfigValidationError, match=r"task 'maniskill_pushcube' names no task\.start_dims"):
        compose_config(
            ["finetune=filtered_bc", "online.steps=100", "online.start_rarity_k=20"], command="finetune"
        )
    can = compose_config(
        ["finetune=filtered_bc", "task=robosuite_can", "online.steps=100", "online.start_rarity_k=20"],
        command="finetune",
    )
    assert list(can.task.start_dims) == [7, 8]
    with pytest.raises(
        ConfigValidationError, match=r"online\.seed_with_offline=true stores them in one buffer"
    ):
        compose_config(
            [
                "finetune=filtered_bc",
                "task=robosuite_can",
                "online.steps=100",
                "online.start_rarity_k=20",
                "online.seed_with_offline=true",
            ],
            command="finetune",
        )
