"""OneDP-S (Wang et al. 2024): a stochastic one-step generator and the auxiliary score network of its
distribution, distilled from a diffusion teacher by the KL divergence along the diffusion chain."""

from __future__ import annotations

import copy

import torch
from tensordict import TensorDictBase
from torch import Tensor

from l1flow_rl.modules.policy import ChunkPolicy
from l1flow_rl.objectives.onedp_d import OneDPDLoss
from l1flow_rl.utils.doc_examples import distillation_example

__all__ = ["OneDPSLoss"]


@distillation_example("EDMHeunSampler(18)", "OneStepEDMSampler()", 1)
class OneDPSLoss(OneDPDLoss):
    """:class:`~l1flow_rl.objectives.onedp_d.OneDPDLoss` with a generator that reads noise z ~ N(0, I), whose
    distribution's score is no longer known: an auxiliary score network (``score_network``, a copy of
    the teacher's network and encoder, trained) learns it by the teacher's own denoising objective on
    the generator's chunks (detached: never on demonstrations), and its clean-chunk estimate stands for
    the generator's side of the score difference.

    Both terms are in ``"loss_onedp"``; their gradients do not mix (the generator's step treats the
    score network as fixed, the score network trains on detached chunks), so one optimiser step trains
    both. The score network's parameters are in :meth:`extra_parameters`, trained at
    ``extra_lr_scale`` (20) times the generator's rate: OneDP's 2e-5 against 1e-6, so that the score
    network keeps pace with the generator. Its weights are in :meth:`training_state`. Diagnostics:
    ``"generator_term"``, ``"score_term"``.
    """

    diagnostic_keys = ("generator_term", "score_term")
    stochastic = True
    #: the score network's learning rate over the generator's (OneDP's Table 7: 2e-5 / 1e-6)
    extra_lr_scale = 20.0

    def _setup(self) -> None:
        super()._setup()
        score = copy.deepcopy(self.teacher)
        score.requires_grad_(True)
        score.train()
        self.score_network: ChunkPolicy = score

    def extra_parameters(self) -> list[torch.nn.Parameter]:
        return [p for p in self.score_network.parameters() if p.requires_grad]

    def training_state(self) -> dict[str, Tensor]:
        return {f"score_network.{k}": v for k, v in self.score_network.state_dict().items()}

    def load_training_state(self, state: dict[str, Tensor]) -> None:
        prefix = "score_network."
        self.score_network.load_state_dict(
            {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}
        )

    def _fake_clean(self, obs: TensorDictBase, generated: Tensor, noisy: Tensor, level: Tensor) -> Tensor:
        score = self.score_network
        return self.teacher_view.clean(score, score.encode(obs), noisy, level)

    def _extra_terms(self, obs: TensorDictBase, generated: Tensor) -> tuple[Tensor | None, dict[str, Tensor]]:
        score = self.score_network
        score_term = self.teacher_view.training_error(score, score.encode(obs), generated.detach())
        return score_term, {"score_term": score_term.mean()}
