"""CUDA only: ManiSkill's physx_cuda backend through make_env (specs, partial resets), a training step
and the captured-latency benchmark on the GPU. Skipped as a whole where torch sees no CUDA device."""

import json

import pytest
import torch

if not torch.cuda.is_available():
    pytest.skip("needs a CUDA device (torch sees none)", allow_module_level=True)

from l1flow_rl.envs import make_env
from l1flow_rl.envs.per_env import num_parallel_envs, seeded_reset
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs, step_mdp

from l1flow_rl import L1FlowActor, L1FlowLoss, dp_ema_decay
from l1flow_rl.workspace.trainer import Trainer

N, STEPS = 8, 6  # parallel envs in one physx_cuda scene; max_episode_steps
STATE_DIM, RGB_STATE_DIM, IMAGE = 35, 25, 64


@pytest.fixture(scope="module")
def gpu_state_env():
    pytest.importorskip("mani_skill")
    env = make_env("maniskill_pushcube", num_envs=N, device="cuda", max_episode_steps=STEPS)
    yield env
    env.close()


@pytest.mark.maniskill
def test_physx_cuda_state_env_passes_check_env_specs(gpu_state_env):
    env = gpu_state_env
    assert num_parallel_envs(env) == N and env.device.type == "cuda"
    check_env_specs(env)
    td = env.reset()
    obs = td["observation"]
    assert obs.shape == (N, 2, STATE_DIM) and obs.device.type == "cuda" and obs.dtype == torch.float32
    assert env.action_spec.shape == (N, 4)
    rollout = env.rollout(3)
    assert rollout["next", "reward"].shape == (N, 3, 1) and rollout["next", "reward"].device.type == "cuda"
    assert not rollout["next", "sim_error"].any()


@pytest.mark.maniskill
def test_physx_cuda_rgb_env_passes_check_env_specs():
    pytest.importorskip("mani_skill")
    env = make_env(
        "maniskill_pushcube", num_envs=N, device="cuda", obs_mode="rgb", image_size=IMAGE, max_episode_steps=4
    )
    try:
        check_env_specs(env)
        obs = env.rollout(3)["next", "observation"]
        assert obs["state"].shape == (N, 3, 2, RGB_STATE_DIM) and obs["state"].device.type == "cuda"
        assert obs["rgb"].shape == (N, 3, 2, 3, IMAGE, IMAGE) and obs["rgb"].dtype == torch.uint8
        assert obs["rgb"].float().std() > 0  # a rendered camera image, not a blank buffer
        assert not torch.equal(obs["rgb"][0, -1, 1], obs["rgb"][1, -1, 1])  # each env its own scene
    finally:
        env.close()


@pytest.mark.maniskill
def test_physx_cuda_partial_reset_leaves_the_other_envs_running(gpu_state_env):
    env = gpu_state_env
    td = seeded_reset(env, None, list(range(100, 100 + N)))
    for _ in range(3):
        td = step_mdp(env.rand_step(td))
    before = td["observation"].clone()
    chosen = [2, 5]
    seeds = [1000 + i if i in chosen else None for i in range(N)]
    td = seeded_reset(env, td, seeds)
    others = [i for i in range(N) if i not in chosen]
    assert td["is_init"].squeeze(-1).tolist() == [i in chosen for i in range(N)]
    assert torch.equal(td["observation"][others], before[others])  # not reset: exactly where they were
    after = td["observation"][chosen]
    assert not torch.equal(after, before[chosen])
    assert torch.equal(after[:, 0], after[:, 1])  # a new episode: history padded with its first frame
    # Each env keeps its own step count: the others reach the time limit 3 steps later, the reset ones not.
    for _ in range(STEPS - 3):
        td = env.rand_step(td)
        flags = td["next", "truncated"].squeeze(-1)
        td = step_mdp(td)
    assert flags[others].all() and not flags[chosen].any()


@pytest.mark.maniskill
def test_physx_cuda_same_seeds_same_start(gpu_state_env):
    # Per-slot seeding on physx_cuda follows ManiSkill: a full reset with the same seed list
    # starts the same episodes.
    first = seeded_reset(gpu_state_env, None, list(range(N)))["observation"].clone()
    again = seeded_reset(gpu_state_env, None, list(range(N)))["observation"]
    assert torch.equal(first, again)
    assert len({tuple(row.tolist()) for row in first[:, -1]}) > 1  # the envs start apart


