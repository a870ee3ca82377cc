"""The reference rasterizer: plain PyTorch, differentiable by autograd, CPU or GPU.

It is the oracle the native backends are tested against, so it favours clarity over speed. Work is split into
screen rectangles small enough that (pixels x overlapping surfels) stays under a memory budget; each rectangle
evaluates every (pixel, surfel) pair densely and composites with a cumulative product.

The appearance is a composition of kinds, as in csrc/surfel_math.h: each kind of the Surfels table has its twin here
(KIND_TWINS, the same maths as its section of the header), and a Python kind (Surfels.appearance_kind, a plugin's
registered function) is one more, which only this backend renders. Their colours add up (clamped at 0), their
opacity gains multiply.
"""
from __future__ import annotations

import math

import torch

from ..errors import ShapeError
from ..types import BUILTIN_KINDS, TEXTURE_RADIUS, Camera, RenderOutput, Surfels
from .common import (LINEAR_LIMIT, SETTINGS, Projected, RasterSettings, background_tensor, centre_footprint, falloff,
                     ndc_depth, project)

# (pixel, surfel, wave) triples evaluated at once; bounds memory with autograd to a few hundred MB.
PAIR_BUDGET = 1 << 19


def rasterize_reference(surfels: Surfels, camera: Camera, background=None, settings: RasterSettings = SETTINGS, *,
                        pair_budget: int = PAIR_BUDGET) -> RenderOutput:
    s = surfels
    dtype, device = s.means.dtype, s.means.device
    cam = camera.to(device)  # as given: project() takes the camera's products in double, as the native backends
    H, W = cam.height, cam.width
    bg = background_tensor(background, s.means)
    out = {
        "rgb": s.means.new_zeros(H, W, 3), "alpha": s.means.new_zeros(H, W), "depth": s.means.new_zeros(H, W),
        "median_depth": s.means.new_zeros(H, W), "normal": s.means.new_zeros(H, W, 3),
        "distortion": s.means.new_zeros(H, W),
    }
    proj = project(s, cam, settings) if s.num else None
    if proj is None or not bool(proj.visible.any()):
        return _finish(_attached(out, s), bg)
    order = _depth_order(proj)
    boxes = proj.boxes[order]
    pieces = []  # (x0, x1, y0, y1, dict of [h,w,...] tensors)
    stack = [(0, W, 0, H, order, boxes)]
    waves = max(1, s.num_waves) + (4 if s.texture_size else 0)
    if s.appearance_kind is not None:
        waves += max(4, math.prod(s.appearance_params.shape[1:]))
    while stack:
        x0, x1, y0, y1, idx, bx = stack.pop()
        keep = (bx[:, 2] >= x0 + 0.5) & (bx[:, 0] <= x1 - 0.5) & (bx[:, 3] >= y0 + 0.5) & (bx[:, 1] <= y1 - 0.5)
        idx, bx = idx[keep], bx[keep]
        if idx.numel() == 0:
            continue
        area = (x1 - x0) * (y1 - y0)
        if area * idx.numel() * waves > pair_budget and area > 1:
            if x1 - x0 >= y1 - y0:
                xm = (x0 + x1) // 2
                stack += [(x0, xm, y0, y1, idx, bx), (xm, x1, y0, y1, idx, bx)]
            else:
                ym = (y0 + y1) // 2
                stack += [(x0, x1, y0, ym, idx, bx), (x0, x1, ym, y1, idx, bx)]
            continue
        pieces.append((x0, x1, y0, y1, _shade_rect(s, proj, idx, x0, x1, y0, y1, settings, cam)))
    if not pieces:
        return _finish(_attached(out, s), bg)
    # assemble without in-place writes into tensors autograd needs: pad each piece to full size and sum
    for key in out:
        acc = out[key]
        for x0, x1, y0, y1, vals in pieces:
            v = vals[key]
            pad = [0, 0] * (v.dim() - 2) + [x0, W - x1, y0, H - y1]
            acc = acc + torch.nn.functional.pad(v, pad)
        out[key] = acc
    return _finish(out, bg)


def _attached(out: dict, s: Surfels) -> dict:
    """A render that draws nothing, tied to the surfels with zero gradients (as the native backends return): a loss
    over it can be backpropagated like any other."""
    tensors = list(s.tensors().values())
    if s.appearance_params is not None:
        tensors.append(s.appearance_params)
    zero = sum(t.sum() for t in tensors) * 0  # the fields are finite (Surfels.validate)
    return {k: v + zero for k, v in out.items()}


