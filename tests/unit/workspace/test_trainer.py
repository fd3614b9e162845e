"""The optimisation step: it learns, its schedule is Diffusion Policy's, and DDP keeps replicas in sync."""

from __future__ import annotations

import copy
import json
import math
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from l1flow_rl import L1FlowActor, L1FlowLoss
from l1flow_rl.workspace.trainer import Trainer, warmup_cosine


def _batch(n: int, seed: int) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, 2, 3, generator=g)
    # A learnable target: the chunk is a fixed function of the observation.
    act = torch.tanh(obs[:, -1:, :2].expand(n, 8, 2) * torch.linspace(0.5, 1.5, 8)[None, :, None])
    return TensorDict({"observation": obs, "action_chunk": act}, batch_size=[n])


def _actor() -> L1FlowActor:
    return L1FlowActor.for_state(
        obs_dim=3,
        action_dim=2,
        obs_horizon=2,
        pred_horizon=8,
        action_steps=4,
        down_dims=(16, 32),
        timestep_embed_dim=16,
    )


def _trainer(steps: int = 60, actor: L1FlowActor | None = None, **kw) -> Trainer:
    actor = actor if actor is not None else _actor()
    return Trainer(actor, L1FlowLoss(actor), total_steps=steps, lr=3e-3, warmup_steps=5, **kw)


