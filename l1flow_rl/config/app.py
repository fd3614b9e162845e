"""The composed config of every ``l1flow-rl`` sub-command (``configs/config.yaml``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from l1flow_rl.config.data import DataConfig, DemosConfig
from l1flow_rl.config.encoder import EncoderConfig
from l1flow_rl.config.evaluation import EvalConfig
from l1flow_rl.config.finetune import FinetuneConfig, OfflineConfig, OnlineConfig
from l1flow_rl.config.network import NetworkConfig
from l1flow_rl.config.policy import PolicyConfig
from l1flow_rl.config.task import TaskConfig
from l1flow_rl.config.toy import ToyConfig
from l1flow_rl.config.train import TrainConfig

__all__ = ["AppConfig"]


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
    data_dir: str = "data"
    # None: the run's own directory (hydra.run.dir, unique per run; see l1flow_rl.commands.cli)
    run_dir: str | None = None
    checkpoint: str | None = None
    teacher: str | None = None  # distillation (policy=consistency|onedp_d|onedp_s): the teacher's checkpoint
    # l1flow-rl export: the pretrained folder to write, and whether it also gets the torch.export
    # program (policy.pt2) and the ONNX model (policy.onnx) of the 2-NFE call
    out: str | None = None
    program: bool = False
    onnx: bool = False
    resume: bool = False
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda
