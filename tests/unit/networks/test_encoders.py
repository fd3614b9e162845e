"""The image encoder's parts: ResNet-18 (GroupNorm) against torchvision's layout, spatial softmax,
crop augmentation, the multi-camera encoder, the registry and the torchvision weight loader."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from l1flow_rl.networks.encoders import (
    ImageCrop,
    ImageObservationEncoder,
    ResNet18GN,
    SpatialSoftmax,
    StateEncoder,
    crop_size,
    encoder_names,
    images_to_float,
    load_torchvision_resnet18,
    make_encoder,
)

# torchvision.models.resnet18().state_dict().keys(), in order (torchvision 0.2x; 122 keys)
TORCHVISION_RESNET18_KEYS = [
    "conv1.weight",
    "bn1.weight",
    "bn1.bias",
    "bn1.running_mean",
    "bn1.running_var",
    "bn1.num_batches_tracked",
    "layer1.0.conv1.weight",
    "layer1.0.bn1.weight",
    "layer1.0.bn1.bias",
    "layer1.0.bn1.running_mean",
    "layer1.0.bn1.running_var",
    "layer1.0.bn1.num_batches_tracked",
    "layer1.0.conv2.weight",
    "layer1.0.bn2.weight",
    "layer1.0.bn2.bias",
    "layer1.0.bn2.running_mean",
    "layer1.0.bn2.running_var",
    "layer1.0.bn2.num_batches_tracked",
    "layer1.1.conv1.weight",
    "layer1.1.bn1.weight",
    "layer1.1.bn1.bias",
    "layer1.1.bn1.running_mean",
    "layer1.1.bn1.running_var",
    "layer1.1.bn1.num_batches_tracked",
    "layer1.1.conv2.weight",
    "layer1.1.bn2.weight",
    "layer1.1.bn2.bias",
    "layer1.1.bn2.running_mean",
    "layer1.1.bn2.running_var",
    "layer1.1.bn2.num_batches_tracked",
    "layer2.0.conv1.weight",
    "layer2.0.bn1.weight",
    "layer2.0.bn1.bias",
    "layer2.0.bn1.running_mean",
    "layer2.0.bn1.running_var",
    "layer2.0.bn1.num_batches_tracked",
    "layer2.0.conv2.weight",
    "layer2.0.bn2.weight",
    "layer2.0.bn2.bias",
    "layer2.0.bn2.running_mean",
    "layer2.0.bn2.running_var",
    "layer2.0.bn2.num_batches_tracked",
    "layer2.0.downsample.0.weight",
    "layer2.0.downsample.1.weight",
    "layer2.0.downsample.1.bias",
    "layer2.0.downsample.1.running_mean",
    "layer2.0.downsample.1.running_var",
    "layer2.0.downsample.1.num_batches_tracked",
    "layer2.1.conv1.weight",
    "layer2.1.bn1.weight",
    "layer2.1.bn1.bias",
    "layer2.1.bn1.running_mean",
    "layer2.1.bn1.running_var",
    "layer2.1.bn1.num_batches_tracked",
    "layer2.1.conv2.weight",
    "layer2.1.bn2.weight",
    "layer2.1.bn2.bias",
    "layer2.1.bn2.running_mean",
    "layer2.1.bn2.running_var",
    "layer2.1.bn2.num_batches_tracked",
    "layer3.0.conv1.weight",
    "layer3.0.bn1.weight",
    "layer3.0.bn1.bias",
    "layer3.0.bn1.running_mean",
    "layer3.0.bn1.running_var",
    "layer3.0.bn1.num_batches_tracked",
    "layer3.0.conv2.weight",
    "layer3.0.bn2.weight",
    "layer3.0.bn2.bias",
    "layer3.0.bn2.running_mean",
    "layer3.0.bn2.running_var",
    "layer3.0.bn2.num_batches_tracked",
    "layer3.0.downsample.0.weight",
    "layer3.0.downsample.1.weight",
    "layer3.0.downsample.1.bias",
    "layer3.0.downsample.1.running_mean",
    "layer3.0.downsample.1.running_var",
    "layer3.0.downsample.1.num_batches_tracked",
    "layer3.1.conv1.weight",
    "layer3.1.bn1.weight",
    "layer3.1.bn1.bias",
    "layer3.1.bn1.running_mean",
    "layer3.1.bn1.running_var",
    "layer3.1.bn1.num_batches_tracked",
    "layer3.1.conv2.weight",
    "layer3.1.bn2.weight",
    "layer3.1.bn2.bias",
    "layer3.1.bn2.running_mean",
    "layer3.1.bn2.running_var",
    "layer3.1.bn2.num_batches_tracked",
    "layer4.0.conv1.weight",
    "layer4.0.bn1.weight",
    "layer4.0.bn1.bias",
    "layer4.0.bn1.running_mean",
    "layer4.0.bn1.running_var",
    "layer4.0.bn1.num_batches_tracked",
    "layer4.0.conv2.weight",
    "layer4.0.bn2.weight",
    "layer4.0.bn2.bias",
    "layer4.0.bn2.running_mean",
    "layer4.0.bn2.running_var",
    "layer4.0.bn2.num_batches_tracked",
    "layer4.0.downsample.0.weight",
    "layer4.0.downsample.1.weight",
    "layer4.0.downsample.1.bias",
    "layer4.0.downsample.1.running_mean",
    "layer4.0.downsample.1.running_var",
    "layer4.0.downsample.1.num_batches_tracked",
    "layer4.1.conv1.weight",
    "layer4.1.bn1.weight",
    "layer4.1.bn1.bias",
    "layer4.1.bn1.running_mean",
    "layer4.1.bn1.running_var",
    "layer4.1.bn1.num_batches_tracked",
    "layer4.1.conv2.weight",
    "layer4.1.bn2.weight",
    "layer4.1.bn2.bias",
    "layer4.1.bn2.running_mean",
    "layer4.1.bn2.running_var",
    "layer4.1.bn2.num_batches_tracked",
    "fc.weight",
    "fc.bias",
]
BN_STATS = ("running_mean", "running_var", "num_batches_tracked")


def _images(n: int, to: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, to, 3, h, w), dtype=torch.uint8, generator=g)


def test_resnet18_keys_are_torchvisions_minus_bn_statistics():
    assert len(TORCHVISION_RESNET18_KEYS) == 122
    expected = [k for k in TORCHVISION_RESNET18_KEYS if k.rsplit(".", 1)[-1] not in BN_STATS]
    assert list(ResNet18GN(num_classes=1000).state_dict()) == expected
    # the trunk the encoder uses has no fc (no unused parameters under DDP)
    assert list(ResNet18GN().state_dict()) == [k for k in expected if not k.startswith("fc.")]


def test_groupnorm_everywhere_with_16_channels_per_group():
    enc = ImageObservationEncoder({"front": (3, 64, 64), "wrist": (3, 64, 64), "state": (4,)})
    norms = [m for m in enc.modules() if isinstance(m, nn.GroupNorm)]
    assert not [m for m in enc.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    assert len(norms) == 2 * 20  # two trunks of 20 norm layers (17 + 3 downsample)
    assert all(m.num_channels // m.num_groups == 16 for m in norms)
    assert {m.num_groups for m in norms} == {4, 8, 16, 32}
    assert not any("running" in name for name, _ in enc.named_buffers())


def test_spatial_softmax_finds_the_peak():
    pool = SpatialSoftmax(4, 5, 7, num_keypoints=None, temperature=0.01)
    x = torch.zeros(1, 4, 5, 7)
    x[0, 0, 0, 0] = x[0, 1, 4, 6] = x[0, 2, 2, 3] = 10.0
    kp = pool(x).view(4, 2)
    torch.testing.assert_close(
        kp[:3], torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0]]), atol=1e-4, rtol=0
    )
    torch.testing.assert_close(kp[3], torch.zeros(2), atol=1e-6, rtol=0)  # flat map: the centre
    assert SpatialSoftmax(512, 4, 4, num_keypoints=32)(torch.randn(3, 512, 4, 4)).shape == (3, 64)
    with pytest.raises(ValueError, match="built for 16 positions"):
        SpatialSoftmax(8, 4, 4)(torch.randn(1, 8, 5, 5))


@pytest.mark.parametrize(
    ("cameras", "shared"), [(["rgb"], False), (["front", "wrist"], False), (["front", "wrist"], True)]
)
def test_encoder_shapes_for_one_and_two_cameras(cameras, shared):
    shapes = {cam: (3, 40, 48) for cam in cameras} | {"state": (7,)}
    enc = ImageObservationEncoder(shapes, shared=shared, crop_ratio=0.9)
    assert enc.feature_dim == 64 * len(cameras) + 7
    assert len(enc.nets) == (1 if shared else len(cameras))
    obs = TensorDict(
        {cam: _images(5, 2, 40, 48) for cam in cameras} | {"state": torch.randn(5, 2, 7)}, [5, 2]
    )
    out = enc(obs)
    assert out.shape == (5, 2, enc.feature_dim)
    # low-dimensional entries come last, unchanged
    torch.testing.assert_close(out[..., -7:], obs["state"])
    out.sum().backward()
    assert all(p.grad is not None for p in enc.parameters())


def test_two_cameras_are_encoded_by_their_own_networks():
    enc = ImageObservationEncoder({"front": (3, 64, 64), "wrist": (3, 64, 64)}).eval()
    img = _images(2, 2, 64, 64)
    obs = TensorDict({"front": img, "wrist": img}, [2, 2])
    out = enc(obs)
    assert out.shape == (2, 2, 128)
    assert not torch.allclose(out[..., :64], out[..., 64:])  # same images, different weights
    shared = ImageObservationEncoder({"front": (3, 64, 64), "wrist": (3, 64, 64)}, shared=True).eval()
    out = shared(obs)
    torch.testing.assert_close(out[..., :64], out[..., 64:])


def test_crop_is_random_in_training_and_centred_in_eval():
    crop = ImageCrop((12, 10), (8, 7))
    x = (
        torch.arange(4 * 12 * 10, dtype=torch.int64)
        .reshape(4, 1, 12, 10)
        .expand(4, 3, 12, 10)
        .to(torch.uint8)
    )
    x = x.contiguous()
    crop.eval()
    a, b = crop(x), crop(x)
    assert a.dtype == torch.uint8 and a.shape == (4, 3, 8, 7)
    assert torch.equal(a, b)  # deterministic
    torch.testing.assert_close(a, x[:, :, 2:10, 1:8])  # centre: (12-8)//2, (10-7)//2
    crop.train()
    torch.manual_seed(0)
    outs = torch.stack([crop(x) for _ in range(20)])
    assert outs.shape == (20, 4, 3, 8, 7)
    # every crop is a window of its own image, and the windows vary
    tops = set()
    for out in outs.reshape(-1, 3, 8, 7)[::4]:
        found = [
            (i, j) for i in range(5) for j in range(4) if torch.equal(out, x[0, :, i : i + 8, j : j + 7])
        ]
        assert len(found) == 1
        tops.add(found[0])
    assert len(tops) > 3
    with pytest.raises(ValueError, match="must fit"):
        ImageCrop((8, 8), (9, 8))
    with pytest.raises(ValueError, match=r"\[N, C, 12, 10\]"):
        crop.eval()(torch.zeros(1, 3, 11, 10, dtype=torch.uint8))


def test_encoder_train_vs_eval_crop():
    enc = ImageObservationEncoder({"rgb": (3, 72, 72)}, crop_ratio=0.75)
    obs = TensorDict({"rgb": _images(3, 2, 72, 72)}, [3, 2])
    enc.eval()
    with torch.no_grad():
        assert torch.equal(enc(obs), enc(obs))
        enc.train()
        torch.manual_seed(1)
        a = enc(obs)
        b = enc(obs)
    assert not torch.allclose(a, b)
    assert crop_size(128, 0.9) == 115 and crop_size(84, 0.9) == 76 and crop_size(96, 0.875) == 84
    with pytest.raises(ValueError, match=r"crop ratio must be in \(0, 1\]"):
        crop_size(10, 1.5)


def test_images_must_be_uint8_and_are_normalised_on_their_device():
    x = torch.tensor([0, 255, 51], dtype=torch.uint8).view(1, 3, 1, 1)
    torch.testing.assert_close(images_to_float(x).flatten(), torch.tensor([-1.0, 1.0, -0.6]))
    torch.testing.assert_close(images_to_float(x, "unit").flatten(), torch.tensor([0.0, 1.0, 0.2]))
    enc = ImageObservationEncoder({"rgb": (3, 64, 64)})
    with pytest.raises(TypeError, match="'rgb' must be a uint8 image"):
        enc(TensorDict({"rgb": torch.rand(1, 2, 3, 64, 64)}, [1, 2]))
    with pytest.raises(ValueError, match="image_norm must be one of"):
        ImageObservationEncoder({"rgb": (3, 64, 64)}, image_norm="zscore")


def test_registry_picks_and_refuses():
    assert {"auto", "state", "resnet18_gn"} <= set(encoder_names())
    assert isinstance(make_encoder("auto", {"state": (5,)}), StateEncoder)
    assert isinstance(make_encoder("auto", {"rgb": (3, 64, 64), "state": (5,)}), ImageObservationEncoder)
    enc = make_encoder("resnet18_gn", {"rgb": (3, 64, 64)}, {"feature_dim": 16, "num_keypoints": 8})
    assert enc.feature_dim == 16 and enc.nets["rgb"].pool.num_keypoints == 8
    with pytest.raises(ValueError, match=r"reads flat vectors only.*'rgb'"):
        make_encoder("state", {"rgb": (3, 64, 64), "state": (5,)})
    with pytest.raises(ValueError, match="not a registered encoder"):
        make_encoder("vit", {"state": (5,)})
    with pytest.raises(ValueError, match="at least one image entry"):
        make_encoder("resnet18_gn", {"state": (5,)})


def _torchvision_style_state_dict(seed: int = 0) -> dict[str, torch.Tensor]:
    """A state_dict with torchvision's resnet18 keys and shapes (BatchNorm statistics included)."""
    g = torch.Generator().manual_seed(seed)
    ref = ResNet18GN(num_classes=1000).state_dict()
    out = {}
    for key in TORCHVISION_RESNET18_KEYS:
        module, leaf = key.rsplit(".", 1)
        if leaf == "num_batches_tracked":
            out[key] = torch.tensor(100)
        elif leaf in ("running_mean", "running_var"):
            out[key] = torch.rand(ref[f"{module}.weight"].shape, generator=g)
        else:
            out[key] = torch.randn(ref[key].shape, generator=g)
    return out


