"""Observation encoders: a TensorDict of observation entries [N, To, ...] -> per-step features [N, To, F].

* :class:`StateEncoder` (``encoder=state``): flat entries concatenated.
* :class:`ImageObservationEncoder` (``encoder=resnet18_gn``): Diffusion Policy's hybrid image
  encoder (ResNet-18 with GroupNorm, spatial softmax, linear) per camera or shared, with crop
  augmentation, and the flat entries after the image features.

New encoders register themselves with :func:`register_encoder` (see ``registry.py``).
"""

from l1flow_rl.networks.encoders import builtin as _builtin  # noqa: F401  (registers state, resnet18_gn)
from l1flow_rl.networks.encoders.base import ObservationEncoder, image_entries, is_image_shape, vector_entries
from l1flow_rl.networks.encoders.crop import ImageCrop, crop_size
from l1flow_rl.networks.encoders.image import (
    IMAGE_NORMS,
    CameraEncoder,
    ImageObservationEncoder,
    images_to_float,
)
from l1flow_rl.networks.encoders.registry import (
    AUTO,
    EncoderSpec,
    encoder_names,
    encoder_problems,
    get_encoder,
    make_encoder,
    register_encoder,
    resolve_encoder_name,
)
from l1flow_rl.networks.encoders.resnet18_gn import ResNet18GN, group_norm, load_torchvision_resnet18
from l1flow_rl.networks.encoders.spatial_softmax import SpatialSoftmax
from l1flow_rl.networks.encoders.state import StateEncoder

__all__ = [
    "AUTO",
    "IMAGE_NORMS",
    "CameraEncoder",
    "EncoderSpec",
    "ImageCrop",
    "ImageObservationEncoder",
    "ObservationEncoder",
    "ResNet18GN",
    "SpatialSoftmax",
    "StateEncoder",
    "crop_size",
    "encoder_names",
    "encoder_problems",
    "get_encoder",
    "group_norm",
    "image_entries",
    "images_to_float",
    "is_image_shape",
    "load_torchvision_resnet18",
    "make_encoder",
    "register_encoder",
    "resolve_encoder_name",
    "vector_entries",
]
