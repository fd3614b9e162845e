"""Chunk windows: padding at both episode ends, reproducibility, storage reuse, normaliser fitting."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from tensordict import MemoryMappedTensor, TensorDict
from torchrl.data import TensorDictReplayBuffer

from l1flow_rl import L1FlowActor
from l1flow_rl.data import (
    EpisodeDataError,
    episodes_metadata,
    fit_normalizers,
    load_episodes,
    make_chunk_buffer,
)

LENGTHS = (1, 3, 7, 20, 40)  # includes episodes shorter than the obs and the prediction horizon


def make_steps(lengths=LENGTHS, obs_dim=3, action_dim=4, rgb=False) -> TensorDict:
    """Episode e, step t: observation e*1000 + t (+ 0.1 * column), action -(e*1000 + t) (+ column), so
    every read row can be traced back."""
    parts = []
    for e, n in enumerate(lengths):
        base = (e * 1000 + torch.arange(n, dtype=torch.float32)).unsqueeze(1)
        obs = base + 0.1 * torch.arange(obs_dim)
        observation = obs
        if rgb:
            image = (torch.arange(n) % 256).to(torch.uint8).view(n, 1, 1, 1).expand(n, 3, 4, 5).clone()
            observation = TensorDict({"state": obs, "rgb": image}, batch_size=[n])
        parts.append(
            TensorDict(
                {
                    "episode": torch.full((n,), e + 10),  # ids need not start at 0
                    "observation": observation,
                    "action": -base + torch.arange(action_dim),
                    "next": {"reward": torch.ones(n, 1), "done": torch.arange(n).eq(n - 1).unsqueeze(1)},
                },
                batch_size=[n],
            )
        )
    return torch.cat(parts)


def reference_window(steps: TensorDict, episode: int, t: int, to: int, h: int, pad: str, gripper=(-1,)):
    """Diffusion Policy's padded window, written out step by step."""
    rows = (steps["episode"] == episode).nonzero().squeeze(1)
    start, n = int(rows[0]), rows.numel()
    obs = torch.stack([steps["observation"][start + max(t + k, 0)] for k in range(1 - to, 1)])
    actions, is_pad = [], []
    for k in range(1 - to, h - to + 1):
        s = t + k
        if s < 0:
            actions.append(steps["action"][start])
        elif s >= n:
            last = steps["action"][start + n - 1].clone()
            if pad == "delta":
                keep = torch.zeros_like(last, dtype=torch.bool)
                keep[list(gripper)] = True
                last = torch.where(keep, last, torch.zeros_like(last))
            actions.append(last)
        else:
            actions.append(steps["action"][start + s])
        is_pad.append(s < 0 or s >= n)
    return obs, torch.stack(actions), torch.tensor(is_pad)


@pytest.mark.parametrize("pad", ["repeat", "delta"])
@pytest.mark.parametrize("to,h", [(2, 16), (1, 4), (3, 5)])
def test_windows_match_reference_padding(pad, to, h):
    steps = make_steps()
    rb = make_chunk_buffer(steps, obs_horizon=to, pred_horizon=h, batch_size=2000, seed=1, action_pad=pad)
    batch = rb.sample()
    assert batch["observation"].shape == (2000, to, 3)
    assert batch["action_chunk"].shape == (2000, h, 4)
    assert batch["action_is_pad"].shape == (2000, h) and batch["action_is_pad"].dtype == torch.bool
    # every step of every episode is a current step, the first and last included
    assert batch.shape == (2000,) and len(set(zip(batch["episode"].tolist(), batch["step"].tolist()))) == sum(
        LENGTHS
    )
    for i in range(batch.shape[0]):
        obs, actions, is_pad = reference_window(
            steps, int(batch["episode"][i]), int(batch["step"][i]), to, h, pad
        )
        torch.testing.assert_close(batch["observation"][i], obs, rtol=0, atol=0)
        torch.testing.assert_close(batch["action_chunk"][i], actions, rtol=0, atol=0)
        assert torch.equal(batch["action_is_pad"][i], is_pad)
    # the chunk step To-1 is the action taken at the current step
    current = batch["action_chunk"][:, to - 1]
    expected = (
        -(batch["episode"] - 10).float().unsqueeze(1) * 1000
        - batch["step"].float().unsqueeze(1)
        + torch.arange(4)
    )
    torch.testing.assert_close(current, expected)


