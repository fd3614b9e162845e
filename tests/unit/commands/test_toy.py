"""The multi-modality demonstration: L1 Flow covers both modes in 2 NFE, L1 regression collapses."""

from __future__ import annotations

import json

import pytest
import torch

from l1flow_rl.commands.cli import main
from l1flow_rl.commands.toy import mode_coverage, sine_modes


def test_mode_coverage_on_known_samples():
    modes = sine_modes()
    samples = torch.cat(
        [modes[[0]].repeat(6, 1), modes[[1]].repeat(2, 1) + 0.05, torch.zeros(2, modes.shape[1])]
    )
    r = mode_coverage(samples, modes, tolerance=0.1)
    assert (r["share_mode_a"], r["share_mode_b"], r["share_neither"]) == pytest.approx((0.6, 0.2, 0.2))
    assert r["balance"] == pytest.approx(1 / 3)
    mode_rms = modes[0].square().mean().sqrt().item()  # distance from the zero curve to either mode
    assert r["mean_distance_to_nearest_mode"] == pytest.approx((2 * 0.05 + 2 * mode_rms) / 10)
    assert r["rms_to_data_mean"] > 0.4  # the data mean is the zero curve


def test_toy_cli_l1flow_covers_both_modes_and_regression_collapses(tmp_path):
    pytest.importorskip("matplotlib")
    args = [
        "toy",
        f"run_dir={tmp_path}",
        "toy.steps=200",
        "toy.methods=[l1flow,regression]",
        "toy.samples=256",
    ]
    assert main(args) == 0
    report = json.loads((tmp_path / "toy.json").read_text())
    assert (tmp_path / "toy.png").stat().st_size > 10_000
    l1flow, regression = report["methods"]["l1flow"], report["methods"]["regression"]
    assert l1flow["nfe"] == 2 and regression["nfe"] == 1
    # L1 Flow: samples on both modes, in balance, almost none in between
    assert l1flow["share_mode_a"] >= 0.3 and l1flow["share_mode_b"] >= 0.3
    assert l1flow["balance"] >= 0.6 and l1flow["share_neither"] <= 0.05
    # regression: one trajectory near the mean of the two modes, on neither of them
    assert regression["share_neither"] == 1.0
    assert regression["rms_to_data_mean"] < 0.3 < regression["mean_distance_to_nearest_mode"]


def test_toy_rejects_bad_config(tmp_path):
    from omegaconf import OmegaConf

    from l1flow_rl.commands.toy import run_toy
    from l1flow_rl.config import AppConfig

    cfg = OmegaConf.structured(AppConfig(run_dir=str(tmp_path)))
    cfg.toy.methods = ["l1flow", "gan"]
    with pytest.raises(ValueError, match=r"toy.methods: got \['l1flow', 'gan'\]"):
        run_toy(cfg)
    cfg.toy.methods = ["l1flow"]
    cfg.toy.steps = 0
    with pytest.raises(ValueError, match=r"toy\.steps must be >= 1, got 0"):
        run_toy(cfg)


@pytest.mark.parametrize(
    ("family", "k"), [("opposite_sines", 2), ("nested_amplitudes", 4), ("phase_shifts", 8)]
)
def test_mode_families_are_separable_at_the_tolerance(family, k):
    from l1flow_rl.commands.toy import TOLERANCE, toy_modes

    modes = toy_modes(family)
    assert modes.shape == (k, 16)
    dist = (modes[:, None] - modes[None]).square().mean(-1).sqrt()
    off_diagonal = dist[~torch.eye(k, dtype=torch.bool)]
    # a sample can sit on one mode at most
    assert off_diagonal.min() > 2 * TOLERANCE
    r = mode_coverage(modes.repeat(3, 1), modes)
    assert r["shares"] == pytest.approx([1 / k] * k) and r["modes_hit"] == k and r["share_neither"] == 0
    one = mode_coverage(modes[[0]].repeat(10, 1), modes)
    assert one["modes_hit"] == 1 and one["balance"] == 0.0
