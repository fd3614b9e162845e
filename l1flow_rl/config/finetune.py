"""Flow-Q fine-tuning settings (``l1flow-rl finetune``): the loss and its optimiser (``finetune``), the
offline phase on the demonstrations (``offline``) and the online phase in the simulator (``online``).

Defaults follow FQL / QC-FQL (2 LayerNorm critics of 4x512, mean aggregation, tau 0.005, gamma 0.99,
Adam 3e-4, batch 256, alpha 100, h = the policy's executed chunk length)."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = [
    "CHECKS",
    "CHOICES",
    "FINETUNE_MODES",
    "REWARDS",
    "REWARD_KEYS",
    "FinetuneConfig",
    "OfflineConfig",
    "OnlineConfig",
    "round_frames",
]

#: ``distill``: FQL's one-step policy mu(s, z) distilled from the L1 Flow 2-NFE chunk and pushed up Q;
#: ``direct``: the L1 Flow policy itself, Q's gradient through its two network evaluations;
#: ``best_of_n``: Q-chunking's QC, the L1 Flow policy as trained, executing the best of
#: ``num_samples`` of its chunks under the critics (which back up that choice).
FINETUNE_MODES = ("distill", "direct", "best_of_n")

#: ``finetune.reward``: the per-step reward entry each choice reads from the stored steps.
REWARD_KEYS = {"recorded": ("next", "reward"), "sparse": ("next", "terminated")}
REWARDS = tuple(REWARD_KEYS)


@dataclass
class FinetuneConfig:
    mode: str = "distill"  # distill | direct | best_of_n
    num_samples: int = 32  # best_of_n: chunks drawn per decision and per TD target (QC: 32)
    # How the TD target values the next state from drawn chunks of the policy: max (QC's expected-max,
    # an optimistic value of the selecting policy) | mean (the value of the policy as it samples: a
    # SARSA-like critic that best_of_n's selection improves on once) | one_step (the policy network's
    # one-step chunk, near the mean of its chunks: a chunk valued as if the averaged policy followed)
    backup: str = "max"
    # chunks drawn per TD target; 0: num_samples in best_of_n with the max or mean backup, else 1
    backup_samples: int = 0
    # best_of_n: the critics read the executed chunk (action) or the chunk minus the BC policy's own
    # chunk from zero noise at that state (residual): the part of the action the state does not
    # predict, so that the ranking rests on demonstrated deviations, not on actions that co-occur
    # with good states
    critic_input: str = "action"
    # distill: weight of the distillation loss (FQL: 3-1000 by task family, QC-FQL 100);
    # direct: weight of the L1 Flow BC loss
    alpha: float = 100.0
    train_teacher: bool = False  # distill: co-train the L1 Flow teacher with its BC loss (else frozen)
    one_step_init: str = "teacher"  # distill: mu starts from the teacher's weights | scratch
    normalize_q_loss: bool = True
    q_agg: str = "mean"  # mean | min over the ensemble's target values
    num_qvalue_nets: int = 2
    critic_hidden_dims: list[int] = field(default_factory=lambda: [512, 512, 512, 512])
    gamma: float = 0.99
    # The critic learns from reward * reward_scale + reward_offset per step. The simulators' rewards
    # lie in [0, 1] (ManiSkill normalized_dense / sparse, PushT coverage, robosuite) and success ends a
    # collected episode: with positive steps a critic values postponing success (gamma 0.99 over a
    # 150-step episode is worth far more than the one success step), so every step is shifted to
    # r - 1 <= 0 (FQL's OGBench convention: -1 per step until the goal, 0 at it), and scaled by
    # 1 - gamma = 0.01 so that values lie in [-1, 0]: under Adam a critic's output layer moves by about
    # the learning rate per update, and at -1 per step (values down to -100) the critics were still
    # far from their Monte-Carlo targets after 3,000 updates (noisy PushCube: best-of-16 under them
    # 0.11, under the same critics on 0.01-scaled rewards 0.24-0.30, BC 0.22).
    reward_scale: float = 0.01
    reward_offset: float = -0.01
    # Which per-step reward the critic learns from: recorded (the data's and the env's ("next",
    # "reward"): ManiSkill's normalized_dense, PushT's coverage, ...) | sparse (1 on a step whose
    # ("next", "terminated") is set, else 0: success, where terminations are on and a task's only
    # terminal state is success, as in ManiSkill's PushCube/PickCube/StackCube and the collector's
    # episodes; a replayed demonstration that holds success for its last few steps pays each of them).
    # With the default offset: -1 per step until success, 0 at it (FQL's OGBench rewards).
    # Why: a shaped reward's reaching terms can rank chunks that hang back near a good pose above
    # chunks that finish the task.
    reward: str = "recorded"
    # What the critics regress onto after any Monte-Carlo pretraining, offline and online: td (the
    # chunked TD target, QC-FQL) | mc (every window's discounted return to its episode's end, as in
    # offline.critic_pretrain; best_of_n only, no actor to train). Why mc: each collection round
    # plays whole episodes, so online windows carry complete returns too, and on noisy PushCube TD
    # updates took a Monte-Carlo critic's correlation with the returns from 0.96 to 0.40 in 900 updates.
    critic_target: str = "td"
    # best_of_n: which critics pick the executed chunk: critic (the ones being trained) | target (their
    # Polyak average, tau per update, also kept during Monte-Carlo regression). Why target: the argmax
    # over N draws of one policy turns on small differences between chunks, and nearby critic snapshots
    # select differently (noisy PushCube, 100 test episodes: 0.24 after 3,000 Monte-Carlo updates, 0.30
    # after 3,100); an average over the last ~1/tau updates is what the checkpoint EMA is to the policy.
    # Measured there after 9,000 Monte-Carlo updates: 0.47 (target) vs 0.44 (critic), within noise.
    select_with: str = "critic"
    rl_horizon: int = 0  # executed actions per critic chunk; 0: the policy's action_steps
    tau: float = 0.005  # Polyak rate of the target critics (TorchRL SoftUpdate)
    lr: float = 3.0e-4
    batch_size: int = 256
    grad_clip: float = 0.0  # 0 disables
    log_every: int = 50  # updates
    checkpoint_every: int = 500  # updates (online: at the first round end past it)


@dataclass
class OfflineConfig:
    steps: int = 1000  # gradient updates on the demonstrations, before any environment step
    # The first critic_pretrain of those updates regress the critics onto the demonstrations'
    # Monte-Carlo returns (no actor call, no bootstrap: cheap), so that TD starts from the data's values.
    critic_pretrain: int = 0
    # The next critic_warmup updates train the critics alone by TD: an untrained critic's gradient
    # only pushes the actor off the data (it has not learned which chunks are better).
    critic_warmup: int = 0
    eval_every: int = 0  # updates; 0: no evaluation during the offline phase


@dataclass
class OnlineConfig:
    steps: int = 0  # environment steps collected by the fine-tuned policy (0: offline only)
    num_envs: int = 2  # collector envs (worker processes on the CPU)
    # env steps per collection round (all envs together); updates and checkpoints fall between. Every
    # round resets its envs, so an env must be able to play a whole episode in its share: at least
    # num_envs * task.max_episode_steps. 0: exactly that (one full-length episode per env)
    frames_per_round: int = 0
    updates_per_step: float = 1.0  # gradient updates per environment step (FQL: 1)
    # seed: one buffer that the demonstrations seed and online episodes extend (FQL's default);
    # balanced: a fixed offline_fraction of every batch from the demonstrations
    # (TorchRL's OfflineToOnlineReplayBuffer)
    mixing: str = "seed"
    offline_fraction: float = 0.5
    capacity: int = 0  # online steps the buffer keeps; 0: all of them
    eval_every: int = 0  # env steps; 0: evaluate only at the end
    env_seed: int = 100_000  # the first collection episode's seed (evaluation uses eval.seed onward)


def round_frames(cfg) -> int:
    """The env steps of one collection round: ``online.frames_per_round``, or with 0, one
    full-length episode per env (``online.num_envs * task.max_episode_steps``)."""
    on = cfg.online
    return int(on.frames_per_round) or int(on.num_envs) * int(cfg.task.max_episode_steps)


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
    elif frames // on.num_envs < cfg.task.max_episode_steps:
        # each round resets its envs: a shorter share cuts every episode before its time limit
        problems.append(
            f"online.frames_per_round={on.frames_per_round} gives each of online.num_envs="
            f"{on.num_envs} envs {frames // on.num_envs} steps per round, fewer than "
            f"task.max_episode_steps={cfg.task.max_episode_steps}: every round resets the envs, so "
            f"episodes would be cut short; use at least {on.num_envs * cfg.task.max_episode_steps} "
            "(or 0 for exactly that)"
        )
    if not 0.0 < on.offline_fraction < 1.0:
        problems.append(f"online.offline_fraction={on.offline_fraction}: expected a value in (0, 1)")
    return problems


def _check_critic(cfg, command: str) -> list[str]:
    ft = cfg.get("finetune")
    if command != "finetune" or ft is None:
        return []
    problems = []
    if ft.get("backup_samples", 0) < 0:
        problems.append(
            f"finetune.backup_samples={ft.backup_samples}: expected chunks drawn per TD target >= 1, or 0 "
            "for the mode's default (num_samples in best_of_n, else 1)"
        )
    if ft.get("critic_target", "td") == "mc" and ft.mode != "best_of_n":
        problems.append(
            f"finetune.critic_target=mc needs finetune.mode=best_of_n (the Monte-Carlo regression trains "
            f"the critics alone; {ft.mode} also trains an actor on the TD loss), got finetune.mode={ft.mode}"
        )
    if ft.get("select_with", "critic") == "target" and ft.mode != "best_of_n":
        problems.append(
            f"finetune.select_with=target needs finetune.mode=best_of_n (only it selects chunks with "
            f"critics), got finetune.mode={ft.mode}"
        )
    if ft.get("critic_input", "action") == "residual" and ft.mode != "best_of_n":
        problems.append(
            f"finetune.critic_input=residual needs finetune.mode=best_of_n (a frozen policy to subtract), "
            f"got finetune.mode={ft.mode}"
        )
    return problems


def _check_offline(cfg, command: str) -> list[str]:
    off = cfg.get("offline")
    if command != "finetune" or off is None:
        return []
    pretrain = off.get("critic_pretrain", 0)
    if pretrain < 0 or off.critic_warmup < 0 or pretrain + off.critic_warmup > off.steps:
        return [
            f"offline.critic_pretrain={pretrain} + offline.critic_warmup={off.critic_warmup}: expected "
            f"two counts >= 0 summing to at most offline.steps={off.steps} (the critic-only updates are "
            "the first of the offline ones)"
        ]
    return []


#: The fine-tuning fields' allowed values and cross-field checks, read by the config validator
#: (l1flow_rl.config.validate), so that a bad value fails at config time, naming the field.
CHOICES = {
    "finetune.mode": lambda: FINETUNE_MODES,
    "finetune.q_agg": lambda: ("mean", "min"),
    "finetune.backup": lambda: ("max", "mean", "one_step"),
    "finetune.critic_input": lambda: ("action", "residual"),
    "finetune.reward": lambda: REWARDS,
    "finetune.critic_target": lambda: ("td", "mc"),
    "finetune.select_with": lambda: ("critic", "target"),
    "finetune.one_step_init": lambda: ("teacher", "scratch"),
    "online.mixing": lambda: ("seed", "balanced"),
}
CHECKS = (_check_online, _check_offline, _check_critic)