def test_contract_shapes_and_rgb_windows():
    steps = make_steps(rgb=True)
    rb = make_chunk_buffer(steps, obs_horizon=2, pred_horizon=16, batch_size=64, seed=0)
    assert isinstance(rb, TensorDictReplayBuffer)
    batch = rb.sample()
    assert batch["observation", "state"].shape == (64, 2, 3)
    assert (
        batch["observation", "rgb"].shape == (64, 2, 3, 4, 5)
        and batch["observation", "rgb"].dtype == torch.uint8
    )
    assert batch["action_chunk"].shape == (64, 16, 4)
    assert batch["episode"].shape == (64,) and batch["step"].shape == (64,)
    assert batch["action_is_pad"].shape == (64, 16)
    # the image rows follow the state rows (frame value = step % 256, first frame repeated before the start)
    frame = batch["observation", "rgb"][:, :, 0, 0, 0].long()
    state_step = batch["observation", "state"][:, :, 0].long() % 1000
    assert torch.equal(frame, state_step % 256)
    assert torch.equal(state_step[:, 1], batch["step"])


def test_same_seed_same_batches_and_prefetch():
    steps = make_steps()
    draws = []
    for prefetch in (None, None, 1):
        rb = make_chunk_buffer(steps, batch_size=32, seed=7, prefetch=prefetch)
        draws.append(torch.stack([rb.sample()["index"] for _ in range(5)]))
    assert torch.equal(draws[0], draws[1])
    assert torch.equal(draws[0], draws[2])  # one prefetch thread keeps the order
    other = make_chunk_buffer(steps, batch_size=32, seed=8).sample()["index"]
    assert not torch.equal(other, draws[0][0])


def test_max_pad_after_caps_padding_and_rejects_short_episodes():
    steps = make_steps(lengths=(10, 12))
    rb = make_chunk_buffer(steps, obs_horizon=2, pred_horizon=16, batch_size=500, seed=0, max_pad_after=7)
    batch = rb.sample()
    padded_after = (batch["action_is_pad"] & (torch.arange(16) > 1)).sum(1)  # past the current step
    assert int(padded_after.max()) == 7
    with pytest.raises(EpisodeDataError, match=r"demo\.h5: episode 11: key 'action': 3 steps is too short"):
        make_chunk_buffer(make_steps(lengths=(10, 3)), max_pad_after=7, source="demo.h5")


def test_bad_episode_layouts():
    steps = make_steps(lengths=(3, 4))
    shuffled = steps[torch.tensor([0, 1, 3, 4, 2, 5, 6])]  # episode 10 split in two runs
    with pytest.raises(
        EpisodeDataError, match="episode 10: key 'episode': the episode's steps are not contiguous"
    ):
        make_chunk_buffer(shuffled)
    with pytest.raises(KeyError, match="'action'"):
        make_chunk_buffer(steps.exclude("action"))
    with pytest.raises(ValueError, match="obs_horizon <= pred_horizon"):
        make_chunk_buffer(steps, obs_horizon=4, pred_horizon=3)
    with pytest.raises(ValueError, match="action_pad"):
        make_chunk_buffer(steps, action_pad="zeros")


def test_storage_dir_is_reused_and_guarded(tmp_path):
    steps = make_steps()
    first = make_chunk_buffer(steps, batch_size=16, seed=3, storage_dir=tmp_path / "store")
    files = {p: p.stat().st_mtime_ns for p in (tmp_path / "store").rglob("*.memmap")}
    again = make_chunk_buffer(steps, batch_size=16, seed=3, storage_dir=tmp_path / "store")
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "store").rglob("*.memmap")} == files
    assert torch.equal(first.sample()["action_chunk"], again.sample()["action_chunk"])
    with pytest.raises(EpisodeDataError, match="holds a stored copy of other episodes"):
        make_chunk_buffer(make_steps(lengths=(5, 6)), storage_dir=tmp_path / "store")
    with pytest.raises(RuntimeError, match="doesn't allow writing"):
        again.extend(steps[:2])
    # an index that is not a window reads plain rows
    assert torch.equal(again[torch.tensor([0, 2])]["action"], steps["action"][[0, 2]])


def _small_robomimic_file(path: Path) -> Path:
    import h5py

    with h5py.File(path, "w") as f:
        for i, n in enumerate((6, 9)):
            g = f.create_group(f"data/demo_{i}")
            g["obs/pos"] = torch.arange(n * 2.0).view(n, 2).numpy() + 100 * i
            g["actions"] = torch.ones(n, 3).numpy() * i
            g["rewards"] = torch.zeros(n).numpy()
            g["dones"] = torch.arange(n).eq(n - 1).numpy()
    return path


