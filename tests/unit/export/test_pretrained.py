"""Pretrained folders (``l1flow-rl export``, ``L1FlowActor.from_pretrained``) and the exported program,
on a policy trained end to end on the point-mass double."""

from __future__ import annotations

import json

import pytest
import torch
from doubles.point_mass import POINT_MASS_TASK  # noqa: F401  (registers the simulator)
from doubles.point_mass import TASK_OVERRIDES as TASK
from tensordict import TensorDict

from l1flow_rl import L1FlowActor
from l1flow_rl.commands.cli import main
from l1flow_rl.export.pretrained import FORMAT_VERSION, PretrainedFolderError, read_pretrained_config
from l1flow_rl.export.program import DeployablePolicy, example_inputs, export_program, load_program
from l1flow_rl.workspace.build import build_actor
from l1flow_rl.workspace.checkpoint import load_actor

TINY = [
    "demos.num=3",
    "train.steps=6",
    "train.batch_size=16",
    "train.warmup_steps=2",
    "eval.enabled=false",
    "network.down_dims=[16,32]",
    "network.timestep_embed_dim=16",
    "device=cpu",
]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """(checkpoint, pretrained folder): a 6-step run on the double, exported with its program."""
    root = tmp_path_factory.mktemp("pretrained")
    run_dir = root / "run"
    assert main(["train", *TASK, *TINY, f"data_dir={root / 'data'}", f"run_dir={run_dir}"]) == 0
    checkpoint = run_dir / "checkpoints" / "latest.pt"
    folder = root / "policy"
    args = [f"checkpoint={checkpoint}", f"out={folder}", "program=true", f"run_dir={root / 'export'}"]
    assert main(["export", *args]) == 0
    return checkpoint, folder


def test_export_writes_a_folder_that_rebuilds_without_hydra_and_gives_identical_chunks(exported):
    checkpoint, folder = exported
    assert {p.name for p in folder.iterdir()} == {
        "config.json",
        "model.safetensors",
        "normalizer.safetensors",
        "train_config.json",
        "policy.pt2",
    }
    config = json.loads((folder / "config.json").read_text())
    assert config["format_version"] == FORMAT_VERSION and config["library_version"]
    assert config["task"]["env_id"] == "PointMassReach-v0"
    assert config["observation"]["entries"] == {"state": {"shape": [6], "dtype": "float32"}}
    assert config["action"]["shape"] == [2] and config["action"]["executed_window"] == [8, 2]
    assert config["sampler"] == {
        "name": "two_step",
        "kwargs": {"t_first": 0.5},
        "nfe": 2,
        "prediction": "sample",
    }
    assert config["network"]["down_dims"] == [16, 32] and config["weights"]["weights"] == "ema"
    assert config["weights"]["step"] == 6
    assert set(config["normalizers"]["modes"]) == {"observation.state", "action"}
    assert config["normalizers"]["modes"]["action"] == "limits"

    original, _ = load_actor(checkpoint, use_ema=True)
    loaded = L1FlowActor.from_pretrained(folder)
    assert not loaded.training
    torch.manual_seed(1)
    obs, noise = torch.randn(4, 2, 6) * 3, torch.randn(4, 16, 2)
    want = original.policy(obs, noise=noise)
    got = loaded.policy(obs, noise=noise)
    assert torch.equal(got, want)
    # the normalisers travelled: outputs are in the environment's units, not [-1, 1]
    assert not torch.equal(loaded.policy.action_normalizer.scale, torch.ones(2))
    # through the TensorDict interface as well
    td = TensorDict({"observation": obs}, batch_size=[4])
    assert loaded(td.clone(), noise=noise)["action_chunk"].shape == (4, 8, 2)


