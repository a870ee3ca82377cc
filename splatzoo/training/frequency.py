"""Frequency-aware densification (`--strategy frequency`), after Neural Gabor splatting (Watanabe and Umetani, CVPR
2026; public code haato-w/neural-gabor-splatting): surfels are added where the rendered image lacks (or has too much)
detail in some frequency band, rather than where position gradients are large.

One step, every densification interval while the count is under the budget:
1. render a random few training views (the trainer draws them);
2. for the render and the photo, BANDS band-energy maps (band_energy): luma, the magnitude of its band-pass, its
   local contrast, normalised to [0, 1], smoothed; a band's error map is |render maps - photo maps|;
3. back-project each error map onto the surfels (back_project): surfel i's error is the mean of e(p) over the pixels
   it draws, weighted by its blending weight w_i(p) = alpha_i(p) T_i(p),
       error_i = sum_p w_i(p) e(p) / sum_p w_i(p)   (0 where it draws nothing),
   and its error for the step the most over views and bands;
4. surfels whose error reaches ERROR_THRESHOLD grow, the worst first, at most GROWTH x the count and never past the
   budget: small ones (largest scale <= percent_dense x scene extent) are cloned, large ones split in two;
5. each cloned parent and its clone, and each split child, get the opacity 1 - sqrt(1 - o) of their parent's o: two
   stacked copies then let through what the one did, (1 - o')^2 = 1 - o;
6. instead of 2DGS's periodic opacity resets every opacity falls by OPACITY_DECAY, and surfels under the run's
   min_opacity are pruned.
"""
from __future__ import annotations

from typing import Iterable

import torch
import torch.nn.functional as F

from ..errors import ShapeError
from ..models.base import SurfelModel, inverse_sigmoid, restart_moments
from ..types import SURFEL_FIELDS, Camera, Surfels
from .densify import split_rows

# the release's bands, in normalised spatial frequency: radius = |f| / max |f| over the FFT grid (|f| in cycles per
# pixel, so 1 is the grid's corner, sqrt(2) / 2 cycles per pixel); a band holds lo <= radius < hi
BANDS = ((0.01, 0.10), (0.10, 0.20), (0.20, 0.40))
LUMA = (0.2126, 0.7152, 0.0722)   # Rec. 709 luma weights of R, G, B
CONTRAST_WINDOW = 17   # local contrast: a band magnitude minus its mean over this many pixels square, clamped at 0
SMOOTH_WINDOW = 3      # the normalised maps are box-averaged over this many pixels square before they are compared
FLAT = 1e-5            # a band's local contrast spanning less than this (luma units) is float noise: its map is 0
ERROR_THRESHOLD = 0.01  # a surfel grows when its back-projected error reaches this
GROWTH = 0.05           # one step adds at most this fraction of the current count
OPACITY_DECAY = 0.001   # every step lowers every opacity by this (in place of opacity resets)
VIEWS = 20              # training views rendered per step (TrainConfig.densify_views)


def fast_length(n: int) -> int:
    """The smallest m >= n with no prime factor above 5 (a size the FFT handles fast)."""
    m = max(1, n)
    while True:
        r = m
        for p in (2, 3, 5):
            while r % p == 0:
                r //= p
        if r == 1:
            return m
        m += 1


