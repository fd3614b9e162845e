"""benchmarks/bench_flow_q.py end to end in its quick mode (tiny budgets on PushCube): every arm runs
and the JSON the README would read holds each arm's success, budget and the online curve."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")

from benchmarks import bench_flow_q

pytestmark = [pytest.mark.maniskill, pytest.mark.slow]


@pytest.mark.timeout(1800)  # two benchmark invocations, 15 CLI processes with their simulator start-ups
def test_quick_mode_runs_every_arm_and_saves_json_and_plot(tmp_path):
    out = tmp_path / "flow_q.json"
    args = [
        "--quick",
        "--root",
        str(tmp_path / "runs"),
        "--data-dir",
        str(tmp_path / "data"),
        "--out",
        str(out),
    ]
    assert bench_flow_q.main(args) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True
    assert set(figures["arms"]) == {
        "bc",
        "flowq_offline",
        "flowq_online",
        "bc_continued",
        "bc_one_step",
        "bc_continued_one_step",
    }
    for arm in figures["arms"].values():
        assert 0.0 <= arm["success_once"] <= 1.0 and arm["episodes"] == 2
    assert figures["arms"]["flowq_online"]["env_steps"] == 40
    assert figures["arms"]["flowq_offline"]["env_steps"] == 0
    # BC + Monte-Carlo pretraining + critic warm-up + offline + online updates: every flow-Q update is
    # matched by a BC step
    assert figures["budget"]["critic_warmup_updates"] == 2
    assert figures["budget"]["critic_pretrain_updates"] == 1
    assert figures["budget"]["bc_continued_steps"] == 20 + 1 + 2 + 4 + 4
    assert figures["arms"]["bc_continued"]["updates"] == 31
    assert figures["arms"]["flowq_offline"]["updates"] == 7
    curve = figures["online_curve"][0]
    assert [e["env_steps"] for e in curve["evaluations"] if e["phase"] == "online"] == [20]
    assert out.with_suffix(".png").stat().st_size > 1000
    # a second call reads the finished runs back instead of repeating them
    assert bench_flow_q.main(args) == 0
    # the README's table reads every arm from the file
    from benchmarks import report

    text = report.render_flow_q(figures)
    for label, arm in (("BC (the start)", "bc"), ("continued BC (same updates)", "bc_continued")):
        value = figures["arms"][arm]["success_once"]
        assert f"| {label} | {report._num(float(value))} |" in text
    assert f"Gain of online FlowQ over continued BC: {report._num(figures['gain_over_continued_bc'])}" in text
    best = max(figures["arms"][a]["success_once"] for a in ("bc_continued", "bc_continued_one_step"))
    assert figures["gain_over_best_continued_bc"] == pytest.approx(
        figures["arms"]["flowq_online"]["success_once"] - best
    )
    assert figures["gain_offline_over_best_continued_bc"] == pytest.approx(
        figures["arms"]["flowq_offline"]["success_once"] - best
    )
    offline_cont = report._num(figures["gain_offline_over_best_continued_bc"])
    assert f"Offline FlowQ over continued BC (the better of its two samplers): {offline_cont}" in text
    best_bc = max(figures["arms"][a]["success_once"] for a in bench_flow_q.BC_ARMS)
    assert figures["gain_offline_over_best_bc"] == pytest.approx(
        figures["arms"]["flowq_offline"]["success_once"] - best_bc
    )
    offline_gain = report._num(figures["gain_offline_over_best_bc"])
    assert f"Offline FlowQ over the best BC arm (either sampler, the start included): {offline_gain}" in text
    assert figures["extra_test_episodes"] == 0 and figures["pooled_gains"] is None
    assert "pooled" not in text

    # re-run with extra test episodes: the arms are read back, each model is scored on the 2 seeds
    # after the first 2 (100002-100003), and the pooled rates and gains land beside the first ones
    assert bench_flow_q.main([*args, "--extra-test-episodes", "2"]) == 0
    pooled_figures = json.loads(out.read_text())
    assert pooled_figures["extra_test_episodes"] == 2
    for name, arm in pooled_figures["arms"].items():
        assert arm["success_once"] == figures["arms"][name]["success_once"]  # the first 2, unchanged
        assert arm["extra"]["episodes"] == 2 and arm["pooled"]["episodes"] == 4
        expected = (arm["success_once"] * 2 + arm["extra"]["success_once"] * 2) / 4
        assert arm["pooled"]["success_once"] == pytest.approx(expected)
    runs = {name: Path(path) for name, path in pooled_figures["runs"].items()}
    extra = json.loads((runs["flowq_offline"] / "rescore_extra2" / "eval.json").read_text())
    assert extra["seed"] == 100002 and extra["episodes"] == 2
    assert Path(extra["checkpoint"]).name == "latest.pt"  # FlowQ's final policy, as its own eval.json
    bc_extra = json.loads((runs["bc"] / "rescore_extra2" / "eval.json").read_text())
    assert Path(bc_extra["checkpoint"]).name == "best.pt"  # the BC arm's own model: its best.pt
    bc_one_step = json.loads((runs["bc"] / "rescore_extra2_one_step" / "eval.json").read_text())
    assert bc_one_step["nfe_per_chunk"] == 1
    assert "pooled success_once" in report.render_flow_q(pooled_figures)


def test_noisy_rollouts_are_recorded_by_maniskill_and_train_every_arm(tmp_path):
    """benchmarks.make_noisy_demos: a BC policy's rollouts with action noise, in ManiSkill's own file
    format (read back with rewards, final observations, actions inside the action space), the same
    for the same seed and different under more noise; then the quick benchmark trains on the file."""
    from benchmarks import make_noisy_demos
    from l1flow_rl.data import load_episodes
    from l1flow_rl.data.metadata import episodes_metadata

    root = tmp_path / "runs"
    common = ["--quick", "--root", str(root), "--data-dir", str(tmp_path / "data")]
    assert bench_flow_q.main([*common, "--out", str(tmp_path / "expert.json")]) == 0
    checkpoint = root / "quick_3demos" / "bc_20" / "checkpoints" / "latest.pt"

    def record(noise: float, folder: str):
        out = tmp_path / folder / "PushCube-v1.noisy.n2.h5"
        return make_noisy_demos.record(checkpoint, episodes=2, noise=noise, out=out), out

    summary, out = record(0.3, "noisy")
    assert out.is_file() and out.with_suffix(".json").is_file()
    assert json.loads(out.with_suffix(".summary.json").read_text()) == summary
    eps = load_episodes(out)
    meta = episodes_metadata(eps)
    assert meta.has_rewards and meta.has_final_observation and meta.control_mode == "pd_ee_delta_pos"
    assert eps.shape[0] == summary["steps"] <= 2 * 20  # the checkpoint's task: 20-step episodes
    assert set(eps["episode"].tolist()) == {0, 1}
    assert (eps["action"].abs() <= 1).all() and torch.isfinite(eps["next", "reward"]).all()
    again = load_episodes(record(0.3, "again")[1])
    assert torch.equal(again["action"], eps["action"])  # seeded: the same episodes again
    louder = load_episodes(record(0.9, "louder")[1])
    n = min(louder.shape[0], eps.shape[0])
    assert not torch.equal(louder["action"][:n], eps["action"][:n])
    with pytest.raises(ValueError, match="--noise -1"):
        make_noisy_demos.record(checkpoint, 1, -1.0, tmp_path / "bad.h5")

    figures_path = tmp_path / "noisy.json"
    assert bench_flow_q.main([*common, "--data", str(out), "--out", str(figures_path)]) == 0
    figures = json.loads(figures_path.read_text())
    assert figures["data"]["path"] == str(out) and figures["data"]["noise"] == 0.3
    from benchmarks import report

    data_line = f"Data: 2 episodes ({summary['steps']} steps) of {checkpoint} with action noise 0.3"
    assert data_line in report.render_flow_q(figures)
    assert figures["runs"]["bc"] != str(checkpoint.parents[1])  # its own BC, trained on the file
    assert f"path: {out}" in (tmp_path / figures["runs"]["bc"] / "config.yaml").read_text()


def test_residual_critic_input_needs_best_of_n_before_anything_runs(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        bench_flow_q.main(["--critic-input", "residual", "--mode", "distill", "--root", str(tmp_path)])
    assert exit_info.value.code == 2
    assert "--critic-input residual needs --mode best_of_n (got --mode distill)" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # refused before any run started
    with pytest.raises(SystemExit):
        bench_flow_q.main(["--critic-target", "mc", "--mode", "direct", "--root", str(tmp_path)])
    assert "--critic-target mc needs --mode best_of_n (got --mode direct)" in capsys.readouterr().err
