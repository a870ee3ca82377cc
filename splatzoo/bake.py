"""Baking: a model whose colour varies inside each surfel (gabor's waves, a plugin's richer appearance) turned into
plain constant-colour 2D Gaussian surfels (the `2dgs` model) that every splat viewer draws.

A bake is a fit, not a conversion. Dropping the waves loses the texture, and cutting each wavy surfel into a grid
of coplanar pieces coloured at their centres recovers little of it: coplanar splats blend in an order no viewer
keeps. So the bake

1. starts from a split: each surfel becomes a small grid of sub-splats laid out along its strongest wave (and across
   it where other waves vary), as many per axis as the waves' frequency asks for (two per period, no finer than a
   pixel of the closest view), within the `max_splats` budget (short of it, the surfels whose waves show most are
   split first and the others stay whole; with budget to spare, up to four per period); each sub-splat is the part
   of its parent's Gaussian around its grid node (exact covariance, in the parent's plane) coloured with the
   parent's colour averaged over it (the waves' Gaussian mean, which also fades waves too fine for the sub-splat);
2. then fits the sub-splats to the source model's own renders (`model.render(camera)`: colour and alpha) from the
   given cameras and jittered copies of them, with the training loss (0.8 L1 + 0.2 D-SSIM) and the model's Adam
   groups (`optim_groups`);
3. and measures the bake error: PSNR of the baked render against the source's render on jittered views that the
   fit never saw.

`bake_model` works on models in memory; `export_baked` reads a run folder or a model file and writes the baked
model with `splatzoo.model_ply.save_ply` (the `baked` export format).
"""
from __future__ import annotations

import dataclasses
import math
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import torch

from .errors import SplatzooError
from .io import say_progress as _say
from .geometry import eval_sh, quat_to_rotmat, rotmat_to_quat
from .options import option_value
from .types import Camera, Surfels

SPLATS_PER_SURFEL = 8   # max_splats=None: this many baked splats per source surfel
SPAN = 2.0              # the split covers the parent's Gaussian to this many sigma either side of its centre
SUB_SIGMA = 1 / math.sqrt(2 * math.pi)  # sub-splat sigma per grid spacing: a row of them sums to a flat 1
MAX_DENSITY = 2.0       # with budget to spare, up to this many times two splats per wave period
SIGNIFICANT = 0.01      # a wave shapes the split when opacity x amplitude (largest channel) reaches this
ORBIT_VIEWS = 32        # no dataset: the bake's cameras, on a sphere around the model ...
ORBIT_SIZE = 256        # ... of this many pixels square ...
ORBIT_FOV = 40.0        # ... and this field of view (degrees)
TARGET_CACHE_BYTES = 1 << 29  # source renders kept in memory up to this; beyond it they are rendered when needed


