"""benchmarks/diagnose_fql.py: its measures on a small FQL loss."""

import torch
from tensordict import TensorDict

from benchmarks.diagnose_fql import compare
from l1flow_rl import FQLLoss, L1FlowActor, OneStepActor
from l1flow_rl.networks.critic import ChunkCritic


def test_the_demonstrations_value_is_the_critic_losss_own_and_every_gap_is_a_mean_distance():
    torch.manual_seed(0)
    flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
    critic = ChunkCritic.from_policy(flow, input_shape=(8, 2), hidden_dims=(32,))
    loss = FQLLoss(OneStepActor.from_flow(flow, hidden_dims=(64,)), flow, critic)
    td = TensorDict(
        {
            "observation": torch.randn(6, 2, 5),
            "action_chunk": torch.rand(6, 16, 2) * 2 - 1,
            "next": {
                "observation": torch.randn(6, 2, 5),
                "reward": torch.rand(6, 1),
                "terminated": torch.zeros(6, 1, dtype=torch.bool),
            },
        },
        [6],
    )
    out = compare(loss, td)
    with torch.no_grad():
        # the stored chunk goes through the normaliser and back: the critics see what the TD loss sees
        assert abs(out["q_demo"] - float(loss(td)["q_data_mean"])) < 1e-5
    gaps = ("mu_vs_teacher", "teacher_spread", "mu_spread", "mu_vs_demo", "teacher_vs_demo")
    assert all(out[k] >= 0 for k in gaps) and out["teacher_spread"] > 0  # two noises, two chunks
    # the demonstrations are no sample of a fresh flow: the teacher misses them by more than its spread
    assert out["teacher_vs_demo"] > out["teacher_spread"]
    # the two gradients at mu's chunk: alpha scales distillation's alone, so twice alpha halves the
    # ratio (same noise draws) and leaves the angle as it was
    assert out["grad_q_over_distill"] > 0 and -1 <= out["grad_cosine"] <= 1
    torch.manual_seed(1)
    once = compare(loss, td)
    loss.alpha *= 2
    torch.manual_seed(1)
    twice = compare(loss, td)
    assert (
        abs(twice["grad_q_over_distill"] - once["grad_q_over_distill"] / 2)
        < 1e-5 * once["grad_q_over_distill"]
    )
    assert abs(twice["grad_cosine"] - once["grad_cosine"]) < 1e-5


def test_the_table_has_a_row_per_checkpoint_with_its_validation_where_one_ran():
    from benchmarks.finetune_report import render_fql_distill

    row = dict(mu_vs_teacher=0.19, teacher_spread=0.017, mu_vs_demo=0.2, teacher_vs_demo=0.035)
    row.update(q_mu=0.74, q_teacher=0.7, q_demo=0.69, env_steps=0)
    data = {"run": "r", "task": "robosuite_can", "alpha": 10.0, "normalize_q_loss": True, "batches": 8}
    data["batch_size"] = 256
    data["rows"] = [{**row, "updates": 1000, "validation": None}, {**row, "updates": 2620, "validation": 0.0}]
    text = render_fql_distill(data)
    assert "alpha 10, Q loss normalised" in text
    assert "| 1,000 | 0 | 0.190 | 0.017 | – | 0.200 | 0.035 | 0.740 | 0.700 | 0.690 | – | – | – |" in text
    assert text.count("| 2,620 | 0 |") == 1 and "| 0.00 |" in text
    row.update(mu_spread=0.048, grad_q_over_distill=0.529, grad_cosine=-0.43)
    data["rows"] = [{**row, "updates": 5240, "validation": 0.0}]
    line = (
        "| 5,240 | 0 | 0.190 | 0.017 | 0.048 | 0.200 | 0.035 | 0.740 | 0.700 | 0.690 | 0.53 | -0.43 | 0.00 |"
    )
    assert line in render_fql_distill(data)


def test_validations_come_from_the_history_and_the_live_log_of_a_stopped_run(tmp_path):
    import json

    from benchmarks.diagnose_fql import validations

    assert validations(tmp_path) == {}
    evals = [
        {"step": 0, "split": "val", "success_once": 0.38},
        {"step": 5240, "split": "test", "success_once": 0.37},
    ]
    (tmp_path / "history.json").write_text(json.dumps({"evals": evals}))
    assert validations(tmp_path) == {0: 0.38}  # a test row is no validation
    live = tmp_path / "logs" / "finetune" / "scalars" / "val"
    live.mkdir(parents=True)
    (live / "success_once.csv").write_text("0,0.38\n6000,0.0\n8000,0.02\n")  # written on, after the history
    assert validations(tmp_path) == {0: 0.38, 6000: 0.0, 8000: 0.02}
