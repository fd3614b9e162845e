"""The composed config of every ``l1flow-rl`` sub-command (``configs/config.yaml``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from l1flow_rl.config.data import DataConfig, DemosConfig
from l1flow_rl.config.encoder import EncoderConfig
from l1flow_rl.config.evaluation import EvalConfig
from l1flow_rl.config.finetune import FinetuneConfig, OfflineConfig, OnlineConfig
from l1flow_rl.config.network import NetworkConfig
from l1flow_rl.config.path_fields import EXISTING, WRITABLE_DIR, path_field
from l1flow_rl.config.policy import PolicyConfig
from l1flow_rl.config.ranges import bounded
from l1flow_rl.config.task import TaskConfig
from l1flow_rl.config.toy import ToyConfig
from l1flow_rl.config.train import TrainConfig

__all__ = ["RESUME_MODES", "AppConfig"]

#: ``resume``: false (a fresh run; a run_dir holding one is refused), true (continue
#: ``checkpoints/latest.pt``), auto (what a grid's jobs need: continue where a checkpoint exists,
#: else start; a run_dir whose finished run has this very config is skipped, one of another
#: setting refused)
RESUME_MODES = (False, True, "auto")


@dataclass
class AppConfig:
    """One field per group or setting; each group's schema lives in its own module."""

    task: TaskConfig = field(default_factory=TaskConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    demos: DemosConfig = field(default_factory=DemosConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    toy: ToyConfig = field(default_factory=ToyConfig)
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    offline: OfflineConfig = field(default_factory=OfflineConfig)
    online: OnlineConfig = field(default_factory=OnlineConfig)
    # the demonstrations made by the task's expert, and caches beside a user's data.path
    data_dir: str = path_field("data", kind=WRITABLE_DIR, commands=("train", "demos", "finetune"))
    # None: the run's own directory (hydra.run.dir, unique per run; see l1flow_rl.commands.cli)
    run_dir: str | None = path_field(None, kind=WRITABLE_DIR)
    # a .pt file, a run's checkpoints/ folder, or a pretrained folder written by l1flow-rl export
    checkpoint: str | None = path_field(
        None, kind=EXISTING, commands=(), required=("eval", "export", "finetune")
    )
    teacher: str | None = None  # distillation (policy=consistency|onedp_d|onedp_s): the teacher's checkpoint
    # l1flow-rl export: the pretrained folder to write, and whether it also gets the torch.export
    # program (policy.pt2) and the ONNX model (policy.onnx) of the 2-NFE call
    out: str | None = path_field(None, kind=WRITABLE_DIR, commands=(), required=("export",))
    program: bool = False
    onnx: bool = False
    resume: Any = False  # false | true | auto (RESUME_MODES)
    seed: int = bounded(0, ge=0, lt=2**32)
    device: str = "auto"  # auto | cpu | cuda
