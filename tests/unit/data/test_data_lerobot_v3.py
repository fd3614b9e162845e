"""LeRobot v3.0 folders both ways: written by the project and read back, written by hand with pyarrow
and PyAV (a different route) and read, refused with a message naming the key or file, and trained on
by ``l1flow-rl train data.path=<folder>``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pa = pytest.importorskip("pyarrow", reason="LeRobot v3 needs the lerobot extra")
pq = pytest.importorskip("pyarrow.parquet")
av = pytest.importorskip("av", reason="LeRobot v3 videos need PyAV (the lerobot extra)")

from l1flow_rl.data import EpisodeDataError, episodes_metadata, load_episodes  # noqa: E402
from l1flow_rl.data.episodes import assemble_episode  # noqa: E402
from l1flow_rl.data.formats.lerobot_v3_writer import write_lerobot_v3  # noqa: E402
from l1flow_rl.data.metadata import attach_metadata  # noqa: E402

FPS = 10


def _frames(episode: int, steps: int, side: int = 32) -> torch.Tensor:
    """uint8 [T, 3, H, W]: smooth gradients, each frame 24 levels brighter than the one before, so a
    frame read from the wrong time is off by >= 24 levels while codec noise stays a few levels."""
    ys, xs = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
    frames = [
        torch.stack([xs * 2 + 24 * t + 8 * episode, ys * 2 + 20, (xs + ys) + 40]).clamp(0, 255)
        for t in range(steps)
    ]
    return torch.stack(frames).to(torch.uint8)


def _episodes(lengths=(5, 8, 6), images: bool = True):
    g = torch.Generator().manual_seed(0)
    parts = []
    for e, steps in enumerate(lengths):
        obs = {"state": torch.randn(steps, 4, generator=g), **({"rgb": _frames(e, steps)} if images else {})}
        parts.append(
            assemble_episode(
                e,
                obs if images else obs["state"],
                torch.randn(steps, 2, generator=g),
                reward=torch.rand(steps, generator=g),
                terminated=e != 1,
                next_extra={"success": torch.arange(steps) == steps - 1},
            )
        )
    meta = {
        "format": "maniskill",
        "env_id": "PickCube-v1",
        "control_mode": "pd_ee_delta_pos",
        "control": "delta",
        "has_rewards": True,
    }
    return attach_metadata(torch.cat(parts, 0), meta)


def _leaves(td):
    return {k for k in td.keys(True, True) if k != "episodes_metadata"}


def test_written_with_image_columns_reads_back_equal_in_every_key(tmp_path):
    eps = _episodes()
    root = write_lerobot_v3(eps, tmp_path / "ds", fps=FPS, cameras="image")
    back = load_episodes(root)
    assert _leaves(back) == _leaves(eps)
    for key in _leaves(eps):
        assert torch.equal(back.get(key), eps.get(key)), key  # PNG cells: frames bit-exact
    meta = episodes_metadata(back)
    assert meta.format == "lerobot_v3" and meta.env_id == "PickCube-v1"
    assert meta.control_mode == "pd_ee_delta_pos" and meta.control == "delta"
    assert meta.has_rewards and meta.has_final_observation is False
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["total_frames"] == 19 and info["total_episodes"] == 3
    assert info["features"]["observation.images.rgb"] == {
        "dtype": "image",
        "shape": [32, 32, 3],
        "names": ["height", "width", "channels"],
    }
    stats = json.loads((root / "meta" / "stats.json").read_text())
    assert stats["action"]["max"] == pytest.approx(eps["action"].amax(0).tolist(), rel=1e-6)
    assert np.asarray(stats["observation.images.rgb"]["mean"]).shape == (3, 1, 1)
    assert not (root / "videos").exists()


def test_written_as_video_reads_back_with_frames_aligned_and_within_codec_noise(tmp_path):
    eps = _episodes()
    root = write_lerobot_v3(eps, tmp_path / "ds", fps=FPS, cameras="video")
    assert (root / "videos" / "observation.images.rgb" / "chunk-000" / "file-000.mp4").is_file()
    back = load_episodes(root)
    for key in _leaves(eps):
        if "rgb" not in key:
            assert torch.equal(back.get(key), eps.get(key)), key
    # H.264 in yuv420p is lossy: each frame is checked to be the right one (nearest to its own original
    # among all frames) and within a few levels of it; measured mean 1.0, max 8 levels at crf 18
    got, want = back["observation", "rgb"].float(), eps["observation", "rgb"].float()
    per_frame = (got - want).abs().mean((1, 2, 3))
    assert per_frame.max() < 3.0, per_frame
    distance = (got[:, None] - want[None]).abs().mean((2, 3, 4))
    assert torch.equal(distance.argmin(1), torch.arange(len(eps)))
    episodes = pq.read_table(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    assert [e["videos/observation.images.rgb/from_timestamp"] for e in episodes] == [0.0, 0.5, 1.3]
    assert [(e["dataset_from_index"], e["dataset_to_index"]) for e in episodes] == [(0, 5), (5, 13), (13, 19)]


def _encode_av1(path, frames: np.ndarray, fps: int) -> None:
    """AV1 through SVT-AV1 (LeRobot's default codec), PyAV's default time base: another route than ours."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libsvtav1", rate=fps)
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        # every frame a key frame: with g=2, SVT-AV1 coded this synthetic brightness ramp's inter
        # frames as copies of the key frame before (each odd frame decoded 24 levels off)
        stream.options = {"g": "1", "crf": "20", "preset": "12"}
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def _by_hand(root, *, lengths=(4, 6, 5), info_changes=None, episode_index=None, state_dim=3):
    """A v3 folder written with pyarrow and PyAV directly: list<float> columns (not fixed-size),
    two data files, the camera as AV1, an environment_state feature, next.done without next.terminated."""
    rng = np.random.default_rng(1)
    features = {
        "observation.state": {"dtype": "float32", "shape": [state_dim], "names": ["x", "y", "z"][:state_dim]},
        "observation.environment_state": {"dtype": "float32", "shape": [2], "names": None},
        "observation.images.top": {
            "dtype": "video",
            "shape": [64, 64, 3],
            "names": ["height", "width", "channels"],
        },
        "action": {"dtype": "float32", "shape": [2], "names": ["vx", "vy"]},
        "next.reward": {"dtype": "float32", "shape": [1], "names": None},
        "next.done": {"dtype": "bool", "shape": [1], "names": None},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    info = {
        "codebase_version": "v3.0",
        "robot_type": "so100",
        "total_episodes": len(lengths),
        "total_frames": sum(lengths),
        "total_tasks": 1,
        "chunks_size": 1000,
        "fps": 15,
        "splits": {"train": f"0:{len(lengths)}"},
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
        "features": features,
        **(info_changes or {}),
    }
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(json.dumps(info))
    truth, rows, video = [], [], []
    start = 0
    for e, steps in enumerate(lengths):
        ep = {
            "state": rng.normal(size=(steps, state_dim)).astype(np.float32),
            "env": rng.normal(size=(steps, 2)).astype(np.float32),
            "action": rng.normal(size=(steps, 2)).astype(np.float32),
            "reward": rng.random(steps).astype(np.float32),
            "done": np.arange(steps) == steps - 1,
            "frames": _frames(e, steps, side=64).permute(0, 2, 3, 1).numpy(),
        }
        truth.append(ep)
        video.append(ep["frames"])
        rows.append(
            {
                "episode_index": e if episode_index is None else episode_index[e],
                "tasks": ["reach"],
                "length": steps,
                "data/chunk_index": 0,
                "data/file_index": 0 if e < 2 else 1,  # the last episode in a second data file
                "dataset_from_index": start,
                "dataset_to_index": start + steps,
                "videos/observation.images.top/chunk_index": 0,
                "videos/observation.images.top/file_index": 0,
                "videos/observation.images.top/from_timestamp": start / 15,
                "videos/observation.images.top/to_timestamp": (start + steps) / 15,
            }
        )
        start += steps
    for file_index, eps in ((0, [0, 1]), (1, [2])):
        table = {
            "observation.state": [list(r) for e in eps for r in truth[e]["state"]],
            "observation.environment_state": [list(r) for e in eps for r in truth[e]["env"]],
            "action": [list(r) for e in eps for r in truth[e]["action"]],
            "next.reward": np.concatenate([truth[e]["reward"] for e in eps]),
            "next.done": np.concatenate([truth[e]["done"] for e in eps]),
            "timestamp": np.concatenate([np.arange(lengths[e]) / 15 for e in eps]).astype(np.float32),
            "frame_index": np.concatenate([np.arange(lengths[e]) for e in eps]),
            "episode_index": np.concatenate([np.full(lengths[e], e) for e in eps]),
            "task_index": np.zeros(sum(lengths[e] for e in eps), dtype=np.int64),
        }
        table["index"] = np.arange(len(table["timestamp"])) + sum(lengths[: file_index * 2])
        path = root / info["data_path"].format(chunk_index=0, file_index=file_index)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table({k: pa.array(v) for k, v in table.items()}), path)
    (root / "meta" / "episodes" / "chunk-000").mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(rows), root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    pq.write_table(pa.table({"task_index": [0], "task": ["reach"]}), root / "meta" / "tasks.parquet")
    _encode_av1(
        root / "videos" / "observation.images.top" / "chunk-000" / "file-000.mp4", np.concatenate(video), 15
    )
    return truth


