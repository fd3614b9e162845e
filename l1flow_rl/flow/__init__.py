"""Flow and diffusion maths shared by every policy: time convention, timestep laws, objectives, samplers."""

from l1flow_rl.flow.diffusion_schedule import DiffusionSchedule
from l1flow_rl.flow.objectives import sample_prediction_error
from l1flow_rl.flow.samplers import (
    ChunkSampler,
    ConsistencySampler,
    DDIMSampler,
    DDPMSampler,
    DirectSampler,
    EDMHeunSampler,
    EulerSampler,
    OneStepDDPMSampler,
    OneStepEDMSampler,
    TwoStepSampler,
    VelocityEulerSampler,
    make_sampler,
)
from l1flow_rl.flow.time import check_time, interpolate, velocity_from_sample
from l1flow_rl.flow.timesteps import (
    BetaTimesteps,
    MixedLogitNormalTimesteps,
    TimestepDistribution,
    UniformTimesteps,
    make_timesteps,
)

__all__ = [
    "BetaTimesteps",
    "ChunkSampler",
    "ConsistencySampler",
    "DDIMSampler",
    "DDPMSampler",
    "DiffusionSchedule",
    "DirectSampler",
    "EDMHeunSampler",
    "EulerSampler",
    "MixedLogitNormalTimesteps",
    "OneStepDDPMSampler",
    "OneStepEDMSampler",
    "TimestepDistribution",
    "TwoStepSampler",
    "UniformTimesteps",
    "VelocityEulerSampler",
    "check_time",
    "interpolate",
    "make_sampler",
    "make_timesteps",
    "sample_prediction_error",
    "velocity_from_sample",
]
