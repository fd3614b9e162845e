"""``l1flow-rl train network=mlp`` end to end on the real ManiSkill simulator, then the same checkpoint
through ``eval`` (re-scored with another sampler) and ``export``."""

from __future__ import annotations

import json

import pytest
import torch

pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")

from l1flow_rl import L1FlowActor
from l1flow_rl.commands.cli import main
from l1flow_rl.networks import MLPDenoiser
from l1flow_rl.workspace.checkpoint import load_actor, load_checkpoint

pytestmark = pytest.mark.maniskill


def test_train_network_mlp_on_pushcube_then_eval_rescore_and_export(tmp_path):
    data_dir, run_dir = tmp_path / "data", tmp_path / "run"
    args = [
        "train",
        "network=mlp",
        "task=maniskill_pushcube",
        "train.steps=20",
        "eval.episodes=1",
        "network.hidden_dims=[64,64]",
        "demos.num=3",
        "train.batch_size=16",
        "train.warmup_steps=2",
        "eval.num_envs=1",
        "task.max_episode_steps=30",
        f"data_dir={data_dir}",
        f"run_dir={run_dir}",
    ]
    assert main(args) == 0
    state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert state["step"] == 20 and state["config"]["network"]["name"] == "mlp"
    actor, _ = load_actor(run_dir / "checkpoints" / "latest.pt")
    assert isinstance(actor.policy.net, MLPDenoiser) and actor.policy.net.hidden_dims == (64, 64)
    assert json.loads((run_dir / "eval.json").read_text())["episodes"] == 1

    # re-scored under another sampler: the checkpoint's network, the command line's sampler
    rescore = tmp_path / "rescore"
    eval_args = [
        f"checkpoint={run_dir / 'checkpoints' / 'latest.pt'}",
        "eval.episodes=1",
        f"run_dir={rescore}",
    ]
    assert main(["eval", *eval_args, "policy.sampler=euler", "policy.sampler_kwargs.steps=4"]) == 0
    record = json.loads((rescore / "eval.json").read_text())
    assert record["sampler"]["name"] == "euler" and record["sampler"]["nfe"] == 4
    assert record["sampler"]["trained_with"]["name"] == "two_step"
    with pytest.raises(ValueError, match=r"takes the network from the checkpoint; \['network'\]"):
        main(["eval", *eval_args, "network=unet"])

    folder = tmp_path / "policy"
    export = [f"checkpoint={run_dir / 'checkpoints'}", f"out={folder}", f"run_dir={tmp_path / 'export'}"]
    assert main(["export", *export]) == 0
    again = L1FlowActor.from_pretrained(folder)
    p = actor.policy
    obs, noise = torch.randn(2, 2, p.encoder.feature_dim), torch.randn(2, p.pred_horizon, p.action_dim)
    assert torch.equal(again.policy(obs, noise=noise), actor.policy(obs, noise=noise))
