"""A third-party primitive type: each surfel carries a checkerboard of period `cells` sigma.

cos(a u) cos(a v) = (cos(a (u + v)) + cos(a (u - v))) / 2, so the checkerboard is two waves of the bank and
renders through splatzoo's rasterizer unchanged.
"""
import math
from dataclasses import dataclass, field

import torch
from torch import nn

from splatzoo import ModelSpec, Surfels
from splatzoo.models.base import SurfelModel


@dataclass
class CheckerConfig:
    cells: float = field(default=1.0, metadata={"help": "checker cells per sigma"})


class CheckerModel(SurfelModel):
    def __init__(self, config, num_primitives=0):
        super().__init__(config, num_primitives)
        self.color_dark = nn.Parameter(torch.zeros(num_primitives, 3))
        self.color_light = nn.Parameter(torch.zeros(num_primitives, 3))

    def init_from_points(self, points, colors, generator):
        self.init_geometry(points, generator)
        self.color_light.copy_(colors)
        self.color_dark.copy_(colors * 0.2)

    def surfels(self, camera):
        g = self.geometry()
        n = self.means.shape[0]
        a = math.pi * self.config.cells
        vectors = torch.tensor([[a, a], [a, -a]], dtype=self.means.dtype).expand(n, 2, 2)
        half = (self.color_light - self.color_dark) / 4
        return Surfels(g["means"], g["quats"], g["scales"], g["opacities"],
                       (self.color_light + self.color_dark) / 2, vectors, self.means.new_zeros(n, 2),
                       torch.stack([half, half], 1))

    def optim_groups(self, scene_extent):
        return self.geometry_groups(scene_extent) + [
            {"name": "color_dark", "params": [self.color_dark], "lr": 2.5e-3},
            {"name": "color_light", "params": [self.color_light], "lr": 2.5e-3}]


SPEC = ModelSpec("checker", CheckerModel, CheckerConfig, "checkerboard surfels (plugin test fixture)")
IMPOSTOR = ModelSpec("gabor", CheckerModel, CheckerConfig, "a plugin that tries to take a built-in name")
