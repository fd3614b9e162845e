"""Diffusion Policy's hybrid image encoder for any number of cameras, plus low-dimensional entries.

Per camera: uint8 [3, H, W] -> crop (random in training, centre in eval) -> float on the encoder's
device -> ResNet-18 (GroupNorm) conv trunk -> spatial softmax (32 keypoints) -> Linear(64). The
camera features come first, in the declared entry order, and the flat entries follow.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn

from l1flow_rl.networks.encoders.base import ObservationEncoder, image_entries, vector_entries
from l1flow_rl.networks.encoders.crop import ImageCrop, crop_size
from l1flow_rl.networks.encoders.resnet18_gn import ResNet18GN, load_torchvision_resnet18
from l1flow_rl.networks.encoders.spatial_softmax import SpatialSoftmax
from l1flow_rl.networks.encoders.state import StateEncoder

__all__ = ["IMAGE_NORMS", "CameraEncoder", "ImageObservationEncoder", "images_to_float"]

#: how uint8 pixels become network inputs: [-1, 1] (Diffusion Policy's image range normaliser),
#: [0, 1], or ImageNet's mean/std (for weights trained on ImageNet)
IMAGE_NORMS = ("signed", "unit", "imagenet")
_IMAGENET_MEAN, _IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)


def images_to_float(images: Tensor, norm: str = "signed", dtype: torch.dtype = torch.float32) -> Tensor:
    """uint8 [N, 3, H, W] -> ``dtype`` on the images' device, scaled as ``norm`` says (see IMAGE_NORMS)."""
    x = images.to(dtype) / 255.0
    if norm == "signed":
        return x * 2.0 - 1.0
    if norm == "unit":
        return x
    if norm == "imagenet":
        mean = torch.tensor(_IMAGENET_MEAN, device=x.device, dtype=dtype).view(3, 1, 1)
        std = torch.tensor(_IMAGENET_STD, device=x.device, dtype=dtype).view(3, 1, 1)
        return (x - mean) / std
    raise ValueError(f"image_norm must be one of {IMAGE_NORMS}, got {norm!r}")


def _trunk_map_size(side: int) -> int:
    # conv1, maxpool and layers 2-4 each halve a side, rounding up (stride 2, "same"-style padding)
    for _ in range(5):
        side = math.ceil(side / 2)
    return side


class CameraEncoder(nn.Module):
    """Float images [N, 3, h, w] (already cropped) -> features [N, feature_dim]: ResNet-18 (GroupNorm)
    conv trunk, spatial softmax over its last map, then a linear projection."""

    def __init__(
        self,
        crop: tuple[int, int],
        feature_dim: int = 64,
        num_keypoints: int = 32,
        group_size: int = 16,
        in_channels: int = 3,
    ) -> None:
        h, w = (_trunk_map_size(s) for s in crop)
        if h * w < 2:
            # a softmax over one position is constant: the features would ignore the image
            raise ValueError(
                f"a {crop[0]}x{crop[1]} crop leaves a 1x1 ResNet-18 feature map, on which the spatial "
                "softmax cannot see the image; crops need a side of at least 33 pixels"
            )
        super().__init__()  # the crop is checked before the trunk is built
        self.trunk = ResNet18GN(num_classes=None, group_size=group_size, in_channels=in_channels)
        self.pool = SpatialSoftmax(ResNet18GN.out_channels, h, w, num_keypoints=num_keypoints)
        self.proj = nn.Linear(self.pool.output_dim, feature_dim)
        self.feature_dim = feature_dim

    def forward(self, images: Tensor) -> Tensor:
        return self.proj(self.pool(self.trunk.forward_features(images)))


