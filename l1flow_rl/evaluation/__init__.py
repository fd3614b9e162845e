"""Evaluation: the batched evaluator, episode schedule, metrics with confidence intervals,
protocols and videos. The ``l1flow-rl eval`` command is :mod:`l1flow_rl.commands.eval` (it loads
checkpoints, so this package does not import it).

``evaluate(actor, env, episodes, seed)`` runs seeded episodes across parallel envs;
:mod:`~l1flow_rl.evaluation.protocols` names how a figure is measured (``eval.protocol``);
:mod:`~l1flow_rl.evaluation.plan` splits seeds into validation (checkpoint selection) and test
(reported figures).
"""

from l1flow_rl.evaluation.evaluator import BUILTIN_METRICS, evaluate, sampler_record
from l1flow_rl.evaluation.metrics import mean_interval, summarize_metrics, wilson_interval
from l1flow_rl.evaluation.plan import SPLITS, EvalPlan, resolve_plan
from l1flow_rl.evaluation.protocols import EvalProtocol, get_protocol, protocol_names, register_protocol

__all__ = [
    "BUILTIN_METRICS",
    "SPLITS",
    "EvalPlan",
    "EvalProtocol",
    "evaluate",
    "get_protocol",
    "mean_interval",
    "protocol_names",
    "register_protocol",
    "resolve_plan",
    "sampler_record",
    "summarize_metrics",
    "wilson_interval",
]
