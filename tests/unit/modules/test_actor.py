"""L1FlowActor: TorchRL actor conventions, batch shapes, deterministic mode, chunk execution, bad input."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MultiStepActorWrapper

from l1flow_rl import L1FlowActor
from l1flow_rl.flow import DDIMSampler, DirectSampler, EulerSampler, VelocityEulerSampler

TO, H, K, D, A = 2, 16, 8, 3, 2


def tiny_actor(**kwargs) -> L1FlowActor:
    kwargs = {"obs_dim": D, "action_dim": A, "down_dims": (16, 32), "timestep_embed_dim": 16} | kwargs
    return L1FlowActor.for_state(obs_horizon=TO, pred_horizon=H, action_steps=K, **kwargs)


def obs_td(*batch: int, d: int = D) -> TensorDict:
    return TensorDict({"observation": torch.randn(*batch, TO, d)}, batch_size=list(batch))


def test_contract_from_the_issue():
    actor = L1FlowActor.for_state(
        obs_dim=5, action_dim=4, obs_horizon=2, pred_horizon=16, action_steps=8, down_dims=(64, 128, 256)
    )
    assert actor.in_keys == ["observation"] and actor.out_keys == ["action_chunk"]
    out = actor(TensorDict({"observation": torch.randn(3, 2, 5)}, batch_size=[3]))["action_chunk"]
    assert out.shape == (3, 8, 4)


@pytest.mark.parametrize("batch", [(), (1,), (5,), (2, 3)], ids=str)
@pytest.mark.parametrize("sampler", [None, DirectSampler(), DDIMSampler(4)], ids=repr)
def test_any_batch_shape(batch, sampler):
    actor = tiny_actor() if sampler is None else tiny_actor(sampler=sampler)
    td = actor(obs_td(*batch))
    assert td["action_chunk"].shape == (*batch, K, A)
    assert torch.isfinite(td["action_chunk"]).all()


def test_observation_as_tensordict_of_entries():
    actor = tiny_actor(obs_dim={"qpos": 3, "goal": 2})
    obs = TensorDict({"qpos": torch.randn(4, TO, 3), "goal": torch.randn(4, TO, 2)}, [4])
    assert actor(TensorDict({"observation": obs}, [4]))["action_chunk"].shape == (4, K, A)


def test_deterministic_mode_starts_from_zero_noise_and_repeats():
    actor = tiny_actor()
    td = obs_td(4)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        a = actor(td.clone())["action_chunk"]
        b = actor(td.clone())["action_chunk"]
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    with torch.no_grad():
        full = actor.policy.sample_chunk(td["observation"], deterministic=True)
        # the sampler run from an explicit zero chunk gives the same result
        cond = actor.policy.encode(actor.policy.as_obs_dict(td["observation"]))
        zero_start = actor.sampler(lambda x, t: actor.policy.denoise(x, t, cond), torch.zeros(4, H, A))
        c, d = actor(td.clone())["action_chunk"], actor(td.clone())["action_chunk"]  # RANDOM by default
    torch.testing.assert_close(full, zero_start)
    torch.testing.assert_close(a, full[:, TO - 1 : TO - 1 + K])
    assert not torch.allclose(c, d)


def test_executable_window_is_steps_to_minus_one_onwards():
    actor = L1FlowActor.for_state(
        obs_dim=D, action_dim=A, obs_horizon=3, pred_horizon=16, action_steps=5, down_dims=(16, 32)
    )
    obs = torch.randn(2, 3, D)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        window = actor(TensorDict({"observation": obs}, [2]))["action_chunk"]
        full = actor.policy.sample_chunk(obs, deterministic=True)
    assert window.shape == (2, 5, A)
    torch.testing.assert_close(window, full[:, 2:7])


def test_custom_and_nested_keys():
    actor = tiny_actor(in_keys=[("agent", "obs")], out_keys=[("agent", "chunk")])
    td = TensorDict({"agent": {"obs": torch.randn(3, TO, D)}}, [3])
    assert actor(td)["agent", "chunk"].shape == (3, K, A)


def test_works_inside_tensordict_sequential():
    prep = TensorDictModule(lambda x: x * 2.0, in_keys=["raw"], out_keys=["observation"])
    seq = TensorDictSequential(prep, tiny_actor())
    out = seq(TensorDict({"raw": torch.randn(4, TO, D)}, [4]))
    assert out["action_chunk"].shape == (4, K, A)


def test_multistep_actor_wrapper_consumes_the_chunk_over_k_steps():
    actor = tiny_actor()
    calls = []
    actor.policy.encoder.register_forward_hook(lambda *_: calls.append(1))
    wrapper = MultiStepActorWrapper(actor, n_steps=K)
    td = TensorDict(
        {"observation": torch.randn(3, TO, D), "is_init": torch.ones(3, 1, dtype=torch.bool)}, [3]
    )
    actions = []
    with torch.no_grad():
        for _ in range(K + 1):
            td = wrapper(td)
            if not actions:
                chunk = td["action_chunk"].clone()
            actions.append(td["action"].clone())
            td["is_init"] = torch.zeros(3, 1, dtype=torch.bool)
    assert chunk.shape == (3, K, A) and all(a.shape == (3, A) for a in actions)
    torch.testing.assert_close(torch.stack(actions[:K], 1), chunk)  # step i executes chunk[:, i]
    assert len(calls) == 2  # queried at step 0, and again once the K cached actions are spent


@pytest.mark.parametrize(
    "sampler", [EulerSampler(3), VelocityEulerSampler(3), DDIMSampler(3), DirectSampler()], ids=repr
)
def test_pluggable_sampler(sampler):
    actor = tiny_actor(sampler=sampler)
    assert actor.sampler is sampler
    assert actor(obs_td(2))["action_chunk"].shape == (2, K, A)


def test_float64_observations_are_accepted():
    out = tiny_actor()(TensorDict({"observation": torch.randn(2, TO, D, dtype=torch.float64)}, [2]))
    assert out["action_chunk"].dtype == torch.float32


# -- bad input ---------------------------------------------------------------------------------------


def test_wrong_observation_shape_names_key_and_expected_shape():
    actor = tiny_actor()
    with pytest.raises(ValueError, match=r"'observation' must have shape \[\*B, 2, 3\] .* got \(4, 2, 5\)"):
        actor(obs_td(4, d=5))
    with pytest.raises(ValueError, match=r"'observation' must have shape \[\*B, 2, 3\] .* got \(4, 3, 3\)"):
        actor(TensorDict({"observation": torch.randn(4, 3, D)}, [4]))


def test_missing_key_and_missing_entry():
    actor = tiny_actor()
    with pytest.raises(KeyError, match="observation"):
        actor(TensorDict({"obs": torch.randn(4, TO, D)}, [4]))
    multi = tiny_actor(obs_dim={"qpos": 3, "goal": 2})
    obs = TensorDict({"qpos": torch.randn(4, TO, 3)}, [4])
    with pytest.raises(KeyError, match=r"observation entry \('observation', 'goal'\) is missing"):
        multi(TensorDict({"observation": obs}, [4]))
    with pytest.raises(TypeError, match=r"'observation' is a tensor, but the encoder expects entries"):
        multi(obs_td(4))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_observation(bad):
    td = obs_td(4)
    td["observation"][2, 1, 0] = bad
    with pytest.raises(ValueError, match="'observation' contains NaN or Inf"):
        tiny_actor()(td)


def test_constructor_errors():
    with pytest.raises(ValueError, match=r"executable window \[To-1, To-1\+K\) must fit"):
        L1FlowActor.for_state(obs_dim=D, action_dim=A, obs_horizon=2, pred_horizon=8, action_steps=8)
    with pytest.raises(ValueError, match="pred_horizon=10 must be divisible by 4"):
        L1FlowActor.for_state(
            obs_dim=D, action_dim=A, pred_horizon=10, action_steps=4, down_dims=(16, 32, 64)
        )
