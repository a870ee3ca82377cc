"""beta-gabor: the waves of gabor-adaptive, each with a colour of its own, on surfels with beta's learned falloff.

Both ways of spending bytes that the zoo measured to pay per byte, on one surfel: a Beta kernel (one number a surfel,
sharper edges and fewer tiles touched) and waves only where the training views show they are worth their bytes
(gabor-adaptive: 8 orientations to start, pruned late by measured cost; a surfel without waves is stored as a plain
surfel). Each wave carries its own RGB amplitude (color_param "per-wave") and learns its own direction
(free_directions): stripes of several colours at any angle fit on one surfel, for 6 stored values a wave where a
wave of the fixed fan with a colour difference shared by the surfel stores 3, plus 3 a waved surfel (BENCHMARKS.md,
"Waves with a colour each"). The wave vectors and phases learn at ten times gabor's rate (wave_lr), so that a
short run reaches stripes several cycles a sigma from where they start ("Waves that learn ten times faster"), and at
30% of the run every surfel's waves are fitted to the stripes the training photos show on its plane (fit_waves,
training/wave_fit.py; "Waves fitted to the photos"). Its sparse-wave penalty is twice gabor's (wave_l1). Under a
byte budget (TrainConfig.max_bytes, `compare --budgets`) it sheds, by measured cost, waves or its weakest surfels
until it fits (training/budget.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

from .beta import BetaFalloff
from .gabor import WAVE_L1 as GABOR_WAVE_L1
from .gabor import AdaptiveGaborConfig, GaborModel

# the sparse-wave penalty: twice gabor's. On the quick sweater, three seeds, it gave +0.30 dB at 5% of 2dgs's bytes,
# -0.07 at 25% and at 100% (BENCHMARKS.md, "Packed files version 3, and a sparser beta-gabor")
WAVE_L1 = 2 * GABOR_WAVE_L1


@dataclass
class BetaGaborConfig(AdaptiveGaborConfig):
    color_param: str = field(default="per-wave", metadata={
        "help": "per-wave: colour = base + sum_i a_i cos(t_i), an RGB amplitude a_i for each wave; residual: the waves "
                "share one colour difference d a surfel (a_i = w_i d); paper: the paper's form (see gabor)"})
    free_directions: bool = field(default=True, metadata={
        "help": "each wave learns its direction: a 2D wave vector (started on the fan of orientations) instead of a "
                "frequency along a fixed orientation; --no-free-directions: the fan's fixed orientations"})
    wave_lr: float = field(default=1e-2, metadata={
        "help": "learning rate of the waves' vectors and phases (Adam; about the most one moves a step: cycles per "
                "sigma, radians): 10x gabor's, so that in a short run a wave reaches stripes several cycles a sigma "
                "from its start in [0, 1) and any phase (BENCHMARKS.md, \"Waves that learn ten times faster\")"})
    wave_l1: float = field(default=WAVE_L1, metadata={
        "help": "L1 penalty on the waves' amplitudes (see gabor's --wave-l1): twice gabor's, worth +0.3 dB on the "
                "test views at 5% of 2dgs's bytes (BENCHMARKS.md, \"Packed files version 3, and a sparser "
                "beta-gabor\")"})
    fit_waves: float = field(default=0.3, metadata={
        "help": "fraction of the run after which every surfel's waves are replaced by the stripes the training "
                "photos show on its plane (training/wave_fit.py; the geometry has settled by then), 0: never"})

    # beta-gabor files written before free directions existed store one frequency a wave along the fan, those from
    # before wave_lr were trained at gabor's rate, and those from before fit_waves without a fit
    stored_defaults: ClassVar[dict] = {**AdaptiveGaborConfig.stored_defaults, "free_directions": False,
                                       "wave_lr": 1e-3, "fit_waves": 0.0}


class BetaGaborModel(BetaFalloff, GaborModel):
    """gabor-adaptive surfels with a learned Beta falloff each."""

    @classmethod
    def budget_start(cls, fit: int) -> float:
        """Waves pay where surfels are few: under a small budget more surfels to choose from are worth their shed
        waves, under a large one the shedding takes waves that were worth more (the quick sweater, three seeds: the
        best start was 3x what fits at 5%, 2x at 25%, 1.5x at 100%; boots at 256 px, 100%: 1.5x +0.46 dB over 2x;
        BENCHMARKS.md, "A budgeted start that falls with the budget"). So it starts with what fits plus 18 times its
        square root: 3x at 80 surfels, 1.8x at 455, 1.4x at 1,864 (never more than 3x)."""
        return min(3.0, 1.0 + 18.0 / math.sqrt(max(fit, 1)))
