"""3D Gabor surfels (the paper) and its ablation baselines A, B, C.

Colour inside a surfel with N waves at fixed orientations theta_i,
t_i = 2 pi f_i (cos theta_i, sin theta_i).(u,v) + phi_i (f in cycles per sigma), in one of two parametrisations
(`color_param`):
- "residual" (default): c(u,v) = c0 + sum_i w_i d cos t_i. The base colour c0 is a 2DGS surfel's colour and moves at
  2DGS's pace; the waves share one colour difference d and are a residual around c0. A surfel whose waves have died
  out is exactly a 2DGS surfel, so on plain colour gabor trains as 2DGS does.
- "paper": c(u,v) = sum_i w_i [cA (1 + cos t_i)/2 + cB (1 - cos t_i)/2]
                  = (sum_i w_i)(cA + cB)/2 + sum_i w_i (cA - cB)/2 cos t_i,
  the paper's, where the weights scale the base colour too.
- "per-wave": c(u,v) = c0 + sum_i w_i cos t_i with w_i an RGB amplitude of its own per wave: "residual" without the
  shared difference d, so crossing stripes of different colours (a tartan) fit on one surfel. One wave stores 5 values
  (3 amplitudes, frequency, phase) against residual's 3 plus the 3 of d a surfel with waves stores, so a surfel with
  one wave is smaller too.
Each is the rasterizer's wave bank with k_i = 2 pi f_i (cos theta_i, sin theta_i) and amplitudes a_i = w_i d
(d = (cA - cB)/2 for "paper"; "per-wave": a_i = w_i).

Two options beyond the paper:
- prune_waves, prune_relative or prune_psnr > 0 (adaptive waves): during training, waves whose visible contribution
  falls below a threshold are removed, so a surfel on flat colour ends as a plain 2DGS surfel. The threshold is fixed
  (prune_waves), a fraction of the recent training error (prune_relative), or measured (prune_psnr): the largest
  whose pruning costs the trainer's probe views at most that many dB, found by rendering them with and without the
  faintest waves (the `gabor-adaptive` model: 8 orientations to start, prune_psnr late in the run). A wave's
  contribution is what its surfel shows
  of it beyond a constant: opacity x the RMS, over the surfel's Gaussian, of the wave's zero-mean part (largest
  channel). Its mean over the Gaussian, a cos(phi) exp(-|k|^2/2) (the Gaussian's characteristic function), is kept,
  so removing a wave leaves each surfel's mean colour exactly as it was: "residual" adds it to c0; "paper" folds it
  into two per-surfel weights on cA and cB (`folded_weights`). Active waves are packed to the front of each surfel's
  row (`wave_index` keeps each slot's orientation) and `wave_counts` tells the rasterizer how many to evaluate. A surfel
  with no wave left becomes a 2DGS surfel: its colour is c0 (color_base; "paper": color_a alone) and d (color_diff;
  "paper": color_b and the folded weights) is zero and receives no gradient. Checkpoints store active waves only
  (packed: each surfel's wave count in unary bits, so a wave-less surfel adds one bit to a 2DGS surfel's bytes, and
  for the fan each waved surfel's orientations as a bit mask) and, for wave-less surfels, only the base colour.
- sh_degree > 0: a view-dependent spherical-harmonics term (degree >= 1 bands, no DC) added to the base colour.
- free_directions: each wave learns its direction too: wave_freqs holds a 2D vector in cycles per sigma (the wave
  vector k / 2 pi), started along its slot's orientation, instead of a frequency along that fixed orientation. One
  more value a wave; a pattern at any angle is fitted without the fan's 22.5 degree steps (8 orientations).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from ..errors import ShapeError, SplatzooError
from ..geometry import SH_C0, eval_sh, num_sh_bases
from ..types import MAX_WAVE_NUMBER, Camera, Surfels
from .base import SurfelModel, restart_moments, view_directions

INIT_OFFSET = 0.05  # init="surfel": half the colour difference cA - cB, per channel, at most
# color_param="residual": the base colour's rate is 2DGS's (2.5e-3 on its SH DC coefficient, in colour units x SH_C0)
BASE_COLOR_LR = 2.5e-3 * SH_C0
# the default sparse-wave penalty: the smallest of those measured that keeps plain colour as 2DGS renders it (LPIPS
# within 0.002 over white, three seeds) and costs fine texture least (BENCHMARKS.md, "Sparse waves by default")
WAVE_L1 = 3e-6
WAVE_L1_COUNT = 2000  # ... chosen with this many surfels (wave_l1_per_count scales it by this / the surfel count)
COLOR_PARAMS = ("residual", "paper", "per-wave")


def sparse_l1(weights: torch.Tensor, strength: float, count: int, per_count: bool = True) -> torch.Tensor:
    """strength x the sum of |weights|, scaled by WAVE_L1_COUNT / count with `per_count` (the sparse-wave penalty
    of gabor's waves and neural-gabor's hidden units; GaborModel.regulariser says why it scales)."""
    if per_count:
        strength *= WAVE_L1_COUNT / max(count, 1)
    return strength * weights.abs().sum()


PRUNE_RAMP = 0.8  # the pruning threshold reaches its full value after this fraction of the pruning period
MEASURED_PRUNINGS = 8  # prune_psnr: about this many measured prunings over the pruning period (and one at the end)
BISECTION_STEPS = 7    # prune_psnr: the share of waves removed is found to 1/2^this of the active waves
# frequencies stop where every rasterizer still agrees (types.MAX_WAVE_NUMBER radians per sigma), in cycles per sigma;
# float's products may round up
FREQ_LIMIT = MAX_WAVE_NUMBER / (2 * math.pi) * (1 - 1e-5)
DAMAGED = "the file is damaged: save the model again"  # what a packed-wave layout's errors tell the user to do
WAVE_LR = 1e-3  # the learning rate of gabor's and gabor-adaptive's wave frequencies and phases (GaborConfig.wave_lr)


@dataclass
class GaborConfig:
    n_waves: int = field(default=4, metadata={"help": "number of wave orientations per surfel (fan at i*pi/N)"})
    color_param: str = field(default="residual", metadata={
        "help": "residual: colour = base + sum_i w_i d cos(t_i), the base a 2DGS surfel's colour at 2DGS's rate and "
                "the waves a residual around it (never worse than 2DGS on plain colour); paper: the paper's "
                "sum_i w_i [cA (1 + cos t_i)/2 + cB (1 - cos t_i)/2], started as --init says; per-wave: residual with "
                "an RGB amplitude for each wave instead of one d a surfel (stripes of different colours on one surfel; "
                "a one-wave surfel stores 5 values for its wave against residual's 6); see BENCHMARKS.md"})
    sh_degree: int = field(default=0, metadata={"help": "spherical-harmonics degree (0..3) of a view-dependent term "
                                                        "added to the base colour; 0: view-independent (the paper)"})
    prune_waves: float = field(default=0.0, metadata={
        "help": "adaptive waves: during training remove waves whose visible contribution (opacity x RMS of the "
                "wave over its surfel, colour units for images in [0,1]) is below this, e.g. 0.01; 0 keeps every wave"})
    prune_relative: float = field(default=0.0, metadata={
        "help": "adaptive waves with a threshold relative to the fit: remove waves whose visible contribution is "
                "below this multiple of the recent mean absolute training error on the covered pixels, e.g. 2 (a "
                "scene fitted to 40 dB keeps fainter waves than one at 25 dB); instead of --prune-waves"})
    prune_psnr: float = field(default=0.0, metadata={
        "help": "adaptive waves by their measured worth: at each pruning remove the faintest waves (by visible "
                "contribution) as long as the training views' PSNR drops by at most this many dB, measured by "
                "rendering a few of them with and without, e.g. 0.02; instead of --prune-waves or --prune-relative"})
    init: str = field(default="paper", metadata={
        "help": "the start of --color-param paper: paper (the public release's: cA = point colour, cB = 0, weights "
                "0.1 U(0,1), a dark start) or surfel (the 2DGS surfel it would be: weights 1/N, cA and cB the point "
                "colour +- a small offset); see BENCHMARKS.md"})
    wave_l1: float = field(default=WAVE_L1, metadata={
        "help": "L1 penalty on the residual waves' weights (wave_l1 x their sum over surfels and waves, added to the "
                "loss; for 2000 surfels, see --wave-l1-per-count): waves the images do not ask for decay to zero, so "
                "plain colour looks as 2DGS's does (LPIPS) while fine texture keeps its waves; see BENCHMARKS.md. "
                "0: off. color_param=residual only (in the paper's form the weights carry the base colour too)"})
    wave_l1_per_count: bool = field(default=True, metadata={
        "help": "scale --wave-l1 by 2000 / the surfel count (2000: the count it was chosen at), so that the pull "
                "against the images' gradient, which shrinks with the pixels each surfel covers, does not grow as "
                "densification multiplies the surfels; off: the same strength at any count"})
    free_directions: bool = field(default=False, metadata={
        "help": "each wave learns its direction: a 2D wave vector (started along its orientation of the fan) instead "
                "of a frequency along a fixed orientation; one more stored value a wave"})
    prune_from: float = field(default=0.5, metadata={
        "help": "adaptive waves (any --prune-* option): fraction of the iterations before the first pruning "
                "(waves need time to grow; with densification on, pruning also waits until the last opacity reset "
                "has recovered)"})
    wave_lr: float = field(default=WAVE_LR, metadata={
        "help": "learning rate of the waves' frequencies and phases (Adam; about the most one moves a step: cycles per "
                "sigma, radians): a wave must travel from its start to the stripes it fits within the run"})
    fit_waves: float = field(default=0.0, metadata={
        "help": "fraction of the run after which every surfel's waves are replaced by the stripes the training "
                "photos show on its plane (found by matching pursuit; training/wave_fit.py), 0: never; free "
                "directions with color_param per-wave only"})

    # what a stored config written before an option existed meant: files from before `color_param` are "paper" models,
    # files from before the sparse-wave default trained without the penalty, and those from before
    # wave_l1_per_count with the same strength at any count
    stored_defaults: ClassVar[dict] = {"color_param": "paper", "wave_l1": 0.0, "wave_l1_per_count": False}

    def __post_init__(self):
        if int(self.n_waves) < 1:
            raise ShapeError(f"n_waves must be at least 1, got {self.n_waves} (use the 2dgs model for no waves)")
        if int(self.n_waves) > 30:
            raise ShapeError(f"n_waves must be at most 30 (orientations are stored as a bit mask), got {self.n_waves}")
        if not 0 <= int(self.sh_degree) <= 3:
            raise ShapeError(f"sh_degree must be 0, 1, 2 or 3, got {self.sh_degree}")
        if not float(self.prune_waves) >= 0:
            raise ShapeError(f"prune_waves must be >= 0 (0: off), got {self.prune_waves}")
        if not 0 <= float(self.wave_l1) < math.inf:
            raise ShapeError(f"wave_l1 must be a finite number >= 0 (0: off), got {self.wave_l1}")
        if not float(self.prune_relative) >= 0:
            raise ShapeError(f"prune_relative must be >= 0 (0: off), got {self.prune_relative}")
        if not 0 <= float(self.prune_psnr) < math.inf:
            raise ShapeError(f"prune_psnr must be a finite number of dB >= 0 (0: off), got {self.prune_psnr}")
        if sum(float(v) > 0 for v in (self.prune_waves, self.prune_relative, self.prune_psnr)) > 1:
            raise ShapeError("give one pruning criterion: prune_waves (fixed, colour units), prune_relative (a "
                             "fraction of the training error) or prune_psnr (a measured PSNR cost), not two")
        if self.color_param not in COLOR_PARAMS:
            raise ShapeError(f"color_param must be {', '.join(COLOR_PARAMS)}, got {self.color_param!r}")
        if self.init not in ("surfel", "paper"):
            raise ShapeError(f"init must be surfel or paper, got {self.init!r}")
        # the model's own default (beta-gabor's is twice gabor's) is nobody's request: the paper's colours
        # leave it unused
        own_default = next(f.default for f in dataclasses.fields(self) if f.name == "wave_l1")
        if self.color_param == "paper" and float(self.wave_l1) not in (0.0, own_default):
            raise ShapeError("wave_l1 applies to color_param=residual only: in the paper's form the wave weights carry "
                             "the base colour too, so shrinking them would darken the surfel")
        if self.color_param != "paper" and self.init != "paper":
            raise ShapeError(f"init={self.init!r} starts the paper's colour parametrisation; add color_param=paper "
                             f"(--color-param paper), or drop it: {self.color_param} has its own start")
        if not 0 <= float(self.prune_from) <= 1:
            raise ShapeError(f"prune_from is a fraction of the run in [0, 1], got {self.prune_from}")
        if not 0 < float(self.wave_lr) <= 1:
            raise ShapeError(f"wave_lr must be a learning rate in (0, 1], got {self.wave_lr}")
        if not 0 <= float(self.fit_waves) < 1:
            raise ShapeError(f"fit_waves is a fraction of the run in [0, 1) (0: never), got {self.fit_waves}")
        if float(self.fit_waves) > 0 and not (self.free_directions and self.color_param == "per-wave"):
            raise ShapeError(f"fit_waves (here {self.fit_waves}) sets each wave's vector and colour, so it needs free "
                             "directions (--free-directions) and a colour a wave (--color-param per-wave); for the "
                             "fan or another colour form add --fit-waves 0")


@dataclass
class AdaptiveGaborConfig(GaborConfig):
    """gabor-adaptive: gabor whose waves stay only where they pay. It starts with twice the default orientations (the
    built-in textured scenes gain up to 8) and removes waves by measured cost, late in the run: pruned at half-way,
    waves that would have grown to matter are gone and the fit loses up to 0.16 dB (BENCHMARKS.md)."""
    n_waves: int = field(default=8, metadata={"help": "wave orientations per surfel at the start (fan at i*pi/N)"})
    prune_psnr: float = field(default=0.02, metadata={
        "help": "each pruning removes the faintest waves while the training views lose at most this many dB"})
    prune_from: float = field(default=0.8, metadata={"help": "fraction of the iterations before the first pruning"})


@dataclass
class BaselineAConfig(GaborConfig):
    n_waves: int = field(default=1, metadata={"help": "number of waves (Baseline A of the paper uses 1)"})


class GaborModel(SurfelModel):
    """The paper's model: waves fanned at i*pi/N, learnable frequency, weight and phase."""

    orientation = "fan"   # "fan": theta_i = i pi / N; "u": every wave along the local u axis
    learn_phase = True
    primitive_buffers = ("wave_counts", "wave_index", "folded_weights")  # present only for adaptive waves
    # packed checkpoints of splatzoo 0.1.0 (_upgrade_single_fold), and files written before the unary wave counts
    # (a bit mask for every surfel, free directions too)
    legacy_state_keys = ("folded_weight", "wave_mask")
    # the PLY properties of the colours and waves (see SplatModel.ply_prefixes): gabor_weight_0, ...
    ply_prefixes = {
        "color_a": "gabor_color_a_", "color_b": "gabor_color_b_", "color_base": "gabor_color_base_",
        "color_diff": "gabor_color_diff_", "wave_weights": "gabor_weight_", "wave_freqs": "gabor_freq_",
        "wave_phases": "gabor_phase_"}

    def __init__(self, config: GaborConfig, num_primitives: int = 0):
        super().__init__(config, num_primitives)
        n, k = num_primitives, config.n_waves
        if self.residual:
            self.color_base = nn.Parameter(torch.zeros(n, 3))
            if not self.per_wave:  # per-wave: each wave holds its own colour
                self.color_diff = nn.Parameter(torch.zeros(n, 3))
        else:
            self.color_a = nn.Parameter(torch.zeros(n, 3))
            self.color_b = nn.Parameter(torch.zeros(n, 3))
        self.wave_weights = nn.Parameter(torch.zeros((n, k, 3) if self.per_wave else (n, k)))
        self.wave_freqs = nn.Parameter(torch.zeros((n, k, 2) if config.free_directions else (n, k)))
        if self.learn_phase:
            self.wave_phases = nn.Parameter(torch.zeros(n, k))
        if config.sh_degree > 0:
            self.sh_rest = nn.Parameter(torch.zeros(n, num_sh_bases(config.sh_degree) - 1, 3))
        if self.adaptive:
            if not self.residual:
                # removed waves' mean colour as weights on cA and cB: bookkeeping, not trained (until the first
                # pruning the model is exactly gabor-K)
                self.register_buffer("folded_weights", torch.zeros(n, 2))
            self.register_buffer("wave_counts", torch.full((n,), k, dtype=torch.int32), persistent=False)
            self.register_buffer("wave_index", torch.arange(k).repeat(n, 1), persistent=False)
        angles = torch.arange(k) * math.pi / k if self.orientation == "fan" else torch.zeros(k)
        self.register_buffer("directions", torch.stack([angles.cos(), angles.sin()], -1), persistent=False)

    @property
    def adaptive(self) -> bool:
        c = self.config
        return float(c.prune_waves) > 0 or float(c.prune_relative) > 0 or float(c.prune_psnr) > 0

    @property
    def residual(self) -> bool:
        """The base colour c0 is a parameter of its own and the waves a residual around it ("residual", "per-wave")."""
        return self.config.color_param in ("residual", "per-wave")

    @property
    def free_directions(self) -> bool:
        """wave_freqs holds each wave's 2D vector in cycles per sigma ([N,width,2]), not a frequency along its slot."""
        return bool(self.config.free_directions)

    @property
    def per_wave(self) -> bool:
        """Each wave's weight is an RGB amplitude of its own ([N,width,3]) instead of a scale on one shared d."""
        return self.config.color_param == "per-wave"

    @property
    def variable_width(self) -> tuple[str, ...]:
        """[N, width] tensors whose stored width pruning trims (export reads the width back from the file)."""
        return tuple(self.wave_parameter_names) + ("wave_index",) if self.adaptive else ()

    @property
    def wave_parameter_names(self) -> list[str]:
        return ["wave_weights", "wave_freqs"] + (["wave_phases"] if self.learn_phase else [])

    def init_from_points(self, points, colors, generator):
        """color_param="residual": the 2DGS surfel of the point (c0 = point colour) with the release's waves around it:
        d = half the point colour, w = 0.1 U(0,1), so each wave starts as the release's does.
        color_param="paper" with init="paper" (its default), as the public release: cA = point colour, cB = black,
        w = 0.1 U(0,1). init="surfel": the 2DGS surfel of the point, waves as a small residual: w = 1/N (so the base
        colour (sum w)(cA + cB)/2 is the point colour) and cA, cB = colour +- d with d ~ INIT_OFFSET U(-1,1) per
        channel (each wave's amplitude w (cA - cB)/2 = d/N). All: f = U(0,1) cycles per sigma, phi = U(0,1)."""
        self.init_geometry(points, generator)
        n, k = self.wave_weights.shape[:2]
        if self.per_wave:  # residual's start: each wave's amplitude w d with d half the point colour
            self.color_base.copy_(colors)
            self.wave_weights.copy_(0.1 * torch.rand(n, k, generator=generator)[..., None] * (colors / 2)[:, None])
        elif self.residual:
            self.color_base.copy_(colors)
            self.color_diff.copy_(colors / 2)
            self.wave_weights.copy_(0.1 * torch.rand(n, k, generator=generator))
        elif self.config.init == "paper":
            self.color_a.copy_(colors)
            self.color_b.zero_()
            self.wave_weights.copy_(0.1 * torch.rand(n, k, generator=generator))
        else:
            offset = INIT_OFFSET * (2 * torch.rand(n, 3, generator=generator) - 1)
            self.color_a.copy_(colors + offset)
            self.color_b.copy_(colors - offset)
            self.wave_weights.fill_(1.0 / k)
        freqs = torch.rand(n, k, generator=generator)
        self.wave_freqs.copy_(freqs[..., None] * self.directions if self.free_directions else freqs)
        if self.learn_phase:
            self.wave_phases.copy_(torch.rand(n, k, generator=generator))

    def phases(self) -> torch.Tensor:
        return self.wave_phases if self.learn_phase else self.wave_weights.new_zeros(self.wave_weights.shape[:2])

    def active_slots(self) -> torch.Tensor:
        """bool [N, width]: which stored wave slots are in use."""
        w = self.wave_weights
        if not self.adaptive:
            return torch.ones(w.shape[:2], dtype=torch.bool, device=w.device)
        return torch.arange(w.shape[1], device=w.device)[None] < self.wave_counts[:, None]

    def half_difference(self) -> torch.Tensor:
        """[N,3] d: the colour every wave of a surfel scales by its weight (amplitude a_i = w_i d)."""
        return self.color_diff if self.residual else (self.color_a - self.color_b) / 2

    def amplitudes(self) -> torch.Tensor:
        """[N,width,3] each wave's RGB amplitude a_i: w_i d, or w_i itself ("per-wave")."""
        if self.per_wave:
            return self.wave_weights
        return self.wave_weights[..., None] * self.half_difference()[:, None, :]

    def wave_vectors(self, freqs: torch.Tensor | None = None, index: torch.Tensor | None = None) -> torch.Tensor:
        """[N,width,2] each wave's vector k in radians per sigma, as rendered, from `freqs` (default wave_freqs) and
        the slots' orientations `index` (default wave_index): 2 pi f along the slot's orientation, f clamped to
        FREQ_LIMIT; free directions: 2 pi times the stored vector, its length clamped to FREQ_LIMIT."""
        f = self.wave_freqs if freqs is None else freqs
        if self.free_directions:
            return (2 * math.pi) * f * (FREQ_LIMIT / f.norm(dim=-1, keepdim=True).clamp_min(FREQ_LIMIT))
        directions = self.directions.to(f)
        if self.adaptive:
            directions = directions[self.wave_index if index is None else index]  # each slot's own orientation
        return (2 * math.pi) * f.clamp(-FREQ_LIMIT, FREQ_LIMIT)[..., None] * directions

    def _wave_number_sq(self) -> torch.Tensor:
        """[N,width] |k|^2 of each wave (unclamped, as the statistics have always read it)."""
        k2 = (2 * math.pi * self.wave_freqs) ** 2
        return k2.sum(-1) if self.free_directions else k2

    def surfels(self, camera: Camera) -> Surfels:
        g = self.geometry()
        w = self.wave_weights
        counts = self.wave_counts if self.adaptive else None
        if self.residual:
            base = self.color_base
        elif self.adaptive:
            # written so that, before any pruning (all slots active, folded weights 0), every operation rounds as
            # in gabor-K's expression below: the two runs stay bit-identical until the first pruning
            base = (w * self.active_slots()).sum(1, keepdim=True) * (self.color_a + self.color_b) / 2
            base = base + self.folded_weights[:, :1] * self.color_a + self.folded_weights[:, 1:] * self.color_b
            base = torch.where((self.wave_counts == 0)[:, None], self.color_a, base)  # wave-less: a 2DGS surfel
        else:
            base = w.sum(1, keepdim=True) * (self.color_a + self.color_b) / 2
        if self.config.sh_degree > 0:
            # bands >= 1 only: the DC term is the Gabor base colour itself
            coeffs = torch.cat([self.sh_rest.new_zeros(self.sh_rest.shape[0], 1, 3), self.sh_rest], 1)
            base = base + eval_sh(self.config.sh_degree, coeffs, view_directions(self.means, camera))
        amplitudes = self.amplitudes()
        vectors = self.wave_vectors()
        return Surfels(g["means"], g["quats"], g["scales"], g["opacities"], base, vectors, self.phases(), amplitudes,
                       wave_counts=counts)

    def split_children(self, rows: dict[str, torch.Tensor], offsets: torch.Tensor,
                       shrink: float) -> dict[str, torch.Tensor]:
        """Each child's waves in its own frame. At the child's (u', v') its parent's wave reads
        cos(k.(offset + (u', v')/shrink) + phi) = cos((k/shrink).(u', v') + phi + k.offset): the child's frequencies
        are the parent's / shrink and its phases phi + k.offset (wrapped to [-pi, pi)), with k the wave vector as
        rendered (frequency clamped as in surfels()). Amplitudes, base colour and SH are constant over (u, v).

        Without a learned phase (baseline C) the shift cannot be stored; each wave's weight becomes w cos(k.offset)
        instead, the zero-phase wave closest to the shifted one over the child's Gaussian (least squares: the
        projection of cos(x + c) on cos(x) under x = k'.(u', v'), (u', v') ~ N(0, I), is cos(c) exactly), which
        also keeps the child's mean colour. In the paper's colours the weights scale the base colour as well: the
        weight taken from a wave, w (1 - cos c), is folded into the base colour as removed waves are (half on cA,
        half on cB) where the model keeps folded weights (adaptive waves); without them the weights stay and only
        the frequencies follow (the pattern is then shifted by the child's offset)."""
        rows = dict(rows)
        if self.free_directions:
            vectors = self.wave_vectors(rows["wave_freqs"])  # [M,width,2]
            shift = (vectors * offsets.to(vectors)[:, None, :]).sum(-1)  # k.offset [M,width]
            rows["wave_freqs"] = vectors / (2 * math.pi * shrink)
        else:
            freqs = rows["wave_freqs"].clamp(-FREQ_LIMIT, FREQ_LIMIT)  # [M,width]
            directions = self.directions.to(freqs)
            directions = directions[rows["wave_index"]] if self.adaptive else directions.expand(freqs.shape[0], -1, -1)
            shift = 2 * math.pi * freqs * (directions * offsets.to(freqs)[:, None, :]).sum(-1)  # k.offset [M,width]
            rows["wave_freqs"] = freqs / shrink
        if self.learn_phase:
            rows["wave_phases"] = torch.remainder(rows["wave_phases"] + shift + math.pi, 2 * math.pi) - math.pi
            return rows
        w, c = rows["wave_weights"], torch.cos(shift)
        if self.per_wave:
            rows["wave_weights"] = w * c[..., None]
        elif self.residual:
            rows["wave_weights"] = w * c
        elif self.adaptive:
            rows["wave_weights"] = w * c
            rows["folded_weights"] = rows["folded_weights"] + (w * (1 - c)).sum(1, keepdim=True) / 2
        return rows

    def optim_groups(self, scene_extent: float) -> list[dict]:
        if self.per_wave:
            color_groups = [{"name": "color_base", "params": [self.color_base], "lr": BASE_COLOR_LR}]
        elif self.residual:
            color_groups = [{"name": "color_base", "params": [self.color_base], "lr": BASE_COLOR_LR},
                            {"name": "color_diff", "params": [self.color_diff], "lr": 2.5e-3}]
        else:
            color_groups = [{"name": "color_a", "params": [self.color_a], "lr": 2.5e-3},
                            {"name": "color_b", "params": [self.color_b], "lr": 2.5e-3}]
        groups = self.geometry_groups(scene_extent) + color_groups + [
            {"name": "wave_weights", "params": [self.wave_weights], "lr": 1e-3},
            {"name": "wave_freqs", "params": [self.wave_freqs], "lr": float(self.config.wave_lr)},
        ]
        if self.learn_phase:
            groups.append({"name": "wave_phases", "params": [self.wave_phases], "lr": float(self.config.wave_lr)})
        if self.config.sh_degree > 0:
            groups.append({"name": "sh_rest", "params": [self.sh_rest], "lr": 2.5e-3 / 20})  # 2DGS's SH rest rate
        return groups

    def regulariser(self) -> torch.Tensor | None:
        """wave_l1 x the sum of |wave weight| (removed waves' slots hold zeros): Adam turns its constant pull into
        steps toward zero wherever the images' gradient does not hold a wave up. None for the paper's colours.
        wave_l1_per_count: the strength scaled by WAVE_L1_COUNT / the surfel count. A wave's gradient from the
        images grows with the pixels its surfel covers, about 1/count of the object's, so the pull against it stays
        what it was at WAVE_L1_COUNT surfels when densification multiplies them."""
        if float(self.config.wave_l1) <= 0 or not self.residual:
            return None
        return sparse_l1(self.wave_weights, float(self.config.wave_l1), self.num_primitives,
                         per_count=self.config.wave_l1_per_count)

    # --- adaptive waves ---------------------------------------------------------------------------------------
    def on_step(self, step: int, train_config, optimizer) -> dict | None:
        """Prune at the densification cadence once `prune_from` of the run has passed (and, with densification on,
        once opacity has recovered from the last reset: right after a reset every wave looks faint). The threshold
        ramps up from 0 over most of the remaining run: a wave still growing is not cut for being small early."""
        if not self.adaptive:
            return None
        cfg = train_config
        if getattr(cfg, "max_bytes", None) and float(self.config.prune_psnr) > 0:
            return None  # under a byte budget the measured pruning runs at each shedding (shed_free)
        first = float(self.config.prune_from) * cfg.iterations
        if cfg.densify:
            first = max(first, cfg.at(cfg.densify_until) + cfg.at(cfg.opacity_reset_interval) // 2)
        every = max(cfg.at(cfg.densify_interval), 10)
        measured = float(self.config.prune_psnr) > 0
        if measured:  # each pruning renders the probe views several times: fewer, larger prunings
            every = max(every, math.ceil((cfg.iterations - first) / MEASURED_PRUNINGS))
        if step < first or (step % every and step != cfg.iterations):
            return None
        if measured:
            if self.probe_error is None:
                return None
            return self.prune_waves(self.measured_threshold(float(self.config.prune_psnr)), optimizer)
        ramp = PRUNE_RAMP * (cfg.iterations - first)
        fraction = 1.0 if ramp <= 0 else min(1.0, (step - first) / ramp)
        return self.prune_waves(fraction * self.prune_threshold(), optimizer)

    def prune_threshold(self) -> float:
        """The full pruning threshold now: prune_waves, or prune_relative x the recent training error (0, pruning
        nothing, before the trainer has measured one)."""
        if float(self.config.prune_relative) > 0:
            return float(self.config.prune_relative) * (self.recent_error or 0.0)
        return float(self.config.prune_waves)

    @torch.no_grad()
    def measured_threshold(self, tolerance_db: float) -> float:
        """The contribution threshold (wave_statistics) that removes the most waves, faintest first, while the
        trainer's probe views lose at most tolerance_db of PSNR: a bisection over the number removed, each trial
        rendered with those waves removed as prune_waves would remove them (their mean colour kept)."""
        mean, contribution = self.wave_statistics()
        on = self.active_slots()
        levels = contribution[on].sort().values
        n = levels.numel()
        if n == 0:
            return 0.0
        allowed = self.probe_error(self.surfels) * 10 ** (tolerance_db / 10)

        def threshold(j):  # removes the j faintest (fewer where contributions tie)
            return math.inf if j >= n else float(levels[j])

        def affordable(j):
            removed = on & (contribution < threshold(j))
            return self.probe_error(lambda camera: self._surfels_without(camera, removed, mean)) <= allowed

        lo, hi = 0, n  # removing lo waves is affordable; more than hi is not known to be
        for _ in range(BISECTION_STEPS):
            if lo >= hi:
                break
            mid = (lo + hi + 1) // 2
            if affordable(mid):
                lo = mid
            else:
                hi = mid - 1
        return threshold(lo) if lo > 0 else 0.0

    def _surfels_without(self, camera: Camera, removed: torch.Tensor, mean: torch.Tensor) -> Surfels:
        """surfels(camera) with the `removed` wave slots ([N,width] bool) gone and their mean colour ([N,width,3],
        wave_statistics) in the base colour: what prune_waves would leave, in either colour form."""
        s = self.surfels(camera)
        return dataclasses.replace(s, base_color=s.base_color + (mean * removed[..., None]).sum(1),
                                   wave_amplitudes=s.wave_amplitudes * (~removed)[..., None])

    def _mean_cos(self) -> torch.Tensor:
        """[N,width]: cos(k.(u,v) + phi) averaged over u,v ~ N(0, I), = cos(phi) e^{-|k|^2/2}."""
        return torch.cos(self.phases()) * torch.exp(-self._wave_number_sq() / 2)

    @torch.no_grad()
    def wave_statistics(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, contribution) of every stored wave slot, [N,width,3] and [N,width].

        Over the surfel's Gaussian (u,v ~ N(0,I) in sigma units) the wave a cos(k.(u,v) + phi) has mean
        a cos(phi) e^{-|k|^2/2} and second moment a^2 (1 + cos(2 phi) e^{-2|k|^2}) / 2. contribution = opacity x the
        standard deviation (largest channel): how far the wave moves the surfel's colour away from its mean."""
        phi, k2 = self.phases(), self._wave_number_sq()
        amp = self.amplitudes()  # [N,width,3]
        mean = amp * self._mean_cos()[..., None]
        second = amp ** 2 * ((1 + torch.cos(2 * phi) * torch.exp(-2 * k2)) / 2)[..., None]
        std = (second - mean ** 2).clamp_min(0).sqrt().amax(-1)
        return mean, torch.sigmoid(self.logit_opacity)[:, None] * std

    @torch.no_grad()
    def prune_waves(self, threshold: float, optimizer=None, remove: torch.Tensor | None = None) -> dict:
        """Remove active waves whose contribution (wave_statistics) is below threshold (or the slots `remove` [N,width]
        marks), folding their mean colour
        into the base colour (color_base, or folded_weights for "paper"); repack each row (kept waves first, in
        orientation order) and trim the stored width to the largest count. A surfel left without waves becomes a 2DGS
        surfel (colour in color_base, or color_a for "paper"). Returns counts."""
        if not self.adaptive:
            raise ShapeError("prune_waves needs a model created with prune_waves, prune_relative or prune_psnr > 0 "
                             "(it tracks per-surfel counts)")
        w = self.wave_weights.detach()
        n, width = w.shape[:2]
        on = self.active_slots()
        if remove is not None and remove.shape != on.shape:
            raise ShapeError(f"prune_waves: remove must mark wave slots [N, width] = {list(on.shape)}, got "
                             f"{list(remove.shape)}")
        _, contribution = self.wave_statistics()
        keep = on & (contribution >= threshold) if remove is None else on & ~remove
        removed = on & ~keep
        n_removed = int(removed.sum())
        if n_removed == 0:
            return {"removed": 0, "active": int(on.sum())}
        m = self._mean_cos()
        gone = w * (removed[..., None] if self.per_wave else removed)
        if self.per_wave:  # a removed wave a cos t has mean a m: the base keeps it
            self.color_base.add_((gone * m[..., None]).sum(1))
        elif self.residual:  # a removed wave w d cos t has mean w d m, m = cos(phi) e^{-|k|^2/2}: the base keeps it
            self.color_base.add_((gone * m).sum(1, keepdim=True) * self.color_diff)
        else:
            # A removed wave's colour w[cA (1 + cos t)/2 + cB (1 - cos t)/2] has mean w[cA (1 + m)/2 + cB (1 - m)/2]:
            # it adds w (1 + m)/2 to cA's weight and w (1 - m)/2 to cB's.
            self.folded_weights.add_(torch.stack([(gone * (1 + m)).sum(1), (gone * (1 - m)).sum(1)], 1) / 2)
        order = torch.sort((~keep).to(torch.int8), dim=1, stable=True).indices  # kept first, order preserved
        counts = keep.sum(1)
        new_width = int(counts.max()) if n else 0
        live = torch.arange(new_width, device=w.device)[None] < counts[:, None]

        def pack(t):  # [N,width(,C)] -> [N,new_width(,C)], unused slots zeroed (values and Adam moments)
            slots = order.view(order.shape + (1,) * (t.dim() - 2)).expand(order.shape + t.shape[2:])
            t = t.gather(1, slots)[:, :new_width]
            return torch.where(live.view(live.shape + (1,) * (t.dim() - 2)), t, torch.zeros_like(t))

        # surfels losing their last wave (every weight is now folded): "residual" drops d (the base holds the
        # colour already); "paper" keeps the colour fa cA + fb cB in color_a alone
        emptied = (counts == 0) & (self.wave_counts > 0)
        if self.per_wave:
            pass  # a per-wave surfel keeps nothing for its waves outside them
        elif bool(emptied.any()) and self.residual:
            self.set_rows("color_diff", emptied, 0.0, optimizer)
        elif bool(emptied.any()):
            fa, fb = self.folded_weights[emptied].unbind(1)
            color = fa[:, None] * self.color_a[emptied] + fb[:, None] * self.color_b[emptied]
            self.set_rows("color_a", emptied, color, optimizer)
            self.set_rows("color_b", emptied, 0.0, optimizer)
            self.set_rows("folded_weights", emptied, 0.0, optimizer)
        for name in self.wave_parameter_names:
            self.swap_parameter(name, pack, optimizer)
        self.wave_index = pack(self.wave_index)
        self.wave_counts = counts.to(torch.int32)
        return {"removed": n_removed, "active": int(counts.sum())}

    # --- a byte budget ----------------------------------------------------------------------------------------
    def _wave_bytes(self, precision: str) -> tuple[float, float]:
        """(bytes of one stored wave, bytes a surfel stores only while it has a wave) at `precision`."""
        from ..packing import value_bytes

        wave = sum(getattr(self, n)[:1, :1].numel() * value_bytes(n, getattr(self, n), precision)
                   for n in self.wave_parameter_names)
        waved = sum(getattr(self, n)[:1].numel() * value_bytes(n, getattr(self, n), precision)
                    for n in self._waved_only)
        return float(wave), float(waved)

    def stored_row_bytes(self, precision: str) -> torch.Tensor:
        """Adaptive waves: a surfel's plain rows, its wave count (unary: one bit a wave and one more), its stored
        waves and, while it has one, its wave colour and (the fan) its orientation mask."""
        if not self.adaptive:
            return super().stored_row_bytes(precision)
        from ..packing import value_bytes

        skip = set(self.wave_parameter_names) | set(self._waved_only) | set(self.primitive_buffers)
        plain = sum(t[:1].numel() * value_bytes(n, t, precision) for n, t in self.per_primitive().items()
                    if n not in skip)
        wave, waved = self._wave_bytes(precision)
        if not self.free_directions:
            waved += torch.empty((), dtype=self._mask_dtype()).element_size()
        counts = self.wave_counts.to(torch.float32)
        return plain + (counts + 1) / 8 + counts * wave + (counts > 0).to(torch.float32) * waved

    @torch.no_grad()
    def shed_free(self, optimizer=None) -> dict | None:
        """The measured pruning (prune_psnr): the waves whose removal costs the probe views at most that many dB."""
        if not self.adaptive or float(self.config.prune_psnr) <= 0 or self.probe_error is None:
            return None
        return self.prune_waves(self.measured_threshold(float(self.config.prune_psnr)), optimizer)

    @torch.no_grad()
    def shed_richness(self) -> "GaborModel":
        if self.adaptive:
            self.prune_waves(math.inf)
        return self

    @torch.no_grad()
    def shedding_options(self, nbytes: int, precision: str, optimizer=None) -> list:
        """Besides the weakest surfels: the faintest waves (wave_statistics) whose stored bytes add up to
        `nbytes`, their mean colour kept, as prune_waves removes them."""
        from .base import Shedding

        options = super().shedding_options(nbytes, precision, optimizer)
        on = self.active_slots() if self.adaptive else None
        if on is None or not bool(on.any()):
            return options
        mean, contribution = self.wave_statistics()
        slots = on.flatten().nonzero().squeeze(1)
        wave, _ = self._wave_bytes(precision)
        j = min(math.ceil(nbytes / wave), slots.numel())
        faintest = slots[contribution.flatten()[slots].argsort()[:j]]  # exactly j, ties or not
        removed = torch.zeros_like(on).flatten().index_fill_(0, faintest, True).view_as(on)
        options.append(Shedding(f"{j} faintest waves", lambda camera: self._surfels_without(camera, removed, mean),
                                lambda: self.prune_waves(0.0, optimizer, remove=removed)))
        return options

    # --- waves fitted to the photos (fit_waves; training/wave_fit.py) ----------------------------------------------
    def wave_fit_step(self, iterations: int) -> int | None:
        fraction = float(self.config.fit_waves)
        return None if fraction <= 0 else max(1, round(fraction * iterations))

    def wave_slots(self) -> torch.Tensor:
        """[N] the waves each surfel has."""
        return self.active_slots().sum(1)

    @torch.no_grad()
    def start_waves(self, rows: torch.Tensor, vectors: torch.Tensor, phases: torch.Tensor, amplitudes: torch.Tensor,
                    optimizer=None) -> None:
        """Replace the waves of surfels `rows` by vectors [n,K,2] (cycles per sigma), phases [n,K] (radians) and RGB
        amplitudes [n,K,3], a surfel's wave j by the j-th given (those past its own count, or past K, stay), and
        restart their optimiser moments. Free directions with a colour a wave (beta-gabor) only: the fitted waves
        are exactly these."""
        if not (self.free_directions and self.per_wave and self.learn_phase):
            raise SplatzooError(f"{type(self).__name__}: waves can be set from vectors, phases and amplitudes only "
                                "with free directions and a colour a wave (color_param per-wave)")
        k = min(vectors.shape[1], self.wave_weights.shape[1])
        if rows.numel() == 0 or k == 0:
            return
        on = self.active_slots()[rows, :k]  # [n,k]
        for p, value in ((self.wave_freqs, vectors[:, :k]), (self.wave_phases, phases[:, :k]),
                         (self.wave_weights, amplitudes[:, :k])):
            mask = on.reshape(on.shape + (1,) * (value.dim() - 2))
            p.data[rows, :k] = torch.where(mask, value.to(p), p.data[rows, :k])
            restart_moments(optimizer, p, rows)

    def summary(self) -> dict:
        n, k = self.wave_weights.shape[0], int(self.config.n_waves)
        active = int(self.active_slots().sum())
        return {"waves_active": active, "wave_slots": n * k,
                "wave_fraction": active / (n * k) if n * k else 0.0}

    @property
    def _waved_only(self) -> tuple[str, ...]:
        """What a wave-less surfel does not store (zero, and frozen: its colour is the base colour alone)."""
        if self.per_wave:
            return ()
        return ("color_diff",) if self.residual else ("color_b", "folded_weights")

    def size_bytes(self) -> int:
        if not self.adaptive:
            return super().size_bytes()
        state = self.checkpoint()["state"]  # what is stored: active waves only, wave-less surfels without color_b
        return sum(t.numel() * t.element_size() for t in state.values() if t.dim() > 0)

    def _mask_dtype(self) -> torch.dtype:
        k = int(self.config.n_waves)
        return torch.uint8 if k <= 8 else torch.int16 if k <= 15 else torch.int32

    def checkpoint(self) -> dict:
        ck = super().checkpoint()
        if not self.adaptive:
            return ck
        state = ck["state"]
        on = self.active_slots().cpu()
        for name in self.wave_parameter_names:
            state[name] = state[name][on]  # active waves only, row-major: surfel by surfel
        counts = self.wave_counts.cpu()
        waved = counts > 0
        for name in self._waved_only:
            state[name] = state[name][waved]
        state["wave_count_bits"] = unary_code(counts)  # a plain surfel: one bit
        if not self.free_directions:  # the fan: the orientations of each waved surfel's waves, as a bit mask
            index = self.wave_index.cpu().long()
            mask = torch.where(on, torch.ones_like(index) << index, torch.zeros_like(index)).sum(1)
            state["wave_mask"] = mask[waved].to(self._mask_dtype())
        state["wave_width"] = torch.tensor(int(self.wave_weights.shape[1]), dtype=torch.uint8)
        return ck

    def load_checkpoint_state(self, state: dict) -> None:
        if not self.adaptive or not {"wave_mask", "wave_count_bits"} & set(state):
            return super().load_checkpoint_state(state)
        if "folded_weight" in state and not self.residual:
            state = _upgrade_single_fold(state)
        k = int(self.config.n_waves)
        width = state.get("wave_width")
        if not (isinstance(width, torch.Tensor) and width.numel() == 1 and not width.is_floating_point()
                and 0 <= int(width) <= k):  # it sizes the arrays below: a crafted count must not allocate gigabytes
            raise ShapeError(f"the packed waves' width (wave_width) must be a whole number in 0..n_waves={k}, got "
                             f"{str(width)[:80]}; {DAMAGED}")
        width = int(width)
        bits = self._orientation_bits(state, k, width)  # [N,K] orientation i in use
        n = bits.shape[0]
        counts = bits.sum(1)
        for name in self.wave_parameter_names:
            if tuple(state[name].shape[:1]) != (int(counts.sum()),):
                raise ShapeError(f"{name} holds {tuple(state[name].shape)} values for the {int(counts.sum())} waves "
                                 f"the file's wave counts give; {DAMAGED}")
        live = torch.arange(width)[None] < counts[:, None]
        index = torch.sort(1 - bits, dim=1, stable=True).indices[:, :width]  # set bits first, increasing
        index = torch.where(live, index, torch.zeros_like(index))
        dense = {}
        for name in self.wave_parameter_names:
            dense[name] = torch.zeros((n, width) + tuple(state[name].shape[1:]), dtype=state[name].dtype)
            dense[name][live] = state[name]
        for name in self._waved_only:
            dense[name] = torch.zeros((n,) + tuple(state[name].shape[1:]), dtype=state[name].dtype)
            dense[name][counts > 0] = state[name]
        layout = ("wave_mask", "wave_width", "wave_count_bits")
        rest = {k2: v for k2, v in state.items() if k2 not in dense and k2 not in layout}
        self.replace_parameters({name: dense.get(name, rest.get(name)) for name, _ in self.named_parameters()})
        buffers = {"wave_counts": counts.to(torch.int32), "wave_index": index}
        if not self.residual:
            buffers["folded_weights"] = dense["folded_weights"]
        self.replace_parameters(buffers)
        self.load_state_dict({k2: v for k2, v in rest.items() if k2 not in dense}, strict=False)

    def _orientation_bits(self, state: dict, k: int, width: int) -> torch.Tensor:
        """[N,K] 0/1: which orientations (slots, for free directions) each surfel's stored waves have, from the
        packed layout: unary wave counts (wave_count_bits) and, for the fan, a bit mask a waved surfel
        (wave_mask); files written before the counts hold a mask for every surfel."""
        coded = None
        if "wave_count_bits" in state:
            means = state.get("means")
            n = means.shape[0] if isinstance(means, torch.Tensor) and means.dim() else 0
            coded = unary_counts(state["wave_count_bits"], n, width)
            if self.free_directions:  # slots in use from the front: the count is all there is
                if "wave_mask" in state:
                    raise ShapeError(f"a model with free directions stores wave counts, not orientations (wave_mask); "
                                     f"{DAMAGED}")
                return (torch.arange(k)[None] < coded[:, None]).long()
            mask, waved = state.get("wave_mask"), coded > 0
            if (not isinstance(mask, torch.Tensor) or mask.is_floating_point()
                    or tuple(mask.shape) != (int(waved.sum()),)):
                raise ShapeError(f"wave_mask must hold one orientation mask for each of the {int(waved.sum())} "
                                 f"surfels with waves; {DAMAGED}")
            full = torch.zeros(n, dtype=torch.long)
            full[waved] = mask.long()
        else:
            full = state["wave_mask"].long()
        if full.dim() != 1 or bool(((full < 0) | (full >= (1 << k))).any()):
            raise ShapeError(f"wave_mask must be [N] with values in 0..2^{k}-1 (one bit per orientation); {DAMAGED}")
        bits = (full[:, None] >> torch.arange(k)) & 1
        counts = bits.sum(1)
        if coded is not None and bool((counts != coded).any()):
            raise ShapeError(f"wave_mask marks other wave counts than wave_count_bits holds; {DAMAGED}")
        if full.shape[0] and int(counts.max()) > width:
            raise ShapeError(f"wave_mask marks up to {int(counts.max())} waves on a surfel but wave_width is {width}; "
                             f"{DAMAGED}")
        return bits


def unary_code(counts: torch.Tensor) -> torch.Tensor:
    """uint8 [ceil((N + sum counts) / 8)]: counts [N] (each >= 0) in unary, surfel after surfel (count ones, then a
    zero), eight bits a byte, the last byte padded with zeros. A surfel without waves costs one bit."""
    c = counts.detach().cpu().long().numpy()
    bits = np.ones(int(c.sum()) + c.size, dtype=np.uint8)
    bits[np.cumsum(c + 1) - 1] = 0
    return torch.from_numpy(np.packbits(bits))


def unary_counts(code: torch.Tensor, n: int, width: int) -> torch.Tensor:
    """The N counts unary_code wrote (each at most `width`), checked: exactly N terminating zeros, then zero padding
    to the byte."""
    if not isinstance(code, torch.Tensor) or code.dtype != torch.uint8 or code.dim() != 1:
        raise ShapeError(f"wave_count_bits must be a 1D uint8 tensor of packed bits; {DAMAGED}")
    bits = np.unpackbits(code.numpy())
    ends = np.flatnonzero(bits == 0)[:n]
    if ends.size < n:
        raise ShapeError(f"wave_count_bits holds counts for {ends.size} surfels, not {n}; {DAMAGED}")
    used = int(ends[-1]) + 1 if n else 0
    if bits.size - used >= 8 or bits[used:].any():
        raise ShapeError(f"wave_count_bits runs on past the counts of its {n} surfels; {DAMAGED}")
    counts = torch.from_numpy(np.diff(ends, prepend=-1) - 1)
    if n and int(counts.max()) > width:
        raise ShapeError(f"wave_count_bits gives a surfel {int(counts.max())} waves but wave_width is {width}; "
                         f"{DAMAGED}")
    return counts


def _upgrade_single_fold(state: dict) -> dict:
    """Checkpoints of splatzoo 0.1.0 folded removed waves into one weight f on (cA + cB)/2 and stored color_b for
    every surfel: the same colours as weights (f/2, f/2), and wave-less surfels' colour moved into color_a."""
    state = dict(state)
    f = state.pop("folded_weight")
    bits = (state["wave_mask"].long()[:, None] >> torch.arange(31)) & 1
    waved = bits.sum(1) > 0
    color_a, color_b = state["color_a"].clone(), state["color_b"]
    color_a[~waved] = (f[~waved, None] / 2) * (color_a[~waved] + color_b[~waved])
    state["color_a"] = color_a
    state["color_b"] = color_b[waved]
    state["folded_weights"] = torch.stack([f, f], 1)[waved] / 2
    return state


class BaselineBModel(GaborModel):
    """Baseline B: every wave along the local u axis (a 3D take on 2D Gabor splatting)."""

    orientation = "u"


class BaselineCModel(GaborModel):
    """Baseline C: phases fixed at zero."""

    learn_phase = False
