"""Appearance kinds written in Python, as a researcher would try one: each a function of the pairs' local (u, v), the
view direction and the surfel's own parameters, rendered and differentiated by splatzoo's reference backend.

wave-bank-py and texture-py say again what two built-in kinds say (csrc/surfel_math.h WaveBank, Texture), so a test
can hold them to the same renders and gradients; gabor-py is the gabor model rendered through wave-bank-py, for a
`splatzoo compare gabor-py gabor --backend reference`.
"""
import torch

from splatzoo import ModelSpec, Surfels
from splatzoo.models.gabor import GaborConfig, GaborModel
from splatzoo.rasterizers.reference import sample_texture
from splatzoo.registry import AppearanceKindSpec

WAVES = 4  # waves per surfel of wave-bank-py's parameters


def wave_bank(u, v, view_dirs, params):
    """sum_k a_k cos(k_k . (u, v) + phi_k), params [n,K,6] = (k_x, k_y, phi, a_r, a_g, a_b) per wave; no gain."""
    k, phi, amp = params[..., :2], params[..., 2], params[..., 3:]
    phase = u[..., None] * k[:, :, 0] + v[..., None] * k[:, :, 1] + phi  # [P,n,K]
    return torch.einsum("pnk,nkc->pnc", torch.cos(phase), amp), None


def texture(u, v, view_dirs, params):
    """params [n,T,T,4] RGBA texels over (u, v) in [-3, 3]^2 sigmas: rgb added, alpha the opacity gain."""
    sample = sample_texture(params, u, v)
    return sample[..., :3], sample[..., 3]


WAVE_BANK = AppearanceKindSpec("wave-bank-py", wave_bank, (WAVES, 6), "the wave bank, in Python (test fixture)")
TEXTURE = AppearanceKindSpec("texture-py", texture, (2, 2, 4), "a 2x2 RGBA texture, in Python (test fixture)")


class GaborPyModel(GaborModel):
    """gabor, its waves handed to the wave-bank-py kind instead of the built-in wave bank."""

    def surfels(self, camera):
        s = super().surfels(camera)
        params = torch.cat([s.wave_vectors, s.wave_phases[..., None], s.wave_amplitudes], -1)  # [N,K,6]
        empty = s.means.new_zeros
        n = s.num
        return Surfels(s.means, s.quats, s.scales, s.opacities, s.base_color, empty(n, 0, 2), empty(n, 0),
                       empty(n, 0, 3), appearance_kind="wave-bank-py", appearance_params=params)


GABOR_PY = ModelSpec("gabor-py", GaborPyModel, GaborConfig, "gabor through a Python appearance kind (test fixture)")
