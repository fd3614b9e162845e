"""Collector data into the chunk storage: a real TorchRL ``Collector`` (synchronous) on a tiny env,
episodes split across batches, the ring wrapping over old episodes, windows that never straddle episodes."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase, SerialEnv, StepCounter, TransformedEnv

from l1flow_rl.data import EpisodeDataError, attach_metadata, make_chunk_buffer
from l1flow_rl.data.episodes import assemble_episode


class CountingEnv(EnvBase):
    """Observation [episode number, step]; reward = step + 1; terminates after a seeded random length
    in [2, 8]. Every observation names its episode, so a window that straddles two is visible."""

    def __init__(self, index: int = 0, seed: int = 0):
        super().__init__(batch_size=[])
        self.index = index
        self.observation_spec = Composite(observation=Unbounded(shape=(2,)))
        self.action_spec = Bounded(-1.0, 1.0, shape=(1,))
        self.reward_spec = Unbounded(shape=(1,))
        self._rng = torch.Generator().manual_seed(seed + 17 * index)
        self._episodes = 0

    def _reset(self, tensordict=None):
        self._episodes += 1
        self._episode = self.index * 1000 + self._episodes
        self._t = 0
        self._length = int(torch.randint(2, 9, (1,), generator=self._rng))
        return TensorDict({"observation": self._obs()}, batch_size=[])

    def _obs(self):
        return torch.tensor([float(self._episode), float(self._t)])

    def _step(self, tensordict):
        self._t += 1
        terminated = torch.tensor([self._t >= self._length])
        return TensorDict(
            {
                "observation": self._obs(),
                "reward": torch.tensor([float(self._t)]),
                "done": terminated.clone(),
                "terminated": terminated,
            },
            batch_size=[],
        )

    def _set_seed(self, seed):
        return seed


def make_collector(frames_per_batch: int, total: int, max_steps: int | None = None):
    def make(i):
        env = CountingEnv(i)
        return TransformedEnv(env, StepCounter(max_steps)) if max_steps else env

    env = SerialEnv(2, [lambda i=i: make(i) for i in range(2)])
    return Collector(env, None, frames_per_batch=frames_per_batch, total_frames=total)


def check_windows(rb, batch, to, h):
    stored = rb.storage.get(slice(None))
    rows = batch["index"][:, : to + h]
    # every row a window reads belongs to its episode, which is alive (not overwritten)
    assert torch.equal(stored["episode"][rows], batch["episode"].unsqueeze(1).expand_as(rows))
    assert rb.storage.alive[rows].all()
    episode_number = batch["observation"][:, :, 0]
    assert (episode_number == episode_number[:, -1:]).all()
    if ("next", "observation") in batch.keys(True):
        assert (batch["next", "observation"][:, :, 0] == episode_number[:, -1:]).all()


def test_collector_batches_become_contiguous_episodes_and_windows_never_straddle():
    collector = make_collector(frames_per_batch=8, total=200)  # 4 steps per env per batch: episodes split
    rb = make_chunk_buffer(
        None, obs_horizon=2, pred_horizon=6, batch_size=256, seed=0, capacity=1000, rl_horizon=3
    )
    seen = []
    for batch in collector:
        seen.append(batch.clone())
        rb.extend(batch)
        if len(rb.storage):
            check_windows(rb, rb.sample(), 2, 6)
    collector.shutdown()
    held = rb._writer.collector.pending_steps
    stored = rb.storage.get(slice(None))
    assert len(rb.storage) + held == 200  # every collected step is stored or held in an unfinished episode
    # each stored episode is one run of rows: steps 0..L-1 of one env episode, in order, ending done
    ids, counts = torch.unique_consecutive(stored["episode"], return_counts=True)
    assert ids.unique().numel() == ids.numel() and ids.numel() >= 20
    start = 0
    for n in counts.tolist():
        ep = stored[start : start + n]
        assert (ep["observation"][:, 0] == ep["observation"][0, 0]).all()
        assert ep["observation"][:, 1].tolist() == list(range(n)) and ep["step"].tolist() == list(range(n))
        assert torch.equal(ep["next", "observation"][:-1], ep["observation"][1:])
        assert ep["next", "observation"][-1, 1] == n  # the observation after the last action
        assert ep["next", "done"][:, 0].tolist() == [False] * (n - 1) + [True]
        assert ep["next", "terminated"][-1] and not ep["next", "truncated"].any()
        start += n
    # the stored steps are exactly the collected ones of finished episodes
    everything = torch.cat([b.reshape(-1) for b in seen])
    finished = everything["observation"][everything["next", "done"][:, 0], 0].unique()
    collected = {int(e): everything["observation"][everything["observation"][:, 0] == e] for e in finished}
    for e, obs in collected.items():
        assert torch.equal(stored["observation"][stored["observation"][:, 0] == e], obs)
    # the RL entries over online data: the chunk return by hand (reward = step + 1, gamma 0.99)
    batch = rb.sample()
    lengths = {
        int(e): int((stored["observation"][:, 0] == e).sum()) for e in stored["observation"][:, 0].unique()
    }
    ends_terminated = {
        e: bool(stored["next", "terminated"][stored["observation"][:, 0] == e][-1]) for e in lengths
    }
    for i in range(batch.shape[0]):
        e = int(batch["observation"][i, -1, 0])
        n, t = lengths[e], int(batch["step"][i])
        expected = sum(0.99**k * (t + k + 1) for k in range(min(3, n - t)))
        assert batch["next", "reward"][i].item() == pytest.approx(expected, rel=1e-6)
        # a chunk crossing a terminal end stays valid (its return is summed to that end)
        assert bool(batch["chunk_valid"][i]) == (t + 3 <= n or ends_terminated[e])


def test_the_ring_drops_overwritten_episodes_whole_and_index_rows_match():
    collector = make_collector(frames_per_batch=10, total=300, max_steps=6)  # some episodes truncated
    rb = make_chunk_buffer(None, obs_horizon=2, pred_horizon=4, batch_size=128, seed=1, capacity=40)
    wrapped = False
    for batch in collector:
        index = rb.extend(batch)
        assert index.shape == batch.shape  # the collector batch gets its rows ("index"), -1 where held
        written = index >= 0
        if written.any():
            stored = rb.storage.get(index[written])
            assert torch.equal(stored["observation"], batch["observation"][written])
        wrapped |= rb._writer._cursor < len(rb.storage)
        if len(rb.storage):
            check_windows(rb, rb.sample(), 2, 4)
    collector.shutdown()
    assert wrapped and len(rb.storage) <= 40
    stored = rb.storage.get(slice(None))
    alive = rb.storage.alive[: len(rb.storage)]
    # a live episode is whole: it starts at step 0 and ends with done
    for e in stored["episode"][alive].unique():
        rows = (stored["episode"] == e).nonzero().squeeze(1)
        assert alive[rows].all() and stored["step"][rows].tolist() == list(range(rows.numel()))
        assert stored["next", "done"][rows[-1]]
    truncated = stored["next", "truncated"][alive][:, 0]
    terminated = stored["next", "terminated"][alive][:, 0]
    assert (truncated & ~terminated).any()  # StepCounter's time limit ends some episodes early
    assert (terminated & ~truncated).any()


def test_demonstrations_seed_the_online_buffer_and_keys_are_checked():
    demos = torch.cat(
        [
            assemble_episode(
                e,
                torch.tensor([[5000.0 + e, t] for t in range(6)]),
                torch.zeros(6, 1),
                reward=torch.ones(6),
                terminated=True,
                final_observation=torch.tensor([5000.0 + e, 6]),
            )
            for e in range(3)
        ]
    )
    demos.set(("next", "success"), torch.ones(18, 1, dtype=torch.bool))  # extra entries are left out
    attach_metadata(demos, {"source": "demos.h5", "has_rewards": True, "control": "delta"})
    rb = make_chunk_buffer(demos, obs_horizon=2, pred_horizon=4, batch_size=64, capacity=200, rl_horizon=2)
    assert len(rb.storage) == 18 and rb.storage.metadata.control == "delta"
    collector = make_collector(frames_per_batch=10, total=40)
    for batch in collector:
        rb.extend(batch)
    collector.shutdown()
    stored = rb.storage.get(slice(None))
    assert ("next", "success") not in stored.keys(True)
    assert stored["episode"].unique().numel() == stored["episode"].unique_consecutive().numel()
    check_windows(rb, rb.sample(), 2, 4)
    with pytest.raises(EpisodeDataError, match="episode 7: its last step has no"):
        unfinished = demos[:4].clone()
        unfinished["episode"][:] = 7
        rb.extend(unfinished)
    with pytest.raises(KeyError, match="lack"):
        rb.extend(demos.exclude(("next", "observation")))
    no_rewards = attach_metadata(demos.clone(), {"source": "plain.zarr", "has_rewards": False})
    with pytest.raises(EpisodeDataError, match=r"plain\.zarr: records no rewards"):
        rb.extend(no_rewards)


def test_writer_state_round_trips(tmp_path):
    collector = make_collector(frames_per_batch=10, total=120)
    rb = make_chunk_buffer(None, obs_horizon=2, pred_horizon=4, batch_size=32, seed=3, capacity=50)
    for batch in collector:
        rb.extend(batch)
    collector.shutdown()
    rb.dumps(tmp_path / "rb")
    again = make_chunk_buffer(None, obs_horizon=2, pred_horizon=4, batch_size=32, seed=3, capacity=50)
    again.loads(tmp_path / "rb")
    assert torch.equal(again.storage.alive, rb.storage.alive) and len(again.storage) == len(rb.storage)
    assert torch.equal(
        again.storage.get(slice(None))["observation"], rb.storage.get(slice(None))["observation"]
    )
    assert torch.equal(again.sample()["index"], rb.sample()["index"])  # same rows, same windows


def test_a_collector_given_the_buffer_writes_into_it_directly():
    rb = make_chunk_buffer(None, obs_horizon=2, pred_horizon=4, batch_size=64, seed=0, capacity=500)
    env = SerialEnv(2, [lambda i=i: CountingEnv(i) for i in range(2)])
    collector = Collector(env, None, frames_per_batch=10, total_frames=100, replay_buffer=rb)
    for _ in collector:
        pass
    collector.shutdown()
    assert len(rb.storage) + rb._writer.collector.pending_steps == 100
    assert rb._writer.flush() > 0 and rb._writer.collector.pending_steps == 0  # held steps end truncated
    stored = rb.storage.get(slice(None))
    assert stored["next", "truncated"][-1] and len(rb.storage) == 100
    check_windows(rb, rb.sample(), 2, 4)


def test_a_reset_without_done_ends_the_held_steps_as_truncated():
    # reset_at_each_iter: every batch starts new trajectories (new traj_ids) without a done before them
    env = SerialEnv(2, [lambda i=i: CountingEnv(i) for i in range(2)])
    collector = Collector(env, None, frames_per_batch=6, total_frames=60, reset_at_each_iter=True)
    rb = make_chunk_buffer(None, obs_horizon=1, pred_horizon=2, batch_size=64, seed=0, capacity=500)
    for batch in collector:
        rb.extend(batch)
    collector.shutdown()
    stored = rb.storage.get(slice(None))
    ends = stored["next", "done"][:, 0]
    cut = ends & ~stored["next", "terminated"][:, 0]
    assert cut.any() and stored["next", "truncated"][:, 0][cut].all()
    # a cut episode is a prefix of an env episode: steps 0..k, ending where the batch ended
    for e in stored["episode"][cut].tolist():
        obs = stored["observation"][stored["episode"] == e]
        assert obs[:, 1].tolist() == list(range(obs.shape[0])) and (obs[:, 0] == obs[0, 0]).all()
