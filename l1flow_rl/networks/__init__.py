"""Networks: the chunk denoisers (Diffusion Policy's conditional temporal UNet, an MLP over the
flattened chunk) and observation encoders."""

from l1flow_rl.networks.encoders import ObservationEncoder, StateEncoder
from l1flow_rl.networks.mlp import MLPDenoiser
from l1flow_rl.networks.registry import make_network, network_names
from l1flow_rl.networks.unet1d import ConditionalUnet1D

__all__ = [
    "ConditionalUnet1D",
    "MLPDenoiser",
    "ObservationEncoder",
    "StateEncoder",
    "make_network",
    "network_names",
]
