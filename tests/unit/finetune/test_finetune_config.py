"""The fine-tuning presets compose and validate through the CLI's compose function, and the registry
decides what each algorithm accepts."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from l1flow_rl import DSRLLoss, DSRLNALoss, FQLLoss, QCLoss
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.config.validate import ConfigValidationError
from l1flow_rl.finetune.registry import get_algorithm


@pytest.mark.parametrize(
    "preset,loss_cls,q_agg,offline_fraction",
    [
        ("qc", QCLoss, "mean", 0.5),
        ("fql", FQLLoss, "mean", 0.5),
        ("dsrl", DSRLLoss, "min", 0.0),
        ("dsrl_na", DSRLNALoss, "min", 0.5),
    ],
)
def test_presets_compose_validate_and_build_their_loss(preset, loss_cls, q_agg, offline_fraction):
    from l1flow_rl import L1FlowActor

    cfg = compose_config([f"finetune={preset}", "checkpoint=bc.pt"], command="finetune")
    assert cfg.finetune.algorithm == preset and cfg.finetune.q_agg == q_agg
    assert cfg.online.offline_fraction == offline_fraction and cfg.online.warmup_steps == 5000
    algorithm = get_algorithm(preset)
    small = OmegaConf.merge(cfg.finetune, {"critic_hidden_dims": [16], "qc": {"num_samples": 2}})
    flow = L1FlowActor.for_state(obs_dim=3, action_dim=2, down_dims=(8, 16))
    loss = algorithm.build(flow, small)
    assert isinstance(loss, loss_cls) and loss.critic.num_critics == cfg.finetune.num_critics


def test_the_delta_control_preset_is_filtered_bc_with_masked_padding_and_action_noise():
    # one run_dir for both: the default is a timestamp, which differs when the two straddle a second
    base = compose_config(["finetune=filtered_bc", "checkpoint=bc.pt", "run_dir=r"], command="finetune")
    delta = compose_config(
        ["finetune=filtered_bc_delta", "checkpoint=bc.pt", "run_dir=r"], command="finetune"
    )
    settings = get_algorithm("filtered_bc").settings_of
    assert delta.finetune.algorithm == "filtered_bc" and settings(delta.finetune).mask_padding
    assert delta.online.action_noise == 0.02 and base.online.action_noise == 0.0
    assert not settings(base.finetune).mask_padding  # the preset leaves the block at its defaults
    # everything else is filtered_bc's: the two settings are the whole difference
    for cfg in (base, delta):
        cfg.finetune.filtered_bc = {"mask_padding": False}
        cfg.online.action_noise = 0.0
    assert OmegaConf.to_container(delta) == OmegaConf.to_container(base)


def test_bad_fine_tuning_settings_fail_at_config_time_naming_the_field():
    with pytest.raises(
        ConfigValidationError,
        match=r"finetune\.algorithm='sac': expected one of "
        r"\['dsrl', 'dsrl_na', 'filtered_bc', 'flowq', 'fql', 'qc'\]",
    ):
        compose_config(["finetune=qc", "finetune.algorithm=sac"], command="finetune")
    with pytest.raises(ConfigValidationError, match=r"offline\.steps=100: finetune\.algorithm=dsrl"):
        compose_config(["finetune=dsrl", "offline.steps=100"], command="finetune")
    with pytest.raises(
        ConfigValidationError, match=r"online\.offline_fraction=0\.5.*finetune\.algorithm=dsrl"
    ):
        compose_config(["finetune=dsrl", "online.offline_fraction=0.5"], command="finetune")
    with pytest.raises(ConfigValidationError, match=r"finetune\.q_agg='max'"):
        compose_config(["finetune=fql", "finetune.q_agg=max"], command="finetune")
    with pytest.raises(
        ConfigValidationError, match=r"finetune\.ema_power=-0\.5: expected >= 0 \(0: the raw weights act\)"
    ):
        compose_config(["finetune=filtered_bc", "finetune.ema_power=-0.5"], command="finetune")
    with pytest.raises(ConfigValidationError, match=r"online\.action_noise=-0\.1: expected >= 0"):
        compose_config(
            ["finetune=filtered_bc", "online.steps=100", "online.action_noise=-0.1"], command="finetune"
        )
    # DSRL's critic values the stored steering noise: noise on the executed action would not match it
    with pytest.raises(ConfigValidationError, match=r"online\.action_noise=0\.02: finetune\.algorithm=dsrl"):
        compose_config(["finetune=dsrl", "online.action_noise=0.02"], command="finetune")
    compose_config(
        ["finetune=filtered_bc", "online.steps=100", "online.action_noise=0.02"], command="finetune"
    )
    with pytest.raises(Exception, match="backup"):  # a retired knob is an unknown key
        compose_config(["finetune=qc", "finetune.backup=max"], command="finetune")


def test_filtered_bc_preset_builds_a_critic_free_loss_on_successful_online_episodes():
    from l1flow_rl import L1FlowActor
    from l1flow_rl.finetune.filtered_bc.loss import FilteredBCLoss

    cfg = compose_config(["finetune=filtered_bc", "checkpoint=bc.pt"], command="finetune")
    assert cfg.finetune.batch_size == 64 and cfg.online.offline_fraction == 0.5
    assert cfg.finetune.ema_power == 0.75  # the flow acts on its EMA, as in its BC run
    algorithm = get_algorithm("filtered_bc")
    assert algorithm.successful_episodes_only and algorithm.uses_offline_data
    flow = L1FlowActor.for_state(obs_dim=3, action_dim=2, down_dims=(8, 16))
    loss = algorithm.build(flow, cfg.finetune)
    assert isinstance(loss, FilteredBCLoss) and loss.actor is flow and loss.rl_horizon == 8
    assert not hasattr(loss, "target_qvalue_network_params")
    assert not loss.bc_loss.mask_padding  # trains on padded steps as its BC run did, unless asked
    masked = compose_config(
        ["finetune=filtered_bc", "checkpoint=bc.pt", "finetune.filtered_bc.mask_padding=true"],
        command="finetune",
    )
    assert algorithm.build(flow, masked.finetune).bc_loss.mask_padding


def test_a_fine_tune_adopts_its_starts_data_unless_the_command_line_sets_it():
    from l1flow_rl.finetune.loop import adopt_start_data

    bc = compose_config(
        ["task=robosuite_can", "demos=mixed", "demos.num=30", "data.labels=[expert,noisy]"], command="train"
    )
    # nothing given: the BC run's demonstrations and label filter, not the defaults (100 expert)
    ft = ["finetune=filtered_bc", "task=robosuite_can", "checkpoint=bc.pt"]
    cfg = compose_config(ft, command="finetune")
    assert cfg.demos.num == 100 and cfg.demos.quality == "expert" and cfg.data.labels is None
    adopt_start_data(cfg, bc, given=[])
    assert (cfg.demos.num, cfg.demos.quality, list(cfg.data.labels)) == (30, "mixed", ["expert", "noisy"])
    # a field the command line sets stands; the others still come from the start
    cfg = compose_config([*ft, "demos.num=50"], command="finetune")
    adopt_start_data(cfg, bc, given=["demos.num"])
    assert (cfg.demos.num, cfg.demos.quality, list(cfg.data.labels)) == (50, "mixed", ["expert", "noisy"])
    # a whole group chosen on the command line stands as chosen
    cfg = compose_config([*ft, "demos=default"], command="finetune")
    adopt_start_data(cfg, bc, given=["demos"])
    assert (
        cfg.demos.num == 100
        and cfg.demos.quality == "expert"
        and list(cfg.data.labels) == ["expert", "noisy"]
    )
