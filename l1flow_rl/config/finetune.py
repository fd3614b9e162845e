"""Fine-tuning settings (``l1flow-rl finetune finetune=<preset> checkpoint=...``): the algorithm and its
critic (``finetune``; the chosen algorithm's own block, ``finetune.<name>``, is typed by that
algorithm's settings dataclass, in its folder under ``l1flow_rl/finetune/``), the offline updates
before any env step (``offline``) and the online loop (``online``).

Defaults are the references' (QC: ColinQiyangLi/qc, FQL: seohongpark/fql, DSRL: ajwagen/dsrl, RLPD:
ikostrikov/rlpd); each departure says why in one line. The presets in ``configs/finetune/`` pick an
algorithm; the algorithms themselves are found by :mod:`l1flow_rl.finetune.registry`, which the
config validator asks.
"""

from __future__ import annotations

from dataclasses import dataclass

from l1flow_rl.config.ranges import bounded

__all__ = [
    "CHECKS",
    "CHOICES",
    "REWARD_KEYS",
    "FinetuneConfig",
    "OfflineConfig",
    "OnlineConfig",
    "round_frames",
]

#: ``finetune.reward``: the per-step entry the chunk return sums. ``sparse``: 1 on the step whose
#: ("next", "terminated") is set, else 0 (success, where a task's only terminal state is success, as
#: in ManiSkill's PushCube/PickCube/StackCube); values then lie in [0, 1] and discounting rewards
#: finishing early. ``recorded``: the data's and the env's ("next", "reward").
REWARD_KEYS = {"sparse": ("next", "terminated"), "recorded": ("next", "reward")}


@dataclass
class FinetuneConfig:
    algorithm: str = "qc"  # a registered algorithm: qc | fql | flowq | dsrl | dsrl_na | filtered_bc
    gamma: float = bounded(0.99, ge=0, le=1)  # discount per env step (per chunk: dsrl.discount_per_chunk)
    tau: float = bounded(0.005, gt=0, le=1)  # Polyak rate of the target critics (TorchRL SoftUpdate)
    lr: float = bounded(3.0e-4, gt=0)  # Adam, every network
    # an EMA that acts (Diffusion Policy's schedule, as BC trains): of the trained BC flow where the
    # acting module wraps it (filtered BC, QC; going on from the BC run's EMA counter), else of the
    # acting module (FQL's mu, DSRL's noise actor; from 0). 0: the raw weights act
    ema_power: float = bounded(0.0, ge=0, zero="the raw weights act")
    batch_size: int = bounded(256, ge=1)
    num_critics: int = bounded(2, ge=1)
    # critics drawn at random for each batch's bootstrap (min/mean over them; the actor climbs the mean
    # of all): RLPD's 2 of 10 against the overestimation measured with 2 critics
    target_critics: int = bounded(0, ge=0, zero="all of them")
    critic_hidden_dims: list[int] = bounded(lambda: [512, 512, 512, 512], ge=1, each=True)  # FQL/QC: 4 x 512
    q_agg: str = "mean"  # mean | min over the target critics (QC, FQL: mean; SAC/DSRL: min)
    # executed actions per critic chunk (QC: all of them)
    rl_horizon: int = bounded(0, ge=0, zero="the policy's action_steps")
    # sparse (success at the terminal step) | recorded (the env's reward), see REWARD_KEYS
    reward: str = "sparse"
    log_every: int = bounded(50, ge=1)  # updates


@dataclass
class OfflineConfig:
    # updates on the demonstrations before any env step (the "offline" arm)
    steps: int = bounded(0, ge=0, zero="none")
    eval_every: int = bounded(0, ge=0, zero="no validation during the offline phase")  # updates
    # updates; a killed offline phase resumes from here (a Square run lost 6,934 of 8,000 updates when
    # only the phase's end was saved)
    checkpoint_every: int = bounded(1000, ge=0, zero="only at the phase's end")
    # train the critics alone (algorithms whose actor is the BC start: flowq, qc). flow-Q's actor
    # trained on the demonstrations' critics fell from 0.32 to 0.00 validation in 5,000 offline updates
    # on PickCube's MLP start (benchmarks/results/, finetune_online_*_mlp_mixed50_flowq_offline_actor.json)
    critic_only: bool = False


