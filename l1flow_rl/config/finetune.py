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

from dataclasses import dataclass, field

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
    algorithm: str = "qc"  # a registered algorithm: qc | fql | dsrl | dsrl_na | filtered_bc
    gamma: float = 0.99
    tau: float = 0.005  # Polyak rate of the target critics (TorchRL SoftUpdate)
    lr: float = 3.0e-4  # Adam, every network
    # an EMA that acts (Diffusion Policy's schedule, as BC trains): of the trained BC flow where the
    # acting module wraps it (filtered BC, QC; going on from the BC run's EMA counter), else of the
    # acting module (FQL's mu, DSRL's noise actor; from 0). 0: the raw weights act
    ema_power: float = 0.0
    batch_size: int = 256
    num_critics: int = 2
    # critics drawn at random for each batch's bootstrap (min/mean over them; the actor climbs the mean
    # of all): RLPD's 2 of 10 against the overestimation measured with 2 critics; 0: all of them
    target_critics: int = 0
    critic_hidden_dims: list[int] = field(default_factory=lambda: [512, 512, 512, 512])  # FQL/QC: 4 x 512
    q_agg: str = "mean"  # mean | min over the target critics (QC, FQL: mean; SAC/DSRL: min)
    rl_horizon: int = 0  # executed actions per critic chunk; 0: the policy's action_steps (QC: all of them)
    # sparse (success at the terminal step) | recorded (the env's reward), see REWARD_KEYS
    reward: str = "sparse"
    log_every: int = 50  # updates


@dataclass
class OfflineConfig:
    steps: int = 0  # updates on the demonstrations before any env step (the "offline" arm)
    eval_every: int = 0  # updates; 0: no validation during the offline phase
    # updates; a killed offline phase resumes from here (a Square run lost 6,934 of 8,000 updates when
    # only the phase's end was saved). 0: only at the phase's end
    checkpoint_every: int = 1000


@dataclass
class OnlineConfig:
    steps: int = 0  # env steps collected by the fine-tuned policy (0: offline only)
    warmup_steps: int = 5000  # QC/RLPD: env steps with the starting policy before the first update
    updates_per_step: float = 1.0  # QC/FQL: 1 update per env step
    num_envs: int = 2  # collector worker envs
    # env steps per collection round (all envs together); 0: one full-length episode per env
    frames_per_round: int = 0
    offline_fraction: float = 0.5  # RLPD/QC: 50/50 offline/online batches (OfflineToOnlineReplayBuffer)
    seed_with_offline: bool = False  # FQL's alternative: one buffer the demonstrations seed
    capacity: int = 0  # online steps kept; 0: all of them
    eval_every: int = 0  # env steps; 0: validate only at the start and the end
    checkpoint_every: int = 10_000  # env steps; an online checkpoint also dumps the replay buffer
    # the first collection round's seeds (each round takes the next 100,000): apart from the validation
    # (eval.val_seed, 10,000 on) and test (eval.seed, 100,000 on) seeds, so no test episode is trained on
    env_seed: int = 1_000_000
    # std of Gaussian noise on every executed action while collecting (TorchRL's AdditiveGaussianModule,
    # kept inside the action bounds; validation and test act without it). PickCube's mixed-50 start never
    # solves 55 of 100 starts under 8 draws of its own sampler noise; std 0.02 reaches 18 of them
    # (benchmarks/results/noise_draw_maniskill_pickcube_mixed50b*.json). 0: the policy's own noise only.
    action_noise: float = 0.0


def round_frames(cfg) -> int:
    """The env steps of one collection round: ``online.frames_per_round``, or with 0, one
    full-length episode per env (``online.num_envs * task.max_episode_steps``)."""
    on = cfg.online
    return int(on.frames_per_round) or int(on.num_envs) * int(cfg.task.max_episode_steps)


def _check_ema(cfg, command: str) -> list[str]:
    ft = cfg.get("finetune")
    if command != "finetune" or ft is None or ft.get("ema_power", 0.0) >= 0.0:
        return []
    return [f"finetune.ema_power={ft.ema_power}: expected 0 (no EMA) or a positive power (DP's: 0.75)"]


def _check_online(cfg, command: str) -> list[str]:
    """Online settings that would otherwise fail only after the offline phase."""
    on = cfg.get("online")
    if command != "finetune" or on is None or on.steps <= 0:
        return []
    problems = []
    frames = round_frames(cfg) if on.num_envs >= 1 else 0
    if on.num_envs < 1 or frames < 1 or frames % on.num_envs:
        problems.append(
            f"online.frames_per_round={on.frames_per_round} must be a positive multiple of "
            f"online.num_envs={on.num_envs} (every env steps as often per round)"
        )
    if not 0.0 <= on.offline_fraction < 1.0:
        problems.append(f"online.offline_fraction={on.offline_fraction}: expected a value in [0, 1)")
    if on.action_noise < 0:
        problems.append(f"online.action_noise={on.action_noise}: expected a std >= 0")
    if on.warmup_steps < 0 or on.updates_per_step < 0:
        problems.append(
            f"online.warmup_steps={on.warmup_steps}, online.updates_per_step={on.updates_per_step}: "
            "expected >= 0"
        )
    return problems


#: The fine-tuning fields' allowed values and cross-field checks, read by the config validator
#: (l1flow_rl.config.validate), so that a bad value fails at config time, naming the field. The algorithm's
#: name, settings and own rules live beside the algorithms (l1flow_rl.finetune.registry).
CHOICES = {
    "finetune.q_agg": lambda: ("mean", "min"),
    "finetune.reward": lambda: tuple(REWARD_KEYS),
}
CHECKS = (_check_online, _check_ema)