def _finish(out: dict, bg: torch.Tensor) -> RenderOutput:
    out["rgb"] = out["rgb"] + (1 - out["alpha"])[..., None] * bg
    return RenderOutput(**out)


def _depth_order(proj: Projected) -> torch.Tensor:
    """Visible surfels sorted front to back by the camera depth of their centre (ties by index)."""
    vis = torch.nonzero(proj.visible).squeeze(1)
    d = proj.depth.detach()[vis]
    # stable sort keeps index order among equal depths, as the native backends do
    return vis[torch.sort(d, stable=True).indices]


def _shade_rect(s: Surfels, proj: Projected, idx: torch.Tensor, x0: int, x1: int, y0: int, y1: int,
                st: RasterSettings, cam: Camera) -> dict:
    """Composite surfels `idx` (front to back) over the pixels of one rectangle; values before background."""
    dtype, device = s.means.dtype, s.means.device
    h, w = y1 - y0, x1 - x0
    ys, xs = torch.meshgrid(torch.arange(y0, y1, device=device, dtype=dtype) + 0.5,
                            torch.arange(x0, x1, device=device, dtype=dtype) + 0.5, indexing="ij")
    px, py = xs.reshape(-1, 1), ys.reshape(-1, 1)  # [P,1]
    T = proj.T[idx]  # [n,3,3]
    m3 = T[:, 2]  # [n,3]: the hit depth z = m3 . (u, v, 1)
    # The intersection uses T only through ratios (u, v, the footprint's Jacobian) that a common scale leaves
    # unchanged; a power of two that brings each surfel's largest entry near 1 changes no rounding, and keeps the
    # products of entries in range for a surfel many orders of magnitude wider than the image (as the native
    # backends' plane_coeffs, csrc/surfel_math.h).
    Tn = _unit_scaled(T)
    m1, m2, m3n = Tn[:, 0], Tn[:, 1], Tn[:, 2]
    # ray-splat intersection: (u, v) from the cross product of the two planes through the pixel
    hx = px[..., None] * m3n - m1  # [P,n,3]
    hy = py[..., None] * m3n - m2
    cr = torch.linalg.cross(hx, hy)
    cz = cr[..., 2]
    hits = (cz.abs() > st.parallel_eps * torch.maximum(cr[..., 0].abs(), cr[..., 1].abs())) & (cz != 0)
    cz_safe = torch.where(hits, cz, torch.ones_like(cz))
    u = torch.where(hits, cr[..., 0] / cz_safe, torch.zeros_like(cz))
    v = torch.where(hits, cr[..., 1] / cz_safe, torch.zeros_like(cz))
    blur = None
    if st.antialiased:
        # the pixel footprint, seen in the surfel's frame, filters the surfel and its waves (footprint_filter)
        A, B = torch.linalg.cross(m2, m3n), torch.linalg.cross(m3n, m1)  # dc/dx and dc/dy
        inv = 1 / cz_safe
        jac = ((A[:, 0] - u * A[:, 2]) * inv, (B[:, 0] - u * B[:, 2]) * inv,
               (A[:, 1] - v * A[:, 2]) * inv, (B[:, 1] - v * B[:, 2]) * inv)
        # the footprint is linearised at the hit: not where the pixel is within a few footprints of the plane's
        # vanishing line c_z = 0 (c_z is affine in the pixel, gradient (A_2, B_2))
        linear = st.pixel_filter * (A[:, 2] ** 2 + B[:, 2] ** 2) <= (LINEAR_LIMIT * cz) ** 2
        gain, q, (u, v) = footprint_filter(u, v, jac, st, hits & linear)
        blur = waves_blur(T, proj.center_px[idx], st)
        z = m3[:, 0] * u + m3[:, 1] * v + m3[:, 2]
        looks = appearance(s, idx, u, v, blur, px, py, cam)
        alpha = s.opacities[idx] * gain * falloff(q, s.falloff[idx])
        for _, g in looks:
            if g is not None:
                alpha = alpha * g
        alpha = torch.clamp(alpha, max=st.alpha_max)
        # the culling box bounds the support (common.FOOTPRINT_PAD): a pixel outside it is not shaded, as in the
        # tile loops, even where a nearly edge-on surfel's footprint would leave a faint fringe beyond it
        box = proj.boxes[idx]
        inbox = (px >= box[:, 0]) & (px <= box[:, 2]) & (py >= box[:, 1]) & (py <= box[:, 3])
        valid = hits & inbox & (gain > 0) & (alpha >= st.alpha_min) & (z >= st.near)
    else:
        rho3d = u * u + v * v
        d = torch.stack([px - proj.center_px[idx, 0], py - proj.center_px[idx, 1]], -1)  # [P,n,2]
        rho2d = st.filter_inv_sq * (d * d).sum(-1)
        use3d = hits & (rho3d <= rho2d)
        rho = torch.where(use3d, rho3d, rho2d)
        # where the screen filter wins, the surfel is seen as its centre (depth and colour at u = v = 0)
        u = torch.where(use3d, u, torch.zeros_like(u))
        v = torch.where(use3d, v, torch.zeros_like(v))
        z = torch.where(use3d, m3[:, 0] * u + m3[:, 1] * v + m3[:, 2], proj.depth[idx].expand_as(u))
        looks = appearance(s, idx, u, v, None, px, py, cam)
        alpha = s.opacities[idx] * falloff(rho, s.falloff[idx])
        for _, g in looks:
            if g is not None:
                alpha = alpha * g
        alpha = torch.clamp(alpha, max=st.alpha_max)
        valid = (alpha >= st.alpha_min) & (z >= st.near)
    alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
    # front-to-back compositing; a prefix of the surfels is kept until T would fall below t_min
    T_after = torch.cumprod(1 - alpha, dim=1)
    T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], dim=1)
    kept = T_after >= st.t_min
    weight = torch.where(kept, alpha * T_before, torch.zeros_like(alpha))  # [P,n]
    T_final = torch.prod(torch.where(kept, 1 - alpha, torch.ones_like(alpha)), dim=1)
    color = looks[0][0]
    for rgb_k, _ in looks[1:]:
        if rgb_k is not None:
            color = color + rgb_k
    color = torch.clamp(color, min=0)  # [P,n,3]
    rgb = (weight[..., None] * color).sum(1)
    acc = 1 - T_final
    z_safe = torch.where(valid, z, torch.ones_like(z))
    depth_sum = (weight * z_safe).sum(1)
    depth = torch.where(acc > 0, depth_sum / torch.where(acc > 0, acc, torch.ones_like(acc)), torch.zeros_like(acc))
    normal = weight @ proj.normal[idx]
    # median depth: the last kept contribution that starts while T > 0.5 (official 2DGS rule)
    mask = kept & valid & (T_before > 0.5)
    pos = torch.arange(1, mask.shape[1] + 1, device=device)
    last = (mask * pos).argmax(1)
    median = torch.where(mask.any(1), z_safe.gather(1, last[:, None]).squeeze(1), torch.zeros_like(acc))
    # distortion: sum_i w_i sum_{j<i} w_j (m_i - m_j)^2 from exclusive running sums
    m = ndc_depth(z_safe, st)
    A = torch.cumsum(weight, 1) - weight
    M1 = torch.cumsum(weight * m, 1) - weight * m
    M2 = torch.cumsum(weight * m * m, 1) - weight * m * m
    distortion = (weight * (m * m * A + M2 - 2 * m * M1)).sum(1)
    return {"rgb": rgb.reshape(h, w, 3), "alpha": acc.reshape(h, w), "depth": depth.reshape(h, w),
            "median_depth": median.reshape(h, w), "normal": normal.reshape(h, w, 3),
            "distortion": distortion.reshape(h, w)}


