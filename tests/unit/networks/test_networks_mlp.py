"""The MLP chunk denoiser (``network=mlp``): its shapes, time conditioning, gradients; every sampler,
loss, EMA, re-scoring, the pretrained folder and export on it; the network group's config rules."""

from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from l1flow_rl import L1FlowActor, make_ema
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.config.validate import ConfigValidationError
from l1flow_rl.export.program import export_program, load_program
from l1flow_rl.flow import (
    DDIMSampler,
    DDPMSampler,
    DirectSampler,
    EulerSampler,
    TwoStepSampler,
    VelocityEulerSampler,
)
from l1flow_rl.networks import MLPDenoiser, make_network
from l1flow_rl.networks.registry import network_config
from l1flow_rl.workspace.build import build_actor, build_loss

OBS, ACT, H = 5, 2, 16


def _actor(**kwargs) -> L1FlowActor:
    return L1FlowActor.for_state(OBS, ACT, network="mlp", hidden_dims=(32, 32), **kwargs)


@pytest.mark.parametrize("residual", [False, True])
@pytest.mark.parametrize(
    ("horizon", "action_dim", "hidden"), [(16, 2, (32, 32)), (5, 7, (8, 16, 8)), (1, 1, (4,))]
)
def test_the_mlp_keeps_the_chunk_shape(horizon, action_dim, hidden, residual):
    net = MLPDenoiser(action_dim, horizon, global_cond_dim=6, hidden_dims=hidden, residual=residual)
    out = net(torch.randn(3, horizon, action_dim), torch.rand(3), torch.randn(3, 6))
    assert out.shape == (3, horizon, action_dim)
    assert sum(isinstance(m, nn.Linear) and m.bias is not None for m in net.modules()) == len(hidden) + 1
    assert sum(isinstance(m, nn.LayerNorm) for m in net.modules()) == len(hidden)


def test_the_default_mlp_is_the_anchors_4x512_stack():
    net = make_network("mlp", action_dim=4, horizon=16, global_cond_dim=2 * 25)
    widths = [m.out_features for m in net.modules() if isinstance(m, nn.Linear)]
    assert widths == [512, 512, 512, 512, 16 * 4]
    assert net.body[0].in_features == 16 * 4 + 64 + 50  # flattened chunk, t features, observation history
    assert isinstance(net.body[1], nn.GELU) and isinstance(net.body[2], nn.LayerNorm)


def test_the_mlp_refuses_inputs_it_was_not_built_for():
    net = MLPDenoiser(2, 16, global_cond_dim=6, hidden_dims=(8,))
    with pytest.raises(ValueError, match=r"MLP input must be \[B, 16, 2\] \(built for chunks of 16 steps\)"):
        net(torch.randn(3, 8, 2), torch.rand(3), torch.randn(3, 6))
    with pytest.raises(ValueError, match=r"global_cond must be \[3, 6\], got \(3, 5\)"):
        net(torch.randn(3, 16, 2), torch.rand(3), torch.randn(3, 5))
    with pytest.raises(ValueError, match="built with a timestep embedding; pass t"):
        net(torch.randn(3, 16, 2), None, torch.randn(3, 6))
    timeless = MLPDenoiser(2, 16, global_cond_dim=6, hidden_dims=(8,), timestep_embed_dim=0)
    with pytest.raises(ValueError, match="without a timestep embedding"):
        timeless(torch.randn(3, 16, 2), torch.rand(3), torch.randn(3, 6))
    with pytest.raises(ValueError, match=r"activation 'relu': expected one of \['gelu', 'mish'\]"):
        MLPDenoiser(2, 16, global_cond_dim=6, activation="relu")
    with pytest.raises(ValueError, match="hidden_dims must name at least one positive width"):
        MLPDenoiser(2, 16, global_cond_dim=6, hidden_dims=())
    with pytest.raises(ValueError, match=r"network 'mlp' takes no setting \['down_dims'\]"):
        make_network("mlp", action_dim=2, horizon=16, global_cond_dim=6, down_dims=(16, 32))
    with pytest.raises(ValueError, match="pred_horizon=8, but the network was built for chunks of 16"):
        from l1flow_rl.modules.policy import ChunkPolicy

        ChunkPolicy(
            MLPDenoiser(2, 16, global_cond_dim=2 * OBS, hidden_dims=(8,)),
            _actor().policy.encoder,
            TwoStepSampler(0.5),
            action_dim=2,
            obs_horizon=2,
            pred_horizon=8,
            action_steps=4,
        )


