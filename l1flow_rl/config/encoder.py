"""The encoder group (``configs/encoder/*.yaml``): how observations become the policy's condition.

``name`` picks a registered encoder (``l1flow_rl.networks.encoders.encoder_names()``): ``state``
(flat entries only), ``resnet18_gn`` (Diffusion Policy's hybrid image encoder), or ``auto`` (the
default), which takes ``resnet18_gn`` when the task observes images and ``state`` otherwise. The
other fields are the image encoder's; the state encoder reads ``state_hidden_dims`` only.
"""

from __future__ import annotations

from dataclasses import dataclass

from l1flow_rl.config.path_fields import EXISTING, path_field
from l1flow_rl.config.ranges import bounded

__all__ = ["EncoderConfig"]


@dataclass
class EncoderConfig:
    name: str = "auto"  # auto | state | resnet18_gn | a registered encoder
    feature_dim: int = bounded(64, ge=1)  # features per camera: the Linear after the spatial softmax (DP: 64)
    num_keypoints: int = bounded(32, ge=1)  # spatial-softmax keypoints (DP: 32)
    # crop side / image side: random crop in training, centre crop in evaluation. 0.9 follows DP's
    # robomimic setting (76 of 84) and gives 115 of ManiSkill's 128; DP's PushT setting is 0.875 (84 of 96).
    crop_ratio: float = bounded(0.9, gt=0, le=1)
    shared: bool = False  # one network for every camera instead of one per camera (DP: per camera)
    group_size: int = bounded(16, ge=1)  # channels per GroupNorm group (DP: 16)
    image_norm: str = "signed"  # signed ([-1, 1], DP) | unit ([0, 1]) | imagenet (mean/std)
    # a local torchvision resnet18 state_dict file to start every camera's trunk from (null: random init)
    pretrained: str | None = path_field(None, kind=EXISTING, commands=("train",))
    norm_affine: str = "copy"  # pretrained BatchNorm affine weights: copy into the GroupNorms | reset
    state_hidden_dims: list[int] = bounded(list, ge=1, each=True)  # MLP over the flat entries (none: DP)
