"""ConditionalUnet1D and the state encoder: layout, shapes, conditioning and errors."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from l1flow_rl.networks import ConditionalUnet1D, StateEncoder
from l1flow_rl.networks.unet1d import SinusoidalEmbedding


@pytest.mark.parametrize(
    "down_dims, horizon", [((16,), 5), ((16, 32), 16), ((16, 32, 64), 8), ((8, 16, 32, 64), 24)]
)
def test_unet_keeps_the_chunk_shape(down_dims, horizon):
    net = ConditionalUnet1D(3, global_cond_dim=10, down_dims=down_dims, timestep_embed_dim=16)
    out = net(torch.randn(4, horizon, 3), torch.rand(4), torch.randn(4, 10))
    assert out.shape == (4, horizon, 3)


def test_unet_layout_follows_diffusion_policy():
    net = ConditionalUnet1D(4, global_cond_dim=70, down_dims=(64, 128, 256), timestep_embed_dim=64)
    convs = [m for m in net.modules() if isinstance(m, nn.Conv1d) and m.kernel_size[0] not in (1, 3)]
    assert {m.kernel_size[0] for m in convs} == {5}
    assert all(m.num_groups == 8 for m in net.modules() if isinstance(m, nn.GroupNorm))
    assert any(isinstance(m, nn.Mish) for m in net.modules())
    down = [m for m in net.modules() if isinstance(m, nn.Conv1d) and m.stride == (2,)]
    up = [m for m in net.modules() if isinstance(m, nn.ConvTranspose1d)]
    assert len(down) == len(up) == 2  # every level but the coarsest halves; every up level doubles
    # FiLM: each residual block predicts a scale and a bias per channel from [time embedding, obs].
    films = [m.film[-1] for m in net.modules() if hasattr(m, "film")]
    assert all(f.in_features == 64 + 70 and f.out_features % 2 == 0 for f in films)
    n_params = sum(p.numel() for p in net.parameters())
    assert 4.0e6 < n_params < 5.0e6  # ManiSkill's state baseline reports about 4.5M for these widths


def test_unet_output_depends_on_time_and_condition():
    torch.manual_seed(0)
    net = ConditionalUnet1D(2, global_cond_dim=6, down_dims=(16, 32), timestep_embed_dim=16)
    x, cond = torch.randn(3, 8, 2), torch.randn(3, 6)
    base = net(x, torch.full((3,), 0.2), cond)
    assert not torch.allclose(base, net(x, torch.full((3,), 0.7), cond))
    assert not torch.allclose(base, net(x, torch.full((3,), 0.2), cond + 1))
    torch.testing.assert_close(base, net(x, torch.tensor(0.2), cond))  # a scalar t broadcasts


def test_unet_gradients_reach_every_parameter():
    net = ConditionalUnet1D(2, global_cond_dim=6, down_dims=(16, 32), timestep_embed_dim=16)
    net(torch.randn(3, 8, 2), torch.rand(3), torch.randn(3, 6)).square().mean().backward()
    assert [n for n, p in net.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0] == []


def test_timestep_free_unet_for_regression():
    net = ConditionalUnet1D(2, global_cond_dim=6, down_dims=(16, 32), timestep_embed_dim=0)
    assert net.time_mlp is None
    assert net(torch.zeros(3, 8, 2), None, torch.randn(3, 6)).shape == (3, 8, 2)
    with pytest.raises(ValueError, match="built without a timestep embedding"):
        net(torch.zeros(3, 8, 2), torch.rand(3), torch.randn(3, 6))


def test_sinusoidal_embedding_of_raw_flow_time():
    emb = SinusoidalEmbedding(16)
    e = emb(torch.tensor([0.0, 0.5, 1.0]))
    assert e.shape == (3, 16)
    torch.testing.assert_close(e[0], torch.cat([torch.zeros(8), torch.ones(8)]))  # sin 0, cos 0
    torch.testing.assert_close(e[2, 0], torch.sin(torch.tensor(1.0)))  # the fastest frequency is 1
    with pytest.raises(ValueError, match="embedding dim must be even"):
        SinusoidalEmbedding(7)


def test_timestep_scale_multiplies_the_time_before_its_embedding():
    torch.manual_seed(0)
    raw = ConditionalUnet1D(2, global_cond_dim=3, down_dims=(16, 32), timestep_embed_dim=16)
    scaled = ConditionalUnet1D(
        2, global_cond_dim=3, down_dims=(16, 32), timestep_embed_dim=16, timestep_scale=1000
    )
    scaled.load_state_dict(raw.state_dict())  # the scale is no weight: the same parameters fit both
    x, cond, t = torch.randn(4, 16, 2), torch.randn(4, 3), torch.tensor([0.0, 0.25, 0.5, 0.999])
    torch.testing.assert_close(scaled(x, t, cond), raw(x, t * 1000, cond))
    # raw flow time: the embedding's fastest feature moves by under one radian over [0, 1], so
    # t = 0.25 and 0.5 embed nearly alike; scaled, they are far apart
    emb = SinusoidalEmbedding(16)
    near = (emb(torch.tensor([0.25])) - emb(torch.tensor([0.5]))).norm()
    far = (emb(torch.tensor([250.0])) - emb(torch.tensor([500.0]))).norm()
    assert near < 0.5 < far
    with pytest.raises(ValueError, match="timestep_scale must be positive"):
        ConditionalUnet1D(2, global_cond_dim=3, down_dims=(16, 32), timestep_scale=0)


def test_unet_errors_name_the_expected_shapes():
    net = ConditionalUnet1D(2, global_cond_dim=6, down_dims=(16, 32), timestep_embed_dim=16)
    with pytest.raises(ValueError, match=r"UNet input must be \[B, H, 2\], got \(3, 8, 3\)"):
        net(torch.zeros(3, 8, 3), torch.rand(3), torch.randn(3, 6))
    with pytest.raises(ValueError, match="chunk length 7 must be divisible by 2"):
        net(torch.zeros(3, 7, 2), torch.rand(3), torch.randn(3, 6))
    with pytest.raises(ValueError, match=r"global_cond must be \[3, 6\], got \(3, 5\)"):
        net(torch.zeros(3, 8, 2), torch.rand(3), torch.randn(3, 5))
    with pytest.raises(ValueError, match="pass t"):
        net(torch.zeros(3, 8, 2), None, torch.randn(3, 6))
    with pytest.raises(ValueError, match="divisible by n_groups=8"):
        ConditionalUnet1D(2, global_cond_dim=6, down_dims=(12, 32))


def test_state_encoder_concatenates_entries_in_declared_order():
    enc = StateEncoder({"qpos": 3, "goal": 2})
    obs = TensorDict({"goal": torch.randn(4, 2, 2), "qpos": torch.randn(4, 2, 3)}, [4, 2])
    out = enc(obs)
    assert enc.feature_dim == 5 and out.shape == (4, 2, 5)
    torch.testing.assert_close(out, torch.cat([obs["qpos"], obs["goal"]], -1))


def test_state_encoder_with_mlp():
    enc = StateEncoder({"state": 3}, hidden_dims=(32, 7))
    assert enc.feature_dim == 7
    assert enc(TensorDict({"state": torch.randn(4, 2, 3)}, [4, 2])).shape == (4, 2, 7)
    with pytest.raises(ValueError, match="at least one observation entry"):
        StateEncoder({})
