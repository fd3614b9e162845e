"""The whole policy call as one self-contained program: ``torch.export`` (and ONNX where it works).

:class:`DeployablePolicy` is the call a robot makes: observation history and starting noise in,
executable actions out. Observations are normalised inside, the sampler's network calls (2 for L1
Flow) are unrolled inside, actions are un-normalised inside, so the program is the whole policy and
needs neither this library nor TensorDict to run::

    program = torch.export.load("policy/policy.pt2").module()
    actions = program(observation, noise)          # [B, K, A], environment units

The noise is an input so that a chunk is reproducible (zeros give the deterministic chunk). Inputs are
the observation entries in the order of config.json's ``program.inputs`` (one tensor for a state
policy: [B, To, D] float32; images are uint8 [B, To, 3, H, W]), then the noise [B, H, A]; the batch
size is dynamic. A sampler that re-noises inside a chunk (ancestral DDPM; Consistency Policy chained
over 3 steps) takes its later draws as one more input, ``inner_noise`` [B, draws, H, A]
(``sampler.inner_noise_draws``), so its program too reproduces the eager chunk
``actor.policy(obs, noise=..., inner_noise=...)``; a program has no random operation inside.

ONNX: :func:`export_onnx` uses the dynamo exporter (``torch.onnx.export(..., dynamo=True)``, which
needs ``onnxscript``) on the same module.

Example:
    >>> import torch
    >>> from l1flow_rl import L1FlowActor
    >>> from l1flow_rl.export.program import DeployablePolicy, example_inputs
    >>> actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32)).eval()
    >>> program = torch.export.export(DeployablePolicy(actor), example_inputs(actor), strict=False)
    >>> obs, noise = torch.randn(1, 2, 5), torch.randn(1, 16, 2)
    >>> torch.allclose(program.module()(obs, noise), actor.policy(obs, noise=noise), atol=1e-5)
    True
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule  # the actor's base: naming the actor would close a circle
from torch import Tensor, nn

__all__ = [
    "ONNX_FILE",
    "PROGRAM_FILE",
    "DeployablePolicy",
    "example_inputs",
    "export_onnx",
    "export_program",
    "load_program",
    "program_description",
]

PROGRAM_FILE = "policy.pt2"
ONNX_FILE = "policy.onnx"


class DeployablePolicy(nn.Module):
    """``forward(*entries, noise[, inner_noise]) -> actions [B, K, A]``: one actor's whole call (2 NFE for
    L1 Flow) on plain tensors.

    ``entries`` are the observation entries [B, To, ...] in :attr:`entry_names` order; ``inner_noise``
    [B, draws, H, A] only for a sampler that re-noises inside a chunk (:attr:`inner_draws` > 0). The
    module shares the actor's weights; put the actor in eval mode first (image crops are centre crops then).
    """

    def __init__(self, actor: TensorDictModule) -> None:
        super().__init__()
        self.policy = actor.policy
        self.entry_names = list(self.policy.encoder.obs_shapes)
        self.inner_draws = self.policy.sampler.inner_noise_draws

    def forward(self, *inputs: Tensor) -> Tensor:
        p = self.policy
        if self.inner_draws:
            *entries, noise, inner = inputs
            extra = {"inner_noise": inner}
        else:
            *entries, noise = inputs
            extra = {}
        n = noise.shape[0]
        obs = TensorDict(dict(zip(self.entry_names, entries)), batch_size=[n, p.obs_horizon])
        cond = p.encode(obs)
        chunk = p.sampler(lambda x, t: p.denoise(x, t, cond), noise.to(cond.dtype), **extra)
        return p.executable(p.action_normalizer.unnormalize(chunk))


def _noise_shapes(actor: TensorDictModule) -> dict[str, tuple[int, ...]]:
    """The noise inputs after the observation entries, without the batch: ``noise`` [H, A], and
    ``inner_noise`` [draws, H, A] for a sampler that re-noises inside a chunk."""
    p = actor.policy
    shapes = {"noise": (p.pred_horizon, p.action_dim)}
    if p.sampler.inner_noise_draws:
        shapes["inner_noise"] = (p.sampler.inner_noise_draws, p.pred_horizon, p.action_dim)
    return shapes


def example_inputs(actor: TensorDictModule, batch: int = 1) -> tuple[Tensor, ...]:
    """Zero observations (uint8 images, float entries) and zero noise of the shapes the actor takes."""
    p = actor.policy
    device = next(p.net.parameters()).device
    entries = [
        torch.zeros(
            batch, p.obs_horizon, *shape, dtype=torch.uint8 if len(shape) == 3 else p.dtype, device=device
        )
        for shape in p.encoder.obs_shapes.values()
    ]
    noises = [torch.zeros(batch, *s, dtype=p.dtype, device=device) for s in _noise_shapes(actor).values()]
    return (*entries, *noises)


def _dynamic_batch(actor: TensorDictModule) -> tuple[tuple[dict[int, Any], ...]]:
    """Dim 0 of every input is the batch (one spec per input, inside the ``*inputs`` tuple)."""
    batch = torch.export.Dim("batch", min=1, max=4096)
    count = len(actor.policy.encoder.obs_shapes) + len(_noise_shapes(actor))
    return (tuple({0: batch} for _ in range(count)),)


def export_program(
    actor: TensorDictModule, path: str | os.PathLike | None = None
) -> torch.export.ExportedProgram:
    """``torch.export`` of :class:`DeployablePolicy` (batch size dynamic), saved to ``path`` when given.

    Exported non-strict: TensorDict glue runs as Python while tracing and leaves only tensor ops."""
    module = DeployablePolicy(actor).eval()
    with torch.no_grad():
        program = torch.export.export(
            module, example_inputs(actor, batch=2), dynamic_shapes=_dynamic_batch(actor), strict=False
        )
    if path is not None:
        torch.export.save(program, str(path))
    return program


def load_program(path: str | os.PathLike) -> nn.Module:
    """The callable saved by :func:`export_program`: ``program(*entries, noise[, inner_noise])`` ->
    actions."""
    return torch.export.load(str(path)).module()


def program_description(actor: TensorDictModule) -> dict[str, Any]:
    """What config.json says about the program: its file, its inputs in order, its output."""
    p = actor.policy
    inputs = [
        {
            "name": k,
            "shape": ["batch", p.obs_horizon, *s],
            "dtype": "uint8" if len(s) == 3 else str(p.dtype).removeprefix("torch."),
        }
        for k, s in p.encoder.obs_shapes.items()
    ]
    inputs += [
        {"name": name, "shape": ["batch", *shape], "dtype": str(p.dtype).removeprefix("torch.")}
        for name, shape in _noise_shapes(actor).items()
    ]
    return {
        "file": PROGRAM_FILE,
        "inputs": inputs,
        "output": {"name": "actions", "shape": ["batch", p.action_steps, p.action_dim]},
        "torch_version": torch.__version__,
    }


def export_onnx(actor: TensorDictModule, path: str | os.PathLike) -> Path:
    """The same call as an ONNX model (dynamo exporter, opset of the installed torch), batch dynamic.

    Needs ``onnx`` and ``onnxscript`` (``pip install 'l1flow-rl[export]'``)."""
    try:
        import onnxscript  # noqa: F401  (the dynamo exporter imports it; fail here with the fix)
    except ImportError as err:
        raise ImportError(
            f"ONNX export needs {err.name}, which is not installed: pip install 'l1flow-rl[export]'"
        ) from err
    module = DeployablePolicy(actor).eval()
    names = [*module.entry_names, *_noise_shapes(actor)]
    with torch.no_grad():
        onnx_program = torch.onnx.export(
            module,
            example_inputs(actor, batch=2),
            dynamo=True,
            input_names=names,
            output_names=["actions"],
            dynamic_shapes=_dynamic_batch(actor),
        )
    path = Path(path)
    onnx_program.save(str(path))
    return path
