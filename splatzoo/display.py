"""Surfels recoloured for display: each surfel one flat colour, drawn where and as opaque as the model draws it. The
compare figure's "surfels" row and the viewer's surfels, waves and frequency modes render these."""
from __future__ import annotations

import dataclasses

import torch

from .types import SURFEL_FIELDS, Surfels


def recolored(surfels: Surfels, colors: torch.Tensor) -> Surfels:
    """`surfels` in the flat colours `colors` [N,3]. Every field the field table (types.SURFEL_FIELDS) marks as
    geometry or opacity is kept (a Beta falloff too), and so is a texture's alpha, which multiplies the opacity; the
    rest of the appearance goes (no waves, a texture without colour). So a recoloured render's alpha is the model's."""
    changes: dict = {"wave_counts": None}
    for f in SURFEL_FIELDS:
        if f.role != "appearance":
            continue
        value = getattr(surfels, f.name)
        if f.name == "base_color":
            changes[f.name] = colors.to(value)
        elif f.name == "texture":  # rgb adds to the colour, alpha multiplies the opacity: keep the alpha
            changes[f.name] = torch.cat([torch.zeros_like(value[..., :3]), value[..., 3:]], -1)
        else:  # the waves (K = 0), and any other appearance: none
            changes[f.name] = value.new_zeros(f.shape(surfels.num, 0, surfels.texture_size))
    return dataclasses.replace(surfels, **changes)


def random_colors(n: int, seed: int = 0) -> torch.Tensor:
    """[n,3] colours in [0,1], the same for the same seed (on the CPU)."""
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed))
