"""Training of CVA-Net (paper section 3.3): data, loop, checkpoints, model cards, ``cva-train``."""

from __future__ import annotations

from cva_confidence_ros.training.card import write_model_card
from cva_confidence_ros.training.config import MODES, TrainConfig
from cva_confidence_ros.training.trainer import train

__all__ = ['MODES', 'TrainConfig', 'train', 'write_model_card']
