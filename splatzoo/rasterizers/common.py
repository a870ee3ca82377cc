"""The rasterizer settings and the per-surfel set-up shared by every backend.

RasterSettings is the one source of the rasterizer's numeric settings: the reference reads it, and the native
backends copy it field by field into the C++ `sz::Settings` struct (csrc/surfel_math.h) on every call.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from ..geometry import quat_to_rotmat
from ..types import Camera, Surfels


@dataclass(frozen=True)
class RasterSettings:
    """Numeric settings of every rasterizer backend (the defaults follow the official 2DGS renderer)."""

    near: float = 0.2              # hits closer than this camera depth are culled
    far: float = 100.0             # far plane of the NDC depth used by the distortion term
    alpha_max: float = 0.99        # alpha clamp
    alpha_min: float = 1.0 / 255.0  # contributions with a smaller alpha are skipped
    t_min: float = 1e-4            # stop before a contribution that would bring transmittance below this
    filter_inv_sq: float = 2.0     # screen-space low-pass filter: rho2d = filter_inv_sq * |pixel - centre|^2
    parallel_eps: float = 1e-6     # a ray with |c_z| <= parallel_eps max(|c_x|, |c_y|) misses the surfel's plane
    # Anti-aliasing: variance (px^2) of a Gaussian pixel footprint that filters every surfel and every wave (its
    # image in the surfel's (u, v) frame, through the ray-splat Jacobian); 0 turns it off and the surfel falls back
    # to the screen-space filter above instead. PIXEL_FILTER is the value `antialias` models render with.
    pixel_filter: float = 0.0
    tile: int = 16                 # tile size of the native tile rasterizers (compiled in: checked, not set)

    def __post_init__(self) -> None:
        from ..errors import SplatzooError

        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise SplatzooError(f"RasterSettings.{f.name} must be a finite number, got {v!r}")
        if not (0 < self.near < self.far):
            raise SplatzooError(f"RasterSettings: need 0 < near < far, got near={self.near}, far={self.far}")
        if not (0 < self.alpha_min <= self.alpha_max < 1):
            raise SplatzooError(f"RasterSettings: need 0 < alpha_min <= alpha_max < 1, got {self.alpha_min}, "
                                f"{self.alpha_max}")
        if not (0 <= self.t_min < 1) or self.filter_inv_sq <= 0 or self.parallel_eps < 0 or self.pixel_filter < 0:
            raise SplatzooError("RasterSettings: need 0 <= t_min < 1, filter_inv_sq > 0, parallel_eps >= 0 and "
                                "pixel_filter >= 0")

    @property
    def antialiased(self) -> bool:
        return self.pixel_filter > 0


SETTINGS = RasterSettings()
# The pixel footprint of anti-aliased rendering: a Gaussian with the variance of a one-pixel box (1/12) rounded up,
# as Mip-Splatting's screen filter; see footprint_filter below.
PIXEL_FILTER = 0.1
ANTIALIASED = RasterSettings(pixel_filter=PIXEL_FILTER)


@dataclass
class Projected:
    """Per-surfel quantities for one camera (autograd flows through all but the boxes).

    T [N,3,3]: rows m1, m2, m3 of M = K [R s_u t_u | R s_v t_v | R p + t];
    center_px [N,2] projected mean; depth [N] camera depth of the mean; normal [N,3] world normal facing the camera;
    boxes [N,4] (xmin, ymin, xmax, ymax) in pixel units covering every pixel centre the surfel can touch;
    visible [N] bool.
    """

    T: torch.Tensor
    center_px: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor
    boxes: torch.Tensor
    visible: torch.Tensor


def project(s: Surfels, cam: Camera, settings: RasterSettings = SETTINGS) -> Projected:
    R = quat_to_rotmat(s.quats)
    tu, tv, tw = R[..., 0], R[..., 1], R[..., 2]
    KR = cam.K @ cam.R
    a = (s.scales[:, :1] * tu) @ KR.T
    b = (s.scales[:, 1:2] * tv) @ KR.T
    c = s.means @ KR.T + cam.K @ cam.t
    T = torch.stack([a, b, c], dim=-1)  # columns a, b, c -> T[:, i, :] is row m_{i+1}
    depth = c[:, 2]
    center_px = c[:, :2] / torch.where(depth.abs() > 1e-12, depth, torch.ones_like(depth))[:, None]
    view = s.means - cam.center
    facing = ((tw * view).sum(-1, keepdim=True) > 0).to(tw.dtype)
    normal = tw * (1 - 2 * facing)
    boxes, visible = screen_boxes(T.detach(), center_px.detach(), depth.detach(), s.opacities.detach(), cam, settings)
    return Projected(T, center_px, depth, normal, boxes, visible)


@torch.no_grad()
def screen_boxes(T, center_px, depth, opacities, cam: Camera, settings: RasterSettings = SETTINGS):
    """Exact screen bounds of each surfel's support.

    A contribution is skipped when o exp(-rho/2) < alpha_min, so the support is the disc u^2+v^2 <= r^2 with
    r^2 = 2 ln(o / alpha_min), together with the filter disc |d|^2 <= ln(o / alpha_min) / (filter_inv_sq / 2) around the
    projected centre. Bounding both exactly means the boxes only save work and never change a pixel.
    The disc's image is a conic; if the disc reaches the camera plane it is unbounded and we use the
    whole image.
    """
    n = T.shape[0]
    log_o = torch.log((opacities.clamp(0, 1) / settings.alpha_min).clamp_min(1e-30))
    visible = (depth > settings.near) & (log_o > 0)
    r2 = (2 * log_o).clamp_min(0)
    # Dual conic Q = T diag(r^2, r^2, -1) T^T; the vertical tangent lines x solve Q00 - 2x Q02 + x^2 Q22 = 0.
    D = torch.stack([r2, r2, -torch.ones_like(r2)], -1)
    Q = torch.einsum("nik,nk,njk->nij", T, D, T)
    q22 = Q[:, 2, 2]
    bounded = q22 < 0  # disc entirely in front of the camera plane
    safe = torch.where(bounded, q22, -torch.ones_like(q22))
    cx, cy = Q[:, 0, 2] / safe, Q[:, 1, 2] / safe
    hx = torch.sqrt((Q[:, 0, 2] ** 2 - Q[:, 0, 0] * q22).clamp_min(0)) / safe.abs()
    hy = torch.sqrt((Q[:, 1, 2] ** 2 - Q[:, 1, 1] * q22).clamp_min(0)) / safe.abs()
    big = float(max(cam.width, cam.height)) * 4 + 1e4
    inf_box = torch.tensor([-big, -big, big, big], dtype=T.dtype, device=T.device).expand(n, 4)
    disc = torch.stack([cx - hx, cy - hy, cx + hx, cy + hy], -1)
    disc = torch.where(bounded[:, None], disc, inf_box)
    if settings.antialiased:
        # footprint-filtered: the support is the disc's image dilated by the footprint's own r-sigma disc
        pad = footprint_pad(r2, settings)
        boxes = torch.cat([disc[:, :2] - pad[:, None], disc[:, 2:] + pad[:, None]], -1)
    else:
        rf = torch.sqrt(log_o.clamp_min(0) / (settings.filter_inv_sq / 2))
        filt = torch.cat([center_px - rf[:, None], center_px + rf[:, None]], -1)
        boxes = torch.cat([torch.minimum(disc[:, :2], filt[:, :2]), torch.maximum(disc[:, 2:], filt[:, 2:])], -1)
    boxes = torch.nan_to_num(boxes, nan=0.0, posinf=big, neginf=-big).clamp(-big, big)
    # slack for rounding: a box is a cull test, never a cut
    pad = 1e-3 * (1 + boxes.abs())
    boxes = boxes + torch.cat([-pad[:, :2], pad[:, 2:]], -1)
    on_screen = (boxes[:, 2] >= 0.5) & (boxes[:, 0] <= cam.width - 0.5) & (boxes[:, 3] >= 0.5) & (boxes[:, 1] <= cam.height - 0.5)
    return boxes, visible & on_screen


def footprint_pad(r2: torch.Tensor, settings: RasterSettings) -> torch.Tensor:
    """How far (pixels) the footprint filter spreads a surfel beyond the image of its support disc.

    A pair is kept when o det(I + S)^-1/2 exp(-q/2) >= alpha_min, so q = x^T (I + S)^-1 x <= r^2 (det >= 1). As
    q = min over x = a + b of |a|^2 + b^T S^-1 b, some a in the disc has |J^-1 b| <= r sqrt(pixel_filter): to first
    order the pixel lies within r sqrt(pixel_filter) of the disc's image. The factor and the half pixel cover the
    perspective's second-order term (the box is a cull test, never a cut: tests/test_antialias.py checks it).
    """
    return 1.25 * torch.sqrt(r2 * settings.pixel_filter) + 0.5


def ndc_depth(z: torch.Tensor, settings: RasterSettings = SETTINGS) -> torch.Tensor:
    """The distortion term's depth map m(z) = f/(f-n) (1 - n/z)."""
    return settings.far / (settings.far - settings.near) * (1 - settings.near / z)


def background_tensor(background, like: torch.Tensor) -> torch.Tensor:
    if background is None:
        return like.new_zeros(3)
    bg = torch.as_tensor(background, dtype=like.dtype, device=like.device).reshape(-1)
    if bg.numel() == 1:
        bg = bg.expand(3)
    if bg.numel() != 3:
        from ..errors import ShapeError
        raise ShapeError(f"background must be a colour of 3 values (or one grey value), got {bg.numel()} values")
    return bg


def max_support_radius_sigma(settings: RasterSettings = SETTINGS) -> float:
    """Largest support radius in sigmas (opacity 1): sqrt(2 ln(1 / alpha_min)) ~ 3.33."""
    return math.sqrt(2 * math.log(1.0 / settings.alpha_min))
