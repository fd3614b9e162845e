"""Images end to end on real ManiSkill rgb demonstrations: uint8 from the file through memory-mapped
storage and the replay buffer to the encoder, a short training run, and an image task refused with
a state-only encoder before any demonstration is made."""

from __future__ import annotations

import json

import pytest
import torch
from tensordict import MemoryMappedTensor

from l1flow_rl.commands.cli import compose_config, main
from l1flow_rl.config import load_task_config
from l1flow_rl.data import load_episodes, make_chunk_buffer
from l1flow_rl.networks.encoders import ImageObservationEncoder
from l1flow_rl.workspace.build import build_actor, build_loss

pytestmark = pytest.mark.maniskill

TASK = "maniskill_pickcube_rgb"


@pytest.fixture(scope="module")
def rgb_demos(tmp_path_factory):
    from l1flow_rl.experts import ensure_demos

    data_dir = tmp_path_factory.mktemp("rgb_demos")
    path = ensure_demos(load_task_config(TASK), 3, data_dir, progress=False)
    return data_dir, path


@pytest.fixture(scope="module")
def rgb_episodes(rgb_demos, tmp_path_factory):
    _, path = rgb_demos
    return load_episodes(path, memmap_dir=tmp_path_factory.mktemp("memmap") / "steps.memmap")


def _small_actor(cfg, episodes):
    obs = episodes["observation"]
    shapes = {k: tuple(v.shape[1:]) for k, v in obs.items()}
    return build_actor(cfg.policy, shapes, int(episodes["action"].shape[-1]), cfg.encoder, cfg.network)


def test_images_stay_uint8_from_storage_to_the_encoder(rgb_episodes):
    eps = rgb_episodes
    rgb = eps.get(("observation", "rgb"))
    assert rgb.dtype == torch.uint8 and tuple(rgb.shape[1:]) == (3, 128, 128)
    assert isinstance(rgb, MemoryMappedTensor) and rgb.filename is not None  # on disk, not in RAM
    rb = make_chunk_buffer(eps, obs_horizon=2, pred_horizon=16, batch_size=8, seed=0)
    stored = rb.storage._storage
    images = [(k, v) for k, v in stored.items(include_nested=True, leaves_only=True) if v.dim() >= 4]
    assert images, "the buffer holds no image entry"
    for key, value in images:  # no float copy of any image entry
        assert value.dtype == torch.uint8, key
        assert isinstance(value, MemoryMappedTensor), key
    batch = rb.sample()
    assert batch.get(("observation", "rgb")).dtype == torch.uint8
    assert batch.get(("observation", "rgb")).shape == (8, 2, 3, 128, 128)
    assert batch.get(("observation", "state")).dtype == torch.float32

    cfg = compose_config([f"task={TASK}", "network.down_dims=[32,64,128]"])
    actor = _small_actor(cfg, eps)
    encoder = actor.policy.encoder
    assert isinstance(encoder, ImageObservationEncoder)
    seen = {}

    def record(name):
        def hook(module, args):
            seen.setdefault(name, args[0])  # returns None: the input goes on unchanged

        return hook

    encoder.register_forward_pre_hook(record("encoder_in"))
    encoder.nets["rgb"].trunk.conv1.register_forward_pre_hook(record("conv_in"))
    build_loss(actor, cfg.policy)(batch)
    assert seen["encoder_in"].get("rgb").dtype == torch.uint8  # the loss hands the encoder bytes...
    conv_in = seen["conv_in"]
    assert conv_in.dtype == torch.float32 and conv_in.shape == (16, 3, 115, 115)  # ...it crops and scales
    assert float(conv_in.min()) >= -1.0 and float(conv_in.max()) <= 1.0


def test_short_training_on_three_rgb_demos_lowers_the_loss(rgb_episodes):
    from l1flow_rl.data import fit_normalizers
    from l1flow_rl.workspace.trainer import Trainer

    torch.manual_seed(0)
    cfg = compose_config([f"task={TASK}", "network.down_dims=[32,64,128]"])
    actor = _small_actor(cfg, rgb_episodes)
    fit_normalizers(
        actor.policy, rgb_episodes, mode=cfg.policy.normalizer, obs_mode=cfg.policy.obs_normalizer
    )
    loss_fn = build_loss(actor, cfg.policy)
    rb = make_chunk_buffer(rgb_episodes, obs_horizon=2, pred_horizon=16, batch_size=8, seed=0)
    held = rb.sample()

    def held_loss() -> float:
        actor.eval()  # centre crop; the same t and noise draws each time
        with torch.no_grad(), torch.random.fork_rng():
            torch.manual_seed(123)
            value = float(loss_fn(held)["loss_l1flow"])
        actor.train()
        return value

    before = held_loss()
    trainer = Trainer(actor, loss_fn, total_steps=30, lr=1e-3, warmup_steps=2)
    losses = [trainer.train_step(rb.sample())["loss"] for _ in range(30)]
    after = held_loss()
    assert all(torch.isfinite(torch.tensor(losses)))
    assert after < 0.7 * before, (before, after, losses)


def test_image_task_with_state_encoder_is_refused_before_any_demo(tmp_path, capsys):
    data_dir = tmp_path / "data"
    code = main(
        ["train", f"task={TASK}", "encoder=state", f"data_dir={data_dir}", f"run_dir={tmp_path / 'run'}"]
    )
    err = capsys.readouterr().err
    assert code == 2
    assert "encoder" in err and "rgb" in err
    assert not data_dir.exists() or not any(data_dir.rglob("*"))  # nothing was generated


@pytest.mark.slow
def test_train_command_runs_end_to_end_on_rgb(rgb_demos, tmp_path):
    data_dir, _ = rgb_demos
    run_dir = tmp_path / "run"
    code = main(
        [
            "train",
            f"task={TASK}",
            "demos.num=3",
            "train.steps=20",
            "eval.episodes=1",
            f"data_dir={data_dir}",
            f"run_dir={run_dir}",
        ]
    )
    assert code == 0
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["episodes"] == 1 and 0.0 <= result["success_once"] <= 1.0
    assert (run_dir / "checkpoints" / "latest.pt").is_file()


def test_evaluate_runs_the_policy_in_eval_mode_and_restores_it():
    from l1flow_rl.envs import make_env

    from l1flow_rl import L1FlowActor, evaluate

    actor = L1FlowActor.for_state(obs_dim=35, action_dim=4, down_dims=(16, 32))
    modes = []
    actor.policy.encoder.register_forward_pre_hook(lambda module, args: modes.append(module.training))
    env = make_env("maniskill_pushcube", max_episode_steps=8)
    try:
        evaluate(actor, env, episodes=1, seed=0)
    finally:
        env.close()
    assert modes and not any(modes)  # random crops never reach a rollout
    assert actor.training  # the caller's mode is back