def test_torchvision_weights_load_from_a_local_file(tmp_path):
    weights = _torchvision_style_state_dict()
    path = tmp_path / "resnet18.pth"
    torch.save(weights, path)
    full = ResNet18GN(num_classes=1000)
    dropped = load_torchvision_resnet18(full, path)
    assert sorted(dropped) == sorted(k for k in weights if k.rsplit(".", 1)[-1] in BN_STATS)
    for key, value in full.state_dict().items():
        torch.testing.assert_close(value, weights[key])  # BN affine -> GN affine, convs and fc as-is
    # a trunk without fc drops fc.*; "reset" leaves the GroupNorm affine at 1 / 0
    trunk = ResNet18GN()
    dropped = load_torchvision_resnet18(trunk, path, norm_affine="reset")
    assert {"fc.weight", "fc.bias", "bn1.weight", "layer4.1.bn2.bias"} <= set(dropped)
    torch.testing.assert_close(trunk.conv1.weight, weights["conv1.weight"])
    assert torch.equal(trunk.bn1.weight, torch.ones(64)) and torch.equal(trunk.bn1.bias, torch.zeros(64))
    # the encoder's option loads the same file into every camera's trunk
    enc = ImageObservationEncoder({"a": (3, 64, 64), "b": (3, 64, 64)}, pretrained=str(path))
    for net in enc.nets.values():
        torch.testing.assert_close(net.trunk.layer3[0].conv2.weight, weights["layer3.0.conv2.weight"])


