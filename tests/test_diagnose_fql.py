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
    gaps = ("mu_vs_teacher", "teacher_spread", "mu_vs_demo", "teacher_vs_demo")
    assert all(out[k] >= 0 for k in gaps) and out["teacher_spread"] > 0  # two noises, two chunks
    # the demonstrations are no sample of a fresh flow: the teacher misses them by more than its spread
    assert out["teacher_vs_demo"] > out["teacher_spread"]
