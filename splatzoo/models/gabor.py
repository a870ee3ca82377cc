"""3D Gabor surfels (the paper) and its ablation baselines A, B, C.

Colour inside a surfel with N waves at fixed orientations theta_i:
    c(u,v) = sum_i w_i [cA (1 + cos t_i)/2 + cB (1 - cos t_i)/2],  t_i = 2 pi f_i (cos theta_i, sin theta_i).(u,v) + phi_i
           = (sum_i w_i)(cA + cB)/2 + sum_i w_i (cA - cB)/2 cos t_i
which is the rasterizer's wave bank with k_i = 2 pi f_i (cos theta_i, sin theta_i), a_i = w_i (cA - cB)/2.
f is in cycles per sigma.

Two options beyond the paper:
- prune_waves > 0 (adaptive waves): during training, waves whose amplitude |w_i| max_c|cA - cB|_c / 2 falls below
  the threshold are removed, so a surfel on flat colour ends as a plain 2DGS surfel. The removed weight is folded
  into `folded_weight` so the base colour does not jump. Active waves are packed to the front of each surfel's row
  (`wave_index` keeps each slot's orientation) and `wave_counts` tells the rasterizer how many to evaluate.
  Checkpoints store active waves only (packed, with a per-surfel orientation bit mask).
- sh_degree > 0: a view-dependent spherical-harmonics term (degree >= 1 bands, no DC) added to the base colour.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import nn

from ..errors import ShapeError
from ..geometry import eval_sh, num_sh_bases
from ..types import Camera, Surfels
from .base import SurfelModel, view_directions


@dataclass
class GaborConfig:
    n_waves: int = field(default=4, metadata={"help": "number of wave orientations per surfel (fan at i*pi/N)"})
    sh_degree: int = field(default=0, metadata={"help": "spherical-harmonics degree (0..3) of a view-dependent term "
                                                        "added to the base colour; 0: view-independent (the paper)"})
    prune_waves: float = field(default=0.0, metadata={
        "help": "adaptive waves: during training remove waves whose amplitude |w| max|cA-cB|/2 is below this "
                "(colour units, images in [0,1]; e.g. 0.01); 0 keeps every wave"})
    prune_from: float = field(default=0.25, metadata={
        "help": "with --prune-waves: fraction of the iterations before the first pruning (waves need time to grow)"})

    def __post_init__(self):
        if int(self.n_waves) < 1:
            raise ShapeError(f"n_waves must be at least 1, got {self.n_waves} (use the 2dgs model for no waves)")
        if int(self.n_waves) > 30:
            raise ShapeError(f"n_waves must be at most 30 (orientations are stored as a bit mask), got {self.n_waves}")
        if not 0 <= int(self.sh_degree) <= 3:
            raise ShapeError(f"sh_degree must be 0, 1, 2 or 3, got {self.sh_degree}")
        if not float(self.prune_waves) >= 0:
            raise ShapeError(f"prune_waves must be >= 0 (0: off), got {self.prune_waves}")
        if not 0 <= float(self.prune_from) <= 1:
            raise ShapeError(f"prune_from is a fraction of the run in [0, 1], got {self.prune_from}")


@dataclass
class BaselineAConfig(GaborConfig):
    n_waves: int = field(default=1, metadata={"help": "number of waves (Baseline A of the paper uses 1)"})


class GaborModel(SurfelModel):
    """The paper's model: waves fanned at i*pi/N, learnable frequency, weight and phase."""

    orientation = "fan"   # "fan": theta_i = i pi / N; "u": every wave along the local u axis
    learn_phase = True
    primitive_buffers = ("wave_counts", "wave_index")  # present only with prune_waves > 0

    def __init__(self, config: GaborConfig, num_primitives: int = 0):
        super().__init__(config, num_primitives)
        n, k = num_primitives, config.n_waves
        self.color_a = nn.Parameter(torch.zeros(n, 3))
        self.color_b = nn.Parameter(torch.zeros(n, 3))
        self.wave_weights = nn.Parameter(torch.zeros(n, k))
        self.wave_freqs = nn.Parameter(torch.zeros(n, k))
        if self.learn_phase:
            self.wave_phases = nn.Parameter(torch.zeros(n, k))
        if config.sh_degree > 0:
            self.sh_rest = nn.Parameter(torch.zeros(n, num_sh_bases(config.sh_degree) - 1, 3))
        if self.adaptive:
            self.folded_weight = nn.Parameter(torch.zeros(n))
            self.register_buffer("wave_counts", torch.full((n,), k, dtype=torch.int32), persistent=False)
            self.register_buffer("wave_index", torch.arange(k).repeat(n, 1), persistent=False)
        angles = torch.arange(k) * math.pi / k if self.orientation == "fan" else torch.zeros(k)
        self.register_buffer("directions", torch.stack([angles.cos(), angles.sin()], -1), persistent=False)

    @property
    def adaptive(self) -> bool:
        return float(self.config.prune_waves) > 0

    @property
    def wave_parameter_names(self) -> list[str]:
        return ["wave_weights", "wave_freqs"] + (["wave_phases"] if self.learn_phase else [])

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

    def active_slots(self) -> torch.Tensor:
        """bool [N, width]: which stored wave slots are in use."""
        w = self.wave_weights
        if not self.adaptive:
            return torch.ones(w.shape, dtype=torch.bool, device=w.device)
        return torch.arange(w.shape[1], device=w.device)[None] < self.wave_counts[:, None]

    def surfels(self, camera: Camera) -> Surfels:
        g = self.geometry()
        w = self.wave_weights
        if self.adaptive:
            w_sum = (w * self.active_slots()).sum(1) + self.folded_weight
            directions = self.directions.to(w)[self.wave_index]  # [N,width,2]: each slot's own orientation
            counts = self.wave_counts
        else:
            w_sum, directions, counts = w.sum(1), self.directions.to(w), None
        base = w_sum[:, None] * (self.color_a + self.color_b) / 2
        if self.config.sh_degree > 0:
            # bands >= 1 only: the DC term is the Gabor base colour itself
            coeffs = torch.cat([self.sh_rest.new_zeros(self.sh_rest.shape[0], 1, 3), self.sh_rest], 1)
            base = base + eval_sh(self.config.sh_degree, coeffs, view_directions(self.means, camera))
        amplitudes = w[..., None] * ((self.color_a - self.color_b) / 2)[:, None, :]
        vectors = (2 * math.pi) * self.wave_freqs[..., None] * directions
        return Surfels(g["means"], g["quats"], g["scales"], g["opacities"], base, vectors, self.phases(), amplitudes,
                       counts)

    def optim_groups(self, scene_extent: float) -> list[dict]:
        groups = self.geometry_groups(scene_extent) + [
            {"name": "color_a", "params": [self.color_a], "lr": 2.5e-3},
            {"name": "color_b", "params": [self.color_b], "lr": 2.5e-3},
            {"name": "wave_weights", "params": [self.wave_weights], "lr": 1e-3},
            {"name": "wave_freqs", "params": [self.wave_freqs], "lr": 1e-3},
        ]
        if self.learn_phase:
            groups.append({"name": "wave_phases", "params": [self.wave_phases], "lr": 1e-3})
        if self.config.sh_degree > 0:
            groups.append({"name": "sh_rest", "params": [self.sh_rest], "lr": 2.5e-3 / 20})  # 2DGS's SH rest rate
        if self.adaptive:
            groups.append({"name": "folded_weight", "params": [self.folded_weight], "lr": 1e-3})
        return groups

    # --- adaptive waves ---------------------------------------------------------------------------------------
    def on_step(self, step: int, train_config, optimizer) -> dict | None:
        """Prune at the densification cadence once `prune_from` of the run has passed."""
        if not self.adaptive:
            return None
        every = max(train_config.at(train_config.densify_interval), 10)
        if step < float(self.config.prune_from) * train_config.iterations or step % every:
            return None
        return self.prune_waves(float(self.config.prune_waves), optimizer)

    @torch.no_grad()
    def prune_waves(self, threshold: float, optimizer=None) -> dict:
        """Remove active waves with amplitude |w| max_c|cA - cB|/2 < threshold; repack each row (kept waves first,
        in orientation order) and trim the stored width to the largest count. Returns counts."""
        if not self.adaptive:
            raise ShapeError("prune_waves needs a model created with prune_waves > 0 (it tracks per-surfel counts)")
        w = self.wave_weights.detach()
        n, width = w.shape
        on = self.active_slots()
        amp = w.abs() * ((self.color_a - self.color_b).abs().amax(1, keepdim=True) / 2)
        keep = on & (amp >= threshold)
        removed = on & ~keep
        n_removed = int(removed.sum())
        if n_removed == 0:
            return {"removed": 0, "active": int(on.sum())}
        # the removed waves' share of the base colour (sum w)(cA + cB)/2 stays, folded into one weight
        self.folded_weight.add_((w * removed).sum(1))
        order = torch.sort((~keep).to(torch.int8), dim=1, stable=True).indices  # kept first, order preserved
        counts = keep.sum(1)
        new_width = int(counts.max()) if n else 0
        live = torch.arange(new_width, device=w.device)[None] < counts[:, None]

        def pack(t):  # [N,width] -> [N,new_width], unused slots zeroed (values and Adam moments)
            t = t.gather(1, order)[:, :new_width]
            return torch.where(live, t, torch.zeros_like(t))

        for name in self.wave_parameter_names:
            self.swap_parameter(name, pack, optimizer)
        self.wave_index = pack(self.wave_index)
        self.wave_counts = counts.to(torch.int32)
        return {"removed": n_removed, "active": int(counts.sum())}

    def summary(self) -> dict:
        n, k = self.wave_weights.shape[0], int(self.config.n_waves)
        active = int(self.active_slots().sum())
        return {"waves_active": active, "wave_slots": n * k,
                "wave_fraction": active / (n * k) if n * k else 0.0}

    def size_bytes(self) -> int:
        if not self.adaptive:
            return super().size_bytes()
        waves = set(self.wave_parameter_names)
        floats = sum(p.numel() for name, p in self.named_parameters() if name not in waves)
        floats += int(self.active_slots().sum()) * len(waves)
        return floats * 4 + self.wave_weights.shape[0] * 4  # + the per-surfel orientation mask (int32)

    def checkpoint(self) -> dict:
        ck = super().checkpoint()
        if not self.adaptive:
            return ck
        state = ck["state"]
        on = self.active_slots().cpu()
        for name in self.wave_parameter_names:
            state[name] = state[name][on]  # active waves only, row-major: surfel by surfel
        index = self.wave_index.cpu()
        state["wave_mask"] = torch.where(on, torch.ones_like(index) << index, torch.zeros_like(index)).sum(1).to(torch.int32)
        state["wave_width"] = torch.tensor(int(self.wave_weights.shape[1]))
        return ck

    def load_checkpoint_state(self, state: dict) -> None:
        if not self.adaptive or "wave_mask" not in state:
            return super().load_checkpoint_state(state)
        mask = state["wave_mask"].long()
        n, k, width = mask.shape[0], int(self.config.n_waves), int(state["wave_width"])
        bits = (mask[:, None] >> torch.arange(k)) & 1  # [N,K] orientation i in use
        counts = bits.sum(1)
        live = torch.arange(width)[None] < counts[:, None]
        index = torch.sort(1 - bits, dim=1, stable=True).indices[:, :width]  # set bits first, increasing
        index = torch.where(live, index, torch.zeros_like(index))
        dense = {}
        for name in self.wave_parameter_names:
            t = torch.zeros(n, width, dtype=state[name].dtype)
            t[live] = state[name]
            dense[name] = t
        rest = {k2: v for k2, v in state.items() if k2 not in dense and k2 not in ("wave_mask", "wave_width")}
        self.replace_parameters({name: dense.get(name, rest.get(name)) for name, _ in self.named_parameters()})
        self.replace_parameters({"wave_counts": counts.to(torch.int32), "wave_index": index})
        self.load_state_dict({k2: v for k2, v in rest.items() if k2 not in dense}, strict=False)


class BaselineBModel(GaborModel):
    """Baseline B: every wave along the local u axis (a 3D take on 2D Gabor splatting)."""

    orientation = "u"


class BaselineCModel(GaborModel):
    """Baseline C: phases fixed at zero."""

    learn_phase = False