def test_a_folder_written_by_hand_with_pyarrow_and_av1_reads_correctly(tmp_path):
    truth = _by_hand(tmp_path / "ds")
    eps = load_episodes(tmp_path / "ds")
    assert eps.batch_size == (15,)
    assert set(eps["observation"].keys()) == {"state", "environment_state", "top"}
    for e, want in enumerate(truth):
        ep = eps[eps["episode"] == e]
        assert torch.equal(ep["step"], torch.arange(len(want["action"])))
        assert torch.equal(ep["observation", "state"], torch.from_numpy(want["state"]))
        assert torch.equal(ep["observation", "environment_state"], torch.from_numpy(want["env"]))
        assert torch.equal(ep["action"], torch.from_numpy(want["action"]))
        assert torch.equal(ep["next", "reward"].reshape(-1), torch.from_numpy(want["reward"]))
        assert ep["next", "done"][-1] and not ep["next", "done"][:-1].any()
        assert ep["next", "terminated"][-1]  # next.done is LeRobot's only end flag here: read as terminal
        frames = ep["observation", "top"]
        assert frames.shape == (len(want["action"]), 3, 64, 64) and frames.dtype == torch.uint8
        error = (frames.permute(0, 2, 3, 1).float() - torch.from_numpy(want["frames"]).float()).abs()
        assert error.mean((1, 2, 3)).max() < 3.0  # AV1 at crf 20: a few levels; a wrong frame is >= 24 off
    meta = episodes_metadata(eps)
    assert meta.has_rewards and meta.env_id is None and meta.control is None
    assert meta.extra["fps"] == 15.0 and meta.extra["robot_type"] == "so100"
    state_only = load_episodes(tmp_path / "ds", cameras=None)
    assert set(state_only["observation"].keys()) == {"state", "environment_state"}


