"""Textured surfels: 2DGS surfels that carry a small RGBA texture each.

Textured Gaussians (Chao et al., "Textured Gaussians for Enhanced 3D Scene Appearance Modeling", 2024) and
Billboard Splatting (BBSplat, Svitov et al., 2024) give every splat a texture over its own plane, so one primitive
can show detail finer than its own footprint: colour and transparency vary inside it instead of needing more
primitives. Here on 2DGS surfels, through the contract's texture kind (Surfels.texture, csrc/surfel_math.h): a
T x T grid of RGBA texels over the surfel's (u, v) in [-R, R]^2 sigmas (R = TEXTURE_RADIUS = 3, the visible support;
the edge texels extend beyond it), sampled bilinearly:

    c(u, v) = max(0, c0 + rgb(u, v)),       alpha = o f(rho) alpha_tex(u, v),

with c0 the 2DGS colour (one per surfel, or spherical harmonics with sh_degree), rgb a residual around it (as in
Textured Gaussians, where the texture modulates the base colour) and alpha_tex = sigmoid(logit) in (0, 1). The
gradients reach the four texels each pixel reads and, through the texture's slope, the surfel's (u, v) and so its
geometry. Anti-aliased (the training default), the texture is prefiltered by the pixel footprint: its deviation from
its mean (weighted by the falloff at the texel centres) fades by the footprint's gain at the texel grid's Nyquist
frequency, so a minified surfel shows the mean colour it shows at full size.

The model starts as its 2DGS surfel: the residual rgb is 0 and alpha_tex = sigmoid(4.6) = 0.99 everywhere. Texel rgb
learns at 2.5e-3 in colour units (about 3.5x 2DGS's colour rate, 2.5e-3 on an SH coefficient worth 0.28: each texel
sees only the few pixels around it), the alpha logits at 0.05, the opacity's rate. texture_size (T) sets the texels
a side: 4, the default (64 floats per surfel on top of 2DGS's 13), or 8 (256); at equal count on the quick sweater
scene 4 gives the most PSNR per byte (BENCHMARKS.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from ..errors import ShapeError
from ..rasterizers.reference import sample_texture
from ..types import TEXTURE_RADIUS, Camera, Surfels
from .base import SplatModel, inverse_sigmoid
from .surfel2d import Surfel2DConfig, Surfel2DModel

ALPHA_INIT_LOGIT = 4.6  # sigmoid: 0.990, the surfel nearly as its 2DGS self
TEXTURE_RGB_LR = 2.5e-3
TEXTURE_ALPHA_LR = 0.05


@dataclass
class TexturedConfig(Surfel2DConfig):
    texture_size: int = field(default=4, metadata={"help": "texels a side of each surfel's RGBA texture (1 to 16)"})

    def __post_init__(self):
        super().__post_init__()
        if not 1 <= int(self.texture_size) <= 16:
            raise ShapeError(f"texture_size must be an integer from 1 to 16, got {self.texture_size}")
        self.texture_size = int(self.texture_size)


class TexturedModel(Surfel2DModel):
    # its textures shed too; the plain surfels' larger start is not measured here
    budget_start = SplatModel.budget_start

    def __init__(self, config: TexturedConfig, num_primitives: int = 0):
        super().__init__(config, num_primitives)
        T = config.texture_size
        self.texture_rgb = nn.Parameter(torch.zeros(num_primitives, T, T, 3))
        self.texture_alpha_logit = nn.Parameter(torch.full((num_primitives, T, T, 1), ALPHA_INIT_LOGIT))

    def texture(self) -> torch.Tensor:
        """[N,T,T,4] the Surfels texture: residual rgb and alpha in (0, 1)."""
        return torch.cat([self.texture_rgb, torch.sigmoid(self.texture_alpha_logit)], -1)

    def init_from_points(self, points, colors, generator):
        super().init_from_points(points, colors, generator)
        self.texture_rgb.zero_()
        self.texture_alpha_logit.fill_(ALPHA_INIT_LOGIT)

    def surfels(self, camera: Camera) -> Surfels:
        s = super().surfels(camera)
        s.texture = self.texture()
        return s

    def optim_groups(self, scene_extent: float) -> list[dict]:
        return super().optim_groups(scene_extent) + [
            {"name": "texture_rgb", "params": [self.texture_rgb], "lr": TEXTURE_RGB_LR},
            {"name": "texture_alpha_logit", "params": [self.texture_alpha_logit], "lr": TEXTURE_ALPHA_LR}]

    def effective_opacity(self) -> torch.Tensor:
        """[N] the most a surfel's texture can let through: its opacity times its most opaque texel's alpha (the
        bilinear samples, and the anti-aliased prefilter's, stay within the texels' range)."""
        return torch.sigmoid(self.logit_opacity) * torch.sigmoid(self.texture_alpha_logit).flatten(1).amax(1)

    def split_children(self, rows: dict[str, torch.Tensor], offsets: torch.Tensor,
                       shrink: float) -> dict[str, torch.Tensor]:
        """Each child's texture resampled from its parent's: the child's texel (r, c), centred at
        (u', v') = -R + (c + 1/2, r + 1/2) 2R/T, takes the parent's RGBA as the rasterizer samples it (bilinear, edge
        clamped) at the parent's (u, v) = offset + (u', v') / shrink. Alpha is interpolated as alpha, as the
        rasterizer does, and turned back into a logit clamped to alpha in [1e-6, 1 - 1e-6] (inverse_sigmoid), so
        the logits stay finite."""
        rows = dict(rows)
        rgb, logit = rows["texture_rgb"], rows["texture_alpha_logit"]
        m, size = rgb.shape[0], rgb.shape[1]
        centres = -TEXTURE_RADIUS + (torch.arange(size, dtype=rgb.dtype, device=rgb.device) + 0.5) * (
            2 * TEXTURE_RADIUS / size)
        v, u = torch.meshgrid(centres, centres, indexing="ij")  # [T,T]: texel (r, c) at (centres[c], centres[r])
        offsets = offsets.to(rgb)
        pu = offsets[:, 0, None] + u.reshape(1, -1) / shrink  # [M,T*T] in the parent's sigmas
        pv = offsets[:, 1, None] + v.reshape(1, -1) / shrink
        sampled = sample_texture(torch.cat([rgb, torch.sigmoid(logit)], -1), pu.T, pv.T)  # [T*T,M,4]
        sampled = sampled.transpose(0, 1).reshape(m, size, size, 4)
        rows["texture_rgb"] = sampled[..., :3]
        rows["texture_alpha_logit"] = inverse_sigmoid(sampled[..., 3:])
        return rows

    def draws_nothing(self) -> str | None:
        from ..rasterizers.common import SETTINGS

        why = super().draws_nothing()
        n = self.texture_alpha_logit.shape[0]
        if why is None and n:
            peak = self.effective_opacity().detach()
            if float(peak.max()) < SETTINGS.alpha_min:
                why = (f"texture_alpha_logit: every one of the {n} surfels has opacity x texture alpha below 1/255 at "
                       "all its texels, which the rasterizer skips: the model draws nothing and cannot learn (the run "
                       "diverged or the file was edited)")
        return why

    def summary(self) -> dict:
        with torch.no_grad():
            n = self.texture_rgb.shape[0]
            if n == 0:
                return {"texture_size": self.config.texture_size}
            rgb = self.texture_rgb.detach()
            # how far the textures stray from flat: the residual's RMS about each surfel's own mean, and alpha's
            spread = (rgb - rgb.mean(dim=(1, 2), keepdim=True)).pow(2).mean().sqrt().item()
            alpha = torch.sigmoid(self.texture_alpha_logit.detach())
            return {"texture_size": self.config.texture_size, "texture_rgb_rms": round(spread, 5),
                    "texture_alpha_mean": round(alpha.mean().item(), 4)}
