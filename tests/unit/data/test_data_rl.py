"""The chunk buffer's RL entries (chunk return, next observation, done flags, validity) against hand
computations at episode ends, and the refusal of data without rewards."""

from __future__ import annotations

import pytest
import torch
from doubles.episodes import GAMMA, make_episodes

from l1flow_rl.data import (
    EpisodeDataError,
    attach_metadata,
    episodes_metadata,
    load_episodes,
    make_chunk_buffer,
)
from l1flow_rl.data.episodes import assemble_episode


def reference(episode: int, t: int, n: int, h: int, to: int, terminated: bool, final: bool = True):
    """The contract written out step by step for one window."""
    ret = sum(GAMMA**i * (1 + (t + i) + 10 * episode) for i in range(min(h, n - t)))
    history = []
    for k in range(to):
        s = min(max(t + h - to + 1 + k, 0), n)  # step L is the final observation
        if s == n and not final:
            s = n - 1  # the stand-in: the last observation repeated
        history.append([episode * 1000 + s, -s])
    done = t + h >= n
    # a chunk crossing a terminal end is valid (its return summed to the end, no bootstrap)
    valid = (t + h <= n and (final or terminated or t + h < n)) or terminated
    return (
        ret,
        torch.tensor(history, dtype=torch.float32),
        done,
        done and terminated,
        done and not terminated,
        valid,
    )


def test_chunk_return_next_observation_and_masks_by_hand_at_an_episode_end():
    eps = make_episodes()
    rb = make_chunk_buffer(
        eps, obs_horizon=2, pred_horizon=8, batch_size=3000, seed=0, rl_horizon=4, gamma=GAMMA
    )
    batch = rb.sample()
    assert batch["next", "reward"].shape == (3000, 1) and batch["next", "reward"].dtype == torch.float32
    assert batch["next", "observation"].shape == (3000, 2, 2)
    for key in ("done", "terminated", "truncated"):
        assert batch["next", key].shape == (3000, 1) and batch["next", key].dtype == torch.bool
    assert batch["chunk_valid"].shape == (3000, 1) and batch["chunk_valid"].dtype == torch.bool

    def window(e, t):
        rows = ((batch["episode"] == e) & (batch["step"] == t)).nonzero()
        assert rows.numel(), f"window ({e}, {t}) not drawn"
        return int(rows[0])

    # episode 0: L = 6, terminated; h = 4, r_t = 1 + t
    i = window(0, 1)  # t+h = 5 < L
    assert batch["next", "reward"][i].item() == pytest.approx(2 + 0.9 * 3 + 0.81 * 4 + 0.729 * 5)
    assert batch["next", "observation"][i].tolist() == [[4, -4], [5, -5]]
    assert not batch["next", "done"][i] and batch["chunk_valid"][i]
    i = window(0, 2)  # t+h = 6 == L: the last observation of the history is the final one
    assert batch["next", "reward"][i].item() == pytest.approx(3 + 0.9 * 4 + 0.81 * 5 + 0.729 * 6)
    assert batch["next", "observation"][i].tolist() == [[5, -5], [6, -6]]
    assert batch["next", "done"][i] and batch["next", "terminated"][i] and not batch["next", "truncated"][i]
    assert batch["chunk_valid"][i]
    i = window(0, 4)  # t+h = 8 > L: only the 2 steps inside count; the history is clamped at the final one
    assert batch["next", "reward"][i].item() == pytest.approx(5 + 0.9 * 6)
    assert batch["next", "observation"][i].tolist() == [[6, -6], [6, -6]]
    # it crosses a terminal end: valid, with no bootstrap (terminated)
    assert batch["next", "done"][i] and batch["next", "terminated"][i] and batch["chunk_valid"][i]
    # episode 1 is truncated: a chunk that crosses its end is left out
    i = window(1, 7)  # t+h = 11 > L = 9
    assert batch["next", "truncated"][i] and not batch["chunk_valid"][i]
    # episode 1: L = 9, truncated (a time limit): done but not terminated
    i = window(1, 5)  # t+h == L
    assert batch["next", "reward"][i].item() == pytest.approx(16 + 0.9 * 17 + 0.81 * 18 + 0.729 * 19)
    assert batch["next", "observation"][i].tolist() == [[1008, -8], [1009, -9]]
    assert batch["next", "truncated"][i] and not batch["next", "terminated"][i] and batch["chunk_valid"][i]

    # every drawn window against the written-out contract
    lengths, terms = {0: 6, 1: 9}, {0: True, 1: False}
    for i in range(batch.shape[0]):
        e, t = int(batch["episode"][i]), int(batch["step"][i])
        ret, hist, done, term, trunc, valid = reference(e, t, lengths[e], 4, 2, terms[e])
        assert batch["next", "reward"][i].item() == pytest.approx(ret, rel=1e-6)
        assert torch.equal(batch["next", "observation"][i], hist)
        assert (bool(batch["next", "done"][i]), bool(batch["next", "terminated"][i])) == (done, term)
        assert (bool(batch["next", "truncated"][i]), bool(batch["chunk_valid"][i])) == (trunc, valid)
    # the BC part is unchanged: the current observation history and chunk
    assert torch.equal(
        batch["observation"][:, -1, 0], batch["step"].float() + 1000 * batch["episode"].float()
    )


