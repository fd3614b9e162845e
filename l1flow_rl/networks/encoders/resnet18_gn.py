"""ResNet-18 with GroupNorm in place of BatchNorm, as Diffusion Policy's image encoder uses it.

Written here because torchvision does not import on the CPU torch build this project targets. The
module and parameter names follow torchvision's ``resnet18`` (``conv1``, ``bn1``, ``layer1.0.conv1``,
..., ``layer2.0.downsample.0``, ``fc``), so a torchvision state_dict loads by name with
:func:`load_torchvision_resnet18`. The norm layers keep torchvision's ``bn*`` / ``downsample.1``
names although they are ``GroupNorm`` (one group per ``group_size`` channels, 16 as in Diffusion
Policy): a GroupNorm has an affine ``weight``/``bias`` but no running statistics.

How an ImageNet (BatchNorm) checkpoint maps onto it:

* convolution and ``fc`` weights load unchanged;
* each BatchNorm's ``weight``/``bias`` become the GroupNorm's affine ``weight``/``bias`` (same
  shape [C]) with ``norm_affine="copy"``, or are left at 1/0 with ``norm_affine="reset"`` (what
  Diffusion Policy gets when it swaps the norm layers after loading);
* ``running_mean``, ``running_var`` and ``num_batches_tracked`` have no GroupNorm counterpart and are
  dropped; the loader returns their names. GroupNorm normalises each image by its own group
  statistics, so an ImageNet network is a starting point to fine-tune, not an equivalent network.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import torch
from safetensors.torch import load_file
from torch import Tensor, nn

__all__ = ["WIDTHS", "BasicBlock", "ResNet18GN", "group_norm", "load_torchvision_resnet18"]

#: the channel counts of the four stages (the stem has the first): each GroupNorm's group_size divides them
WIDTHS = (64, 128, 256, 512)

#: BatchNorm entries of a torchvision state_dict that a GroupNorm has no place for
BN_STATISTICS = ("running_mean", "running_var", "num_batches_tracked")


def group_norm(channels: int, group_size: int = 16) -> nn.GroupNorm:
    """GroupNorm with ``channels // group_size`` groups (Diffusion Policy: 16 channels per group)."""
    if channels % group_size:
        raise ValueError(f"group_size={group_size} must divide the channel count {channels}")
    return nn.GroupNorm(channels // group_size, channels)


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with a residual connection (torchvision's ``BasicBlock`` layout)."""

    def __init__(self, in_ch: int, out_ch: int, stride: int = 1, group_size: int = 16) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride=stride, padding=1, bias=False)
        self.bn1 = group_norm(out_ch, group_size)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, padding=1, bias=False)
        self.bn2 = group_norm(out_ch, group_size)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_ch != out_ch:
            # a 1x1 projection when the shape changes; torchvision names it downsample.{0,1}
            self.downsample = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, 1, stride=stride, bias=False), group_norm(out_ch, group_size)
            )

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet18GN(nn.Module):
    """ResNet-18 whose norm layers are GroupNorm.

    ``forward_features`` returns the last convolutional map [N, 512, H/32, W/32] (Diffusion
    Policy's hybrid encoder stops there and adds a spatial softmax); ``forward`` adds the global
    average pool and ``fc`` when ``num_classes`` is set (the full torchvision layout). With
    ``num_classes=None`` there is no ``fc`` and no unused parameter, which DDP requires.

    Example:
        >>> import torch
        >>> net = ResNet18GN()
        >>> net.forward_features(torch.zeros(2, 3, 64, 64)).shape
        torch.Size([2, 512, 2, 2])
        >>> len(ResNet18GN(num_classes=1000).state_dict())  # torchvision's 122 minus 60 BN statistics
        62
    """

    out_channels = 512

    def __init__(self, num_classes: int | None = None, group_size: int = 16, in_channels: int = 3) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, WIDTHS[0], 7, stride=2, padding=3, bias=False)
        self.bn1 = group_norm(WIDTHS[0], group_size)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        channels = WIDTHS[0]
        for i, width in enumerate(WIDTHS):
            stride = 1 if i == 0 else 2
            layer = nn.Sequential(
                BasicBlock(channels, width, stride, group_size), BasicBlock(width, width, 1, group_size)
            )
            self.add_module(f"layer{i + 1}", layer)
            channels = width
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.fc: nn.Module = nn.Linear(512, num_classes) if num_classes else nn.Identity()
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward_features(self, x: Tensor) -> Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))

    def forward(self, x: Tensor) -> Tensor:
        return self.fc(torch.flatten(self.avgpool(self.forward_features(x)), 1))


def load_torchvision_resnet18(
    model: ResNet18GN,
    source: str | os.PathLike | Mapping[str, Tensor],
    *,
    norm_affine: str = "copy",
) -> list[str]:
    """Load a torchvision ``resnet18`` state_dict (a local file or a mapping) into ``model``.

    The key check is strict: every parameter of ``model`` must be in ``source`` with the same shape,
    and ``source`` may hold nothing else except BatchNorm statistics (dropped: GroupNorm has none)
    and ``fc.*`` when ``model`` has no ``fc`` (a trunk built with ``num_classes=None``).
    ``norm_affine="copy"`` loads the BatchNorm affine weights into the GroupNorms, ``"reset"``
    leaves them at 1/0. Files are read with ``torch.load(weights_only=True)`` (or safetensors).

    Returns the names of the source entries that were dropped.
    """
    if norm_affine not in ("copy", "reset"):
        raise ValueError(f"norm_affine must be 'copy' or 'reset', got {norm_affine!r}")
    where = str(source) if isinstance(source, (str, os.PathLike)) else "the given state_dict"
    if isinstance(source, (str, os.PathLike)):
        if str(source).endswith(".safetensors"):
            weights: Mapping[str, Tensor] = load_file(str(source))
        else:
            weights = torch.load(source, map_location="cpu", weights_only=True)
    else:
        weights = source
    if not isinstance(weights, Mapping):
        raise TypeError(
            f"{where}: expected a state_dict (a mapping of tensors), got {type(weights).__name__}"
        )
    own = model.state_dict()
    dropped = [
        k
        for k in weights
        if k.rsplit(".", 1)[-1] in BN_STATISTICS or (k.startswith("fc.") and "fc.weight" not in own)
    ]
    kept = {k: v for k, v in weights.items() if k not in dropped}
    missing, unexpected = sorted(set(own) - set(kept)), sorted(set(kept) - set(own))
    shapes = [
        f"{k}: file {tuple(kept[k].shape)} vs model {tuple(own[k].shape)}"
        for k in own
        if k in kept and tuple(kept[k].shape) != tuple(own[k].shape)
    ]
    if missing or unexpected or shapes:
        raise ValueError(
            f"{where} is not a torchvision resnet18 state_dict for this model: missing {missing[:8]}, "
            f"unexpected {unexpected[:8]}, shape mismatches {shapes[:8]}"
        )
    if norm_affine == "reset":
        norm_keys = {
            f"{n}.{p}"
            for n, m in model.named_modules()
            if isinstance(m, nn.GroupNorm)
            for p in ("weight", "bias")
        }
        dropped += sorted(norm_keys)
        kept = {k: (own[k] if k in norm_keys else v) for k, v in kept.items()}
    model.load_state_dict(kept, strict=True)
    return dropped
