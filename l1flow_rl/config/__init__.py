"""Structured config schemas, one module per group. Hydra merges YAML from ``configs/`` onto these,
so a wrong key or a value of the wrong type fails before any work starts, naming the key."""

from l1flow_rl.config.app import AppConfig
from l1flow_rl.config.data import PADDING_RULES, DataConfig, DemosConfig
from l1flow_rl.config.encoder import EncoderConfig
from l1flow_rl.config.evaluation import EvalConfig
from l1flow_rl.config.network import NetworkConfig
from l1flow_rl.config.paths import CONFIG_DIR
from l1flow_rl.config.policy import PolicyConfig
from l1flow_rl.config.task import CONTROL_KINDS, TaskConfig, load_task_config, task_names
from l1flow_rl.config.toy import ToyConfig
from l1flow_rl.config.train import TrainConfig

__all__ = [
    "CONFIG_DIR",
    "CONTROL_KINDS",
    "PADDING_RULES",
    "AppConfig",
    "DataConfig",
    "DemosConfig",
    "EncoderConfig",
    "EvalConfig",
    "NetworkConfig",
    "PolicyConfig",
    "TaskConfig",
    "ToyConfig",
    "TrainConfig",
    "load_task_config",
    "task_names",
]
