"""Where the hydra configs live: ``configs/`` beside the package (a source checkout or an editable
install), else the copy installed as ``l1flow_rl.configs``."""

from __future__ import annotations

from pathlib import Path

__all__ = ["CONFIG_DIR"]

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"
if not (CONFIG_DIR / "task").is_dir():  # installed (non-editable): configs ship as l1flow_rl.configs
    CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
