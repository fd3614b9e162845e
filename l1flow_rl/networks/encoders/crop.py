"""Crop augmentation for image batches: a random crop per image in training, the centre crop in eval."""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["ImageCrop", "crop_size"]


def crop_size(size: int, ratio: float) -> int:
    """The crop side for an image side and a ratio (rounded; e.g. 0.9 of 84 is 76, of 128 is 115)."""
    if not 0.0 < ratio <= 1.0:
        raise ValueError(f"crop ratio must be in (0, 1], got {ratio}")
    return max(1, round(size * ratio))


class ImageCrop(nn.Module):
    """[N, C, H, W] -> [N, C, h, w] on the images' own device, for any dtype (uint8 stays uint8).

    In training mode each image gets its own uniformly random offset (Diffusion Policy's random crop
    augmentation); in eval mode every image is cropped at the centre, so evaluation is deterministic.
    The offsets are drawn as one tensor and the crop is one gather, so a batch costs one kernel
    launch rather than a Python loop over images.

    Example:
        >>> import torch
        >>> crop = ImageCrop((8, 8), (6, 6)).eval()
        >>> x = torch.arange(64, dtype=torch.uint8).reshape(1, 1, 8, 8)
        >>> crop(x)[0, 0, 0].tolist()
        [9, 10, 11, 12, 13, 14]
    """

    def __init__(self, image_size: tuple[int, int], crop: tuple[int, int]) -> None:
        super().__init__()
        (self.height, self.width), (self.crop_h, self.crop_w) = image_size, crop
        if not (0 < self.crop_h <= self.height and 0 < self.crop_w <= self.width):
            raise ValueError(f"crop {crop} must fit in the image {image_size}")

    def extra_repr(self) -> str:
        return f"image=({self.height}, {self.width}), crop=({self.crop_h}, {self.crop_w})"

    def offsets(self, n: int, device: torch.device) -> tuple[Tensor, Tensor]:
        """Top-left corners [n] (rows, cols): random in training, the centre in eval."""
        free_h, free_w = self.height - self.crop_h, self.width - self.crop_w
        if self.training:
            return (
                torch.randint(0, free_h + 1, (n,), device=device),
                torch.randint(0, free_w + 1, (n,), device=device),
            )
        return (
            torch.full((n,), free_h // 2, device=device, dtype=torch.long),
            torch.full((n,), free_w // 2, device=device, dtype=torch.long),
        )

    def forward(self, images: Tensor) -> Tensor:
        if images.dim() != 4 or tuple(images.shape[-2:]) != (self.height, self.width):
            raise ValueError(
                f"ImageCrop expects [N, C, {self.height}, {self.width}] images, got {tuple(images.shape)}"
            )
        if (self.crop_h, self.crop_w) == (self.height, self.width):
            return images
        n, device = images.shape[0], images.device
        top, left = self.offsets(n, device)
        rows = (top[:, None] + torch.arange(self.crop_h, device=device))[:, :, None]  # [N, h, 1]
        cols = (left[:, None] + torch.arange(self.crop_w, device=device))[:, None, :]  # [N, 1, w]
        batch = torch.arange(n, device=device)[:, None, None]
        # advanced indices around a slice put their dims first: [N, h, w, C]
        return images[batch, :, rows, cols].permute(0, 3, 1, 2)
