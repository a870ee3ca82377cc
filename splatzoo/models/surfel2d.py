"""2DGS: 2D Gaussian surfels with one colour each (optionally view-dependent through spherical harmonics)."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from ..errors import ShapeError
from ..geometry import eval_sh, num_sh_bases, rgb_to_sh0
from ..types import Camera, Surfels
from .base import SurfelModel, view_directions


@dataclass
class Surfel2DConfig:
    sh_degree: int = field(default=0, metadata={"help": "spherical-harmonics degree of the colour, 0 (none) to 3"})

    def __post_init__(self):
        if not 0 <= int(self.sh_degree) <= 3:
            raise ShapeError(f"sh_degree must be 0, 1, 2 or 3, got {self.sh_degree}")


class Surfel2DModel(SurfelModel):
    @classmethod
    def budget_start(cls, fit: int) -> float:
        """Plain surfels have no richness to shed, only surfels: three times what fits beat twice (the quick sweater,
        three seeds, at 5 / 25 / 100%: 2dgs +0.19 / +0.37 / +0.20 dB, beta +0.13 / +0.25 / +0.06; the fox, 2dgs, +0.24
        / +0.36 at 25 / 100%; BENCHMARKS.md, "Each member's own budgeted start")."""
        return 3.0

    def __init__(self, config: Surfel2DConfig, num_primitives: int = 0):
        super().__init__(config, num_primitives)
        self.sh_dc = nn.Parameter(torch.zeros(num_primitives, 1, 3))
        self.sh_rest = nn.Parameter(torch.zeros(num_primitives, num_sh_bases(config.sh_degree) - 1, 3))

    def init_from_points(self, points, colors, generator):
        self.init_geometry(points, generator)
        self.sh_dc.copy_(rgb_to_sh0(colors)[:, None])

    def surfels(self, camera: Camera) -> Surfels:
        g = self.geometry()
        coeffs = torch.cat([self.sh_dc, self.sh_rest], 1)
        dirs = view_directions(self.means, camera) if self.config.sh_degree > 0 else self.means
        color = torch.clamp(eval_sh(self.config.sh_degree, coeffs, dirs) + 0.5, min=0)
        return Surfels.constant_color(g["means"], g["quats"], g["scales"], g["opacities"], color)

    def optim_groups(self, scene_extent: float) -> list[dict]:
        groups = self.geometry_groups(scene_extent) + [{"name": "sh_dc", "params": [self.sh_dc], "lr": 2.5e-3}]
        if self.sh_rest.shape[1]:
            groups.append({"name": "sh_rest", "params": [self.sh_rest], "lr": 2.5e-3 / 20})
        return groups
