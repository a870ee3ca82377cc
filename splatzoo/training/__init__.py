"""Training: the 2DGS recipe (losses, schedules, densification) for any registered model. The loop that owns
a run folder (checkpoints, logs, interrupts) is splatzoo.runs.train."""
from .trainer import TrainConfig, Trainer

__all__ = ["TrainConfig", "Trainer"]