def _box(x: torch.Tensor, k: int) -> torch.Tensor:
    """Mean of x [B,C,H,W] over a k x k window around each pixel, over the window's part inside the image (a
    rectangle: a mean along columns of means along rows, 2k reads a pixel instead of k^2)."""
    x = F.avg_pool2d(x, (1, k), stride=1, padding=(0, k // 2), count_include_pad=False)
    return F.avg_pool2d(x, (k, 1), stride=1, padding=(k // 2, 0), count_include_pad=False)


def band_masks(height: int, width: int, bands=BANDS, device=None) -> torch.Tensor:
    """[K, height, width // 2 + 1] bool: the rfft2 coefficients of a height x width grid in each band."""
    fy = torch.fft.fftfreq(height, device=device)
    fx = torch.fft.rfftfreq(width, device=device)
    radius = torch.sqrt(fy[:, None] ** 2 + fx[None] ** 2)
    radius = radius / radius.max().clamp_min(1e-12)
    return torch.stack([(radius >= lo) & (radius < hi) for lo, hi in bands])


def _images(images: torch.Tensor) -> torch.Tensor:
    if images.dim() == 3:
        images = images[None]
    if images.dim() != 4 or images.shape[-1] != 3:
        raise ShapeError(f"expected images [B,H,W,3] or [H,W,3], got {list(images.shape)}")
    return images


@torch.no_grad()
def band_magnitudes(images: torch.Tensor, bands=BANDS) -> torch.Tensor:
    """|band-pass of the luma| [B, K, H, W] of images [B, H, W, 3] (or one [H, W, 3]: [K, H, W]): the luma
    reflect-padded to an FFT-friendly size, its spectrum kept in each band only, transformed back and cropped."""
    single = images.dim() == 3
    images = _images(images)
    b, h, w, _ = images.shape
    luma = images.float() @ torch.tensor(LUMA, device=images.device)  # [B,H,W]
    ph, pw = fast_length(h) - h, fast_length(w) - w  # each under the side (n < 2 needs none): reflection can fill it
    padded = F.pad(luma[:, None], (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2), mode="reflect")[:, 0] \
        if ph or pw else luma
    hp, wp = padded.shape[-2:]
    spectrum = torch.fft.rfft2(padded)  # [B, hp, wp//2+1]
    masks = band_masks(hp, wp, bands, images.device)  # [K, hp, wp//2+1]
    passed = torch.fft.irfft2(spectrum[:, None] * masks, s=(hp, wp))  # [B,K,hp,wp]
    magnitude = passed[..., ph // 2:ph // 2 + h, pw // 2:pw // 2 + w].abs()
    return magnitude[0] if single else magnitude


@torch.no_grad()
def band_energy(images: torch.Tensor, bands=BANDS) -> torch.Tensor:
    """Band-energy maps [B, K, H, W] in [0, 1] of images [B, H, W, 3] in [0, 1] (or one [H, W, 3]: [K, H, W]): per
    band, the band magnitude (band_magnitudes) less its CONTRAST_WINDOW local mean, clamped at 0 (local contrast);
    scaled to [0, 1] by the map's own min and max (0 where its span is under FLAT: float noise, not detail); then a
    SMOOTH_WINDOW box average."""
    single = images.dim() == 3
    magnitude = band_magnitudes(images, bands)
    if single:
        magnitude = magnitude[None]
    contrast = (magnitude - _box(magnitude, CONTRAST_WINDOW)).clamp_min(0)
    lo = contrast.amin(dim=(-2, -1), keepdim=True)
    span = contrast.amax(dim=(-2, -1), keepdim=True) - lo
    normalised = torch.where(span > FLAT, (contrast - lo) / span.clamp_min(FLAT), torch.zeros_like(contrast))
    maps = _box(normalised, SMOOTH_WINDOW)
    return maps[0] if single else maps


def weight_surfels(surfels: Surfels, color: torch.Tensor) -> Surfels:
    """`surfels` with their appearance replaced by the constant colour `color` [N,3] (no waves, texture colour 0),
    keeping everything that shapes their alpha (opacity, falloff, texture alpha): rendered over black, each pixel's
    colour is then sum_i w_i(p) color_i, with w_i(p) = alpha_i(p) T_i(p) the surfels' blending weights."""
    out = Surfels.constant_color(surfels.means, surfels.quats, surfels.scales, surfels.opacities, color)
    for f in SURFEL_FIELDS:
        if f.role == "opacity" and f.name != "opacities":
            setattr(out, f.name, getattr(surfels, f.name))
    if surfels.texture_size:
        out.texture = torch.cat([torch.zeros_like(surfels.texture[..., :3]), surfels.texture[..., 3:]], -1)
    return out


def back_project(model: SurfelModel, camera: Camera, errors: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """Each surfel's blending-weighted mean of up to three error maps [K, H, W] (K <= 3) seen from `camera`:
    [N, K], sum_p w_i(p) e_k(p) / sum_p w_i(p), 0 for a surfel that draws nothing.

    Computed with the (differentiable) rasterizer, no kernel of its own: with every surfel's colour a constant c_i,
    rgb(p) = sum_i w_i(p) c_i + T(p) background, so the gradient of sum_p V(p) . rgb(p) with respect to c_i is
    sum_p w_i(p) V(p), per channel. One render with c = 1 (a colour of 1 is never clamped), two backward passes: V =
    the error maps (one per channel) and V = 1 (the weights' sum)."""
    k = errors.shape[0]
    if errors.dim() != 3 or not 1 <= k <= 3 or tuple(errors.shape[1:]) != (camera.height, camera.width):
        raise ShapeError(f"back_project expects 1 to 3 error maps [K,{camera.height},{camera.width}], got "
                         f"{list(errors.shape)}")
    p = next(model.parameters())
    cam = camera.to(p.device, p.dtype)
    with torch.no_grad():
        surfels = model.surfels(cam)
    color = torch.ones(surfels.num, 3, device=p.device, dtype=p.dtype, requires_grad=True)
    with torch.enable_grad():
        rgb = model.render(cam, background=0.0, backend=backend, surfels=weight_surfels(surfels, color)).rgb
        v = torch.zeros_like(rgb)
        v[..., :k] = errors.permute(1, 2, 0).to(rgb)
        weighted, = torch.autograd.grad((rgb * v).sum(), color, retain_graph=True)
        weight, = torch.autograd.grad(rgb[..., 0].sum(), color)
    weight = weight[:, :1]
    return torch.where(weight > 0, weighted[:, :k] / weight.clamp_min(1e-30), torch.zeros_like(weighted[:, :k]))


def primitive_errors(model: SurfelModel, views: Iterable[tuple[Camera, torch.Tensor]], *, background,
                     backend: str = "auto", bands=BANDS) -> torch.Tensor:
    """[N] each surfel's frequency error: the most, over `views` ((camera, photo [H,W,3]) pairs, the photo over
    `background`) and bands, of its back-projected band-energy error (module docstring, steps 1-3)."""
    if len(bands) > 3:
        raise ValueError(f"at most 3 bands are back-projected at once, got {len(bands)}")
    p = next(model.parameters())
    worst = torch.zeros(model.num_primitives, device=p.device, dtype=p.dtype)
    for camera, photo in views:
        cam = camera.to(p.device, p.dtype)
        with torch.no_grad():
            render = model.render(cam, background=background, backend=backend, image_only=True).rgb
            maps = band_energy(torch.stack([render, photo.to(render)]), bands)  # [2, K, H, W]
            error = (maps[0] - maps[1]).abs()
        worst = torch.maximum(worst, back_project(model, cam, error, backend).amax(1))
    return worst


def stacked_opacity(opacity: torch.Tensor) -> torch.Tensor:
    """The opacity o' of each of two stacked copies that together let through what one of opacity o did:
    (1 - o')^2 = 1 - o."""
    return 1 - torch.sqrt((1 - opacity).clamp_min(0))


@torch.no_grad()
def densify_step(model: SurfelModel, optimizer: torch.optim.Optimizer, views: Iterable[tuple[Camera, torch.Tensor]],
                 *, scene_extent: float, budget: int, generator: torch.Generator, min_opacity: float,
                 background=None, backend: str = "auto", percent_dense: float = 0.01,
                 threshold: float = ERROR_THRESHOLD, growth: float = GROWTH, opacity_decay: float = OPACITY_DECAY,
                 comm=None) -> dict:
    """One frequency-aware densification step (module docstring); returns counts of cloned, split and pruned
    surfels and the count after. Nothing happens once the count has reached `budget`. With several processes
    (`comm`), the errors are averaged over them so that every process makes the same edit."""
    n = model.num_primitives
    if n >= budget:
        return {"cloned": 0, "split": 0, "pruned": 0, "primitives": n}
    errors = primitive_errors(model, views, background=background, backend=backend)
    if comm is not None and comm.world > 1:
        comm.sum_([errors])
        errors /= comm.world
    params = {k: v.detach() for k, v in model.per_primitive().items()}
    hot = errors >= threshold
    room = min(budget - n, max(1, int(growth * n)))
    if int(hot.sum()) > room:  # the worst first
        top = torch.topk(torch.where(hot, errors, torch.full_like(errors, -1.0)), room).indices
        hot = torch.zeros_like(hot)
        hot[top] = True
    scales = torch.exp(params["log_scales"]).max(1).values
    clone = hot & (scales <= percent_dense * scene_extent)
    split = hot & ~clone
    stacked = inverse_sigmoid(stacked_opacity(torch.sigmoid(params["logit_opacity"])))
    new = {k: v[clone] for k, v in params.items()}
    new["logit_opacity"] = stacked[clone]
    if split.any():
        parents = split.nonzero().squeeze(1).repeat(2)
        children = split_rows(model, params, parents, generator)
        children["logit_opacity"] = stacked[parents]
        new = {k: torch.cat([new[k], children[k]]) for k in params}
    # a cloned parent is now one of two stacked copies: its opacity is another quantity, so are its moments
    model.logit_opacity[clone] = stacked[clone]
    restart_moments(optimizer, model.logit_opacity, clone)

    def decayed(logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        opacity = (torch.sigmoid(logits) - opacity_decay).clamp_min(0)
        return inverse_sigmoid(opacity), opacity >= min_opacity

    model.logit_opacity[:], keep = decayed(params["logit_opacity"])
    new["logit_opacity"], keep_new = decayed(new["logit_opacity"])
    # what this step chose to grow is not pruned by it: halving a faint surfel's opacity may take both copies under
    # min_opacity, which would delete the very surfels the images asked for (they fade later if unneeded)
    keep = (keep | clone) & ~split
    keep_new = torch.ones_like(keep_new)
    if not keep.any() and not keep_new.any():  # never prune everything: an empty model cannot recover
        keep, keep_new = ~split, torch.ones_like(keep_new)
    model.edit_primitives(optimizer, keep, {k: v[keep_new] for k, v in new.items()})
    return {"cloned": int(clone.sum()), "split": int(split.sum()),
            "pruned": int((~keep).sum() - split.sum()) + int((~keep_new).sum()), "primitives": model.num_primitives}
