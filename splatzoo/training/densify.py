"""Adaptive density control for surfel models (2DGS): clone small, split large, prune transparent.

Editing the primitive count also edits Adam's moment buffers row by row, so training continues smoothly.
"""
from __future__ import annotations

import torch

from ..geometry import quat_to_rotmat
from ..models.base import SurfelModel, inverse_sigmoid
from ..types import Camera


class DensifyStats:
    """Running sum of each primitive's screen-space position-gradient norm over the views that saw it."""

    def __init__(self, n: int):
        self.grad_sum = torch.zeros(n)
        self.count = torch.zeros(n)

    @torch.no_grad()
    def accumulate(self, model: SurfelModel, camera: Camera) -> None:
        """Add this view's gradient. The world gradient of a mean, projected on the image plane and scaled by
        depth / focal, is the gradient with respect to its pixel position; times W/2, H/2 it is the NDC
        gradient that the 2e-4 threshold of 2DGS refers to."""
        g = model.means.grad
        if g is None:
            return
        cam = camera.to(g.device, g.dtype)
        p_cam = model.means.detach() @ cam.R.T + cam.t
        g_cam = g @ cam.R.T
        depth = p_cam[:, 2]
        px = cam.K[0, 0] * p_cam[:, 0] / depth.clamp_min(1e-6) + cam.K[0, 2]
        py = cam.K[1, 1] * p_cam[:, 1] / depth.clamp_min(1e-6) + cam.K[1, 2]
        visible = (depth > 0.2) & (px >= 0) & (px < cam.width) & (py >= 0) & (py < cam.height)
        gx = g_cam[:, 0] * depth / cam.K[0, 0] * cam.width / 2
        gy = g_cam[:, 1] * depth / cam.K[1, 1] * cam.height / 2
        norm = torch.sqrt(gx * gx + gy * gy)
        self.grad_sum += torch.where(visible, norm, torch.zeros_like(norm)).cpu()
        self.count += visible.float().cpu()

    def mean(self) -> torch.Tensor:
        return self.grad_sum / self.count.clamp_min(1)

    def state_dict(self) -> dict:
        return {"grad_sum": self.grad_sum, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.grad_sum, self.count = state["grad_sum"].clone(), state["count"].clone()


SPLIT_SHRINK = 1.6  # a split child's scales are its parent's divided by this (2DGS)


def split_rows(model: SurfelModel, params: dict[str, torch.Tensor], idx: torch.Tensor,
               generator: torch.Generator, shrink: float = SPLIT_SHRINK) -> dict[str, torch.Tensor]:
    """Per-primitive rows of split children, one per entry of `idx` (a parent's index, repeated for each of its
    children): each child is drawn on its parent's plane at an offset ~ N(0, diag(s^2)) and its scales are the
    parent's / shrink. The model's `split_children` then moves whatever it defines over (u, v) (waves, textures) so
    that each child shows the part of its parent's pattern it sits on."""
    R = quat_to_rotmat(params["quats"][idx])
    s = torch.exp(params["log_scales"][idx])
    offset_sigmas = torch.randn(idx.numel(), 2, generator=generator).to(s)  # the offset in the parent's sigmas
    children = {k: v[idx] for k, v in params.items()}
    children["means"] = params["means"][idx] + (R[:, :, :2] @ (offset_sigmas * s)[..., None]).squeeze(-1)
    children["log_scales"] = torch.log(s / shrink)
    return model.split_children(children, offset_sigmas, shrink)


@torch.no_grad()
def densify_and_prune(model: SurfelModel, optimizer, stats: DensifyStats, *, grad_threshold: float,
                      scene_extent: float, min_opacity: float, generator: torch.Generator,
                      percent_dense: float = 0.01, max_world_scale: float | None = None,
                      max_primitives: int | None = None, max_growth: float | None = None) -> dict:
    """One densification step; returns counts of cloned, split and pruned primitives. At most max_primitives in
    all and max_growth x the current count new ones (each clone or split adds one): the hottest candidates win."""
    params = {k: v.detach() for k, v in model.per_primitive().items()}
    n = model.num_primitives
    grads = stats.mean().to(params["means"].device)
    scales = torch.exp(params["log_scales"]).max(1).values
    hot = grads >= grad_threshold
    limits = ([max(0, max_primitives - n)] if max_primitives is not None else []) + \
        ([max(1, int(max_growth * n))] if max_growth is not None else [])
    room = min(limits) if limits else None
    if room is not None:  # keep only the hottest candidates
        if int(hot.sum()) > room:
            top = torch.topk(torch.where(hot, grads, torch.zeros_like(grads)), room).indices
            hot = torch.zeros_like(hot)
            hot[top] = True
    clone = hot & (scales <= percent_dense * scene_extent)
    split = hot & ~clone
    # clones copy the primitive; splits draw two children on the tangent plane, shrunk by SPLIT_SHRINK
    new = {k: v[clone] for k, v in params.items()}
    if split.any():
        children = split_rows(model, params, split.nonzero().squeeze(1).repeat(2), generator)
        new = {k: torch.cat([new[k], children[k]]) for k in params}
    opacity = torch.sigmoid(params["logit_opacity"])
    keep = ~split & (opacity >= min_opacity)
    if max_world_scale is not None:
        keep &= scales <= max_world_scale
    # never prune everything: an empty model cannot recover
    if not keep.any() and not any(v.shape[0] for v in new.values()):
        keep = torch.ones_like(keep)
    model.edit_primitives(optimizer, keep.cpu() if keep.device.type == "cpu" else keep, new)
    n_new = model.num_primitives
    stats.grad_sum = torch.zeros(n_new)
    stats.count = torch.zeros(n_new)
    return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int((~keep).sum() - split.sum()),
            "primitives": n_new}


@torch.no_grad()
def reset_opacity(model: SurfelModel, optimizer, value: float = 0.01) -> None:
    """Clamp every opacity to at most `value` (and clear its Adam moments), as 2DGS does periodically."""
    p = model.logit_opacity
    p.copy_(torch.minimum(p, inverse_sigmoid(torch.tensor(value)).to(p)))
    state = optimizer.state.get(p)
    if state:
        for key in ("exp_avg", "exp_avg_sq"):
            if key in state:
                state[key].zero_()
