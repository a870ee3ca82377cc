"""Beta-kernel surfels: 2D surfels whose opacity falls off with a learned Beta kernel instead of the Gaussian.

Deformable Beta Splatting (Liu et al., SIGGRAPH 2025) replaces the Gaussian exp(-r^2/2) of a splat by the Beta kernel
(1 - r^2)^b over the unit disc, with a learned b per primitive: bounded support, and a shape that goes from a soft
bump (large b) to a flat, sharp-edged disc (b near 1). Here, on 2DGS surfels, with r^2 = s rho / 2 and b = 1/s over
rho = u^2 + v^2 in sigmas squared (the contract's falloff, csrc/surfel_math.h):

    alpha = o (1 - s rho / 2)_+^(1/s),   s in (0, 1],

the Gaussian again as s -> 0 and a support of rho < 2/s: the tighter the kernel, the fewer tiles a surfel touches.
Each surfel learns s = sigmoid(t) (t its logit). It starts at s = sigmoid(-3) = 0.047 (b = 21): within 5% of the
2DGS surfel over the support that opacity 1 gives a Gaussian, so a run starts where 2DGS would. Colour: one per
surfel, or spherical harmonics (sh_degree), as 2dgs. Anti-aliased, the pixel footprint's gain multiplies f at the
footprint's q (exact for the Gaussian, a close approximation for the Beta kernel).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ..types import MAX_FALLOFF, Camera, Surfels
from .surfel2d import Surfel2DConfig, Surfel2DModel

FALLOFF_INIT_LOGIT = -3.0  # s = 0.047 at the start: nearly the Gaussian
# the logit's rate: 0.02 / 0.01 / 0.005 / 0.002 measured on the quick knit scenes; 0.005 is ahead of 2DGS on all four
# (0.02 fell 0.06-0.07 dB under it on vest and shirt; BENCHMARKS.md, "beta's falloff rate")
FALLOFF_LR = 0.005


@dataclass
class BetaConfig(Surfel2DConfig):
    pass


class BetaFalloff:
    """The learned Beta falloff, added to a surfel model by listing this class before it: `class BetaModel(BetaFalloff,
    Surfel2DModel)`; the model's colour stays its own."""

    def __init__(self, config, num_primitives: int = 0):
        super().__init__(config, num_primitives)
        self.falloff_logit = nn.Parameter(torch.full((num_primitives,), FALLOFF_INIT_LOGIT))

    def falloff(self) -> torch.Tensor:
        """[N] each surfel's falloff exponent s in (0, MAX_FALLOFF]."""
        return MAX_FALLOFF * torch.sigmoid(self.falloff_logit)

    def init_from_points(self, points, colors, generator):
        super().init_from_points(points, colors, generator)
        self.falloff_logit.fill_(FALLOFF_INIT_LOGIT)

    def surfels(self, camera: Camera) -> Surfels:
        s = super().surfels(camera)
        s.falloff = self.falloff()
        return s

    def optim_groups(self, scene_extent: float) -> list[dict]:
        return super().optim_groups(scene_extent) + [
            {"name": "falloff_logit", "params": [self.falloff_logit], "lr": FALLOFF_LR}]


class BetaModel(BetaFalloff, Surfel2DModel):
    """2D surfels with one colour each (as 2dgs) and the learned Beta falloff."""
