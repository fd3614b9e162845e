"""The critic-bias benchmark: its Monte-Carlo yardstick against a hand computation, the dump it picks, its
table, and its CLI's argument errors (no simulator, no run)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.finetune.bench_critic_bias import aggregate, latest_dump, main, mc_values, parse_configs
from benchmarks.report.finetune import render_critic_bias

G = 0.99


def _steps(rows: list[tuple[int, int, bool, bool, bool]]) -> dict[str, np.ndarray]:
    episode, step, terminated, truncated, anchor = map(np.array, zip(*rows, strict=True))
    return dict(episode=episode, step=step, terminated=terminated, truncated=truncated, anchor=anchor)


def _two_episodes() -> dict[str, np.ndarray]:
    """Episode 7 terminates (succeeds) at step 5, anchors at steps 0 and 4; episode 3 is truncated after
    step 3, an anchor at step 0. Rows shuffled: the function must not rely on their order."""
    rows = [(7, s, s == 5, False, s in (0, 4)) for s in range(6)]
    rows += [(3, s, False, s == 3, s == 0) for s in range(4)]
    order = np.random.default_rng(0).permutation(len(rows))
    return _steps([rows[i] for i in order])


def test_the_yardstick_is_the_discounted_success_to_the_end_over_the_anchors():
    out = mc_values(**_two_episodes(), gamma=G)
    assert out["windows"] == 3 and out["episodes"] == 2
    assert out["mc_mean"] == pytest.approx((G**5 + G**1 + 0.0) / 3)
    assert out["truncated_fraction"] == pytest.approx(1 / 3)
    assert out["success_fraction"] == pytest.approx(2 / 3)


def test_windows_whose_chunk_runs_past_a_truncated_end_drop_out_as_the_critic_drops_them():
    steps = _two_episodes()
    steps["anchor"] = steps["anchor"] | ((steps["episode"] == 3) & (steps["step"] == 3))  # 3 + 2 > 4
    steps["anchor"] |= (steps["episode"] == 7) & (steps["step"] == 5)  # past a terminal end: kept
    every = mc_values(**steps, gamma=G)
    kept = mc_values(**steps, gamma=G, rl_horizon=2)
    assert every["windows"] == 5 and kept["windows"] == 4
    assert kept["mc_mean"] == pytest.approx((G**5 + G**1 + G**0 + 0.0) / 4)
    assert kept["truncated_fraction"] == pytest.approx(1 / 4)


def test_a_recorded_reward_is_summed_to_the_end():
    steps = _steps([(0, s, False, s == 2, s == 0) for s in range(3)])
    out = mc_values(**steps, gamma=0.5, reward=np.array([1.0, 1.0, 1.0]))
    assert out["mc_mean"] == pytest.approx(1 + 0.5 + 0.25)
    with pytest.raises(ValueError, match="no window"):
        mc_values(**{**steps, "anchor": np.zeros(3, bool)}, gamma=G)


def test_the_latest_dump_is_the_highest_round_not_the_last_name(tmp_path):
    for name in ("online_buffer_round99", "online_buffer_round100", ".online_buffer_round200.partial"):
        (tmp_path / "checkpoints" / name).mkdir(parents=True)
    assert latest_dump(tmp_path).name == "online_buffer_round100"
    assert latest_dump(tmp_path / "none") is None


def test_configs_are_checked_against_the_finetune_schema():
    overrides = ["finetune.num_critics=10", "finetune.critic_hidden_dims=[256,256]"]
    assert parse_configs(['preset=""', "a=" + " ".join(overrides)]) == {"preset": [], "a": overrides}
    assert "num_critic" in parse_configs(["a=finetune.num_critic=10"])
    assert "not finetune.KEY=VALUE" in parse_configs(["a=online.steps=10"])
    assert "twice" in parse_configs(["a=", "a="])


def _run_dir(tmp_path, config: bool, dump: bool):
    if config:
        (tmp_path / "config.yaml").write_text("finetune: {algorithm: dsrl}\n")
    (tmp_path / "checkpoints").mkdir()
    if dump:
        (tmp_path / "checkpoints" / "online_buffer_round1").mkdir()
    return str(tmp_path)


@pytest.mark.parametrize(
    ("config", "dump", "config_arg", "flag", "said"),
    [
        (True, True, "preset", "--config", "'preset' is not NAME="),
        (True, True, "a=finetune.nope=1", "--config", "nope"),
        (False, True, 'preset=""', "--run", "has no config.yaml"),
        (True, False, 'preset=""', "--run", "no online_buffer_round* dump"),
    ],
)
def test_a_bad_argument_is_one_line_naming_it(tmp_path, capsys, config, dump, config_arg, flag, said):
    run = _run_dir(tmp_path, config, dump)
    with pytest.raises(SystemExit) as exit_:
        main(["--run", run, "--config", config_arg])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"argument {flag}" in err and said in err


def test_report_points_beyond_the_updates_are_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        run = _run_dir(tmp_path, True, True)
        main(["--run", run, "--config", "p=", "--updates", "9", "--report-at", "20"])
    assert "argument --report-at" in capsys.readouterr().err


def test_the_table_has_a_row_per_setting_and_the_yardstick_in_its_caption():
    def curve(q):
        return [{"update": 0, "q_data_mean": 0.1}, {"update": 10, "q_data_mean": q, "s_per_update": 0.2}]

    settings = {"num_critics": 10, "target_critics": 2, "critic_hidden_dims": [256, 256], "q_agg": "min"}
    seeds = {"0": curve(0.5), "1": curve(0.7)}
    data = {
        "run": "runs/x",
        "task": "t",
        "algorithm": "dsrl",
        "dump": "online_buffer_round3",
        "env_steps": 600,
        "updates": 10,
        "batch_size": 256,
        "seeds": [0, 1],
        "report_at": [0, 10],
        "yardstick": {
            "reward": "sparse",
            "gamma": G,
            "mc_mean": 0.0451,
            "windows": 12,
            "episodes": 2,
            "truncated_fraction": 0.5,
            "success_fraction": 0.5,
        },
        "configs": {"redq": {"settings": settings, "seeds": seeds, "mean": aggregate(seeds)}},
        "finished": True,
    }
    text = render_critic_bias(data)
    assert "**0.045**" in text and "50%" in text
    row = next(line for line in text.splitlines() if line.startswith("| redq"))
    assert "10 x 256x256, min of 2 drawn" in row and "0.60 (0.50, 0.70)" in row and "| 0.2 |" in row