def test_a_v2_1_folder_is_refused_naming_its_version(tmp_path):
    root = tmp_path / "old"
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(
        json.dumps({"codebase_version": "v2.1", "fps": 10, "features": {}})
    )
    (root / "meta" / "episodes.jsonl").write_text('{"episode_index": 0, "length": 3}\n')
    with pytest.raises(EpisodeDataError, match=r"a LeRobot v2\.1 data set .* this reader expects v3\.0"):
        load_episodes(root)


def test_missing_feature_gaps_and_shapes_are_named(tmp_path):
    _by_hand(
        tmp_path / "a", info_changes={"features": {"observation.state": {"dtype": "float32", "shape": [3]}}}
    )
    with pytest.raises(EpisodeDataError, match=r"info\.json: key 'features\.action': missing"):
        load_episodes(tmp_path / "a")
    _by_hand(tmp_path / "b", episode_index=[0, 2, 3])
    with pytest.raises(EpisodeDataError, match=r"key 'episode_index'.* without gaps; missing \[1\]"):
        load_episodes(tmp_path / "b")
    _by_hand(tmp_path / "c")
    info = json.loads((tmp_path / "c" / "meta" / "info.json").read_text())
    info["features"]["observation.state"]["shape"] = [5]
    (tmp_path / "c" / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(EpisodeDataError, match=r"file-000\.parquet: key 'observation\.state'.* shape \[5\]"):
        load_episodes(tmp_path / "c")


def test_train_on_a_v3_folder_end_to_end(tmp_path):
    from doubles.point_mass import POINT_MASS_TASK, TASK_OVERRIDES

    from l1flow_rl.commands.cli import main
    from l1flow_rl.experts import ensure_demos
    from l1flow_rl.workspace.checkpoint import load_checkpoint

    demos = load_episodes(ensure_demos(POINT_MASS_TASK, 3, tmp_path / "data"))
    folder = write_lerobot_v3(demos, tmp_path / "point_mass_v3", fps=10)
    run_dir = tmp_path / "run"
    args = [
        *TASK_OVERRIDES,
        f"data.path={folder}",
        "train.steps=8",
        "train.batch_size=16",
        "train.warmup_steps=2",
        "eval.episodes=2",
        "eval.num_envs=1",
        "network.down_dims=[16,32]",
        "device=cpu",
        f"data_dir={tmp_path / 'data'}",
        f"run_dir={run_dir}",
    ]
    assert main(["train", *args]) == 0
    state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert state["step"] == 8 and state["obs_shapes"] == {"state": [6]} and state["action_dim"] == 2
    assert all(np.isfinite(state["history"]["loss"]))
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["episodes"] == 2