def test_memmapped_episodes_are_used_in_place(tmp_path):
    path = _small_robomimic_file(tmp_path / "robomimic.hdf5")
    eps = load_episodes(path, memmap_dir=tmp_path / "mm")
    assert isinstance(eps["action"], MemoryMappedTensor) and eps.shape == (15,)
    files = {p: p.stat().st_mtime_ns for p in (tmp_path / "mm").rglob("*.memmap")}
    rb = make_chunk_buffer(eps, obs_horizon=2, pred_horizon=4, batch_size=8)
    assert Path(rb.storage.scratch_dir) == tmp_path / "mm"  # the stored copy itself, no second copy
    again = load_episodes(path, memmap_dir=tmp_path / "mm")  # reopened, not rewritten
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "mm").rglob("*.memmap")} == files
    assert torch.equal(again["observation"], eps["observation"])
    with pytest.raises(EpisodeDataError, match="holds a stored copy of"):
        load_episodes(path, memmap_dir=tmp_path / "mm", state_keys=[])


def test_runs_storing_the_same_file_at_once_share_the_first_copy(tmp_path, monkeypatch):
    """Runs trained side by side on one data_dir store the same demonstrations at once: the one that
    finishes second finds the first one's copy under the final name, checks it and reads it."""
    import subprocess
    import sys

    from l1flow_rl.data import loading

    path = _small_robomimic_file(tmp_path / "robomimic.hdf5")
    target = tmp_path / "mm"
    publish = loading.publish_dir

    def another_process_finishes_first(tmp, dest):
        code = f"import l1flow_rl.data as d; d.load_episodes({str(path)!r}, memmap_dir={str(dest)!r})"
        subprocess.run([sys.executable, "-c", code], check=True)
        assert (dest / loading.SOURCE_FILE).is_file()
        return publish(tmp, dest)  # the real rename, onto the other process's copy

    monkeypatch.setattr(loading, "publish_dir", another_process_finishes_first)
    eps = load_episodes(path, memmap_dir=target)
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["mm", "robomimic.hdf5"]  # our partial copy is gone, theirs is the one
    assert eps.shape == (15,) and torch.equal(eps["action"][6:], torch.ones(9, 3))
    assert Path(episodes_metadata(eps).extra["memmap_dir"]) == target.resolve()


def test_publish_dir_replaces_an_empty_target_and_yields_to_a_full_one(tmp_path):
    from l1flow_rl.data.publish import publish_dir

    ours, target = tmp_path / "ours", tmp_path / "target"
    ours.mkdir()
    (ours / "a").write_text("ours")
    target.mkdir()
    assert publish_dir(ours, target) and (target / "a").read_text() == "ours" and not ours.exists()
    ours.mkdir()
    (ours / "a").write_text("late")
    assert not publish_dir(ours, target)  # someone published first: theirs stays
    assert (target / "a").read_text() == "ours" and (ours / "a").read_text() == "late"


@pytest.mark.parametrize("mode", ["limits", "gaussian"])
def test_fit_normalizers_from_episodes_or_buffer(mode):
    steps = make_steps()
    actor = L1FlowActor.for_state(obs_dim=3, action_dim=4, obs_horizon=2, pred_horizon=16, down_dims=(8, 16))
    policy = fit_normalizers(actor, steps, mode=mode)
    obs = policy.obs_normalizer["state"].normalize(steps["observation"])
    act = policy.action_normalizer.normalize(steps["action"])
    if mode == "limits":
        torch.testing.assert_close(act.amin(0), -torch.ones(4), atol=1e-5, rtol=0)
        torch.testing.assert_close(obs.amax(0), torch.ones(3), atol=1e-5, rtol=0)
    else:
        torch.testing.assert_close(act.mean(0), torch.zeros(4), atol=1e-4, rtol=0)
        torch.testing.assert_close(obs.std(0, correction=0), torch.ones(3), atol=1e-4, rtol=0)
    other = L1FlowActor.for_state(obs_dim=3, action_dim=4, obs_horizon=2, pred_horizon=16, down_dims=(8, 16))
    fit_normalizers(other.policy, make_chunk_buffer(steps, batch_size=4), mode=mode)
    for mine, theirs in [
        (policy.obs_normalizer, other.policy.obs_normalizer),
        (policy.action_normalizer, other.policy.action_normalizer),
    ]:
        for a, b in zip(mine.state_dict().values(), theirs.state_dict().values()):
            assert torch.equal(a, b)
