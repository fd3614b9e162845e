"""``l1flow-rl export checkpoint=CKPT out=DIR [program=true] [onnx=true]``: a training checkpoint as a
pretrained folder (:mod:`l1flow_rl.export.pretrained`), with the EMA weights."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from l1flow_rl.export.pretrained import save_pretrained
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.workspace.checkpoint import load_actor, load_checkpoint

__all__ = ["run_export"]


def run_export(cfg: DictConfig) -> int:
    if not cfg.checkpoint or not cfg.out:
        print(
            "l1flow-rl export: pass checkpoint=PATH (a .pt file or a run's checkpoints/ folder) and out=DIR"
        )
        return 2
    state = load_checkpoint(cfg.checkpoint)
    actor, train_cfg = load_actor(cfg.checkpoint, use_ema=True)
    if not isinstance(actor, L1FlowActor):
        raise ValueError(
            f"checkpoint {cfg.checkpoint!r} holds a fine-tuned acting module ({type(actor).__name__}, "
            "policy.finetune), not the flow policy alone that a pretrained folder holds; it is not exported"
        )
    folder = save_pretrained(
        actor,
        cfg.out,
        policy=train_cfg.policy,
        encoder=train_cfg.get("encoder"),
        task=train_cfg.task,
        train_config=train_cfg,
        source={
            "checkpoint": str(Path(cfg.checkpoint).resolve()),
            "step": state.get("step"),
            "weights": "ema" if state.get("ema") is not None else "model",
        },
        program=bool(cfg.program),
        onnx=bool(cfg.onnx),
    )
    files = ", ".join(sorted(p.name for p in folder.iterdir()))
    print(f"wrote {folder}: {files}")
    return 0
