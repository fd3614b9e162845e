"""Networks: Diffusion Policy's conditional temporal UNet and observation encoders."""

from l1flow_rl.networks.encoders import ObservationEncoder, StateEncoder
from l1flow_rl.networks.unet1d import ConditionalUnet1D

__all__ = ["ConditionalUnet1D", "ObservationEncoder", "StateEncoder"]