@dataclass
class BakeOptions:
    """How `bake_model` bakes. Field names are the options of `splatzoo export --format baked:NAME=VALUE,...`."""

    max_splats: int | None = field(default=None, metadata={
        "help": f"the most constant-colour splats the bake may use (default: {SPLATS_PER_SURFEL} x the source's "
                "surfel count)"})
    steps: int = field(default=600, metadata={"help": "optimiser steps of the fit (0: the split alone)"})
    views: int = field(default=96, metadata={
        "help": "fitting views: the given cameras, then jittered copies of them up to this many"})
    jitter: float = field(default=0.15, metadata={
        "help": "a jittered view turns around the point its camera looks at by up to this angle (radians), and "
                "moves up to this fraction closer or farther"})
    eval_views: int = field(default=8, metadata={
        "help": "held-out jittered views (never fitted) on which the bake error is measured"})
    scale: float = field(default=1.0, metadata={
        "help": "fit at this multiple of the cameras' image size (above 1: finer than the source was trained at)"})
    lambda_dssim: float = field(default=0.2, metadata={"help": "weight of D-SSIM in the photometric loss"})
    lambda_alpha: float = field(default=0.1, metadata={
        "help": "weight of the L1 loss on alpha (the source's coverage), so the bake holds up over any background"})
    color_lr: float = field(default=2.5e-3, metadata={
        "help": "learning rate of the splats' colour (SH coefficients; 2dgs trains at 2.5e-3)"})
    position_lr: float = field(default=1.6e-5, metadata={
        "help": "position learning rate at the start, x the cameras' extent (decays 100x over the fit)"})
    max_per_surfel: int = field(default=16, metadata={"help": "the most splats one source surfel is split into"})
    seed: int = field(default=0, metadata={"help": "seed of the jittered views and the view order"})
    backend: str = field(default="auto", metadata={"help": "rasterizer: auto, reference, cpu or cuda"})

    def __post_init__(self):
        self.validate()

    def validate(self) -> "BakeOptions":
        def bad(name, want):
            return SplatzooError(f"bake option {name} must be {want}, got {getattr(self, name)!r}")

        for name in ("steps", "views", "eval_views", "max_per_surfel", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int):
                raise bad(name, "a whole number")
        if self.max_splats is not None and (isinstance(self.max_splats, bool) or not isinstance(self.max_splats, int)
                                            or self.max_splats < 1):
            raise bad("max_splats", "a whole number of at least 1 (or unset: "
                      f"{SPLATS_PER_SURFEL} x the source's surfels)")
        if self.steps < 0:
            raise bad("steps", "at least 0")
        for name in ("views", "max_per_surfel"):
            if getattr(self, name) < 1:
                raise bad(name, "at least 1")
        if self.eval_views < 0:
            raise bad("eval_views", "at least 0")
        if self.seed < 0:
            raise bad("seed", "at least 0")
        for name, lo, hi in (("jitter", 0.0, 1.0), ("scale", 1e-3, 8.0), ("lambda_dssim", 0.0, 1.0),
                             ("lambda_alpha", 0.0, 100.0), ("position_lr", 0.0, 1.0),
                             ("color_lr", 0.0, 1.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= float(v) <= hi:
                raise bad(name, f"a number from {lo:g} to {hi:g}")
            if name == "scale" and float(v) <= 0:
                raise bad(name, "above 0")
        if not isinstance(self.backend, str):
            raise bad("backend", "a backend name")
        return self


def bake_options(**options) -> BakeOptions:
    """BakeOptions from keyword options (strings too, as the command line gives them), each checked: an unknown
    name or a value of the wrong kind is a SplatzooError that says what is known."""
    fields = {f.name: f for f in dataclasses.fields(BakeOptions)}
    hints = typing.get_type_hints(BakeOptions)
    values = {}
    for name, value in options.items():
        if name not in fields:
            raise SplatzooError(f"unknown bake option {name!r}; the options are {', '.join(fields)}")
        values[name] = option_value("bake", name, hints[name], value, fields[name].default)
    return BakeOptions(**values).validate()


# --- cameras ---------------------------------------------------------------------------------------------------

def _look_from(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor, like: Camera, name: str) -> Camera:
    """A camera at `eye` looking at `target` with `like`'s intrinsics and size; `up` shows as up in the image."""
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, -up)
    if x.norm() < 1e-9:
        x = torch.linalg.cross(z, torch.tensor([1.0, 0.0, 0.0], dtype=z.dtype))
        if x.norm() < 1e-9:
            x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=z.dtype))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return Camera(w2c, like.K.detach().double().cpu().clone(), like.width, like.height, name)


def jittered_cameras(cameras: list[Camera], count: int, jitter: float, center: torch.Tensor, seed: int,
                     prefix: str = "jitter") -> list[Camera]:
    """`count` cameras, each a copy of one of `cameras` (in turn) turned around the point of its optical axis
    nearest `center` by a random angle up to `jitter` radians about a random axis, and moved up to `jitter` (a
    fraction) closer or farther. Deterministic in `seed`."""
    g = torch.Generator().manual_seed(seed)
    center = center.double().cpu()
    out = []
    for i in range(count):
        cam = cameras[i % len(cameras)].detach().to("cpu", torch.float64)
        eye, forward, up = cam.center, cam.R[2], -cam.R[1]
        target = eye + forward * max(float((center - eye) @ forward), 1e-6)
        axis = torch.randn(3, generator=g, dtype=torch.float64)
        axis = axis / axis.norm().clamp_min(1e-12)
        angle = jitter * float(torch.rand(1, generator=g, dtype=torch.float64))
        distance = 1 + jitter * (2 * float(torch.rand(1, generator=g, dtype=torch.float64)) - 1)
        turn = _axis_angle(axis, angle)
        new_eye = target + distance * (turn @ (eye - target))
        out.append(_look_from(new_eye, target, turn @ up, cam, f"{prefix}_{i:03d}"))
    return out