@pytest.mark.parametrize("to,h,horizon", [(1, 1, 4), (3, 2, 8), (2, 7, 8)])
def test_every_window_matches_the_contract(to, h, horizon):
    lengths, terms = (1, 3, 7, 12), (False, True, True, False)
    eps = make_episodes(lengths, terms)
    batch = make_chunk_buffer(
        eps, obs_horizon=to, pred_horizon=horizon, batch_size=2000, seed=1, rl_horizon=h, gamma=GAMMA
    ).sample()
    assert len(set(zip(batch["episode"].tolist(), batch["step"].tolist()))) == sum(lengths)
    for i in range(batch.shape[0]):
        e, t = int(batch["episode"][i]), int(batch["step"][i])
        ret, hist, done, term, trunc, valid = reference(e, t, lengths[e], h, to, terms[e])
        assert batch["next", "reward"][i].item() == pytest.approx(ret, rel=1e-6)
        assert torch.equal(batch["next", "observation"][i], hist)
        assert [bool(batch["next", k][i]) for k in ("done", "terminated", "truncated")] == [done, term, trunc]
        assert bool(batch["chunk_valid"][i]) == valid


def test_without_a_recorded_final_observation_a_truncated_end_is_not_valid():
    lengths, terms = (6, 9), (True, False)
    eps = make_episodes(lengths, terms, final=False)
    assert episodes_metadata(eps).has_final_observation is False
    batch = make_chunk_buffer(
        eps, obs_horizon=2, pred_horizon=8, batch_size=2000, seed=0, rl_horizon=4, gamma=GAMMA
    ).sample()
    for i in range(batch.shape[0]):
        e, t = int(batch["episode"][i]), int(batch["step"][i])
        *_, hist, _, _, _, valid = reference(e, t, lengths[e], 4, 2, terms[e], final=False)
        assert torch.equal(batch["next", "observation"][i], hist)
        assert bool(batch["chunk_valid"][i]) == valid
    at_end = batch["step"] + 4 == torch.tensor(lengths)[batch["episode"]]
    # the terminated episode needs no bootstrap at its end, the truncated one would
    assert batch["chunk_valid"][at_end & (batch["episode"] == 0)].all()
    assert not batch["chunk_valid"][at_end & (batch["episode"] == 1)].any()


def test_a_file_without_rewards_is_refused_for_rl_naming_it(tmp_path):
    import zarr

    path = tmp_path / "pusht.zarr"
    root = zarr.open_group(str(path), mode="w")
    root.create_group("data").create_array("state", data=torch.rand(10, 5).numpy())
    root["data"].create_array("action", data=torch.rand(10, 2).numpy())
    root.create_group("meta").create_array("episode_ends", data=torch.tensor([4, 10]).numpy())
    eps = load_episodes(path)
    assert episodes_metadata(eps).has_rewards is False
    make_chunk_buffer(eps, obs_horizon=2, pred_horizon=4, batch_size=4)  # imitation needs no rewards
    with pytest.raises(EpisodeDataError, match=r"pusht\.zarr: records no rewards"):
        make_chunk_buffer(eps, obs_horizon=2, pred_horizon=4, rl_horizon=2)
    with pytest.raises(EpisodeDataError, match=r"pusht\.zarr: records no rewards"):
        make_chunk_buffer(eps, obs_horizon=2, pred_horizon=4, rl_horizon=2, capacity=100)