def test_the_exported_program_loads_with_torch_alone_and_matches_eager(exported):
    _, folder = exported
    program = torch.export.load(str(folder / "policy.pt2")).module()
    actor = L1FlowActor.from_pretrained(folder)
    config = read_pretrained_config(folder)
    assert [i["name"] for i in config["program"]["inputs"]] == ["state", "noise"]
    for batch in (1, 5):  # the batch size is dynamic
        obs, noise = torch.randn(batch, 2, 6), torch.randn(batch, 16, 2)
        assert torch.equal(program(obs, noise), actor.policy(obs, noise=noise))
    zeros = torch.zeros(1, 16, 2)
    deterministic = actor.policy(obs[:1], deterministic=True)
    assert torch.equal(program(obs[:1], zeros), deterministic)  # zero noise is the deterministic chunk


def test_eval_accepts_the_pretrained_folder(exported, tmp_path):
    _, folder = exported
    args = [*TASK, f"checkpoint={folder}", "eval.episodes=2", "eval.num_envs=1", f"run_dir={tmp_path}"]
    assert main(["eval", *args]) == 0
    result = json.loads((tmp_path / "eval.json").read_text())
    assert result["episodes"] == 2 and result["sampler"]["nfe"] == 2
    assert [e["length"] for e in result["per_episode"]] == [30, 30]


def test_a_folder_that_is_not_ours_or_incomplete_is_refused_by_name(exported, tmp_path):
    _, folder = exported
    with pytest.raises(PretrainedFolderError, match=r"config\.json: missing"):
        L1FlowActor.from_pretrained(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"type": "diffusion", "n_obs_steps": 2}))
    with pytest.raises(PretrainedFolderError, match="format is None, not 'l1flow-rl-pretrained'"):
        L1FlowActor.from_pretrained(tmp_path)
    config = json.loads((folder / "config.json").read_text())
    (tmp_path / "config.json").write_text(json.dumps({**config, "format_version": 99}))
    with pytest.raises(
        PretrainedFolderError, match=r"format_version 99, but this l1flow-rl .* reads version 1 or 2"
    ):
        L1FlowActor.from_pretrained(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps(config))
    (tmp_path / "model.safetensors").write_bytes((folder / "model.safetensors").read_bytes())
    with pytest.raises(PretrainedFolderError, match=r"normalizer\.safetensors: missing"):
        L1FlowActor.from_pretrained(tmp_path)
    (tmp_path / "normalizer.safetensors").write_bytes(b"not safetensors")
    with pytest.raises(PretrainedFolderError, match="cannot be read as safetensors"):
        L1FlowActor.from_pretrained(tmp_path)
    with pytest.raises(PretrainedFolderError, match="not a folder"):
        L1FlowActor.from_pretrained(folder / "config.json")


def test_save_pretrained_records_the_network_from_the_network_itself(tmp_path):
    actor = L1FlowActor.for_state(obs_dim=3, action_dim=2, down_dims=(16, 32), kernel_size=3)
    # a stale setting given for the policy (from before the network section) does not override it
    folder = actor.save_pretrained(tmp_path / "p", policy={"kernel_size": 5, "down_dims": [8, 16]})
    network = json.loads((folder / "config.json").read_text())["network"]
    assert network["name"] == "unet" and network["kernel_size"] == 3 and network["down_dims"] == [16, 32]
    obs, noise = torch.randn(2, 2, 3), torch.randn(2, 16, 2)
    assert torch.equal(
        L1FlowActor.from_pretrained(folder).policy(obs, noise=noise), actor.policy(obs, noise=noise)
    )


def test_an_image_policy_exports_whole_and_matches_eager(tmp_path):
    policy = {
        "down_dims": [16, 32],
        "timestep_embed_dim": 16,
        "kernel_size": 5,
        "n_groups": 8,
        "obs_horizon": 2,
        "pred_horizon": 16,
        "action_steps": 8,
        "sampler": "two_step",
    }
    shapes = {"state": (4,), "rgb": (3, 40, 40)}
    actor = build_actor(policy, shapes, 2, {"name": "resnet18_gn", "feature_dim": 8}).eval()
    actor.policy.fit_normalizers({"state": torch.randn(50, 4) * 5}, torch.rand(50, 2) * 512)
    export_program(actor, tmp_path / "policy.pt2")
    program = load_program(tmp_path / "policy.pt2")
    torch.manual_seed(0)
    state = torch.randn(3, 2, 4)
    rgb = torch.randint(0, 256, (3, 2, 3, 40, 40), dtype=torch.uint8)
    noise = torch.randn(3, 16, 2)
    eager = actor.policy(TensorDict({"state": state, "rgb": rgb}, batch_size=[3]), noise=noise)
    assert torch.equal(program(state, rgb, noise), eager)
    assert eager.abs().max() > 2  # un-normalised inside the program (actions in [0, 512])