def _unit_scaled(T: torch.Tensor) -> torch.Tensor:
    """T [n,3,3] times a power of two per surfel that brings its largest entry into [0.5, 1) (1 where that entry is
    0 or not finite). The factor is a constant for autograd: nothing that uses the result depends on it."""
    top = T.detach().abs().amax(dim=(1, 2))
    top = torch.where(torch.isfinite(top) & (top > 0), top, torch.ones_like(top))
    # a product with the factor (torch.ldexp passes no gradient)
    return T * torch.ldexp(torch.ones_like(top), -torch.frexp(top).exponent)[:, None, None]


def footprint_filter(u, v, jac, st: RasterSettings, hits):
    """The surfel's Gaussian and its colour seen through a Gaussian pixel footprint (anti-aliasing).

    The footprint, variance st.pixel_filter in pixels, is N(x, S) in the surfel's frame around the hit x = (u, v),
    with S = pixel_filter J J^T and J = d(u, v)/d(pixel) (jac = J00, J01, J10, J11). With P = (I + S)^-1:
    - the surfel's falloff exp(-|x'|^2/2) averaged over the footprint is gain exp(-q/2), gain = det(I + S)^-1/2 and
      q = x^T P x: a surfel much smaller than a pixel keeps its coverage, not its peak;
    - the colour, averaged over the footprint weighted by that falloff, is the colour's mean under N(P x, I - P):
      a wave a cos(k.x' + phi) becomes a exp(-k^T (I - P) k / 2) cos(k.(P x) + phi).
    S -> 0 gives back the unfiltered surfel; S -> infinity (a sub-pixel surfel) its mean colour over its Gaussian.
    Returns gain (0 where the pair is culled), q and the colour's centre P x. The waves' blur I - P is taken once
    per surfel, at its projected centre (waves_blur). Pairs with tr S > 1 / alpha_min^2 are culled: their gain
    alone is below alpha_min.
    """
    j00, j01, j10, j11 = jac
    f = st.pixel_filter
    s00 = f * (j00 * j00 + j01 * j01)
    s01 = f * (j00 * j10 + j01 * j11)
    s11 = f * (j10 * j10 + j11 * j11)
    keep = hits & (s00 + s11 <= 1 / st.alpha_min ** 2)
    zero = torch.zeros_like(s00)
    s00, s01, s11 = (torch.where(keep, t, zero) for t in (s00, s01, s11))
    det = (1 + s00) * (1 + s11) - s01 * s01
    p00, p01, p11 = (1 + s11) / det, -s01 / det, (1 + s00) / det
    gain = torch.where(keep, torch.rsqrt(det), zero)
    q = p00 * u * u + 2 * p01 * u * v + p11 * v * v
    mu = (p00 * u + p01 * v, p01 * u + p11 * v)
    return gain, q, mu