@pytest.mark.parametrize("residual", [False, True])
def test_time_conditions_the_output_and_every_layer_gets_a_gradient(residual):
    torch.manual_seed(0)
    net = MLPDenoiser(2, 8, global_cond_dim=4, hidden_dims=(16, 16, 16), residual=residual)
    x, cond = torch.randn(5, 8, 2), torch.randn(5, 4)
    at = {t: net(x, torch.full((5,), t), cond) for t in (0.0, 0.5, 1.0)}
    assert (at[0.0] - at[0.5]).abs().min() > 0 and (at[0.5] - at[1.0]).abs().mean() > 1e-3
    assert torch.equal(net(x, torch.tensor(0.5), cond), at[0.5])  # a scalar t is every row's
    # each row's t is its own: row 0's output does not move when only row 1's t does
    t = torch.full((5,), 0.5)
    t2 = t.clone()
    t2[1] = 0.9
    moved = net(x, t2, cond)
    assert torch.equal(moved[0], at[0.5][0]) and not torch.equal(moved[1], at[0.5][1])
    assert not torch.equal(net(x, t, cond + 1), at[0.5])  # the observation conditions it too
    net(x, t, cond).square().mean().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_timestep_scale_multiplies_t_before_the_embedding():
    torch.manual_seed(0)
    raw = MLPDenoiser(2, 8, global_cond_dim=3, hidden_dims=(16,))
    scaled = MLPDenoiser(2, 8, global_cond_dim=3, hidden_dims=(16,), timestep_scale=1000)
    scaled.load_state_dict(raw.state_dict())
    x, cond = torch.randn(2, 8, 2), torch.randn(2, 3)
    torch.testing.assert_close(scaled(x, torch.full((2,), 0.25), cond), raw(x, torch.full((2,), 250.0), cond))


@pytest.mark.parametrize(
    ("sampler", "nfe"),
    [
        (TwoStepSampler(0.5), 2),
        (EulerSampler(4), 4),
        (VelocityEulerSampler(4), 4),
        (DDPMSampler(num_train_timesteps=20), 20),
        (DDIMSampler(5, num_train_timesteps=20), 5),
        (DirectSampler(), 1),
    ],
    ids=repr,
)
def test_every_sampler_runs_the_mlp(sampler, nfe):
    actor = _actor(sampler=sampler)
    calls = []
    actor.policy.net.register_forward_hook(lambda *_: calls.append(1))
    with torch.no_grad():
        out = actor(TensorDict({"observation": torch.randn(4, 2, OBS)}, [4]))["action_chunk"]
    assert out.shape == (4, 8, ACT) and torch.isfinite(out).all()
    assert len(calls) == nfe
    assert bool(actor.policy.net.timestep_embed_dim) == sampler.uses_timestep  # regression: no t input


@pytest.mark.parametrize("policy", ["l1flow", "flow", "ddpm", "ddim", "regression"])
def test_every_method_trains_on_the_mlp_and_its_ema_acts(policy):
    cfg = compose_config([f"policy={policy}", "network=mlp", "network.hidden_dims=[32,32]"])
    actor = build_actor(cfg.policy, {"state": (OBS,)}, ACT, None, cfg.network)
    assert isinstance(actor.policy.net, MLPDenoiser) and actor.policy.net.hidden_dims == (32, 32)
    loss_fn = build_loss(actor, cfg.policy)
    ema = make_ema(actor)
    opt = torch.optim.Adam(actor.parameters(), lr=1e-3)
    torch.manual_seed(0)
    td = TensorDict({"observation": torch.randn(32, 2, OBS), "action_chunk": torch.rand(32, H, ACT)}, [32])
    before = {k: v.clone() for k, v in actor.policy.net.state_dict().items()}
    for _ in range(3):
        loss = loss_fn(td)[loss_fn.loss_name]
        assert torch.isfinite(loss)
        opt.zero_grad()
        loss.backward()
        assert all(p.grad is not None for p in actor.policy.net.parameters())
        opt.step()
        ema.update_parameters(actor)
    after = actor.policy.net.state_dict()
    assert all(not torch.equal(before[k], after[k]) for k in before if k.endswith("weight"))
    averaged = ema.module.policy.net.state_dict()
    assert any(not torch.equal(averaged[k], after[k]) for k in after)  # an average, not a copy
    with torch.no_grad():
        chunk = ema.module(TensorDict({"observation": torch.randn(3, 2, OBS)}, [3]))["action_chunk"]
    assert chunk.shape == (3, 8, ACT)