class ImageObservationEncoder(ObservationEncoder):
    """Camera images (uint8 [N, To, 3, H, W] entries) and flat entries -> [N, To, F].

    F = cameras * ``feature_dim`` + the summed flat dims. Images are cropped while still uint8 and
    turned into floats on the encoder's device, so they travel as bytes from storage to here.

    Args:
        obs_shapes: entry -> per-step shape ([3, H, W] for a camera, [D] for a flat entry).
        feature_dim: features per camera (Diffusion Policy: 64). num_keypoints: spatial-softmax K (32).
        crop_ratio: crop side / image side (0.9: 115 of 128, 76 of 84; the PushT paper setting
            84 of 96 is 0.875). 1.0 disables cropping.
        shared: one network for every camera (they must share a size) instead of one per camera.
        group_size: channels per GroupNorm group (16).
        image_norm: one of :data:`IMAGE_NORMS`.
        pretrained: a local torchvision ``resnet18`` state_dict file loaded into every trunk
            (see :func:`~l1flow_rl.networks.encoders.resnet18_gn.load_torchvision_resnet18`);
            norm_affine: how its BatchNorm affine weights map ("copy" or "reset").
        state_hidden_dims: an optional MLP over the flat entries (none by default, as in DP).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> enc = ImageObservationEncoder({"rgb": (3, 64, 64), "state": (5,)}, crop_ratio=0.875)
        >>> obs = TensorDict({"rgb": torch.zeros(2, 2, 3, 64, 64, dtype=torch.uint8),
        ...                   "state": torch.zeros(2, 2, 5)}, [2, 2])
        >>> enc(obs).shape  # 64 image features + 5 state dims per step
        torch.Size([2, 2, 69])
    """

    def __init__(
        self,
        obs_shapes: Mapping[str, Sequence[int]],
        *,
        feature_dim: int = 64,
        num_keypoints: int = 32,
        crop_ratio: float = 0.9,
        shared: bool = False,
        group_size: int = 16,
        image_norm: str = "signed",
        pretrained: str | os.PathLike | None = None,
        norm_affine: str = "copy",
        state_hidden_dims: Sequence[int] = (),
    ) -> None:
        super().__init__()
        shapes = {k: tuple(int(d) for d in s) for k, s in obs_shapes.items()}
        odd = {k: s for k, s in shapes.items() if len(s) not in (1, 3)}
        if odd:
            raise ValueError(f"observation entries {odd}: expected [D] (flat) or [3, H, W] (image) per step")
        self.obs_shapes = shapes
        self.cameras = image_entries(shapes)
        if not self.cameras:
            raise ValueError(
                f"ImageObservationEncoder needs at least one image entry [3, H, W]; got {shapes} "
                "(use the state encoder for flat observations)"
            )
        if image_norm not in IMAGE_NORMS:
            raise ValueError(f"image_norm must be one of {IMAGE_NORMS}, got {image_norm!r}")
        self.image_norm, self.shared = image_norm, shared
        if shared and len(set(self.cameras.values())) > 1:
            raise ValueError(f"a shared encoder needs cameras of one size, got {self.cameras}")
        self.crops = nn.ModuleDict()
        nets: dict[str, CameraEncoder] = {}
        for cam, (c, h, w) in self.cameras.items():
            crop = (crop_size(h, crop_ratio), crop_size(w, crop_ratio))
            self.crops[cam] = ImageCrop((h, w), crop)
            if not shared or not nets:
                nets[cam] = CameraEncoder(crop, feature_dim, num_keypoints, group_size, in_channels=c)
        self.nets = nn.ModuleDict(nets)  # one per camera, or the first camera's for all when shared
        if pretrained is not None:
            for net in self.nets.values():
                load_torchvision_resnet18(net.trunk, pretrained, norm_affine=norm_affine)
        flat = vector_entries(shapes)
        self.state = StateEncoder(flat, hidden_dims=state_hidden_dims) if flat else None
        self.feature_dim = feature_dim * len(self.cameras) + (self.state.feature_dim if self.state else 0)

    def _net(self, cam: str) -> CameraEncoder:
        return self.nets[next(iter(self.nets))] if self.shared else self.nets[cam]

    def forward(self, obs: TensorDictBase) -> Tensor:
        n, to = obs.batch_size[:2]
        dtype = self.nets[next(iter(self.nets))].proj.weight.dtype
        crops = []
        for cam in self.cameras:
            x = obs.get(cam)
            if x.dtype != torch.uint8:
                raise TypeError(f"observation entry {cam!r} must be a uint8 image, got {x.dtype}")
            crops.append(
                images_to_float(self.crops[cam](x.reshape(n * to, *x.shape[2:])), self.image_norm, dtype)
            )
        if self.shared:  # one pass over every camera's images
            feats = self._net("").forward(torch.cat(crops)).split(n * to)
        else:
            feats = [self.nets[cam](x) for cam, x in zip(self.cameras, crops, strict=True)]
        parts = [f.reshape(n, to, -1) for f in feats]
        if self.state is not None:
            parts.append(self.state(obs))
        return torch.cat(parts, dim=-1)