def waves_blur(T, center_px, st: RasterSettings):
    """The waves' blur I - (I + S)^-1 per surfel, (b00, b01, b11), with S the pixel footprint at the projected
    centre (common.centre_footprint): one blur for all the surfel's pixels, so each wave's gain exp(-k^T b k / 2) is
    computed once per surfel. I where S is not finite (a surfel seen exactly edge on). In double, as the native
    backends: for a surfel seen nearly edge on S is huge and nearly singular, and det(I + S) cancels to 0 in float."""
    dtype = T.dtype
    s00, s01, s11, _ = centre_footprint(T.double(), center_px.double(), st)
    finite = s00 + s11 < 1e30  # False for NaN and inf too
    s00, s01, s11 = (torch.where(finite, t, torch.zeros_like(t)) for t in (s00, s01, s11))
    det = (1 + s00) * (1 + s11) - s01 * s01
    one, zero = torch.ones_like(det), torch.zeros_like(det)
    blur = (torch.where(finite, 1 - (1 + s11) / det, one), torch.where(finite, s01 / det, zero),
            torch.where(finite, 1 - (1 + s00) / det, one))
    return tuple(b.to(dtype) for b in blur)


def texture_gain(blur, size: int):
    """The texture's footprint gain per surfel, exp(-k_n^2 (b00 + b11) / 4): the mean over the u and v axes of a wave's
    gain (exp(-k^T b k / 2)) at the texel grid's Nyquist frequency k_n = pi T / (2 R) (csrc/surfel_math.h
    texture_gain)."""
    b00, _, b11 = blur
    kn = math.pi * size / (2 * TEXTURE_RADIUS)
    return torch.exp(-0.25 * (kn * kn) * (b00 + b11))