def _axis_angle(axis: torch.Tensor, angle: float) -> torch.Tensor:
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def orbit_cameras_around(model, views: int = ORBIT_VIEWS, size: int = ORBIT_SIZE) -> list[Camera]:
    """Cameras on a sphere around the model's surfels (a Fibonacci lattice, away from the poles of world z, which
    shows as up), each seeing all of them: for a model without its dataset."""
    from .data.synthetic import scene_camera

    means = _visible_means(model)
    center = means.median(0).values
    radius = float(torch.quantile((means - center).norm(dim=1), 0.98)) if means.shape[0] > 1 else 1.0
    radius = max(radius, 1e-3)
    distance = 1.15 * radius / math.sin(math.radians(ORBIT_FOV) / 2)
    spec = SimpleNamespace(target=center.double().numpy(), fov_deg=ORBIT_FOV)
    cams = []
    golden = math.pi * (3 - math.sqrt(5))
    for i in range(views):
        z = 0.9 * (1 - 2 * (i + 0.5) / views)
        r = math.sqrt(1 - z * z)
        d = torch.tensor([r * math.cos(golden * i), r * math.sin(golden * i), z], dtype=torch.float64)
        cams.append(scene_camera(spec, (center.double() + distance * d).numpy(), size, size, f"orbit_{i:03d}"))
    return cams


def _visible_means(model) -> torch.Tensor:
    """Centres [M,3] (float64, CPU) of the surfels that draw something (opacity of at least 1/255)."""
    s = model.surfels(_any_camera(model))
    keep = s.opacities.detach() >= 1 / 255
    means = s.means.detach()[keep] if bool(keep.any()) else s.means.detach()
    return means.double().cpu()


def _any_camera(model) -> Camera:
    p = next(model.parameters())
    return Camera.look_at([0.0, 0.0, -1.0], [0.0, 0.0, 0.0]).to(p.device, p.dtype)


# --- the split ---------------------------------------------------------------------------------------------------

@torch.no_grad()
def _pixel_size(means: torch.Tensor, cameras: list[Camera]) -> torch.Tensor:
    """[N] the world size of one pixel at each point, in the camera that sees it largest (inf: seen by none)."""
    best = torch.full((means.shape[0],), math.inf, dtype=means.dtype, device=means.device)
    for cam in cameras:
        c = cam.to(means.device, means.dtype)
        p = means @ c.R.T + c.t
        z = p[:, 2]
        f = float(torch.sqrt(c.K[0, 0] * c.K[1, 1]))
        x = c.K[0, 0] * p[:, 0] / z.clamp_min(1e-9) + c.K[0, 2]
        y = c.K[1, 1] * p[:, 1] / z.clamp_min(1e-9) + c.K[1, 2]
        seen = (z > 0.2) & (x >= 0) & (x < c.width) & (y >= 0) & (y < c.height)
        best = torch.where(seen, torch.minimum(best, z / f), best)
    return best


def _view_independent_base(model, s: Surfels, camera: Camera) -> torch.Tensor:
    """The surfels' base colour without a view-dependent SH term the model adds to it (gabor's sh_rest)."""
    degree = int(getattr(getattr(model, "config", None), "sh_degree", 0) or 0)
    rest = getattr(model, "sh_rest", None)
    if degree == 0 or not isinstance(rest, torch.Tensor) or rest.shape[0] != s.num:
        return s.base_color
    from .models.base import view_directions

    coeffs = torch.cat([rest.new_zeros(rest.shape[0], 1, 3), rest], 1)
    return s.base_color - eval_sh(degree, coeffs, view_directions(s.means, camera.to(s.means.device, s.means.dtype)))


