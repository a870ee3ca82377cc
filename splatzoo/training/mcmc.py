"""A budgeted density strategy (`--strategy mcmc`): the count grows to a cap and then stays, and surfels that have
died (opacity under DEAD_OPACITY) are moved onto live ones instead of being deleted, in the manner of 3D Gaussian
Splatting as Markov Chain Monte Carlo and gsplat's MCMC strategy, restated for 2D surfels.

Moving a surfel onto another is a relocation: a source of opacity o and scale s sampled n - 1 times becomes n
copies at its place with opacity o' and scale s' chosen so that the stack looks like the source. The stack's alpha
is 1 - (1 - o' g')^n with g' the copies' Gaussian; its peak equals the source's when o' = 1 - (1 - o)^(1/n), and its
integral over the surfel plane equals the source's, o 2 pi s^2, when

    s'^2 = s^2 o / sum_{i=1..n} (1 - (1 - o')^i) / i

(expand 1 - (1 - o' g')^n = sum_i o' g' (1 - o' g')^(i-1) and integrate each power of the 2D Gaussian g'^(k+1),
2 pi s'^2 / (k+1); the inner binomial sum is the integral from 0 to o' of (1 - t)^(i-1)). n = 1 leaves o and s as
they were. Sources are drawn with probability proportional to opacity, and nearly dead surfels get positional noise
along their own plane (a random walk that explores without moving what the images pin down).

"Opacity" in deciding who is dead, who is drawn and who gets noise is the model's effective_opacity(): the most
opacity a surfel can show anywhere (a textured surfel's times its most opaque texel), so a surfel whose texture has
turned transparent is dead however opaque its scalar. A relocation still rescales the scalar opacity only (whatever
else scales it, such as a texture's alpha, is copied from the source as it is).
"""
from __future__ import annotations

import torch

from ..geometry import quat_to_rotmat
from ..models.base import SurfelModel, inverse_sigmoid, restart_moments

DEAD_OPACITY = 0.005      # under this a surfel is dead and gets relocated
GROWTH = 0.05             # each refinement step adds at most this fraction of the count (until the budget)
OPACITY_REG = 0.01        # loss weights on the mean opacity and the mean scale: unused surfels fade and die
SCALE_REG = 0.01
NOISE_LR = 5e5            # positional noise: this x the position learning rate x the surfel's tangent covariance
REFINE_UNTIL = 25000      # refinement stops here on the 30k schedule (scaled to the run)


