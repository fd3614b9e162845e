"""The multi-modality demonstration (the L1 Flow paper's Figure 2), as ``l1flow-rl toy run_dir=DIR``.

Every demonstration sees the same observation, and each follows one of K trajectories ("modes") picked
at random: by default a sine and its mirror image (K=2); ``toy.modes`` picks harder families (4 nested
amplitudes, 8 phase shifts). A policy that captures both modes must sample one of the two
curves; a regressor can only return one trajectory for the one observation, and the L1 loss has no
reason to leave the middle ground between the modes. The job trains L1 Flow (2 NFE), velocity flow
matching (10 Euler steps) and L1 regression with the library's own actor and losses, then writes
``DIR/toy.json`` (mode coverage per method) and ``DIR/toy.png`` (heatmaps of the samples).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from torch import Tensor

from l1flow_rl.commands.toy_plot import plot_toy
from l1flow_rl.flow.samplers import (
    ChunkSampler,
    DirectSampler,
    EulerSampler,
    TwoStepSampler,
    VelocityEulerSampler,
)
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.objectives import FlowMatchingLoss, L1FlowLoss, RegressionLoss
from l1flow_rl.objectives.chunk_loss import ChunkLossBase

__all__ = [
    "MODE_FAMILIES",
    "TOY_METHODS",
    "ToyMethod",
    "mode_coverage",
    "run_toy",
    "sine_modes",
    "toy_modes",
    "train_and_evaluate",
    "train_toy_method",
]

HORIZON = 16  # chunk length; the two modes are one full sine period over it
AMPLITUDE = 0.8
#: A sample counts as on a mode when its RMS distance to that mode's trajectory is below this;
#: the two modes lie 2 * AMPLITUDE / sqrt(2) ~ 1.13 apart.
TOLERANCE = 0.1
DOWN_DIMS = (16, 32)  # a small UNet is enough for one-dimensional actions
TIMESTEP_EMBED_DIM = 32


@dataclass(frozen=True)
class ToyMethod:
    """One trained method: its loss, the sampler it trains with and extra samplers to evaluate."""

    name: str
    label: str
    loss: Callable[[L1FlowActor], ChunkLossBase]
    sampler: ChunkSampler
    #: evaluation name -> (label, sampler) for the same trained network
    extra_samplers: tuple[tuple[str, str, ChunkSampler], ...] = ()


TOY_METHODS: dict[str, ToyMethod] = {
    m.name: m
    for m in (
        ToyMethod(
            "l1flow",
            "L1 Flow (x-pred, L1)",
            L1FlowLoss,
            TwoStepSampler(0.5),
            # What the method allows without retraining: another t_first, or more sample-prediction steps.
            (
                ("l1flow_tfirst0.3", "L1 Flow, t_first 0.3", TwoStepSampler(0.3)),
                ("l1flow_tfirst0.7", "L1 Flow, t_first 0.7", TwoStepSampler(0.7)),
                ("l1flow_euler10", "L1 Flow net, x-pred Euler", EulerSampler(10)),
            ),
        ),
        ToyMethod(
            "l1flow_uniform_t",
            "L1 Flow, uniform t",
            lambda actor: L1FlowLoss(actor, timesteps="uniform"),
            TwoStepSampler(0.5),
        ),
        ToyMethod(
            "flow_matching",
            "Flow matching (v-pred)",
            FlowMatchingLoss,
            VelocityEulerSampler(10),
            # The same network with L1 Flow's budget of 2 NFE, to show what few steps cost v-prediction.
            (("flow_matching_2nfe", "Flow matching (v-pred)", VelocityEulerSampler(2)),),
        ),
        ToyMethod("regression", "L1 regression", RegressionLoss, DirectSampler()),
    )
}


def sine_modes(horizon: int = HORIZON, amplitude: float = AMPLITUDE) -> Tensor:
    """The two demonstrated trajectories [2, horizon]: a sine period and its opposite phase."""
    tau = torch.arange(horizon, dtype=torch.float32) / (horizon - 1)
    mode_a = amplitude * torch.sin(2 * math.pi * tau)
    return torch.stack([mode_a, -mode_a])


def nested_amplitude_modes(horizon: int = HORIZON, amplitude: float = AMPLITUDE) -> Tensor:
    """Four modes [4, horizon]: the sine pair at full and at half amplitude (0.28 RMS apart)."""
    pair = sine_modes(horizon, amplitude)
    return torch.cat([pair, pair / 2])


def phase_shift_modes(horizon: int = HORIZON, amplitude: float = AMPLITUDE, k: int = 8) -> Tensor:
    """``k`` modes [k, horizon]: one sine period at k evenly spaced phases (neighbours 0.43 RMS apart
    for k=8)."""
    tau = torch.arange(horizon, dtype=torch.float32) / (horizon - 1)
    phases = 2 * math.pi * torch.arange(k, dtype=torch.float32) / k
    return amplitude * torch.sin(2 * math.pi * tau[None] + phases[:, None])


#: family name -> the demonstrated trajectories [K, H]
MODE_FAMILIES: dict[str, Callable[[], Tensor]] = {
    "opposite_sines": sine_modes,
    "nested_amplitudes": nested_amplitude_modes,
    "phase_shifts": phase_shift_modes,
}


def toy_modes(family: str) -> Tensor:
    try:
        return MODE_FAMILIES[family]()
    except KeyError:
        raise ValueError(f"toy.modes: got {family!r}; expected one of {list(MODE_FAMILIES)}") from None


def toy_batch(modes: Tensor, n: int, generator: torch.Generator) -> TensorDict:
    """``n`` demonstrations, each mode equally likely, all under the same (zero) observation."""
    pick = torch.randint(0, modes.shape[0], (n,), generator=generator)
    return TensorDict(
        {"observation": torch.zeros(n, 1, 1), "action_chunk": modes[pick].unsqueeze(-1)}, batch_size=[n]
    )


def make_toy_actor(sampler: ChunkSampler, horizon: int = HORIZON) -> L1FlowActor:
    """A small chunk actor: one step of a one-dimensional observation, one-dimensional actions."""
    return L1FlowActor.for_state(
        obs_dim=1,
        action_dim=1,
        obs_horizon=1,
        pred_horizon=horizon,
        action_steps=horizon,
        down_dims=DOWN_DIMS,
        timestep_embed_dim=TIMESTEP_EMBED_DIM,
        sampler=sampler,
    )


def train_toy_method(
    method: ToyMethod, modes: Tensor, *, steps: int, batch_size: int, lr: float, seed: int, progress=None
) -> tuple[L1FlowActor, dict[str, float]]:
    """Train one method on the two-mode data; returns the actor and training statistics."""
    torch.manual_seed(seed)  # network initialisation and the loss's noise and time draws
    actor = make_toy_actor(method.sampler, modes.shape[-1])
    loss_fn = method.loss(actor)
    optim = torch.optim.Adam(actor.parameters(), lr=lr)
    data_gen = torch.Generator().manual_seed(seed)
    losses: list[float] = []
    start = time.perf_counter()
    for _ in range(steps):
        loss = loss_fn(toy_batch(modes, batch_size, data_gen))[loss_fn.loss_name]
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()
        losses.append(float(loss.detach()))
        if progress is not None:
            progress.update(1)
    tail = losses[-max(1, min(50, len(losses))) :]
    stats = {"train_seconds": time.perf_counter() - start, "final_loss": sum(tail) / len(tail)}
    return actor, stats


@torch.no_grad()
def sample_toy(actor: L1FlowActor, sampler: ChunkSampler, n: int, seed: int) -> Tensor:
    """``n`` sampled trajectories [n, H] under the shared observation, drawn with ``sampler``."""
    policy = actor.policy
    trained_with, policy.sampler = policy.sampler, sampler
    try:
        chunk = policy.sample_chunk(torch.zeros(n, 1, 1), generator=torch.Generator().manual_seed(seed))
    finally:
        policy.sampler = trained_with
    return chunk[..., 0]


def mode_coverage(samples: Tensor, modes: Tensor, tolerance: float = TOLERANCE) -> dict[str, Any]:
    """How the samples [N, H] split between the modes [K, H].

    A sample is on a mode when its RMS distance to it is below ``tolerance`` (tolerances must stay
    below half the distance between modes, so a sample is on one mode at most). ``shares`` lists
    each mode's share; ``share_neither`` is the off-mode mass; ``modes_hit`` counts the modes that get
    at least half their fair share (0.5 / K); ``balance`` is the smallest share over the largest (1
    is an even split, 0 means a mode is missed); ``rms_to_data_mean`` is the RMS distance to the
    average demonstration, which a mean-collapsed policy sits on. For K=2 the shares are also
    ``share_mode_a`` and ``share_mode_b``.
    """
    dist = (samples[:, None, :] - modes[None]).square().mean(-1).sqrt()  # [N, K]
    on = dist < tolerance
    shares = on.float().mean(0).tolist()
    k = modes.shape[0]
    hi = max(shares)
    out: dict[str, Any] = {
        "shares": shares,
        "share_neither": (~on.any(-1)).float().mean().item(),
        "modes_hit": sum(s >= 0.5 / k for s in shares),
        "num_modes": k,
        "balance": min(shares) / hi if hi > 0 else 0.0,
        "mean_distance_to_nearest_mode": dist.min(-1).values.mean().item(),
        "rms_to_data_mean": (samples - modes.mean(0)).square().mean(-1).sqrt().mean().item(),
    }
    if k == 2:
        out["share_mode_a"], out["share_mode_b"] = shares
    return out


def run_toy(cfg: DictConfig) -> int:
    """Train the toy methods (``cfg.toy``), write ``toy.json`` and ``toy.png`` under ``cfg.run_dir``."""
    try:
        import matplotlib  # noqa: F401
        import tqdm  # noqa: F401
    except ImportError as err:  # the app extra brings tqdm and matplotlib
        raise ImportError("the toy needs tqdm and matplotlib: pip install 'l1flow-rl[app]'") from err
    toy = cfg.toy
    unknown = [m for m in toy.methods if m not in TOY_METHODS]
    if unknown or not toy.methods:
        raise ValueError(
            f"toy.methods: got {list(toy.methods)}; expected a non-empty subset of {list(TOY_METHODS)}"
        )
    for field in ("steps", "batch_size", "samples"):
        if toy[field] < 1:
            raise ValueError(f"toy.{field} must be >= 1, got {toy[field]}")
    if toy.lr <= 0:
        raise ValueError(f"toy.lr must be positive, got {toy.lr}")
    modes = toy_modes(toy.modes)
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    # The toy's tiny convolutions gain nothing from intra-op threads, and on shared cores OpenMP's
    # spin-waiting made a training step several times slower with 2 threads than with 1.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        report, samples = train_and_evaluate(toy, modes)
    finally:
        torch.set_num_threads(threads)
    (run_dir / "toy.json").write_text(json.dumps(report, indent=2) + "\n")
    plot_toy(modes, samples, report["methods"], run_dir / "toy.png")
    print(f"wrote {run_dir / 'toy.json'} and {run_dir / 'toy.png'}")
    return 0


def train_and_evaluate(
    toy: DictConfig, modes: Tensor, *, verbose: bool = True
) -> tuple[dict[str, Any], dict[str, tuple[str, Tensor]]]:
    """Train each of ``toy.methods`` on ``modes`` and evaluate every sampler it lists."""
    # optional dependency (app extra): the progress bar
    from tqdm import tqdm

    results: dict[str, dict[str, Any]] = {}
    samples: dict[str, tuple[str, Tensor]] = {}
    for name in toy.methods:
        method = TOY_METHODS[name]
        with tqdm(total=toy.steps, desc=f"toy {name}", leave=False, mininterval=1.0) as bar:
            actor, stats = train_toy_method(
                method,
                modes,
                steps=toy.steps,
                batch_size=toy.batch_size,
                lr=toy.lr,
                seed=toy.seed,
                progress=bar,
            )
        for eval_name, label, sampler in ((name, method.label, method.sampler), *method.extra_samplers):
            x = sample_toy(actor, sampler, toy.samples, toy.seed + 1)
            results[eval_name] = {"trained": name, "nfe": sampler.nfe, **stats, **mode_coverage(x, modes)}
            samples[eval_name] = (f"{label}, {sampler.nfe} NFE", x)
            if verbose:
                _print_row(eval_name, results[eval_name])
    report = {
        "config": OmegaConf.to_container(toy, resolve=True),
        "modes": toy.get("modes", "opposite_sines"),
        "num_modes": modes.shape[0],
        "horizon": HORIZON,
        "amplitude": AMPLITUDE,
        "tolerance": TOLERANCE,
        "methods": results,
    }
    return report, samples


def _print_row(name: str, r: dict[str, Any]) -> None:
    shares = " ".join(f"{s:5.1%}" for s in r["shares"])
    print(
        f"{name:<20} nfe={r['nfe']:<3} modes [{shares}]  hit {r['modes_hit']}/{r['num_modes']}  "
        f"neither {r['share_neither']:6.1%}  balance {r['balance']:.2f}  "
        f"dist to nearest mode {r['mean_distance_to_nearest_mode']:.3f}  train {r['train_seconds']:.0f}s"
    )