def test_warmup_cosine_schedule():
    f = warmup_cosine(10, 110)
    assert f(0) == 0.0
    assert f(5) == pytest.approx(0.5)
    assert f(10) == pytest.approx(1.0)
    assert f(60) == pytest.approx(0.5)
    assert f(110) == pytest.approx(0.0, abs=1e-12)
    assert f(200) == pytest.approx(0.0, abs=1e-12)
    assert f(35) == pytest.approx(0.5 * (1 + math.cos(math.pi * 0.25)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_training_cuts_the_loss_by_a_stated_factor_and_updates_ema(seed):
    # A fixed batch of 64 learnable chunks, 60 steps at lr 3e-3: the mean of the last 10 losses falls
    # below 0.3x the mean of the first 5 (measured: 0.12-0.19x over seeds 0-5).
    torch.manual_seed(seed)
    trainer = _trainer(grad_clip=1.0)
    data = _batch(64, seed=1)
    losses = [trainer.train_step(data)["loss"] for _ in range(60)]
    start, end = sum(losses[:5]) / 5, sum(losses[-10:]) / 10
    assert end < 0.3 * start, f"loss {start:.4f} -> {end:.4f} ({end / start:.2f}x)"
    assert trainer.step == 60
    assert trainer.optimizer.param_groups[0]["betas"] == (0.95, 0.999)
    assert trainer.optimizer.param_groups[0]["weight_decay"] == 1e-6
    # EMA differs from the live weights but tracks them.
    live = torch.nn.utils.parameters_to_vector(trainer.actor.parameters())
    ema = torch.nn.utils.parameters_to_vector(trainer.ema_actor.parameters())
    assert not torch.equal(live, ema)
    assert (live - ema).norm() < live.norm()


def test_state_dict_round_trip_continues_identically():
    torch.manual_seed(0)
    a = _trainer()
    data = _batch(32, seed=2)
    for _ in range(5):
        a.train_step(data)
    state = copy.deepcopy(a.state_dict())  # state_dict holds live references
    torch.manual_seed(123)
    m1 = [a.train_step(data)["loss"] for _ in range(3)]
    b = _trainer()
    b.load_state_dict(state)
    torch.manual_seed(123)
    m2 = [b.train_step(data)["loss"] for _ in range(3)]
    assert m1 == m2
    assert b.step == 8
    for (k, v1), v2 in zip(a.actor.state_dict().items(), b.actor.state_dict().values()):
        assert torch.equal(v1, v2), k


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# Launched with torchrun in a fresh interpreter, as users launch DDP training: this keeps the test
# independent of the multiprocessing state earlier tests leave behind (worker servers, start methods).
_DDP_SCRIPT = """
import json, sys
import torch
import torch.distributed as dist
sys.path.insert(0, {tests_dir!r})
from test_trainer import _actor, _batch, _trainer

dist.init_process_group("gloo")
rank, world = dist.get_rank(), dist.get_world_size()
torch.manual_seed(100 + rank)  # different initial weights: DDP must broadcast rank 0's
actor = _actor()
initial = torch.nn.utils.parameters_to_vector(actor.parameters()).detach().clone()
trainer = _trainer(actor=actor)
assert trainer.distributed
for step in range(4):
    trainer.train_step(_batch(16, seed=10 * step + rank))  # each rank sees other data
final = torch.nn.utils.parameters_to_vector(trainer.actor.parameters()).detach()
finals = [torch.empty_like(final) for _ in range(world)]
dist.all_gather(finals, final)
initials = [torch.empty_like(initial) for _ in range(world)]
dist.all_gather(initials, initial)
if rank == 0:
    with open({out!r}, "w") as f:
        json.dump({{
            "max_replica_gap": max(float((g - finals[0]).abs().max()) for g in finals),
            "moved": float((final - initials[0]).abs().max()),
            "init_gap": float((initials[1] - initials[0]).abs().max()),
        }}, f)
dist.destroy_process_group()
"""


def test_ddp_two_processes_on_gloo_stay_in_sync(tmp_path):
    out = tmp_path / "ddp.json"
    script = tmp_path / "ddp_check.py"
    script.write_text(_DDP_SCRIPT.format(tests_dir=str(Path(__file__).parents[2]), out=str(out)))
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node=2",
        "--master_addr=127.0.0.1",
        f"--master_port={_free_port()}",
        str(script),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["init_gap"] > 0  # the replicas were built differently...
    assert result["max_replica_gap"] == 0.0  # ...and DDP made and kept them identical
    assert result["moved"] > 0  # while training actually changed the weights


# -- the step without host synchronisations computes what the step with them computed ----------------


def _dp_decay(k: int, power: float = 0.75, max_value: float = 0.9999) -> float:
    """Diffusion Policy's EMAModel decay for its k-th update (k = 0, 1, ...), written out here."""
    s = max(0, k - 1)
    return 0.0 if s <= 0 else max(0.0, min(1 - (1 + s) ** -power, max_value))


def _reference_run(actor: L1FlowActor, data: TensorDict, steps: int, grad_clip: float, ema_blend):
    """The step as it was before the host-sync removal: float() reads every step, clip_grad_norm_
    with an infinite bound when not clipping, and a per-parameter EMA loop."""
    loss_fn = L1FlowLoss(actor)
    params = [p for p in actor.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=3e-3, betas=(0.95, 0.999), weight_decay=1e-6)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, warmup_cosine(5, steps))
    ema = [p.detach().clone() for p in actor.parameters()]
    losses, norms = [], []
    for k in range(steps):
        out = loss_fn(data)
        loss = sum(v for key, v in out.items() if key.startswith("loss_"))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        norm = torch.nn.utils.clip_grad_norm_(
            actor.parameters(), grad_clip if grad_clip > 0 else float("inf")
        )
        opt.step()
        sched.step()
        with torch.no_grad():
            decay = _dp_decay(k)
            ema = [ema_blend(e, p.detach(), decay) for e, p in zip(ema, actor.parameters())]
        losses.append(float(loss.detach()))
        norms.append(float(norm))
    return losses, norms, ema


@pytest.mark.parametrize("grad_clip", [0.0, 0.05])
def test_step_without_host_syncs_matches_the_old_step(grad_clip):
    # 30 steps through the warm-up and into the cosine; grad_clip 0.05 clips on most steps.
    steps, data = 30, _batch(32, seed=3)
    torch.manual_seed(0)
    initial = _actor()
    ref_actor, ref_actor_lerp = copy.deepcopy(initial), copy.deepcopy(initial)

    torch.manual_seed(7)  # the loss draws t and noise from the global generator: same draws in each run
    trainer = _trainer(steps=steps, actor=initial, grad_clip=grad_clip, check_values=False)
    metrics = [trainer.train_step(data) for _ in range(steps)]
    assert all(isinstance(m["loss"], torch.Tensor) and m["loss"].dim() == 0 for m in metrics)
    losses = [float(m["loss"]) for m in metrics]
    norms = [float(m["grad_norm"]) for m in metrics]

    torch.manual_seed(7)
    old_losses, old_norms, old_ema = _reference_run(
        ref_actor, data, steps, grad_clip, lambda e, p, d: e * d + p * (1.0 - d)
    )
    # Same operations on the same values: the losses, norms and live weights agree to the bit.
    assert losses == old_losses
    assert norms == old_norms
    if grad_clip:
        assert sum(n > grad_clip for n in norms) > steps // 2  # the clipping branch really ran
    for (name, mine), theirs in zip(trainer.actor.named_parameters(), ref_actor.parameters()):
        assert torch.equal(mine, theirs), name
    # The EMA blends with one lerp, a + w (b - a), where the old step computed a d + b (1 - d): the
    # two round differently in the last bit, so they agree to float32 precision, not to the bit
    # (measured over these 30 steps: at most 3.6e-7 apart, a few float32 ulps of weights near 1).
    new_ema = list(trainer.ema_actor.parameters())
    for mine, theirs in zip(new_ema, old_ema, strict=True):
        torch.testing.assert_close(mine, theirs, rtol=1e-5, atol=1e-6)
    # A per-parameter torch.lerp with the same decays is what the one foreach call must equal exactly.
    torch.manual_seed(7)
    _, _, lerp_ema = _reference_run(
        ref_actor_lerp,
        data,
        steps,
        grad_clip,
        lambda e, p, d: p.clone() if d == 0 else torch.lerp(e, p, 1 - d),
    )
    for mine, theirs in zip(new_ema, lerp_ema, strict=True):
        assert torch.equal(mine, theirs)
    assert int(trainer.ema.n_averaged) == steps
    # the EMA lags the live weights (the decay reached 1 - 29**-0.75 = 0.92 by the last step)
    live = torch.nn.utils.parameters_to_vector(trainer.actor.parameters())
    assert not torch.equal(live, torch.nn.utils.parameters_to_vector(new_ema))


def test_value_checks_guard_direct_input_and_are_skipped_only_when_asked():
    from l1flow_rl.utils.value_checks import value_checks_enabled

    bad = _batch(8, seed=4)
    bad["action_chunk"][3, 2, 1] = float("nan")
    torch.manual_seed(0)
    with pytest.raises(ValueError, match=r"'action_chunk' contains NaN or Inf \(flat batch rows \[3\]\)"):
        _trainer().train_step(bad)  # the default: data handed over directly is checked
    unchecked = _trainer(check_values=False)
    metrics = unchecked.train_step(bad)  # what the train job does with loader-checked batches
    assert math.isnan(float(metrics["loss"]))  # no check ran: the NaN went through
    assert value_checks_enabled()  # the switch is back on after the step
    with pytest.raises(ValueError, match="contains NaN or Inf"):
        L1FlowLoss(_actor())(bad)
