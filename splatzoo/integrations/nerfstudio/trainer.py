"""nerfstudio's Trainer with splatzoo's step: each iteration takes nerfstudio's next training view and hands it to
the model's splatzoo Trainer (model.SplatzooModel.splatzoo_step), which renders, backpropagates, steps its own Adam
and densifies. nerfstudio keeps its loop, viewer, logging, evaluation and checkpoint files. Imports nerfstudio.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from ...errors import SplatzooError


@dataclass
class SplatzooTrainerConfig(TrainerConfig):
    """nerfstudio's training configuration with splatzoo's step. max_num_iterations is the length of splatzoo's
    schedule (its learning-rate decay and densification windows scale with it, as `splatzoo train --iterations`)."""

    _target: type = field(default_factory=lambda: SplatzooTrainer)


class SplatzooTrainer(Trainer):
    """A resumed run (--load-dir) finishes the schedule it started: it trains up to that run's max_num_iterations,
    not that many more steps, with the training options it was started with."""

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        if self.world_size > 1:
            raise SplatzooError("the splatzoo methods train in one process (splatzoo train --nproc runs several)")
        self.schedule = self.config.max_num_iterations
        super().setup(test_mode)

    def _load_checkpoint(self) -> None:
        super()._load_checkpoint()
        schedule = self.pipeline.model.schedule
        if self._start_step > 0 and schedule is not None:
            self.schedule = schedule
            left = max(0, schedule - self._start_step)
            CONSOLE.print(f"splatzoo: resuming at iteration {self._start_step} of {schedule}: {left} to go")
            self.config.max_num_iterations = left

    def train_iteration(self, step: int):
        camera, batch = self.pipeline.datamanager.next_train(step)
        return self.pipeline.model.splatzoo_step(camera, batch, datamanager=self.pipeline.datamanager,
                                                 iterations=self.schedule)
