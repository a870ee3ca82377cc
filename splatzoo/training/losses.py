"""Training losses (2DGS): 0.8 L1 + 0.2 D-SSIM, normal consistency, depth distortion."""
from __future__ import annotations

import torch

from ..metrics import dssim_loss
from ..types import Camera, RenderOutput


def photometric_loss(rgb: torch.Tensor, target: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    return (1 - lambda_dssim) * (rgb - target).abs().mean() + lambda_dssim * dssim_loss(rgb, target)


def depth_to_normal(depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """World-space normals [H,W,3] of the surface given by a camera-depth map [H,W], from central differences
    of the back-projected points, oriented towards the camera (zero on the border)."""
    H, W = depth.shape
    K = camera.K.to(depth)
    ys, xs = torch.meshgrid(torch.arange(H, device=depth.device, dtype=depth.dtype) + 0.5,
                            torch.arange(W, device=depth.device, dtype=depth.dtype) + 0.5, indexing="ij")
    pts = torch.stack([(xs - K[0, 2]) / K[0, 0] * depth, (ys - K[1, 2]) / K[1, 1] * depth, depth], -1)
    normal = torch.zeros_like(pts)
    if H >= 3 and W >= 3:
        dx = pts[1:-1, 2:] - pts[1:-1, :-2]
        dy = pts[2:, 1:-1] - pts[:-2, 1:-1]
        # +x right, +y down, +z forward: dy x dx points back at the camera for a fronto-parallel surface
        n = torch.linalg.cross(dy, dx)
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        normal = torch.nn.functional.pad(n.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)
    return normal @ camera.R.to(depth)  # camera -> world: n_w = R^T n_c, as row vectors n_c @ R


def normal_consistency_loss(out: RenderOutput, camera: Camera) -> torch.Tensor:
    """mean over pixels of sum_i w_i (1 - n_i . N) = alpha - (sum_i w_i n_i) . N, N from the rendered depth."""
    surface = depth_to_normal(out.depth, camera)
    return (out.alpha - (out.normal * surface).sum(-1)).mean()


def distortion_loss(out: RenderOutput) -> torch.Tensor:
    return out.distortion.mean()
