"""3D Gabor surfels (the paper) and its ablation baselines A, B, C.

Colour inside a surfel with N waves at fixed orientations theta_i:
    c(u,v) = sum_i w_i [cA (1 + cos t_i)/2 + cB (1 - cos t_i)/2],  t_i = 2 pi f_i (cos theta_i, sin theta_i).(u,v) + phi_i
           = (sum_i w_i)(cA + cB)/2 + sum_i w_i (cA - cB)/2 cos t_i
which is the rasterizer's wave bank with k_i = 2 pi f_i (cos theta_i, sin theta_i), a_i = w_i (cA - cB)/2.
f is in cycles per sigma.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import nn

from ..errors import ShapeError
from ..types import Camera, Surfels
from .base import SurfelModel


@dataclass
class GaborConfig:
    n_waves: int = field(default=4, metadata={"help": "number of wave orientations per surfel (fan at i*pi/N)"})

    def __post_init__(self):
        if int(self.n_waves) < 1:
            raise ShapeError(f"n_waves must be at least 1, got {self.n_waves} (use the 2dgs model for no waves)")


@dataclass
class BaselineAConfig(GaborConfig):
    n_waves: int = field(default=1, metadata={"help": "number of waves (Baseline A of the paper uses 1)"})


class GaborModel(SurfelModel):
    """The paper's model: waves fanned at i*pi/N, learnable frequency, weight and phase."""

    orientation = "fan"   # "fan": theta_i = i pi / N; "u": every wave along the local u axis
    learn_phase = True

    def __init__(self, config: GaborConfig, num_primitives: int = 0):
        super().__init__(config, num_primitives)
        n, k = num_primitives, config.n_waves
        self.color_a = nn.Parameter(torch.zeros(n, 3))
        self.color_b = nn.Parameter(torch.zeros(n, 3))
        self.wave_weights = nn.Parameter(torch.zeros(n, k))
        self.wave_freqs = nn.Parameter(torch.zeros(n, k))
        if self.learn_phase:
            self.wave_phases = nn.Parameter(torch.zeros(n, k))
        angles = torch.arange(k) * math.pi / k if self.orientation == "fan" else torch.zeros(k)
        self.register_buffer("directions", torch.stack([angles.cos(), angles.sin()], -1), persistent=False)

    def init_from_points(self, points, colors, generator):
        """As the public release: cA = point colour, cB = black, w = 0.1 U(0,1), f = U(0,1), phi = U(0,1)."""
        self.init_geometry(points, generator)
        n, k = self.wave_weights.shape
        self.color_a.copy_(colors)
        self.color_b.zero_()
        self.wave_weights.copy_(0.1 * torch.rand(n, k, generator=generator))
        self.wave_freqs.copy_(torch.rand(n, k, generator=generator))
        if self.learn_phase:
            self.wave_phases.copy_(torch.rand(n, k, generator=generator))

    def phases(self) -> torch.Tensor:
        return self.wave_phases if self.learn_phase else self.wave_weights.new_zeros(self.wave_weights.shape)

    def surfels(self, camera: Camera) -> Surfels:
        g = self.geometry()
        w = self.wave_weights
        base = w.sum(1, keepdim=True) * (self.color_a + self.color_b) / 2
        amplitudes = w[..., None] * ((self.color_a - self.color_b) / 2)[:, None, :]
        vectors = (2 * math.pi) * self.wave_freqs[..., None] * self.directions.to(w)
        return Surfels(g["means"], g["quats"], g["scales"], g["opacities"], base, vectors, self.phases(), amplitudes)

    def optim_groups(self, scene_extent: float) -> list[dict]:
        groups = self.geometry_groups(scene_extent) + [
            {"name": "color_a", "params": [self.color_a], "lr": 2.5e-3},
            {"name": "color_b", "params": [self.color_b], "lr": 2.5e-3},
            {"name": "wave_weights", "params": [self.wave_weights], "lr": 1e-3},
            {"name": "wave_freqs", "params": [self.wave_freqs], "lr": 1e-3},
        ]
        if self.learn_phase:
            groups.append({"name": "wave_phases", "params": [self.wave_phases], "lr": 1e-3})
        return groups


class BaselineBModel(GaborModel):
    """Baseline B: every wave along the local u axis (a 3D take on 2D Gabor splatting)."""

    orientation = "u"


class BaselineCModel(GaborModel):
    """Baseline C: phases fixed at zero."""

    learn_phase = False