def test_rl_arguments_are_checked():
    eps = make_episodes()
    with pytest.raises(ValueError, match=r"rl_horizon must be in \[1, pred_horizon - obs_horizon \+ 1 = 7\]"):
        make_chunk_buffer(eps, obs_horizon=2, pred_horizon=8, rl_horizon=8)
    with pytest.raises(ValueError, match="gamma must be in"):
        make_chunk_buffer(eps, obs_horizon=2, pred_horizon=8, rl_horizon=2, gamma=1.5)
    with pytest.raises(EpisodeDataError, match=r"hand\.h5: rl_horizon needs the \('next', 'observation'\)"):
        make_chunk_buffer(eps.exclude(("next", "observation")), obs_horizon=2, pred_horizon=8, rl_horizon=2)
    # another reward entry can be summed instead
    eps.set(("next", "bonus"), torch.ones(eps.shape[0], 1))
    batch = make_chunk_buffer(
        eps,
        obs_horizon=2,
        pred_horizon=8,
        batch_size=64,
        rl_horizon=3,
        gamma=0.5,
        reward_key=("next", "bonus"),
    ).sample()
    inside = torch.minimum(torch.tensor([6, 9])[batch["episode"]] - batch["step"], torch.tensor(3))
    expected = sum(0.5**i * (inside > i).float() for i in range(3))
    torch.testing.assert_close(batch["next", "reward"][:, 0], expected)


def test_image_observations_get_their_final_frame():
    # state [e*100 + t], frame value 10 e + t: the history at t+h, the final frame (t = L) included
    parts = []
    for e, n in enumerate((5, 7)):
        frames = (torch.arange(n + 1) + 10 * e).to(torch.uint8).view(n + 1, 1, 1, 1).expand(n + 1, 3, 2, 2)
        obs = {"state": torch.arange(n + 1.0).unsqueeze(1) + 100 * e, "rgb": frames.clone()}
        parts.append(
            assemble_episode(
                e,
                {k: v[:n] for k, v in obs.items()},
                torch.zeros(n, 2),
                reward=torch.ones(n),
                terminated=True,
                final_observation={k: v[n] for k, v in obs.items()},
            )
        )
    eps = attach_metadata(torch.cat(parts), {"has_rewards": True, "has_final_observation": True})
    batch = make_chunk_buffer(eps, obs_horizon=2, pred_horizon=4, batch_size=300, rl_horizon=3).sample()
    lengths = torch.tensor([5, 7])[batch["episode"]].unsqueeze(1)
    steps = (batch["step"].unsqueeze(1) + 3 - 1 + torch.arange(2)).clamp(max=lengths)
    assert batch["next", "observation", "rgb"].shape == (300, 2, 3, 2, 2)
    assert torch.equal(
        batch["next", "observation", "rgb"][:, :, 0, 0, 0].long(), steps + 10 * batch["episode"].unsqueeze(1)
    )
    assert torch.equal(
        batch["next", "observation", "state"][:, :, 0].long(), steps + 100 * batch["episode"].unsqueeze(1)
    )
    assert (batch["step"].unsqueeze(1) + 3 >= lengths).any()  # windows that read the final frame were drawn


@pytest.mark.parametrize("writable", [False, True])
def test_an_anchor_key_draws_windows_only_where_a_chunk_starts(writable):
    # MultiStepActorWrapper's counter: 1, 2, 3, 1, 2, 3, ... from each episode's first step
    eps = make_episodes(lengths=(7, 10), terminated=(True, False))
    counter = torch.cat([torch.arange(7) % 3 + 1, torch.arange(10) % 3 + 1])[:, None]
    eps.set("counter", counter)
    kwargs = dict(obs_horizon=2, pred_horizon=8, batch_size=512, rl_horizon=3, gamma=GAMMA)
    if writable:
        keys = ("episode", "step", "observation", "action", "next", "counter")
        rb = make_chunk_buffer(None, capacity=64, keys=keys, anchor_key="counter", **kwargs)
        rb.extend(eps)
    else:
        rb = make_chunk_buffer(eps, anchor_key="counter", **kwargs)
    batch = rb.sample()
    assert (batch["counter"] == 1).all()
    assert set(batch["step"].tolist()) == {0, 3, 6, 9}  # every chunk start of both episodes, nothing else
    # the windows read what an unanchored buffer reads at the same step
    plain = make_chunk_buffer(eps, **kwargs).sample()
    for step in (0, 3, 6):
        a = batch[(batch["episode"] == 0) & (batch["step"] == step)][0]
        b = plain[(plain["episode"] == 0) & (plain["step"] == step)][0]
        torch.testing.assert_close(a["next", "reward"], b["next", "reward"])
        torch.testing.assert_close(a["next", "observation"], b["next", "observation"])