@torch.no_grad()
def split_surfels(model, cameras: list[Camera], max_splats: int, max_per_surfel: int = 16):
    """The bake's start: the source's surfels split into at most `max_splats` constant-colour Gaussians.
    Returns (means [M,3], quats [M,4], scales [M,2], opacities [M], colors [M,3], sh_rest or None, parent [M])."""
    cam0 = _any_camera(model)
    s = model.surfels(cam0)
    dev, dt = s.means.device, s.means.dtype
    keep = (s.opacities >= 1 / 255).nonzero().squeeze(1)
    if keep.numel() == 0:
        raise SplatzooError("the model has no surfel with an opacity of at least 1/255: it draws nothing to bake")
    s = s.index(keep)
    base = _view_independent_base(model, s, cam0)
    n = s.num
    k = s.num_waves
    vec, amp = s.wave_vectors, s.wave_amplitudes  # [n,K,2] radians per sigma, [n,K,3]
    if k and s.wave_counts is not None:
        live = torch.arange(k, device=dev)[None] < s.wave_counts[:, None].to(dev)
        amp = amp * live[..., None]
    # the grid's axes in sigma space: along the strongest significant wave and across it
    strength = amp.abs().amax(-1) * s.opacities[:, None] if k else s.means.new_zeros(n, 0)
    significant = (strength >= SIGNIFICANT) & (vec.norm(dim=-1) > 1e-6) if k else strength.bool()
    if k:
        lead = torch.where(significant, strength, torch.full_like(strength, -1.0)).argmax(1)
        ea = vec[torch.arange(n, device=dev), lead]
        ea = ea / ea.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        ea = torch.where(significant.any(1, keepdim=True), ea, torch.tensor([1.0, 0.0], device=dev, dtype=dt))
    else:
        ea = s.means.new_zeros(n, 2)
        ea[:, 0] = 1
    eb = torch.stack([-ea[:, 1], ea[:, 0]], -1)
    # wave number along each axis (radians per sigma) of the significant waves
    if k:
        ka = torch.where(significant, (vec * ea[:, None]).sum(-1).abs(), torch.zeros_like(strength)).amax(1)
        kb = torch.where(significant, (vec * eb[:, None]).sum(-1).abs(), torch.zeros_like(strength)).amax(1)
    else:
        ka = kb = s.means.new_zeros(n)
    # two splats per period over the span, but no closer together than a pixel of the nearest view
    stretch_a = (s.scales * ea).norm(dim=-1)  # world length of one sigma-unit along each axis
    stretch_b = (s.scales * eb).norm(dim=-1)
    pixel = _pixel_size(s.means, cameras)
    # what a surfel's waves are worth: their visible variance over the pixels the surfel covers
    energy = (strength ** 2 * significant).sum(1) if k else s.means.new_zeros(n)
    area = (s.scales.prod(-1) / pixel ** 2).nan_to_num(0.0, posinf=0.0)
    counts_a, counts_b = _fit_budget(2 * SPAN * ka / math.pi, 2 * SPAN * kb / math.pi, 2 * SPAN * stretch_a / pixel,
                                     2 * SPAN * stretch_b / pixel, energy * area, max_splats, max_per_surfel)
    if int((counts_a * counts_b).sum()) > max_splats:  # more surfels than splats: keep the most visible (opacity, area)
        order = torch.argsort(s.opacities * s.scales.prod(-1), descending=True)[:max_splats]
        order = order.sort().values
        ones = torch.ones_like(order)
        return split_from(s.index(order), base[order], ea[order], eb[order], ones, ones, model, keep[order])
    return split_from(s, base, ea, eb, counts_a, counts_b, model, keep)