def texel_weights(size: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """[T,T] the texels' weights in the texture's mean: the Gaussian falloff exp(-|centre|^2 / 2) at each texel's
    centre, normalised (what a surfel far smaller than a pixel shows of its texture)."""
    c = -TEXTURE_RADIUS + (torch.arange(size, dtype=torch.float64) + 0.5) * (2 * TEXTURE_RADIUS / size)
    a = torch.exp(-0.5 * c * c)
    w = a[:, None] * a[None, :]
    return (w / w.sum()).to(dtype=dtype, device=device)


def prefilter_texture(texture, blur):
    """The texture an anti-aliased pixel sees [n,T,T,4]: per channel, its mean as the surfel shows it (texel_weights)
    plus its deviation from that mean times texture_gain, so texel detail finer than the pixel footprint fades to
    the mean (as the waves do)."""
    w = texel_weights(texture.shape[1], texture.dtype, texture.device)[None, :, :, None]
    mean = (texture * w).sum(dim=(1, 2), keepdim=True)
    return mean + texture_gain(blur, texture.shape[1])[:, None, None, None] * (texture - mean)


def sample_texture(tex: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Textures [n,T,T,C] sampled bilinearly at (u, v) [P,n] (each texture's surfel's sigmas) -> [P,n,C].

    Texel (r, c) is centred at (u, v) = -R + (c + 1/2, r + 1/2) 2R/T, R = TEXTURE_RADIUS; outside the centres the edge
    texels extend (clamp to edge)."""
    size, channels = tex.shape[1], tex.shape[-1]
    scale = size / (2 * TEXTURE_RADIUS)

    def axis(x):
        t = ((x + TEXTURE_RADIUS) * scale - 0.5).nan_to_num(nan=0.0).clamp(0, size - 1)
        i = t.detach().floor().clamp(max=max(size - 2, 0))
        return t - i, i.long(), (i + 1).clamp(max=size - 1).long()

    fu, iu0, iu1 = axis(u)
    fv, iv0, iv1 = axis(v)
    flat = tex.reshape(tex.shape[0], size * size, channels)
    n = torch.arange(tex.shape[0], device=tex.device)[None, :]

    def texel(iv, iu):
        return flat[n, iv * size + iu]  # [P,n,C]

    fu, fv = fu[..., None], fv[..., None]
    t00, t01, t10, t11 = texel(iv0, iu0), texel(iv0, iu1), texel(iv1, iu0), texel(iv1, iu1)
    a = t00 + fu * (t01 - t00)
    b = t10 + fu * (t11 - t10)
    return a + fv * (b - a)


# ---- the appearance kinds' twins (csrc/surfel_math.h: one section each) ----------------------------------------------
# A twin takes the batch, the surfels idx [n] of a shading pass, the points (u, v) [P,n] where the pairs' colours are
# taken and, anti-aliased, the blur (b00, b01, b11) per surfel (waves_blur; else None), and returns (rgb [P,n,3] or
# None, opacity gain [P,n] or None). The first kind's rgb must not be None (the wave bank's holds the base colour).

def wave_bank_twin(s: Surfels, idx: torch.Tensor, u: torch.Tensor, v: torch.Tensor, blur=None):
    """The wave bank (csrc/surfel_math.h WaveBank): c0 + sum_k a_k g_k cos(k_k . (u, v) + phi_k), no opacity gain.
    g_k = 1, or with blur = (b00, b01, b11) per surfel exp(-k_k^T b k_k / 2)."""
    base = s.base_color[idx]  # [n,3]
    if s.num_waves == 0:
        return base.expand(u.shape[0], -1, -1), None
    k = s.wave_vectors[idx]  # [n,K,2]
    phase = u[..., None] * k[:, :, 0] + v[..., None] * k[:, :, 1] + s.wave_phases[idx]  # [P,n,K]
    amp = s.wave_amplitudes[idx]  # [n,K,3]
    if s.wave_counts is not None:
        # waves at index >= wave_counts[i] do not exist: zero amplitude, and torch.where also blocks every gradient
        # into them (their phase's only path to the colour is through the zeroed amplitude)
        on = torch.arange(s.num_waves, device=amp.device) < s.wave_counts[idx][:, None]
        amp = torch.where(on[..., None], amp, torch.zeros_like(amp))
    wave = torch.cos(phase)
    if blur is not None:
        b00, b01, b11 = (b[..., None] for b in blur)
        kx, ky = k[:, :, 0], k[:, :, 1]
        wave = wave * torch.exp(-0.5 * (b00 * kx * kx + 2 * b01 * kx * ky + b11 * ky * ky))
    return base + torch.einsum("pnk,nkc->pnc", wave, amp), None


def texture_twin(s: Surfels, idx: torch.Tensor, u: torch.Tensor, v: torch.Tensor, blur=None):
    """The texture (csrc/surfel_math.h Texture): its bilinear RGBA at (u, v), rgb added to the colour, alpha the opacity
    gain; nothing without one (T = 0). Anti-aliased (blur given), the prefiltered texture."""
    if s.texture_size == 0:
        return None, None
    tex = s.texture[idx]
    if blur is not None:
        tex = prefilter_texture(tex, blur)
    sample = sample_texture(tex, u, v)  # [P,n,4]
    return sample[..., :3], sample[..., 3]


# Each kind of the Surfels table (splatzoo.types.BUILTIN_KINDS) -> its twin; a test holds the two lists equal.
KIND_TWINS = {"wave_bank": wave_bank_twin, "texture": texture_twin}


def view_directions(px: torch.Tensor, py: torch.Tensor, cam: Camera, dtype) -> torch.Tensor:
    """Unit world directions [P,1,3] of the rays through pixel centres (px, py) [P,1] (from the camera)."""
    cam64 = cam.to(dtype=torch.float64)
    ray = torch.stack([px.double(), py.double(), torch.ones_like(px, dtype=torch.float64)], -1)  # [P,1,3]
    d = ray @ torch.linalg.inv(cam64.K).T @ cam64.R  # R^T K^-1 (x, y, 1), as rows
    return (d / d.norm(dim=-1, keepdim=True)).to(dtype)


def python_kind_twin(s: Surfels, idx: torch.Tensor, u: torch.Tensor, v: torch.Tensor, px, py, cam: Camera):
    """A Python kind (Surfels.appearance_kind, splatzoo.registry.APPEARANCE_KINDS): its function at every pair, its
    output checked and its gain clamped into [0, 1]. Anti-aliased, it is evaluated at the footprint's centre and not
    prefiltered."""
    from ..registry import APPEARANCE_KINDS

    spec = APPEARANCE_KINDS.get(s.appearance_kind)
    dirs = view_directions(px, py, cam, u.dtype).to(u.device).expand(*u.shape, 3)
    out = spec.fn(u, v, dirs, s.appearance_params[idx])
    if not (isinstance(out, tuple) and len(out) == 2):
        raise ShapeError(f"appearance kind {spec.name!r}: its function must return (rgb, gain), got "
                         f"{type(out).__name__}")
    rgb, gain = out
    P, n = u.shape
    if not isinstance(rgb, torch.Tensor) or tuple(rgb.shape) != (P, n, 3):
        raise ShapeError(f"appearance kind {spec.name!r}: rgb must be [P,n,3] = [{P},{n},3], got "
                         f"{list(rgb.shape) if isinstance(rgb, torch.Tensor) else type(rgb).__name__}")
    if gain is not None:
        if not isinstance(gain, torch.Tensor) or tuple(gain.shape) != (P, n):
            raise ShapeError(f"appearance kind {spec.name!r}: gain must be [P,n] = [{P},{n}] or None, got "
                             f"{list(gain.shape) if isinstance(gain, torch.Tensor) else type(gain).__name__}")
        gain = torch.clamp(gain, 0, 1)
    return rgb.to(u.dtype), None if gain is None else gain.to(u.dtype)


def appearance(s: Surfels, idx: torch.Tensor, u: torch.Tensor, v: torch.Tensor, blur, px, py, cam: Camera) -> list:
    """(rgb, gain) of every kind at the pairs (surfels idx [n], points (u, v) [P,n]), in table order, then the
    batch's Python kind if it has one (px, py [P,1]: the pixel centres, for its view directions)."""
    looks = [KIND_TWINS[kind](s, idx, u, v, blur) for kind in BUILTIN_KINDS]
    if s.appearance_kind is not None:
        looks.append(python_kind_twin(s, idx, u, v, px, py, cam))
    return looks


def _texture_sample(s: Surfels, idx: torch.Tensor, u: torch.Tensor, v: torch.Tensor, blur=None):
    """The texture's RGBA at (u, v) [P,n,4] (texture_twin's rgb and gain in one tensor), or None without one."""
    rgb, gain = texture_twin(s, idx, u, v, blur)
    return None if rgb is None else torch.cat([rgb, gain[..., None]], -1)


def _appearance_color(s: Surfels, idx: torch.Tensor, u: torch.Tensor, v: torch.Tensor, blur=None,
                      tex=None) -> torch.Tensor:
    """The clamped colour [P,n,3] of the wave bank plus tex's rgb (tex: _texture_sample's, or None), as the
    reference shades the table's kinds."""
    color, _ = wave_bank_twin(s, idx, u, v, blur)
    if tex is not None:
        color = color + tex[..., :3]
    return torch.clamp(color, min=0)