def test_padded_steps_leave_the_mlps_loss():
    from l1flow_rl import RegressionLoss

    actor = L1FlowActor.for_state(OBS, ACT, network="mlp", hidden_dims=(32,), sampler=DirectSampler())
    is_pad = torch.zeros(6, H, dtype=torch.bool)
    is_pad[:, 10:] = True
    td = TensorDict(
        {
            "observation": torch.randn(6, 2, OBS),
            "action_chunk": torch.rand(6, H, ACT),
            "action_is_pad": is_pad,
        },
        [6],
    )
    each = RegressionLoss(actor, reduction="none", mask_padding=True)(td)["loss_regression"]
    assert each.shape == (6, H, ACT) and (each[:, 10:] == 0).all() and (each[:, :10] > 0).all()
    masked = RegressionLoss(actor, mask_padding=True)(td)["loss_regression"]
    torch.testing.assert_close(masked, each[:, :10].mean())
    assert not torch.equal(RegressionLoss(actor)(td)["loss_regression"], masked)


def test_a_sampler_swap_on_the_mlp_shares_the_network():
    actor = _actor()
    euler = actor.with_sampler("euler", steps=3)
    assert euler.policy.net is actor.policy.net and euler.sampler.nfe == 3
    with pytest.raises(ValueError, match="velocity"):
        actor.with_sampler("velocity_euler", steps=3)  # a sample-prediction net read as a velocity net


def test_the_pretrained_folder_rebuilds_the_mlp_and_its_program_equals_eager(tmp_path):
    actor = _actor(residual=True, activation="mish", timestep_scale=10.0).eval()
    actor.policy.fit_normalizers(torch.randn(100, OBS) * 3, torch.randn(100, ACT) * 4)
    folder = actor.save_pretrained(tmp_path / "policy", program=True)
    network = json.loads((folder / "config.json").read_text())["network"]
    assert network == {
        "name": "mlp",
        "hidden_dims": [32, 32],
        "timestep_embed_dim": 64,
        "timestep_scale": 10.0,
        "activation": "mish",
        "layer_norm": True,
        "residual": True,
    }
    again = L1FlowActor.from_pretrained(folder)
    assert isinstance(again.policy.net, MLPDenoiser) and again.policy.net.residual
    obs, noise = torch.randn(3, 2, OBS), torch.randn(3, H, ACT)
    eager = actor.policy(obs, noise=noise)
    assert torch.equal(again.policy(obs, noise=noise), eager)
    program = load_program(folder / "policy.pt2")
    assert torch.equal(program(obs, noise), eager)
    one = export_program(actor).module()(obs[:1], noise[:1])  # the batch is dynamic
    assert torch.equal(one, actor.policy(obs[:1], noise=noise[:1]))


def test_onnx_of_the_mlp_matches_eager_within_1e_5(tmp_path):
    ort = pytest.importorskip("onnxruntime", reason="ONNX needs the export extra")
    pytest.importorskip("onnxscript", reason="the dynamo ONNX exporter needs onnxscript")
    from l1flow_rl.export.program import export_onnx

    actor = _actor().eval()
    actor.policy.fit_normalizers(torch.randn(100, OBS) * 3, torch.randn(100, ACT) * 4)
    session = ort.InferenceSession(str(export_onnx(actor, tmp_path / "policy.onnx")))
    obs, noise = torch.randn(3, 2, OBS), torch.randn(3, H, ACT)
    (out,) = session.run(None, {"state": obs.numpy(), "noise": noise.numpy()})
    torch.testing.assert_close(
        torch.from_numpy(out), actor.policy(obs, noise=noise).detach(), atol=1e-5, rtol=1e-5
    )


def test_a_version_1_folder_reads_as_the_unet_its_policy_section_describes(tmp_path):
    actor = L1FlowActor.for_state(OBS, ACT, down_dims=(16, 32), timestep_embed_dim=16).eval()
    folder = actor.save_pretrained(tmp_path / "p")
    config = json.loads((folder / "config.json").read_text())
    network = config.pop("network")
    config["format_version"] = 1
    config["policy"].update(down_dims=network["down_dims"], timestep_embed_dim=16)  # no kernel_size: 5
    (folder / "config.json").write_text(json.dumps(config))
    again = L1FlowActor.from_pretrained(folder)
    obs, noise = torch.randn(2, 2, OBS), torch.randn(2, H, ACT)
    assert torch.equal(again.policy(obs, noise=noise), actor.policy(obs, noise=noise))


def test_network_config_reads_a_config_from_before_the_network_group():
    unet = {"timestep_embed_dim": 64, "timestep_scale": 1.0, "kernel_size": 5, "n_groups": 8}
    assert network_config({"down_dims": [8, 16]}, None) == {"name": "unet", **unet, "down_dims": [8, 16]}
    with pytest.raises(ValueError, match="no network settings: the network is the network config group"):
        network_config({"loss": "l1flow"}, None)  # today's policy config alone: where is its network?
    assert network_config({}, {"name": "mlp", "hidden_dims": [4], "down_dims": None}) == {
        "name": "mlp",
        "hidden_dims": [4],
    }


