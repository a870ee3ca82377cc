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
# as Mip-Splatting's screen filter; see reference.footprint_filter.
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
    dtype = s.means.dtype
    R = quat_to_rotmat(s.quats)
    tu, tv, tw = R[..., 0], R[..., 1], R[..., 2]
    # The camera's products in double, rounded once to the surfels' dtype, and the centre's camera coordinates
    # accumulated in double: a scene far from the origin cancels large coordinates against the camera's translation.
    # The native backends do the same (rasterizers/native.py, csrc/surfel_math.h project_surfel), so they agree
    # there to the rounding of the result.
    cam64 = cam.to(dtype=torch.float64)
    KR, Kt = (cam64.K @ cam64.R).to(dtype), (cam64.K @ cam64.t).to(dtype)
    a = (s.scales[:, :1] * tu) @ KR.T
    b = (s.scales[:, 1:2] * tv) @ KR.T
    c = (s.means.double() @ KR.double().T + Kt.double()).to(dtype)
    T = torch.stack([a, b, c], dim=-1)  # columns a, b, c -> T[:, i, :] is row m_{i+1}
    depth = c[:, 2]
    center_px = c[:, :2] / torch.where(depth.abs() > 1e-12, depth, torch.ones_like(depth))[:, None]
    view = s.means - cam64.center.to(dtype)
    facing = ((tw * view).sum(-1, keepdim=True) > 0).to(tw.dtype)
    normal = tw * (1 - 2 * facing)
    boxes, visible = screen_boxes(T.detach(), center_px.detach(), depth.detach(), s.opacities.detach(), cam, settings,
                                  s.falloff.detach())
    return Projected(T, center_px, depth, normal, boxes, visible)


