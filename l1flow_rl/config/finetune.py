"""Fine-tuning settings (``l1flow-rl finetune finetune=<preset> checkpoint=...``): the algorithm and its
critic (``finetune``, one block of knobs per algorithm), the offline updates before any env step
(``offline``) and the online loop (``online``).

Defaults are the references' (QC: ColinQiyangLi/qc, FQL: seohongpark/fql, DSRL: ajwagen/dsrl, RLPD:
ikostrikov/rlpd); each departure says why in one line. The presets in ``configs/finetune/`` pick an
algorithm; the algorithms themselves are registered in :mod:`l1flow_rl.objectives.finetune_registry`,
which the config validator asks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from l1flow_rl.config.ranges import bounded

__all__ = [
    "CHECKS",
    "CHOICES",
    "REWARD_KEYS",
    "DSRLNASettings",
    "DSRLSettings",
    "FQLSettings",
    "FilteredBCSettings",
    "FinetuneConfig",
    "OfflineConfig",
    "OnlineConfig",
    "QCSettings",
    "round_frames",
]

#: ``finetune.reward``: the per-step entry the chunk return sums. ``sparse``: 1 on the step whose
#: ("next", "terminated") is set, else 0 (success, where a task's only terminal state is success, as
#: in ManiSkill's PushCube/PickCube/StackCube); values then lie in [0, 1] and discounting rewards
#: finishing early. ``recorded``: the data's and the env's ("next", "reward").
REWARD_KEYS = {"sparse": ("next", "terminated"), "recorded": ("next", "reward")}


@dataclass
class QCSettings:
    num_samples: int = 32  # QC: best of 32 proposals, for acting and for the backup
    freeze_flow: bool = False  # QC trains the flow with its BC loss on the replay buffer


@dataclass
class FQLSettings:
    # FQL's README: alpha in {0.03, ..., 10} once Q is normalised; 10 is TorchRL 0.15's FQLLoss default
    alpha: float = 10.0
    normalize_q_loss: bool = True  # FQL: lambda = 1 / mean|Q| (detached)
    actor_hidden_dims: list[int] = field(default_factory=lambda: [512, 512, 512, 512])  # FQL: 4 x 512


@dataclass
class DSRLSettings:
    noise_bound: float = 1.5  # DSRL: |w| <= 1.5 (tanh-squashed)
    target_entropy: float = 0.0  # DSRL's configs
    # SAC's automatic temperature (stable-baselines3, which DSRL uses) starts at 1; measured on PushCube:
    # log pi over the 16 x 4 noise is ~-69 nats, so at 1 the soft target adds ~62 per bootstrap against
    # sparse rewards <= 1 (Q 17 -> 49 in 400 updates). 1e-3 keeps the entropy term at the rewards' scale.
    init_alpha: float = 1.0e-3
    actor_hidden_dims: list[int] = field(
        default_factory=lambda: [512, 512, 512]
    )  # DSRL: 3 x 2048; cost on 2 cores


@dataclass
class DSRLNASettings(DSRLSettings):
    # noises per observation the noise critic is fitted on, decoded once (the flow is frozen; DSRL-NA
    # draws one fresh noise per state at every distillation step, a flow call per update on 2 cores)
    distill_samples: int = 4


@dataclass
class FilteredBCSettings:
    """The L1 Flow loss on demonstrations and successful online episodes (``finetune.lr``,
    ``finetune.batch_size`` and the ``online`` block set its schedule)."""

    # leave the chunk steps padded past an episode's end out of the loss. An online success ends the
    # episode at the first step inside the goal while the arm still moves toward it, and delta
    # control pads "no motion" after the end: a false "stop here" at the threshold. PickCube's
    # fine-tuned policy then parks 2.7-4.6 cm from the goal (42 of its 47 test failures; its
    # collected successes end at a median 2.2 cm, moving at 0.077, the demonstrations at 0.8 cm):
    # benchmarks/results/diagnose_pickcube_mixed50b.json. Masked, with online.action_noise=0.02, the
    # same start tests 0.64 / 0.67 / 0.57 at 100k env steps against 0.53 / 0.46 / 0.52 unmasked
    # (finetune_online_maniskill_pickcube_mixed50b_filtered_bc_an0p02_mask_100k.json). Off by default:
    # absolute control (Can) pads by holding the last target, a true label, and is not measured masked.
    mask_padding: bool = False


@dataclass
class FinetuneConfig:
    algorithm: str = "qc"  # a registered algorithm: qc | fql | dsrl | dsrl_na | filtered_bc
    gamma: float = bounded(0.99, ge=0, le=1)  # discount per env step
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
    qc: QCSettings = field(default_factory=QCSettings)
    fql: FQLSettings = field(default_factory=FQLSettings)
    dsrl: DSRLSettings = field(default_factory=DSRLSettings)
    dsrl_na: DSRLNASettings = field(default_factory=DSRLNASettings)
    filtered_bc: FilteredBCSettings = field(default_factory=FilteredBCSettings)
    log_every: int = bounded(50, ge=1)  # updates


@dataclass
class OfflineConfig:
    # updates on the demonstrations before any env step (the "offline" arm)
    steps: int = bounded(0, ge=0, zero="none")
    eval_every: int = bounded(0, ge=0, zero="no validation during the offline phase")  # updates
    # updates; a killed offline phase resumes from here (a Square run lost 6,934 of 8,000 updates when
    # only the phase's end was saved)
    checkpoint_every: int = bounded(1000, ge=0, zero="only at the phase's end")


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
    # kept inside the action bounds; validation and test act without it). PickCube's mixed-50 start never
    # solves 55 of 100 starts under 8 draws of its own sampler noise; std 0.02 reaches 18 of them
    # (benchmarks/results/noise_draw_maniskill_pickcube_mixed50b*.json).
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
#: name and its own rules live beside the algorithms (l1flow_rl.objectives.finetune_registry).
CHOICES = {
    "finetune.q_agg": lambda: ("mean", "min"),
    "finetune.reward": lambda: tuple(REWARD_KEYS),
}
CHECKS = (_check_finetune,)