def test_onnx_export_matches_eager_within_float_tolerance(tmp_path):
    ort = pytest.importorskip("onnxruntime", reason="ONNX needs the export extra")
    pytest.importorskip("onnxscript", reason="the dynamo ONNX exporter needs onnxscript")
    from l1flow_rl.export.program import export_onnx

    actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32)).eval()
    actor.policy.fit_normalizers(torch.randn(100, 5) * 3, torch.randn(100, 2) * 4)
    path = export_onnx(actor, tmp_path / "policy.onnx")
    session = ort.InferenceSession(str(path))
    assert [i.name for i in session.get_inputs()] == ["state", "noise"]
    obs, noise = torch.randn(3, 2, 5), torch.randn(3, 16, 2)
    (out,) = session.run(None, {"state": obs.numpy(), "noise": noise.numpy()})
    eager = actor.policy(obs, noise=noise).detach()
    # onnxruntime fuses and reorders float ops: not bitwise, measured max |diff| 1e-5 on values ~4
    assert torch.allclose(torch.from_numpy(out), eager, atol=1e-4, rtol=1e-4)
    assert DeployablePolicy(actor).entry_names == ["state"] and len(example_inputs(actor)) == 2


@pytest.mark.parametrize("sampler", ["consistency_3", "ddpm_8"])
def test_a_renoising_sampler_exports_with_its_inner_noise_as_an_input_and_reproduces_eager(sampler):
    # CP chained over 3 steps renoises twice, ancestral DDPM at every step but the last: with those draws
    # drawn inside, a program could not reproduce a chunk from its start noise. They are an input instead.
    from l1flow_rl.export.program import program_description
    from l1flow_rl.flow import ConsistencySampler, DDPMSampler

    chosen, scale = {
        "consistency_3": (ConsistencySampler(3), 1000.0),
        "ddpm_8": (DDPMSampler(num_train_timesteps=8), 1.0),
    }[sampler]
    actor = L1FlowActor.for_state(
        obs_dim=5, action_dim=2, down_dims=(16, 32), sampler=chosen, timestep_scale=scale
    ).eval()
    actor.policy.fit_normalizers(torch.randn(100, 5) * 3, torch.randn(100, 2) * 4)
    draws = chosen.inner_noise_draws
    assert draws == {"consistency_3": 2, "ddpm_8": 7}[sampler]
    inputs = program_description(actor)["inputs"]
    assert [i["name"] for i in inputs] == ["state", "noise", "inner_noise"]
    assert inputs[-1]["shape"] == ["batch", draws, 16, 2]
    exported = export_program(actor)
    ops = {str(n.target) for n in exported.graph.nodes if n.op == "call_function"}
    assert "aten.conv1d.default" in ops and not [o for o in ops if "rand" in o or "normal" in o]
    program = exported.module()
    torch.manual_seed(0)
    obs, noise, inner = torch.randn(3, 2, 5), torch.randn(3, 16, 2), torch.randn(3, draws, 16, 2)
    eager = actor.policy(obs, noise=noise, inner_noise=inner)
    assert torch.allclose(program(obs, noise, inner), eager, atol=1e-5)
    assert torch.allclose(program(obs[:1], noise[:1], inner[:1]), eager[:1], atol=1e-5)  # batch dynamic
    assert not torch.allclose(program(obs, noise, torch.randn_like(inner)), eager, atol=1e-3)
    with pytest.raises(ValueError, match=r"inner_noise must have shape \[\*B, draws"):
        actor.policy(obs, noise=noise, inner_noise=inner[:, :1])
