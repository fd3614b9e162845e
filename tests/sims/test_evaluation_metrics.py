"""Confidence intervals, the simulator's own episode metrics on the real ManiSkill env, what
evaluations send to a TorchRL logger, and a training run that picks its checkpoint on validation
seeds and reports test seeds."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule

from l1flow_rl.evaluation import evaluate, mean_interval, wilson_interval
from l1flow_rl.workspace.logging import log_evaluation, logger_kwargs

Z2 = 1.959963984540054**2


def test_wilson_interval_at_the_edges_and_its_coverage():
    # closed forms at 0/n and n/n: [0, z^2/(n+z^2)] and [n/(n+z^2), 1]
    assert wilson_interval(0, 10) == pytest.approx((0.0, Z2 / (10 + Z2)))
    assert wilson_interval(10, 10) == pytest.approx((10 / (10 + Z2), 1.0))
    # exactly, not 1e-17 beside the rate (a plot's error bar below the point would be negative)
    assert [wilson_interval(0, n)[0] for n in (10, 50, 100)] == [0.0, 0.0, 0.0]
    assert [wilson_interval(n, n)[1] for n in (10, 50, 100)] == [1.0, 1.0, 1.0]
    lo, hi = wilson_interval(25, 50)
    assert (lo, hi) == pytest.approx((0.3664, 0.6336), abs=1e-4)  # the textbook value for 25/50
    # about 95 % of intervals hold the true rate (p = 0.3, n = 50, 4000 draws)
    rng = np.random.default_rng(0)
    hits = [lo <= 0.3 <= hi for lo, hi in (wilson_interval(int(k), 50) for k in rng.binomial(50, 0.3, 4000))]
    assert 0.93 <= np.mean(hits) <= 0.97
    with pytest.raises(ValueError, match="successes must lie in"):
        wilson_interval(11, 10)


def test_mean_interval_is_students_t():
    scipy_stats = pytest.importorskip("scipy.stats")
    x = [1.0, 2.5, 2.0, 4.0, 3.5]
    want = scipy_stats.t.interval(0.95, len(x) - 1, loc=np.mean(x), scale=scipy_stats.sem(x))
    assert mean_interval(x) == pytest.approx(want)
    assert mean_interval([1.0]) == (None, None)


def zero_chunks(observation: torch.Tensor) -> torch.Tensor:
    return torch.zeros(*observation.shape[:-2], 4, 4)


@pytest.mark.maniskill
def test_simulator_episode_metrics_equal_the_rollout_by_hand():
    pytest.importorskip("mani_skill")
    from l1flow_rl.envs import make_env
    from torchrl.modules import MultiStepActorWrapper

    policy = TensorDictModule(zero_chunks, in_keys=["observation"], out_keys=["action_chunk"])
    metrics = {
        "max_reward": ("max", "reward"),
        "reward_sum": ("sum", "reward"),
        "last_reward": ("last", "reward"),
        "ever_success": ("any", "success"),
    }
    env = make_env("maniskill_pushcube", max_episode_steps=6, reconfigure_each_episode=True)
    try:
        result = evaluate(policy, env, episodes=2, seed=5, episode_metrics=metrics)
        by_hand = []
        for seed in (5, 6):
            start = env.reset(seed=[seed])
            executor = MultiStepActorWrapper(policy, n_steps=4)
            rollout = env.rollout(12, executor, auto_reset=False, tensordict=start)[0]
            by_hand.append(rollout["next", "reward"].reshape(-1))
    finally:
        env.close()
    for got, reward in zip(result["per_episode"], by_hand):
        assert got["max_reward"] == pytest.approx(reward.max().item(), rel=1e-5)
        assert got["reward_sum"] == pytest.approx(reward.sum().item(), rel=1e-5)
        assert got["reward_sum"] == pytest.approx(got["return"], rel=1e-6)
        assert got["last_reward"] == pytest.approx(reward[-1].item(), rel=1e-5)
        assert got["ever_success"] == got["success_once"]
    assert result["max_reward"] == pytest.approx(np.mean([r.max().item() for r in by_hand]), rel=1e-5)
    assert result["ci_method"]["max_reward"] == "t" and result["ci_method"]["ever_success"] == "wilson"
    low, high = result["ci95"]["max_reward"]
    assert low <= result["max_reward"] <= high


def test_every_metric_and_the_video_reach_the_logger(tmp_path):
    from torchrl.record.loggers import CSVLogger, get_logger

    from l1flow_rl.evaluation.metrics import summarize_metrics
    from l1flow_rl.evaluation.videos import write_video

    # an evaluation result as evaluate() returns it, with one filmed episode (rendering is slow on
    # the CPU; test_evaluation.py films a real one)
    frames = [np.full((16, 16, 3), 40 * t, dtype=np.uint8) for t in range(4)]
    video = write_video(tmp_path / "videos" / "episode000_seed3.mp4", frames, fps=5)
    per_episode = [
        {"seed": 3, "success_once": True, "return": 2.0, "video": str(video)},
        {"seed": 4, "success_once": False, "return": 1.0},
    ]
    stats = summarize_metrics(per_episode, {"success_once": "rate", "return": "mean"})
    result = {
        **{k: v["mean"] for k, v in stats.items()},
        "ci95": {k: [v["ci95_low"], v["ci95_high"]] for k, v in stats.items()},
        "latency_ms_median": 3.0,
        "nfe_per_chunk": 2.0,
        "errors": 0,
        "per_episode": per_episode,
    }
    logger = CSVLogger("run", log_dir=str(tmp_path / "logs"), video_format="pt")
    logged = log_evaluation(logger, result, step=7, prefix="test")
    assert set(logged) == {
        *(f"test/{m}{s}" for m in ("success_once", "return") for s in ("", "_ci95_low", "_ci95_high")),
        "test/latency_ms_median",
        "test/nfe_per_chunk",
        "test/errors",
        "test/video_seed3",
    }
    scalars = tmp_path / "logs" / "run" / "scalars" / "test"
    assert (scalars / "return.csv").read_text().split() == ["7,1.5"]
    low = float((scalars / "success_once_ci95_low.csv").read_text().split(",")[1])
    assert low == pytest.approx(wilson_interval(1, 2)[0])
    logged_video = torch.load(
        tmp_path / "logs" / "run" / "videos" / "test" / "video_seed3_7.pt", weights_only=True
    )
    assert logged_video.dtype == torch.uint8 and logged_video.shape == (1, 4, 3, 16, 16)  # [1, T, 3, H, W]
    assert logged_video[0, -1].float().mean().item() == pytest.approx(120, abs=3)  # mp4 is lossy

    # TorchRL's default CSV logger writes mp4 through torchcodec; without it the run goes on
    csv_mp4 = get_logger("csv", logger_name=str(tmp_path / "logs2"), experiment_name="run")
    try:
        import torchcodec  # noqa: F401
    except ImportError:
        with pytest.warns(UserWarning, match="cannot log videos here"):
            log_evaluation(csv_mp4, result, step=7, prefix="test")


def test_wandb_takes_project_group_and_run_name_from_the_config(tmp_path):
    kwargs = logger_kwargs(
        "wandb", tmp_path / "run7", project="proj", group="sweep1", run_name=None, config={"seed": 3}
    )
    assert kwargs["experiment_name"] == "run7" and kwargs["logger_name"] == str(tmp_path / "run7" / "logs")
    assert kwargs["wandb_kwargs"] == {"project": "proj", "group": "sweep1", "config": {"seed": 3}}
    assert logger_kwargs("csv", tmp_path, run_name="mine")["experiment_name"] == "mine"
    with pytest.raises(ValueError, match=r"train.logger=.mlflow."):
        logger_kwargs("mlflow", tmp_path)


@pytest.mark.maniskill
@pytest.mark.slow  # about a minute: demos, training, three evaluations
def test_training_picks_the_checkpoint_on_validation_seeds_and_reports_test_seeds(tmp_path):
    pytest.importorskip("mani_skill")
    from l1flow_rl.commands.cli import main

    run_dir = tmp_path / "run"
    args = [
        f"data_dir={tmp_path / 'data'}",
        f"run_dir={run_dir}",
        "demos.num=2",
        "train.steps=20",
        "train.eval_every=10",
        "train.checkpoint_every=10",
        "train.batch_size=16",
        "train.warmup_steps=2",
        "network.down_dims=[16,32]",
        "network.timestep_embed_dim=16",
        "eval.episodes=2",
        "eval.val_episodes=1",
        "eval.num_envs=1",
        "task.max_episode_steps=8",
    ]
    assert main(["train", *args]) == 0
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["split"] == "test" and [e["seed"] for e in result["per_episode"]] == [100_000, 100_001]
    selection = result["selection"]
    assert selection["split"] == "val" and selection["seeds"] == {"first": 10_000, "episodes": 1}
    assert [e["step"] for e in selection["evaluations"]] == [10, 20]  # periodic, then the final model
    top = max(e["success_once"] for e in selection["evaluations"])
    # training keeps the latest of equally validated models
    assert selection["step"] == max(e["step"] for e in selection["evaluations"] if e["success_once"] == top)
    assert selection["rule"].endswith("the latest of equals")
    assert torch.load(run_dir / "checkpoints" / "best.pt", weights_only=True)["step"] == selection["step"]
    assert result["sampler"]["name"] == "two_step"
    scalars = next((run_dir / "logs").glob("*/scalars"))
    steps = [int(line.split(",")[0]) for line in (scalars / "val" / "success_once.csv").read_text().split()]
    assert steps == [10, 20]
    assert (scalars / "test" / "return_ci95_high.csv").is_file()


def test_selection_takes_the_earliest_or_latest_best_validation_and_the_final_model_without_one():
    from l1flow_rl.commands.cli import compose_config
    from l1flow_rl.workspace.evaluator import PeriodicEvaluator

    evaluator = PeriodicEvaluator(compose_config(["eval.val_episodes=5"]), torch.device("cpu"))
    evals = [
        {"step": 10, "split": "val", "success_once": 0.4},
        {"step": 20, "split": "val", "success_once": 0.8},
        {"step": 30, "split": "val", "success_once": 0.8},
        {"step": 30, "split": "test", "success_once": 1.0},  # test figures never choose
    ]
    chosen = evaluator.selection(evals, final_step=30)  # of equals the earliest
    assert (chosen["split"], chosen["step"], chosen["value"]) == ("val", 20, 0.8)
    latest = evaluator.selection(evals, final_step=30, rule="latest")  # training's rule
    assert (latest["step"], latest["value"]) == (30, 0.8) and latest["rule"].endswith("latest of equals")
    with pytest.raises(ValueError, match="rule='last'"):
        evaluator.selection(evals, final_step=30, rule="last")
    assert chosen["seeds"] == {"first": 10_000, "episodes": 5}
    assert [e["step"] for e in chosen["evaluations"]] == [10, 20, 30]
    final = evaluator.selection([], final_step=30)
    assert (final["split"], final["step"]) == (None, 30) and "eval_every=0" in final["rule"]


@pytest.mark.maniskill
def test_validation_can_use_a_cheaper_sampler_of_the_same_network(tmp_path):
    """eval.val_sampler: a DDPM-100 run validated under DDIM-4 (curve, checkpoint choice); its test
    figures keep DDPM-100. The counted network evaluations per chunk say which sampler scored what."""
    pytest.importorskip("mani_skill")
    from l1flow_rl.commands.cli import main

    run_dir = tmp_path / "run"
    args = [
        f"data_dir={tmp_path / 'data'}",
        f"run_dir={run_dir}",
        "policy=ddpm",
        "eval.val_sampler=ddim",
        "eval.val_sampler_kwargs.steps=4",
        "demos.num=2",
        "train.steps=20",
        "train.eval_every=10",
        "train.batch_size=16",
        "train.warmup_steps=2",
        "network.down_dims=[16,32]",
        "network.timestep_embed_dim=16",
        "eval.episodes=1",
        "eval.val_episodes=1",
        "eval.num_envs=1",
        "task.max_episode_steps=8",
    ]
    assert main(["train", *args]) == 0
    evals = json.loads((run_dir / "history.json").read_text())["evals"]
    assert [(e["split"], e["nfe_per_chunk"]) for e in evals] == [("val", 4.0), ("val", 4.0), ("test", 100.0)]
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["selection"]["sampler"] == "ddim" and result["sampler"]["name"] == "ddpm"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["eval.val_sampler=ddim9"], "eval.val_sampler='ddim9': expected one of"),
        (
            ["eval.val_sampler=ddim", "eval.val_sampler_kwargs.t_first=0.5"],
            "eval.val_sampler_kwargs.t_first",
        ),
        (["eval.val_sampler=ddim"], "eval.val_sampler='ddim' reads a 'epsilon'-prediction network"),
    ],
)
def test_a_validation_sampler_that_cannot_work_fails_at_config_time(overrides, message):
    from l1flow_rl.commands.cli import compose_config
    from l1flow_rl.config.validate import ConfigValidationError, validate_config

    with pytest.raises(ConfigValidationError, match=re.escape(message)):
        validate_config(compose_config(["policy=l1flow", *overrides]), "train")
