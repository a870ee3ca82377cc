"""Training: the 2DGS recipe (losses, schedules, densification) for any registered model."""
from .trainer import TrainConfig, train

__all__ = ["TrainConfig", "train"]
