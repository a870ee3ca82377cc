"""beta-gabor: the waves of gabor-adaptive on surfels with beta's learned falloff.

Both ways of spending bytes that the zoo measured to pay per byte, on one surfel: a Beta kernel (one number a surfel,
sharper edges and fewer tiles touched) and waves only where the training views show they are worth their bytes
(gabor-adaptive: 8 orientations to start, pruned late by measured cost; a surfel without waves is stored as a plain
surfel). Under a byte budget (TrainConfig.max_bytes, `compare --budgets`) it starts with as many surfels as fit plain
and sheds, by measured cost, waves or its weakest surfels until it fits (training/budget.py).
"""
from __future__ import annotations

from dataclasses import dataclass

from .beta import BetaFalloff
from .gabor import AdaptiveGaborConfig, GaborModel


@dataclass
class BetaGaborConfig(AdaptiveGaborConfig):
    pass


class BetaGaborModel(BetaFalloff, GaborModel):
    """gabor-adaptive surfels with a learned Beta falloff each."""