def test_trainer_step_on_cuda_updates_weights_and_ema_without_host_syncs():
    torch.manual_seed(0)
    device = torch.device("cuda")
    actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(32, 64), timestep_embed_dim=16).to(
        device
    )
    trainer = Trainer(actor, L1FlowLoss(actor), total_steps=20, lr=1e-3, warmup_steps=0, check_values=False)
    assert trainer.optimizer.param_groups[0]["fused"]  # the one-kernel AdamW on CUDA
    batch = TensorDict(
        {"observation": torch.randn(64, 2, 5), "action_chunk": torch.rand(64, 16, 2) * 2 - 1}, [64]
    ).to(device)

    def live() -> torch.Tensor:
        return torch.nn.utils.parameters_to_vector(actor.parameters()).detach().clone()

    trainer.train_step(batch)  # the first update copies the weights; lazy CUDA set-up happens here
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")  # any host synchronisation inside the steps raises
    try:
        metrics, weights = [], []
        for _ in range(3):
            metrics.append(trainer.train_step(batch))
            weights.append(live())
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert all(m["loss"].device.type == "cuda" for m in metrics)
    assert all(torch.isfinite(torch.stack([m["loss"], m["grad_norm"]])).all() for m in metrics)
    assert not torch.equal(weights[0], weights[-1])  # the weights moved
    # Updates 2-4 of the EMA: a copy (decay 0), then blends with Diffusion Policy's decays 1 - 2**-0.75
    # and 1 - 3**-0.75.
    d1, d2 = dp_ema_decay(1), dp_ema_decay(2)
    expected = torch.lerp(torch.lerp(weights[0], weights[1], 1 - d1), weights[2], 1 - d2)
    ema = torch.nn.utils.parameters_to_vector(trainer.ema_actor.parameters())
    torch.testing.assert_close(ema, expected)
    assert not torch.equal(ema, weights[2])
    assert int(trainer.ema.n_averaged) == 4 and trainer.ema.n_averaged.device.type == "cpu"


@pytest.mark.parametrize("amp", [False, True])
def test_trainer_bf16_autocast_step_on_cuda(amp):
    torch.manual_seed(0)
    actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(32, 64), timestep_embed_dim=16).cuda()
    trainer = Trainer(actor, L1FlowLoss(actor), total_steps=10, lr=1e-3, warmup_steps=0, amp=amp)
    batch = TensorDict(
        {"observation": torch.randn(32, 2, 5), "action_chunk": torch.rand(32, 16, 2) * 2 - 1}, [32]
    ).cuda()
    losses = [float(trainer.train_step(batch)["loss"]) for _ in range(5)]
    assert all(torch.isfinite(torch.tensor(losses)))


def test_captured_latency_benchmark_runs_and_matches_eager(tmp_path):
    from benchmarks.speed import bench_latency_cuda

    out = tmp_path / "latency_cuda.json"
    assert bench_latency_cuda.main(["--quick", "--no-peers", "--out", str(out)]) == 0
    figures = json.loads(out.read_text())
    for block in figures["networks"].values():
        assert {
            "l1flow_2nfe",
            "l1flow_2nfe_cuda_graph",
            "l1flow_2nfe_cuda_graph_bf16",
            "floor_2_unet",
        } <= set(block["ms"])
    # The graph computes what the eager call computes: same weights, zero noise -> the same chunk.
    actor = bench_latency_cuda.build_state_actor("l1flow_2nfe", torch.device("cuda"))
    obs = bench_latency_cuda.observation("state", torch.device("cuda"))
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    with set_exploration_type(ExplorationType.DETERMINISTIC):
        captured = bench_latency_cuda.CapturedActor(actor, obs)
        with torch.no_grad():
            eager = actor(obs.clone())["action_chunk"]
        torch.testing.assert_close(captured(obs).clone(), eager)
        new_obs = obs.clone()
        new_obs["observation"] += 1.0
        with torch.no_grad():
            eager_new = actor(new_obs.clone())["action_chunk"]
        torch.testing.assert_close(captured(new_obs).clone(), eager_new)  # the graph reads the new input
        # Under bf16 autocast the graph returns a float32 chunk of the same shape, near the fp32 one.
        chunk_bf16 = bench_latency_cuda.CapturedActor(actor, obs, bf16=True)(new_obs).clone()
        assert chunk_bf16.dtype == torch.float32 and chunk_bf16.shape == eager_new.shape
        assert (chunk_bf16 - eager_new).abs().max() < 0.1