def _fit_budget(wave_a: torch.Tensor, wave_b: torch.Tensor, limit_a: torch.Tensor, limit_b: torch.Tensor,
                value: torch.Tensor, budget: int, cap: int):
    """Per-surfel grid sizes (na, nb) >= 1 whose products sum to at most `budget`, each within `cap`. The waves ask
    for wave_a, wave_b (fractional counts: two splats per period), each axis at most its pixel limit. With budget to
    spare every ask is scaled up by one common factor up to MAX_DENSITY (bisection: the largest that fits). Short of
    it, surfels get their full ask in order of `value` per extra splat, and the rest stay whole: a wave cut into too
    few pieces aliases, and starts the fit worse than its mean colour would."""
    def counts(factor):
        na = torch.minimum(wave_a * factor, limit_a).ceil().clamp(1, cap).long()
        nb = torch.minimum(wave_b * factor, limit_b).ceil().clamp(1, cap).long()
        over = na * nb > cap  # shrink the cross axis first, then the main one
        nb = torch.where(over, (cap // na).clamp_min(1), nb)
        na = torch.where(na * nb > cap, torch.full_like(na, cap), na)
        return na, nb

    na, nb = counts(MAX_DENSITY)
    if int((na * nb).sum()) <= budget:
        return na, nb
    na, nb = counts(1.0)
    if int((na * nb).sum()) > budget:
        extra = na * nb - 1
        order = torch.argsort(value / extra.clamp_min(1).to(value.dtype), descending=True)
        order = order[extra[order] > 0]
        chosen = order[torch.cumsum(extra[order], 0) <= budget - na.numel()]
        one = torch.ones_like(na)
        return one.index_copy(0, chosen, na[chosen]), one.index_copy(0, chosen, nb[chosen])
    lo, hi = 1.0, MAX_DENSITY
    for _ in range(40):
        mid = (lo + hi) / 2
        a, b = counts(mid)
        if int((a * b).sum()) <= budget:
            lo = mid
        else:
            hi = mid
    return counts(lo)


def split_from(s: Surfels, base, ea, eb, counts_a, counts_b, model, parent):
    """Split each surfel i of `s` into a counts_a[i] x counts_b[i] grid over +-SPAN sigma along the sigma-space axes
    ea[i], eb[i] (see split_surfels)."""
    dev, dt = s.means.device, s.means.dtype
    per = counts_a * counts_b
    idx = torch.repeat_interleave(torch.arange(s.num, device=dev), per)
    first = torch.cumsum(per, 0) - per
    local = torch.arange(idx.numel(), device=dev) - first[idx]
    na, nb = counts_a[idx].to(dt), counts_b[idx].to(dt)
    ja, jb = (local // counts_b[idx]).to(dt), (local % counts_b[idx]).to(dt)
    step_a, step_b = 2 * SPAN / na, 2 * SPAN / nb
    a = -SPAN + step_a * (ja + 0.5)
    b = -SPAN + step_b * (jb + 0.5)
    a = torch.where(na > 1, a, torch.zeros_like(a))
    b = torch.where(nb > 1, b, torch.zeros_like(b))
    sig_a = torch.where(na > 1, SUB_SIGMA * step_a, torch.ones_like(a))
    sig_b = torch.where(nb > 1, SUB_SIGMA * step_b, torch.ones_like(b))
    A, B = ea[idx], eb[idx]
    uv = a[:, None] * A + b[:, None] * B  # sub-splat centres in the parent's sigma units
    R = quat_to_rotmat(s.quats[idx])
    scales = s.scales[idx]
    means = s.means[idx] + (R[:, :, :2] @ (scales * uv)[..., None]).squeeze(-1)
    # the sub-splat's Gaussian in the parent's plane: J J^T, J = diag(s) [A B] diag(sig_a, sig_b)
    J = scales[:, :, None] * torch.stack([A * sig_a[:, None], B * sig_b[:, None]], -1)  # [M,2,2]
    U, S, _ = torch.linalg.svd(J)
    flip = torch.linalg.det(U) < 0
    U = torch.where(flip[:, None, None], U * torch.tensor([1.0, -1.0], device=dev, dtype=dt), U)
    tangents = R[:, :, :2] @ U  # [M,3,2]
    normal = torch.linalg.cross(tangents[:, :, 0], tangents[:, :, 1])
    quats = rotmat_to_quat(torch.stack([tangents[:, :, 0], tangents[:, :, 1], normal], -1))
    # the parent's opacity where the sub-splat sits (its Gaussian at the node)
    opacities = s.opacities[idx] * torch.exp(-(a * a + b * b) / 2)
    # colour: the parent's, averaged over the sub-splat's Gaussian; cos(k.x + phi) averages to
    # cos(k.mu + phi) exp(-k^T Sigma k / 2), Sigma = sig_a^2 A A^T + sig_b^2 B B^T in sigma units
    color = base[idx]
    if s.num_waves:
        k = s.wave_vectors[idx]  # [M,K,2]
        amp = s.wave_amplitudes[idx]
        if s.wave_counts is not None:
            live = torch.arange(s.num_waves, device=dev)[None] < s.wave_counts[idx][:, None].to(dev)
            amp = amp * live[..., None]
        var = (sig_a[:, None] * (k * A[:, None]).sum(-1)) ** 2 + (sig_b[:, None] * (k * B[:, None]).sum(-1)) ** 2
        wave = torch.cos((k * uv[:, None]).sum(-1) + s.wave_phases[idx]) * torch.exp(-var / 2)
        color = color + (amp * wave[..., None]).sum(1)
    rest = getattr(model, "sh_rest", None)
    degree = int(getattr(getattr(model, "config", None), "sh_degree", 0) or 0)
    sh_rest = rest.detach()[parent[idx]] if degree and isinstance(rest, torch.Tensor) else None
    return means, quats, S, opacities, color.clamp(0, 1), sh_rest, parent[idx]


def plain_model(means, quats, scales, opacities, colors, sh_rest=None, *, like=None):
    """A `2dgs` model with these surfels (colours in [0,1]; sh_rest [M,bands,3] for view-dependent colour), with
    `like`'s render settings (anti-aliasing, background)."""
    from .geometry import rgb_to_sh0
    from .models.base import inverse_sigmoid
    from .zoo import create_model

    degree = {0: 0, 3: 1, 8: 2, 15: 3}[sh_rest.shape[1]] if sh_rest is not None else 0
    out = create_model("2dgs", sh_degree=degree)
    m = means.shape[0]
    out.replace_parameters({
        "means": means.detach().float().cpu(),
        "log_scales": torch.log(scales.detach().float().cpu().clamp_min(1e-9)),
        "quats": quats.detach().float().cpu(),
        "logit_opacity": inverse_sigmoid(opacities.detach().float().cpu()),
        "sh_dc": rgb_to_sh0(colors.detach().float().cpu())[:, None],
        "sh_rest": sh_rest.detach().float().cpu() if sh_rest is not None else torch.zeros(m, 0, 3),
    })
    if like is not None:
        out.set_render_settings(like.render_settings)
    return out


# --- the fit -----------------------------------------------------------------------------------------------------

def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.clamp(0, 1) - b.clamp(0, 1)) ** 2).mean())
    return min(100.0, -10 * math.log10(max(mse, 1e-10)))