def test_an_anchor_key_the_data_lack_is_named():
    with pytest.raises(EpisodeDataError, match=r"hand\.h5: anchor_key='counter' names no stored entry"):
        make_chunk_buffer(make_episodes(), obs_horizon=2, pred_horizon=8, anchor_key="counter")


def test_terminated_episodes_only_gives_windows_of_successful_episodes_alone():
    kwargs = dict(obs_horizon=2, pred_horizon=8, batch_size=500, seed=0, rl_horizon=4, gamma=GAMMA)
    rb = make_chunk_buffer(make_episodes(), terminated_episodes_only=True, **kwargs)
    batch = rb.sample()
    assert set(batch["episode"].tolist()) == {0}  # episode 1 was truncated
    assert rb.sampler.window_count(rb.storage) == 6  # every step of the terminated episode
    # a writable (online) buffer with no terminated episode yet gives no window, and says so on sampling
    online = make_chunk_buffer(None, capacity=50, terminated_episodes_only=True, **kwargs)
    online.extend(make_episodes(lengths=(5,), terminated=(False,)))
    assert online.sampler.window_count(online.storage) == 0
    with pytest.raises(EpisodeDataError, match="no episode ended in a terminal state"):
        online.sample()
    online.extend(make_episodes(lengths=(7,), terminated=(True,)))
    assert online.sampler.window_count(online.storage) == 7
    assert set(online.sample()["step"].tolist()) <= set(range(7))


def test_filtered_bc_buffers_drop_the_demonstrations_that_fail_and_count_them():
    from l1flow_rl.commands.cli import compose_config
    from l1flow_rl.finetune.buffers import RLBuffers

    cfg = compose_config(
        ["finetune=filtered_bc", "checkpoint=bc.pt", "finetune.batch_size=300"], command="finetune"
    )
    mixed = make_episodes(lengths=(20, 25, 30), terminated=(True, False, True))  # episode 1 failed
    buffers = RLBuffers(cfg, mixed, 8, seed=0, successful_episodes_only=True)
    assert buffers.demo_episodes == {"kept": 2, "given": 3}
    assert set(buffers.sample_offline()["episode"].tolist()) == {0, 2}
    # the critic algorithms keep every demonstration (a failure is a value target for them)
    every = RLBuffers(cfg, mixed, 8, seed=0)
    assert every.demo_episodes == {"kept": 3, "given": 3}
    assert set(every.sample_offline()["episode"].tolist()) == {0, 1, 2}
    failed = make_episodes(lengths=(20, 25), terminated=(False, False))
    recorded = compose_config(
        ["finetune=filtered_bc", "checkpoint=bc.pt", "finetune.reward=recorded"], command="finetune"
    )
    with pytest.raises(EpisodeDataError, match=r"none of the 2 demonstration episodes .* ends in success"):
        RLBuffers(recorded, failed, 8, seed=0, successful_episodes_only=True)


class _Planted:
    """A pickle that writes a file when unpickled: what a planted ``prefetch.pkl`` could run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_resumed_online_buffer_refuses_a_prefetch_pickle_that_names_code(tmp_path):
    # TorchRL's ReplayBuffer.loads unpickles prefetch.pkl with plain pickle.load
    import pickle

    from l1flow_rl.commands.cli import compose_config
    from l1flow_rl.errors import CheckpointReadError
    from l1flow_rl.finetune.buffers import RLBuffers

    cfg = compose_config(["finetune=qc", "checkpoint=bc.pt", "finetune.batch_size=16"], command="finetune")
    demos = make_episodes(lengths=(20, 25), terminated=(True, False))
    buffers = RLBuffers(cfg, demos, 8, seed=0)
    buffers.online.extend(make_episodes(lengths=(12,), terminated=(True,)))
    buffers.dump_online(tmp_path / "online")
    again = RLBuffers(cfg, demos, 8, seed=0)
    again.load_online(tmp_path / "online")  # what the run wrote: builtins only, read back
    assert len(again.online.storage) == len(buffers.online.storage) == 12

    marker = tmp_path / "ran"
    (tmp_path / "online" / "prefetch.pkl").write_bytes(pickle.dumps(_Planted(marker)))
    with pytest.raises(
        CheckpointReadError, match=r"prefetch\.pkl' cannot be read safely \(it names io\.open\)"
    ):
        RLBuffers(cfg, demos, 8, seed=0).load_online(tmp_path / "online")
    assert not marker.exists()