def test_the_network_group_refuses_the_other_networks_settings_naming_them():
    cfg = compose_config(["network=mlp"])
    assert cfg.network.hidden_dims == [512, 512, 512, 512] and cfg.network.down_dims is None
    assert compose_config([]).network.name == "unet"  # the default stays the UNet
    with pytest.raises(
        ConfigValidationError, match=r"network\.down_dims=\[8, 16\]: a setting of network=unet"
    ):
        compose_config(["network=mlp", "network.down_dims=[8,16]"])
    with pytest.raises(ConfigValidationError, match=r"network\.hidden_dims=\[8\]: a setting of network=mlp"):
        compose_config(["network.hidden_dims=[8]"])
    with pytest.raises(
        ConfigValidationError, match=r"network\.timestep_embed_dim=5: expected an even number"
    ):
        compose_config(["network=mlp", "network.timestep_embed_dim=5"])
    with pytest.raises(ConfigValidationError, match=r"policy\.pred_horizon=10: must be divisible by 4"):
        compose_config(["policy.pred_horizon=10", "policy.action_steps=4"])
    with pytest.raises(
        ValueError, match=r"^policy\.down_dims moved to network\.down_dims .*network\.down_dims=\[8,16\]$"
    ):
        compose_config(["policy.down_dims=[8,16]"])


def test_an_image_task_composes_with_the_mlp_and_its_actor_runs():
    cfg = compose_config(["task=maniskill_pushcube_rgb", "network=mlp", "network.hidden_dims=[32]"])
    shapes = {"state": (9,), "rgb": (3, 40, 40)}
    encoder = {"name": "resnet18_gn", "feature_dim": 8}
    actor = build_actor(cfg.policy, shapes, 4, encoder, cfg.network).eval()
    obs = TensorDict(
        {"state": torch.randn(2, 2, 9), "rgb": torch.randint(0, 256, (2, 2, 3, 40, 40), dtype=torch.uint8)},
        [2],
    )
    assert actor.policy(obs).shape == (2, 8, 4)


def test_a_checkpoint_from_before_the_network_group_loads_as_its_unet(tmp_path):
    from omegaconf import OmegaConf

    from l1flow_rl.networks import ConditionalUnet1D
    from l1flow_rl.workspace.checkpoint import check_compatible, load_actor, save_checkpoint

    cfg = OmegaConf.to_container(compose_config(["network.down_dims=[16,32]", "network.kernel_size=3"]))
    actor = build_actor(cfg["policy"], {"state": (OBS,)}, ACT, None, cfg["network"]).eval()
    old = {**cfg, "policy": {**cfg["policy"], "down_dims": [16, 32], "timestep_embed_dim": 64}}
    old["policy"].update(kernel_size=3, n_groups=8)  # the layout before: no network block, no timestep_scale
    del old["network"]
    path = save_checkpoint(
        tmp_path / "old.pt",
        {"model": actor.state_dict(), "config": old, "obs_shapes": {"state": [OBS]}, "action_dim": ACT},
    )
    again, saved = load_actor(path)
    assert isinstance(again.policy.net, ConditionalUnet1D) and again.policy.net.down_dims == (16, 32)
    assert saved.network.name == "unet" and saved.network.kernel_size == 3 and "down_dims" not in saved.policy
    obs, noise = torch.randn(2, 2, OBS), torch.randn(2, H, ACT)
    assert torch.equal(again.policy(obs, noise=noise), actor.policy(obs, noise=noise))
    check_compatible(old, cfg, str(path))  # the same network, in either layout


def test_the_network_groups_fields_are_the_registrys_settings():
    from dataclasses import fields

    from l1flow_rl.config import NetworkConfig
    from l1flow_rl.config.network import NETWORK_FIELDS
    from l1flow_rl.networks.registry import NETWORKS

    assert {name: set(f) for name, f in NETWORK_FIELDS.items()} == {
        name: set(spec.defaults) for name, spec in NETWORKS.items()
    }
    assert {f.name for f in fields(NetworkConfig)} == {"name"}.union(*NETWORK_FIELDS.values())


def test_network_mlp_composes_on_every_task():
    from l1flow_rl.config import load_task_config, task_names

    for task in task_names():
        cfg = compose_config([f"task={task}", "network=mlp"])
        assert cfg.network.name == "mlp" and cfg.task.obs_mode == load_task_config(task).obs_mode