def falloff(rho: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """The kernel falloff f(rho) (csrc/surfel_math.h falloff, the same maths): exp(-rho/2) where the falloff exponent
    s is 0, the Beta kernel (1 - s rho/2)_+^(1/s) where 0 < s <= 1. Where s = 0 the Gaussian carries a term
    -s rho^2/8 in its exponent, 0 in value, so that d f/ds there is the Beta kernel's limit, as in the native
    backward (a surfel can move from the Gaussian into the Beta family)."""
    beta = s > 0
    x = 0.5 * s * rho
    inside = beta & (x < 1)
    s_safe = torch.where(beta, s, torch.ones_like(s))
    log_f = torch.log1p(-torch.where(inside, x, torch.zeros_like(x))) / s_safe
    b = torch.where(inside, torch.exp(log_f), torch.zeros_like(x))
    r = rho.clamp(max=1e15)  # keeps s r^2 at 0 (not NaN) for an unbounded rho
    return torch.where(beta, b, torch.exp(-0.5 * rho - s * r * r / 8))


def support_rho(log_o: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """rho where o f(rho) falls to alpha_min (log_o = ln(o / alpha_min) > 0): 2 log_o for the Gaussian,
    (2/s)(1 - (alpha_min / o)^s) for the Beta kernel."""
    beta = s > 0
    return torch.where(beta, -2 * torch.expm1(-s * log_o) / torch.where(beta, s, torch.ones_like(s)), 2 * log_o)


@torch.no_grad()
def screen_boxes(T, center_px, depth, opacities, cam: Camera, settings: RasterSettings = SETTINGS, falloffs=None):
    """Exact screen bounds of each surfel's support.

    A contribution is skipped when o f(rho) < alpha_min, so the support is the disc u^2+v^2 <= r^2 with
    r^2 = support_rho (2 ln(o / alpha_min) for the Gaussian), together with the filter disc |d|^2 <= r^2 / filter_inv_sq
    around the projected centre. Bounding both exactly means the boxes only save work and never change a pixel.
    The disc's image is a conic; if the disc reaches the camera plane it is unbounded and we use the
    whole image. Anti-aliased, the support is the footprint-widened one (no screen filter), bounded as described in
    the code; there the boxes also bound what the rasterizers shade (see FOOTPRINT_PAD).
    """
    n = T.shape[0]
    log_o = torch.log((opacities.clamp(0, 1) / settings.alpha_min).clamp_min(1e-30))
    visible = (depth > settings.near) & (log_o > 0)
    s = torch.zeros_like(log_o) if falloffs is None else falloffs.to(log_o)
    r2 = torch.where(log_o > 0, support_rho(log_o.clamp_min(0), s), torch.zeros_like(log_o))
    big = float(max(cam.width, cam.height)) * 4 + 1e4
    inf_box = torch.tensor([-big, -big, big, big], dtype=T.dtype, device=T.device).expand(n, 4)
    zero = torch.zeros_like(r2)
    disc = _conic_box(T, r2, zero, zero, zero, inf_box)
    if settings.antialiased:
        # no screen filter: the support seen through the footprint, bounded two ways (both exact bounds for a surfel
        # seen face on): the conic of x^T (I + S)^-1 x <= r^2 with the centre's footprint S, and the disc's image
        # grown by r footprint sigmas; then padded for the footprint's change over a tilted surfel
        s00, s01, s11, tilt = centre_footprint(T, center_px, settings)
        wide = _conic_box(T, r2, s00, s01, s11, inf_box)
        grown = torch.sqrt(r2 * settings.pixel_filter)[:, None]
        grown = torch.cat([disc[:, :2] - grown, disc[:, 2:] + grown], -1)
        support = torch.cat([torch.maximum(wide[:, :2], grown[:, :2]), torch.minimum(wide[:, 2:], grown[:, 2:])], -1)
        pad = (FOOTPRINT_PAD * (support[:, 2:] - support[:, :2]) + FOOTPRINT_PAD_PX) * tilt[:, None]
        boxes = torch.cat([support[:, :2] - pad, support[:, 2:] + pad], -1)
    else:
        rf = torch.sqrt(r2 / settings.filter_inv_sq)
        filt = torch.cat([center_px - rf[:, None], center_px + rf[:, None]], -1)
        boxes = torch.cat([torch.minimum(disc[:, :2], filt[:, :2]), torch.maximum(disc[:, 2:], filt[:, 2:])], -1)
    boxes = torch.nan_to_num(boxes, nan=0.0, posinf=big, neginf=-big).clamp(-big, big)
    # slack for rounding: a box is a cull test, never a cut
    pad = 1e-3 * (1 + boxes.abs())
    boxes = boxes + torch.cat([-pad[:, :2], pad[:, 2:]], -1)
    on_screen = (boxes[:, 2] >= 0.5) & (boxes[:, 0] <= cam.width - 0.5) & (boxes[:, 3] >= 0.5) & (boxes[:, 1] <= cam.height - 0.5)
    return boxes, visible & on_screen


# The footprint changes over a tilted surfel (J is taken per pixel); the box of the support seen with the centre's
# footprint grows by this fraction of its size and this many pixels, times the tilt (centre_footprint). Exact for
# a surfel seen face on; nearly edge on, the box may trim a faint fringe (alpha near alpha_min), the same in every
# backend: the reference shades only inside the boxes. The same numbers are in csrc/surfel_math.h;
# tests/test_antialias.py measures the trim.
FOOTPRINT_PAD = 0.05
FOOTPRINT_PAD_PX = 1.0
# Anti-aliased: a pair is culled where the pixel footprint's standard deviation exceeds this fraction of the pixel's
# distance to the surfel plane's vanishing line (there the footprint's linearisation fails and would leave a faint
# fringe toward the horizon of large grazing surfels).
LINEAR_LIMIT = 0.2


def centre_footprint(T: torch.Tensor, center_px: torch.Tensor, settings: RasterSettings):
    """The pixel footprint's covariance S = pixel_filter J J^T in the surfel's frame at its projected centre, per
    surfel: (s00, s01, s11), and how much it changes over the surfel, 0..1 (tilt). There c = x A + y B + C =
    (0, 0, c_z), so J = d(u, v)/d(pixel) = [[A0, B0], [A1, B1]] / c_z (A = m2 x m3, B = m3 x m1, C = m1 x m2). J
    changes with c_z, which is affine in the pixel (gradient (A2, B2)): constant for a surfel seen face on (tilt 0);
    tilt 1 at LINEAR_LIMIT footprints from the vanishing line, beyond which pairs are culled. Only for culling
    boxes; the render takes J at every pixel."""
    m1, m2, m3 = T[:, 0], T[:, 1], T[:, 2]
    A, B, C = torch.linalg.cross(m2, m3), torch.linalg.cross(m3, m1), torch.linalg.cross(m1, m2)
    cz = C[:, 2] + center_px[:, 0] * A[:, 2] + center_px[:, 1] * B[:, 2]
    inv = 1 / torch.where(cz != 0, cz, torch.full_like(cz, 1e-30))
    j00, j01, j10, j11 = A[:, 0] * inv, B[:, 0] * inv, A[:, 1] * inv, B[:, 1] * inv
    f = settings.pixel_filter
    tilt = (math.sqrt(f) * torch.sqrt(A[:, 2] ** 2 + B[:, 2] ** 2) * inv.abs() / LINEAR_LIMIT).clamp(max=1.0)
    return f * (j00 * j00 + j01 * j01), f * (j00 * j10 + j01 * j11), f * (j10 * j10 + j11 * j11), tilt


def _conic_box(T, r2, s00, s01, s11, inf_box):
    """Screen box of the image of x^T (I + S)^-1 x <= r^2 in the surfel's plane (S = 0: the disc of radius r), from
    the dual conic Q = T diag(r^2 (I + S), -1) T^T: the vertical tangent lines x solve Q00 - 2x Q02 + x^2 Q22 = 0.
    The whole image (inf_box) where the region reaches the camera plane or S is not finite."""
    finite = s00 + s11 < 1e12  # False for NaN and inf too
    s00, s01, s11 = (torch.where(finite, t, torch.zeros_like(t)) for t in (s00, s01, s11))
    D = torch.diag_embed(torch.stack([r2 * (1 + s00), r2 * (1 + s11), -torch.ones_like(r2)], -1))
    D[:, 0, 1] = D[:, 1, 0] = r2 * s01
    Q = torch.einsum("nik,nkl,njl->nij", T, D, T)
    q22 = Q[:, 2, 2]
    bounded = (q22 < 0) & finite  # entirely in front of the camera plane
    safe = torch.where(bounded, q22, -torch.ones_like(q22))
    cx, cy = Q[:, 0, 2] / safe, Q[:, 1, 2] / safe
    hx = torch.sqrt((Q[:, 0, 2] ** 2 - Q[:, 0, 0] * q22).clamp_min(0)) / safe.abs()
    hy = torch.sqrt((Q[:, 1, 2] ** 2 - Q[:, 1, 1] * q22).clamp_min(0)) / safe.abs()
    box = torch.stack([cx - hx, cy - hy, cx + hx, cy + hy], -1)
    return torch.where(bounded[:, None], box, inf_box)


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