@torch.no_grad()
def bake_error(baked, source, cameras: list[Camera], *, backend: str = "auto") -> float:
    """Mean over `cameras` of the PSNR (dB) of `baked`'s render against `source`'s (each with its own settings)."""
    if not cameras:
        return float("nan")
    vals = [_psnr(baked.render(c, backend=backend, image_only=True).rgb,
                  source.render(c, backend=backend, image_only=True).rgb) for c in cameras]
    return float(sum(vals) / len(vals))


def waves_dropped(model):
    """`model` rendered without its waves (a surfels_of for render(surfels=...)): what a constant-colour viewer shows
    of it."""
    def surfels_of(camera):
        s = model.surfels(camera)
        return dataclasses.replace(s, wave_amplitudes=torch.zeros_like(s.wave_amplitudes))
    return surfels_of


@torch.no_grad()
def plain_error(source, cameras: list[Camera], *, backend: str = "auto") -> float:
    """Mean PSNR (dB) of the source rendered with its waves dropped against its own render."""
    vals = []
    for c in cameras:
        p = next(source.parameters())
        cam = c.to(p.device, p.dtype)
        dropped = source.render(cam, backend=backend, image_only=True, surfels=waves_dropped(source)(cam)).rgb
        vals.append(_psnr(dropped, source.render(cam, backend=backend, image_only=True).rgb))
    return float(sum(vals) / len(vals)) if vals else float("nan")


def is_plain(model) -> bool:
    return getattr(model, "name", "") == "2dgs"