def relocated(opacity: torch.Tensor, scale: torch.Tensor, copies: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Opacity [M] and scale [M, ...] of each of `copies` [M] (>= 1) stacked surfels that together look like one
    surfel of (opacity, scale): equal peak alpha and equal alpha integral (module docstring)."""
    n = copies.to(opacity.dtype)
    new_opacity = (1 - (1 - opacity).clamp_min(0) ** (1 / n)).clamp(DEAD_OPACITY, 1 - 1e-6)
    i = torch.arange(1, int(copies.max()) + 1, device=opacity.device, dtype=opacity.dtype)  # [n_max]
    terms = (1 - (1 - new_opacity[:, None]) ** i) / i
    denominator = torch.where(i <= n[:, None], terms, torch.zeros_like(terms)).sum(1)
    ratio = torch.sqrt(opacity / denominator.clamp_min(1e-12))
    return new_opacity, scale * ratio.reshape((-1,) + (1,) * (scale.dim() - 1))


def _reset_moments(optimizer, params: dict[str, torch.Tensor], rows: torch.Tensor) -> None:
    for p in params.values():
        restart_moments(optimizer, p, rows)


def _sample_sources(opacity: torch.Tensor, candidates: torch.Tensor, count: int, generator) -> torch.Tensor:
    weights = opacity[candidates].double().cpu()
    picks = torch.multinomial(weights, count, replacement=True, generator=generator)
    return candidates[picks.to(candidates.device)]


@torch.no_grad()
def _apply_relocation(model: SurfelModel, sources: torch.Tensor, count_extra: torch.Tensor) -> tuple[torch.Tensor,
                                                                                                       torch.Tensor]:
    """Give each distinct source the opacity and scale of one of its (1 + extra) copies; returns them per source
    row (for the copies)."""
    opacity = torch.sigmoid(model.logit_opacity)
    new_opacity, new_scale = relocated(opacity[sources], torch.exp(model.log_scales[sources]), count_extra + 1)
    model.logit_opacity[sources] = inverse_sigmoid(new_opacity)
    model.log_scales[sources] = torch.log(new_scale)
    return model.logit_opacity[sources].clone(), model.log_scales[sources].clone()


@torch.no_grad()
def relocate_dead(model: SurfelModel, optimizer, generator: torch.Generator) -> int:
    """Move every dead surfel onto a live one (drawn by opacity); returns how many moved."""
    opacity = model.effective_opacity()
    dead = opacity <= DEAD_OPACITY
    alive = (~dead).nonzero().squeeze(1)
    n_dead = int(dead.sum())
    if n_dead == 0 or alive.numel() == 0:
        return 0
    sources = _sample_sources(opacity, alive, n_dead, generator)
    extra = torch.bincount(sources, minlength=opacity.shape[0])[sources]
    logits, log_scales = _apply_relocation(model, sources, extra)
    targets = dead.nonzero().squeeze(1)
    params = model.per_primitive()
    for name, p in params.items():
        p.data[targets] = p.data[sources]
    model.logit_opacity[targets] = logits
    model.log_scales[targets] = log_scales
    _reset_moments(optimizer, params, torch.cat([sources, targets]))
    return n_dead


@torch.no_grad()
def add_surfels(model: SurfelModel, optimizer, count: int, generator: torch.Generator) -> int:
    """Append `count` copies of live surfels (drawn by opacity), relocated as above; returns how many."""

    opacity = model.effective_opacity()
    alive = (opacity > DEAD_OPACITY).nonzero().squeeze(1)
    if count <= 0 or alive.numel() == 0:
        return 0
    sources = _sample_sources(opacity, alive, count, generator)
    extra = torch.bincount(sources, minlength=opacity.shape[0])[sources]
    _apply_relocation(model, sources, extra)
    params = model.per_primitive()
    _reset_moments(optimizer, params, sources)
    new = {name: p.detach()[sources] for name, p in params.items()}
    keep = torch.ones(opacity.shape[0], dtype=torch.bool, device=opacity.device)
    model.edit_primitives(optimizer, keep, new)
    return count


@torch.no_grad()
def inject_noise(model: SurfelModel, position_lr: float, generator: torch.Generator) -> None:
    """Move nearly dead surfels at random along their own plane: noise ~ N(0, tangent covariance) scaled by
    NOISE_LR x the position learning rate, gated by a steep sigmoid of 1 - opacity (live surfels keep still)."""
    means = model.means
    opacity = model.effective_opacity()
    gate = torch.sigmoid(100 * ((1 - opacity) - 0.995))
    R = quat_to_rotmat(model.quats)
    scales = torch.exp(model.log_scales)
    z = torch.randn(means.shape[0], 2, generator=generator).to(means)
    # tangent covariance R diag(s_u^2, s_v^2, 0) R^T applied to a 3D normal sample: only the plane's part matters
    step = (R[:, :, :2] @ (scales ** 2 * z)[..., None]).squeeze(-1)
    means.add_(step * (gate * position_lr * NOISE_LR)[:, None])


def regulariser(model: SurfelModel) -> torch.Tensor:
    """OPACITY_REG x mean opacity + SCALE_REG x mean scale: what keeps an unneeded surfel from lingering."""
    return OPACITY_REG * torch.sigmoid(model.logit_opacity).mean() + SCALE_REG * torch.exp(model.log_scales).mean()
