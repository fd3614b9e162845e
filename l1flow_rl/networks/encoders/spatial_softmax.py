"""Spatial softmax: a feature map -> the expected image coordinates of K learned keypoints."""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["SpatialSoftmax"]


class SpatialSoftmax(nn.Module):
    """[N, C, H, W] -> [N, 2K]: a 1x1 convolution makes K keypoint maps, a softmax over the H*W
    positions of each turns it into a distribution, and its expected (x, y) in [-1, 1]² is the output
    (Levine et al. 2016; robomimic's and Diffusion Policy's hybrid image encoder, K = 32).

    Args:
        in_channels: C. num_keypoints: K (None keeps one keypoint per input channel, no projection).
        height, width: the feature map's size, which fixes the coordinate grid.
        temperature: softmax temperature; ``learnable_temperature`` makes it a parameter.

    Example:
        >>> import torch
        >>> SpatialSoftmax(512, 4, 4, num_keypoints=32)(torch.randn(2, 512, 4, 4)).shape
        torch.Size([2, 64])
    """

    def __init__(
        self,
        in_channels: int,
        height: int,
        width: int,
        num_keypoints: int | None = 32,
        temperature: float = 1.0,
        learnable_temperature: bool = False,
    ) -> None:
        super().__init__()
        self.num_keypoints = num_keypoints or in_channels
        self.proj = nn.Conv2d(in_channels, num_keypoints, 1) if num_keypoints else nn.Identity()
        log_t = torch.tensor(float(temperature)).log()
        if learnable_temperature:
            self.log_temperature = nn.Parameter(log_t)
        else:
            self.register_buffer("log_temperature", log_t)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, height), torch.linspace(-1, 1, width), indexing="ij")
        # not saved: they follow from (height, width)
        self.register_buffer("grid", torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1), persistent=False)
        self.output_dim = 2 * self.num_keypoints

    def forward(self, features: Tensor) -> Tensor:
        maps = self.proj(features).flatten(2)  # [N, K, H*W]
        if maps.shape[-1] != self.grid.shape[0]:
            raise ValueError(
                f"SpatialSoftmax was built for {self.grid.shape[0]} positions, got a map of {maps.shape[-1]}"
            )
        attention = torch.softmax(maps / self.log_temperature.exp(), dim=-1)
        keypoints = attention @ self.grid.to(attention.dtype)  # [N, K, 2] expected (x, y)
        return keypoints.flatten(1)