def test_torchvision_loader_refuses_other_networks(tmp_path):
    weights = _torchvision_style_state_dict()
    missing = {k: v for k, v in weights.items() if not k.startswith("layer4.1.")}
    with pytest.raises(ValueError, match=r"missing \['layer4.1.bn1.bias'"):
        load_torchvision_resnet18(ResNet18GN(), missing)
    extra = dict(weights, **{"layer5.0.conv1.weight": torch.zeros(1)})
    with pytest.raises(ValueError, match=r"unexpected \['layer5.0.conv1.weight'\]"):
        load_torchvision_resnet18(ResNet18GN(), extra)
    wrong = dict(weights, **{"conv1.weight": torch.zeros(64, 1, 7, 7)})
    with pytest.raises(ValueError, match=r"conv1.weight: file \(64, 1, 7, 7\) vs model \(64, 3, 7, 7\)"):
        load_torchvision_resnet18(ResNet18GN(), wrong)
    with pytest.raises(ValueError, match=r"missing \['fc.bias', 'fc.weight'\]"):
        load_torchvision_resnet18(
            ResNet18GN(num_classes=1000), {k: v for k, v in weights.items() if "fc" not in k}
        )
    torch.save({"model": weights}, tmp_path / "wrapped.pth")
    with pytest.raises(ValueError, match=r"wrapped\.pth is not a torchvision resnet18 state_dict"):
        load_torchvision_resnet18(ResNet18GN(), tmp_path / "wrapped.pth")


def test_crops_too_small_for_the_spatial_softmax_are_refused():
    with pytest.raises(ValueError, match="1x1 ResNet-18 feature map"):
        ImageObservationEncoder({"rgb": (3, 32, 32)})