def bake_model(model, cameras: list[Camera], options: BakeOptions | None = None, *, progress=None):
    """Bake `model` into constant-colour splats (a `2dgs` model) fitted to its renders from `cameras` and jittered
    copies of them. Returns (baked model, report): report["bake_db"] is the PSNR of the baked render against the
    source's on held-out jittered views (the bake error in dB: higher is closer), with "start_db" (the split before
    the fit), "plain_db" (the source with its waves dropped), "splats", "source_surfels", "seconds" and the options.
    A `2dgs` model is returned unchanged. progress: a callable receiving messages, or True to print them."""
    options = (options or BakeOptions()).validate()
    say = _say(progress)
    if not cameras:
        raise SplatzooError("bake_model needs at least one camera to fit the bake from; pass the run's training "
                            "cameras, or orbit_cameras_around(model)")
    p = next(model.parameters(), None)
    if p is None or model.num_primitives == 0:
        raise SplatzooError("the model has no primitives to bake")
    n_source = model.num_primitives
    if is_plain(model):
        say("the model is a plain 2dgs model already: nothing to bake")
        return model, {"bake_db": math.inf, "splats": n_source, "source_surfels": n_source, "passed_through": True}
    t0 = time.perf_counter()
    from .rasterizers import select_backend

    backend = options.backend
    device = p.device if backend == "auto" else select_backend(backend).torch_device()
    model = model.to(device)
    budget = options.max_splats or SPLATS_PER_SURFEL * n_source
    fit_cams, eval_cams = _bake_cameras(model, cameras, options, device)

    means, quats, scales, opac, colors, sh_rest, _ = split_surfels(model, fit_cams, budget, options.max_per_surfel)
    baked = plain_model(means, quats, scales, opac, colors, sh_rest, like=model).to(device)
    baked.name = "2dgs"
    say(f"bake: {n_source} surfels split into {baked.num_primitives} splats (at most {budget})")
    start_db = bake_error(baked, model, eval_cams, backend=backend)
    _fit(baked, _source_renders(model, fit_cams, backend), fit_cams, len(cameras), options, say)
    bake_db = bake_error(baked, model, eval_cams, backend=backend)
    report = {"bake_db": bake_db, "start_db": start_db, "plain_db": plain_error(model, eval_cams, backend=backend),
              "splats": baked.num_primitives, "max_splats": budget, "source_surfels": n_source,
              "source_model": getattr(model, "name", ""), "fit_views": len(fit_cams), "eval_views": len(eval_cams),
              "seconds": time.perf_counter() - t0, "options": dataclasses.asdict(options)}
    say(f"bake error: {bake_db:.2f} dB PSNR against the {report['source_model'] or 'source'} render on "
        f"{len(eval_cams)} held-out views (split alone {start_db:.2f} dB, waves dropped {report['plain_db']:.2f} dB), "
        f"{baked.num_primitives} splats")
    return baked, report