@dataclass
class OnlineConfig:
    # env steps collected by the fine-tuned policy
    steps: int = bounded(0, ge=0, zero="offline only")
    # QC/RLPD: env steps with the starting policy before the first update
    warmup_steps: int = bounded(5000, ge=0)
    # QC/FQL: 1 update per env step
    updates_per_step: float = bounded(1.0, ge=0, zero="collect without updating")
    num_envs: int = bounded(2, ge=1)  # collector worker envs
    # env steps per collection round (all envs together), a multiple of num_envs
    frames_per_round: int = bounded(0, ge=0, zero="one full-length episode per env")
    # RLPD/QC: 50/50 offline/online batches (OfflineToOnlineReplayBuffer)
    offline_fraction: float = bounded(0.5, ge=0, lt=1)
    seed_with_offline: bool = False  # FQL's alternative: one buffer the demonstrations seed
    capacity: int = bounded(0, ge=0, zero="all of them")  # online steps kept
    eval_every: int = bounded(0, ge=0, zero="validate only at the start and the end")  # env steps
    # env steps; an online checkpoint also dumps the replay buffer
    checkpoint_every: int = bounded(10_000, ge=0, zero="only at the end")
    # the first collection round's seeds (each round takes the next 100,000): apart from the validation
    # (eval.val_seed, 10,000 on) and test (eval.seed, 100,000 on) seeds, so no test episode is trained on
    env_seed: int = bounded(1_000_000, ge=0, lt=2**32)
    # std of Gaussian noise on every executed action while collecting (TorchRL's AdditiveGaussianModule,
    # kept inside the action bounds; validation and test act without it): the 2-NFE sampler's own noise
    # moves the executed actions little (benchmarks/results/noise_authority.json), so starts it never
    # solves stay unsolved without it; PickCube's arms with and without it:
    # finetune_online_maniskill_pickcube_mixed50b_filtered_bc_an0p0*.json.
    action_noise: float = bounded(0.0, ge=0, zero="the policy's own noise only")


def round_frames(cfg) -> int:
    """The env steps of one collection round: ``online.frames_per_round``, or with 0, one
    full-length episode per env (``online.num_envs * task.max_episode_steps``)."""
    on = cfg.online
    return int(on.frames_per_round) or int(on.num_envs) * int(cfg.task.max_episode_steps)


def _check_finetune(cfg, command: str) -> list[str]:
    """Relations between fine-tuning fields (each field's own range is declared beside it): the
    critics drawn for a bootstrap, and collection rounds that every env steps through alike."""
    ft, on = cfg.get("finetune"), cfg.get("online")
    problems = []
    if ft is not None and ft.get("target_critics", 0) > ft.get("num_critics", 1) >= 1:
        problems.append(
            f"finetune.target_critics={ft.target_critics}: expected at most finetune.num_critics="
            f"{ft.num_critics} (0: all of them)"
        )
    if command != "finetune" or on is None or on.steps <= 0 or on.num_envs < 1 or on.frames_per_round < 0:
        return problems  # a count out of its range is reported by the range check
    if round_frames(cfg) % on.num_envs:
        problems.append(
            f"online.frames_per_round={on.frames_per_round}: expected a multiple of "
            f"online.num_envs={on.num_envs} (every env steps as often per round)"
        )
    return problems


#: The fine-tuning fields' allowed values and cross-field checks, read by the config validator
#: (l1flow_rl.config.validate), so that a bad value fails at config time, naming the field. The algorithm's
#: name, settings and own rules live beside the algorithms (l1flow_rl.finetune.registry).
CHOICES = {
    "finetune.q_agg": lambda: ("mean", "min"),
    "finetune.reward": lambda: tuple(REWARD_KEYS),
}
CHECKS = (_check_finetune,)
