"""Neural Gabor surfels: 2DGS surfels whose colour is a tiny per-surfel network.

Neural Gabor splatting (Watanabe and Umetani, "Neural Gabor Splatting: Enhanced Gaussian Splatting with Neural Gabor
for High-frequency Surface Reconstruction", CVPR 2026; public code haato-w/neural-gabor-splatting, on 2DGS) gives
every surfel a one-hidden-layer SIREN: inputs x = (u, v, d), the point's coordinates on the surfel and the view
direction, H = 6 hidden units with a sine activation, 3 outputs; 57 numbers per surfel at H = 6 (39 without the view
input, which stores no weights for it). Here:

    h_j = sin(omega (w1_j . x + b1_j)),   c(u, v) = max(0, b2 + sum_j w2_j h_j),

with (u, v) in sigmas (the contract's coordinates), d the unit direction from the camera centre to the surfel's
centre in world coordinates (one per surfel and view, as 2DGS evaluates spherical harmonics), and omega SIREN's
frequency factor on the first layer. The output is the colour, clamped at 0 as every model's.

One hidden layer with a sine is a bank of waves: with sin(t) = cos(t - pi/2) each hidden unit is the contract's wave
k_j = omega w1_j[u, v], phi_j = omega (w1_j[d] . d + b1_j) - pi/2, a_j = w2_j over the base colour b2, and its view
input shifts the wave's phase (and only the phase) from view to view. So the network runs in every rasterizer
through the wave kind (csrc/surfel_math.h): exact, differentiable through the same kernels, anti-aliased by the same
footprint gain (a wave's amplitude fades by exp(-k^T b k / 2) under the pixel footprint's blur b), exportable and
bakeable as waves. Without the view input it is a bank of H waves with free directions (gabor fans them at fixed
angles). What the release's rasterizer does beyond the formula above (its output activation, omega) is not in its
public repository; the choices here are splatzoo's, measured on the built-in scenes (BENCHMARKS.md, "neural-gabor"):
- omega = OMEGA: SIREN's usual 30 starts patterns far finer than a surfel can fit here, (u, v) being in sigmas over
  [-3, 3] (with the view input, 30 gave 20.9 dB on the quick sweater where 3 gave 24.7); without it 2, 3, 4, 6 and 8
  gave 24.9, 25.4, 25.9, 26.1 and 26.2 dB;
- the view input is off by default (`view_dependent`): a phase that moves with the view is not how colour changes
  with the view (it lost 0.6-0.8 dB on both the quick sweater and its specular twin at 21 training views, as if it
  fitted each view's phase on its own); `--view-dependent` gives the paper's network.

Start (the release's SIREN initialisation for the first layer, with our colour start): w1, b1 ~ U(-1/5, 1/5) (its 5
inputs), w2 = 0 and b2 the point colour, so every surfel starts as its 2DGS surfel. The release draws w2 over the
whole SIREN range, U(-sqrt(6/5), sqrt(6/5)), with a random b2; here a hidden unit starts colourless and grows where
the images ask for a pattern (its gradient is sin(...) x the colour's, nonzero with random w1 and b1), which beat a
faint random start on plain colour and fine texture alike (BENCHMARKS.md, "neural-gabor"). Learning rates: the
release's 2.5e-3 for w1, b1, w2; 2DGS's colour pace for b2 (gabor's base colour's). As gabor's waves, the hidden
units' colours w2 carry a small L1 penalty (`amplitude_l1`, gabor's `wave_l1`), so units the images do not ask for
fade and plain colour renders as 2DGS renders it. Densification: the release's frequency-aware densification (`--strategy
auto` picks "frequency" for this model; splatzoo/training/frequency.py) with a hard cap on the count (the trainer's
budget).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import nn

from ..errors import ShapeError
from ..types import MAX_WAVE_NUMBER, Camera, Surfels
from .base import SurfelModel, view_directions
from .gabor import BASE_COLOR_LR, WAVE_L1, sparse_l1

INIT_BOUND = 1 / 5       # w1, b1 ~ U(-INIT_BOUND, INIT_BOUND): SIREN's first layer, 1 / its 5 inputs
NETWORK_LR = 2.5e-3      # the release's rate for every network parameter
OMEGA = 8.0              # the first layer's frequency factor (module docstring)


@dataclass
class NeuralGaborConfig:
    hidden: int = field(default=6, metadata={"help": "hidden units of each surfel's network (the paper: 6)"})
    omega: float = field(default=OMEGA, metadata={
        "help": "SIREN's frequency factor on the first layer: a hidden unit's wave vector is omega x its (u, v) "
                "weights, in radians per sigma (larger: finer patterns within reach at the start, and faster)"})
    amplitude_l1: float = field(default=WAVE_L1, metadata={
        "help": "L1 penalty on the hidden units' colours (amplitude_l1 x their sum over surfels, for 2000 surfels, "
                "scaled by 2000 / the count), gabor's --wave-l1: units the images do not ask for decay, so plain "
                "colour renders as 2DGS renders it; 0: off"})
    view_dependent: bool = field(default=False, metadata={
        "help": "feed the view direction to the network (the paper's network; measured worse on the built-in scenes, "
                "see BENCHMARKS.md); off: colour depends on (u, v) only"})

    def __post_init__(self):
        if not 1 <= int(self.hidden) <= 32:
            raise ShapeError(f"hidden must be an integer from 1 to 32, got {self.hidden}")
        self.hidden = int(self.hidden)
        if not 0 < float(self.omega) <= 1000:
            raise ShapeError(f"omega must be a number in (0, 1000], got {self.omega}")
        if not 0 <= float(self.amplitude_l1) < math.inf:
            raise ShapeError(f"amplitude_l1 must be a finite number >= 0 (0: off), got {self.amplitude_l1}")


class NeuralGaborModel(SurfelModel):
    densify_strategy = "frequency"

    def __init__(self, config: NeuralGaborConfig, num_primitives: int = 0):
        super().__init__(config, num_primitives)
        n, h = num_primitives, config.hidden
        inputs = 5 if config.view_dependent else 2
        self.net_w1 = nn.Parameter(torch.zeros(n, h, inputs))  # per hidden unit: weights on u, v (, d_x, d_y, d_z)
        self.net_b1 = nn.Parameter(torch.zeros(n, h))
        self.net_w2 = nn.Parameter(torch.zeros(n, h, 3))       # per hidden unit: its colour (the output layer)
        self.net_b2 = nn.Parameter(torch.zeros(n, 3))          # the output bias: the surfel's base colour

    def init_from_points(self, points, colors, generator):
        self.init_geometry(points, generator)
        n, h, inputs = self.net_w1.shape
        self.net_w1.copy_(INIT_BOUND * (2 * torch.rand(n, h, inputs, generator=generator) - 1))
        self.net_b1.copy_(INIT_BOUND * (2 * torch.rand(n, h, generator=generator) - 1))
        self.net_w2.zero_()  # colourless hidden units: the start renders as the 2DGS surfel
        self.net_b2.copy_(colors)

    def hidden_inputs(self, camera: Camera) -> torch.Tensor:
        """[N,H] each hidden unit's pre-activation less its (u, v) term, omega (w1[d] . d + b1): a per-surfel
        constant for this view."""
        pre = self.net_b1
        if self.config.view_dependent:
            d = view_directions(self.means, camera)
            pre = pre + (self.net_w1[..., 2:] * d[:, None, :]).sum(-1)
        return float(self.config.omega) * pre

    def network_color(self, uv: torch.Tensor, camera: Camera) -> torch.Tensor:
        """[N,P,3] the network evaluated as written (no waves) at points uv [N,P,2] of each surfel, clamped at 0:
        what surfels() hands the rasterizer, stated directly (tests compare the two)."""
        omega = float(self.config.omega)
        t = omega * (uv[:, :, None, :] * self.net_w1[:, None, :, :2]).sum(-1) + self.hidden_inputs(camera)[:, None]
        return (self.net_b2[:, None] + (torch.sin(t)[..., None] * self.net_w2[:, None]).sum(2)).clamp_min(0)

    def surfels(self, camera: Camera) -> Surfels:
        g = self.geometry()
        omega = float(self.config.omega)
        # wave numbers stop where every rasterizer still agrees (types.MAX_WAVE_NUMBER radians per sigma)
        limit = MAX_WAVE_NUMBER * (1 - 1e-5)
        vectors = (omega * self.net_w1[..., :2]).clamp(-limit, limit)
        phases = self.hidden_inputs(camera) - math.pi / 2  # sin(t) = cos(t - pi/2)
        return Surfels(g["means"], g["quats"], g["scales"], g["opacities"], self.net_b2, vectors, phases, self.net_w2)

    def split_children(self, rows, offsets, shrink):
        """A child at `offsets` (parent sigmas), sigmas / shrink: the parent's (u, v) = offsets + (u', v') / shrink, so
        the (u, v) weights divide by shrink and each hidden unit's bias takes w1[u, v] . offsets."""
        w1 = rows["net_w1"].clone()
        rows = dict(rows)
        rows["net_b1"] = rows["net_b1"] + (w1[..., :2] * offsets[:, None, :].to(w1)).sum(-1)
        w1[..., :2] = w1[..., :2] / shrink
        rows["net_w1"] = w1
        return rows

    def optim_groups(self, scene_extent: float) -> list[dict]:
        return self.geometry_groups(scene_extent) + [
            {"name": name, "params": [getattr(self, name)], "lr": NETWORK_LR}
            for name in ("net_w1", "net_b1", "net_w2")] + [
            {"name": "net_b2", "params": [self.net_b2], "lr": BASE_COLOR_LR}]

    def regulariser(self) -> torch.Tensor | None:
        """amplitude_l1 x the sum of |w2| scaled by WAVE_L1_COUNT / the count: gabor's sparse waves (see
        GaborModel.regulariser), for the hidden units' colours."""
        if float(self.config.amplitude_l1) <= 0:
            return None
        return sparse_l1(self.net_w2, float(self.config.amplitude_l1), self.num_primitives)

    def summary(self) -> dict:
        with torch.no_grad():
            if self.net_w1.shape[0] == 0:
                return {}
            # how fine the surfels' patterns are: the median wave number, and how much colour the waves carry
            k = float(self.config.omega) * self.net_w1[..., :2].norm(dim=-1)
            amplitude = self.net_w2.abs().amax(-1)
            return {"wave_number_median": round(float(k.median()), 3),
                    "amplitude_mean": round(float(amplitude.mean()), 4)}