def _bake_cameras(model, cameras: list[Camera], options: BakeOptions, device) -> tuple[list[Camera], list[Camera]]:
    """(fitting views, held-out views) on `device`: the given cameras (scaled by options.scale) and jittered copies
    up to options.views (or every n-th of them down to it), and options.eval_views jittered views never fitted."""
    fit_cams = [c.detach().to("cpu", torch.float64) for c in cameras]
    if options.scale != 1:
        fit_cams = [c.scaled(options.scale) for c in fit_cams]
    center = _visible_means(model).median(0).values
    if options.views > len(fit_cams):
        fit_cams = fit_cams + jittered_cameras(fit_cams, options.views - len(fit_cams), options.jitter, center,
                                               options.seed * 2 + 1)
    else:
        fit_cams = fit_cams[:: max(1, len(fit_cams) // options.views)][:options.views]
    eval_cams = jittered_cameras(fit_cams[:len(cameras)], options.eval_views, options.jitter, center,
                                 options.seed * 2 + 2, prefix="held_out")
    return [c.to(device, torch.float32) for c in fit_cams], [c.to(device, torch.float32) for c in eval_cams]


def _source_renders(model, cameras: list[Camera], backend: str):
    """target(i): the source's render (colour, alpha) from cameras[i], the fit's target; all kept in memory when
    they fit in TARGET_CACHE_BYTES (rendered here, in order), else rendered when asked for."""
    pixels = sum(c.width * c.height for c in cameras)
    cache = [] if pixels * 4 * 4 <= TARGET_CACHE_BYTES else None

    @torch.no_grad()
    def target(i):
        if cache is not None and i < len(cache):
            return cache[i]
        out = model.render(cameras[i], backend=backend, image_only=True)
        t = (out.rgb.detach(), out.alpha.detach())
        if cache is not None:
            cache.append(t)
        return t

    if cache is not None:
        for i in range(len(cameras)):
            target(i)
    return target


def _fit(baked, target, fit_cams: list[Camera], given: int, options: BakeOptions, say) -> None:
    """Fit `baked` (in place) to target(i), the source's render from fit_cams[i], with the training loss and the
    model's Adam groups; the position rate decays 100x over the fit. `given`: how many of fit_cams were given (their
    extent sets the position rate)."""
    from .data.scene import camera_extent
    from .training.losses import photometric_loss

    extent = camera_extent([c.to("cpu", torch.float64) for c in fit_cams[:given] or fit_cams])
    groups = baked.optim_groups(extent)
    for g in groups:
        if g["name"] == "means":
            g["lr"] = options.position_lr * extent
        elif g["name"] == "sh_dc":
            g["lr"] = options.color_lr
        elif g["name"] == "sh_rest":
            g["lr"] = options.color_lr / 20
    optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
    gen = torch.Generator().manual_seed(options.seed)
    order: list[int] = []
    steps = options.steps
    for step in range(1, steps + 1):
        if not order:
            order = torch.randperm(len(fit_cams), generator=gen).tolist()
        i = order.pop()
        rgb_t, alpha_t = target(i)
        t = step / steps
        for g in optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = options.position_lr * extent * 0.01 ** t
        out = baked.render(fit_cams[i], backend=options.backend)
        loss = photometric_loss(out.rgb, rgb_t, options.lambda_dssim)
        if options.lambda_alpha > 0:
            loss = loss + options.lambda_alpha * (out.alpha - alpha_t).abs().mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        value = float(loss.detach())
        if not math.isfinite(value):
            raise SplatzooError(f"the bake's loss became {value} at step {step}; lower position_lr or steps")
        optimizer.step()
        if step % max(1, steps // 10) == 0 or step == steps:
            say(f"bake: step {step}/{steps} loss {value:.4f}")


# --- export --------------------------------------------------------------------------------------------------

def cameras_to_bake_from(opened) -> list[Camera]:
    """The cameras a model from splatzoo.model_files.open_model is baked from: a run folder's training cameras, or
    orbit cameras around the model for a model file (or a run whose dataset is gone)."""
    from .runs import Run

    cameras = []
    if opened.format == "run":
        try:
            cameras = [v.camera for v in Run(opened.path).scene().train]
        except SplatzooError:  # the dataset moved, or the run trained on a scene in memory
            pass
    return cameras or orbit_cameras_around(opened.model)


def export_baked(source, out, *, progress=None, **options) -> Path:
    """Bake the model of `source` (a run folder or a model file) into constant-colour splats and write them to the
    PLY `out` with splatzoo.model_ply.save_ply. `options` are BakeOptions fields (strings are parsed). Reports the bake
    error in dB through `progress` (a callable, or True to print)."""
    from .model_files import open_model
    from .model_ply import save_ply

    opts = bake_options(**options)
    source, out = Path(source), Path(out)
    if out.suffix.lower() != ".ply":
        raise SplatzooError(f"the baked export writes a PLY file, so --out must end in .ply; got {out}")
    opened = open_model(source, backend=opts.backend)
    if out.exists() and out.resolve() == opened.file.resolve():
        raise SplatzooError(f"refusing to write the bake onto the model being read ({opened.file}); choose another "
                            "--out")
    baked, report = bake_model(opened.model, cameras_to_bake_from(opened), opts, progress=progress)
    path = save_ply(baked, out)
    _say(progress)(f"baked {report['splats']} splats, bake error {report['bake_db']:.2f} dB (PSNR against the "
                   "model's own renders)")
    return path