def test_compiled_trainer_then_other_batch_sizes_on_cuda():
    # train.compile=true: training at one batch size, then the policy at evaluation's batch sizes.
    # With dynamic shapes, torch 2.11's GroupNorm-backward kernel failed here ("misaligned address");
    # the Trainer compiles with static shapes, so each size gets its own kernels.
    torch.manual_seed(0)
    actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(32, 64), timestep_embed_dim=16).cuda()
    trainer = Trainer(actor, L1FlowLoss(actor), total_steps=10, lr=1e-3, warmup_steps=0, compile=True)
    for n in (32, 24):  # the second size recompiles rather than going dynamic
        batch = TensorDict(
            {"observation": torch.randn(n, 2, 5), "action_chunk": torch.rand(n, 16, 2) * 2 - 1}, [n]
        ).cuda()
        losses = torch.stack([trainer.train_step(batch)["loss"] for _ in range(3)])
        assert torch.isfinite(losses).all()
    for n in (1, 7):
        with torch.no_grad():
            chunk = actor(TensorDict({"observation": torch.randn(n, 2, 5)}, [n]).cuda())["action_chunk"]
        assert chunk.shape == (n, 8, 2) and torch.isfinite(chunk).all()  # the 8 executed actions


@pytest.mark.parametrize("env_device", [None, "cpu"])
def test_train_job_on_cuda_then_eval_of_its_checkpoint_on_cpu(tmp_path, env_device):
    # `l1flow-rl train device=cuda` end to end on the point-mass double (CPU simulator, CUDA policy),
    # then the checkpoint it wrote re-scored with device=cpu: a GPU-trained policy loads on a CPU box.
    from doubles.point_mass import (
        POINT_MASS_TASK,  # noqa: F401  (registers the double)
        TASK_OVERRIDES,
    )

    from l1flow_rl.commands.cli import main

    run_dir = tmp_path / "run"
    common = [*TASK_OVERRIDES, "eval.num_envs=2"]
    train = [
        *common,
        "network.down_dims=[16,32]",
        "demos.num=4",
        "train.steps=30",
        "train.batch_size=16",
        "train.warmup_steps=2",
        "eval.episodes=2",
        "device=cuda",
        *([f"eval.env_device={env_device}"] if env_device else []),  # cpu: envs on the CPU, policy on the GPU
        f"data_dir={tmp_path / 'data'}",
        f"run_dir={run_dir}",
    ]
    assert main(["train", *train]) == 0
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["steps"] == 30
    record = json.loads((run_dir / "eval.json").read_text())["protocol"]
    assert record["env_device"].startswith(env_device or "cuda")
    eval_dir = tmp_path / "eval"
    rescore = [*common, f"checkpoint={run_dir / 'checkpoints' / 'best.pt'}", "eval.episodes=3", "device=cpu"]
    assert main(["eval", *rescore, f"run_dir={eval_dir}"]) == 0
    rescored = json.loads((eval_dir / "eval.json").read_text())
    assert rescored["episodes"] == 3 and [e["length"] for e in rescored["per_episode"]] == [30, 30, 30]


@pytest.mark.maniskill
def test_finetune_online_on_cuda_steps_envs_in_cpu_workers(tmp_path):
    # seen on an H200: with the collector's env made on the GPU, the first online round failed
    # ("indices should be either on cpu or on the same device"); the envs now step on the CPU and the
    # collector moves each step to the actor's device and back
    pytest.importorskip("mani_skill")
    from test_finetune_job import BC, FT

    from l1flow_rl.commands.cli import main
    from l1flow_rl.workspace.checkpoint import load_checkpoint

    data, bc_dir, ft_dir = tmp_path / "data", tmp_path / "bc", tmp_path / "ft"
    assert main(["train", f"data_dir={data}", f"run_dir={bc_dir}", *BC]) == 0
    checkpoint = bc_dir / "checkpoints" / "latest.pt"
    args = [f"checkpoint={checkpoint}", f"data_dir={data}", f"run_dir={ft_dir}", *FT, "finetune=qc"]
    assert main(["finetune", *args, "device=cuda"]) == 0
    progress = load_checkpoint(ft_dir / "checkpoints" / "latest.pt")["progress"]
    assert progress["env_steps"] == 80 and progress["online_updates"] == 4
