"""Waves fitted to the photos (a model's `wave_fit_step`, e.g. beta-gabor's GaborConfig.fit_waves).

Gradient descent finds stripes slowly: a wave started at a random vector of [0, 1) cycles per sigma hardly feels
stripes several cycles a sigma away, and its colour grows at the amplitudes' learning rate. So once in a run, when
the geometry has settled, every surfel's waves are replaced by the stripes the training photos show on its plane:

1. samples: a GRID x GRID grid of points over the surfel's plane, u, v in [-RADIUS, RADIUS] sigmas (GRID grows with
   the surfel's largest size in pixels, so that the points are at most half a pixel apart: a large surfel's stripes
   are resolved finely, a pixel apart fits worse, -0.19 dB at 5% on the quick sweater, and a small surfel costs
   little), is projected into each training view (at most VIEWS, evenly spaced). A point counts in a view that sees
   the surfel there (the point's depth within DEPTH_TOLERANCE of the view's rendered median depth) and faces its
   plane (|cos| of the view ray and the normal at least MIN_FACING), weighted by that |cos|; its colour is the
   weighted mean of the photos' colours over the views.
2. pursuit: the colours less their mean, windowed by a Gaussian of one sigma (the surfel's own falloff), are matched
   against waves on a grid of vectors STEP cycles per sigma apart, up to what the grid resolves. The wave of most
   energy is fitted (one phase for the three channels, an RGB amplitude by least squares), subtracted, and the next
   one is found; as many as the surfel has waves.
3. a surfel whose counted points cover less than MIN_COVER of its window (hidden, seen edge-on, or off every photo)
   keeps the waves it has.

The fitted waves replace the old ones with their optimiser moments restarted, and training refines them.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..geometry import quat_to_rotmat

RADIUS = 2.0            # the sampled square: u, v in [-RADIUS, RADIUS] sigmas
GRIDS = (8, 16, 32, 64)  # points a side; a surfel takes the smallest with points at most half a pixel apart
STEP = 0.125            # spacing of the candidate wave vectors, cycles per sigma (the window resolves ~0.16)
VIEWS = 32              # training views sampled, evenly spaced, at most
DEPTH_TOLERANCE = 0.05  # a point is seen where the rendered median depth is within this fraction of its own
MIN_FACING = 0.3        # views more oblique than this |cos| of the ray and the plane's normal are not used
MIN_COVER = 0.5         # a surfel is fitted when its counted points hold this share of its window's weight
CHUNK_POINTS = 1 << 21  # grid points sampled and searched at once (a few hundred bytes each)


def grid_sizes(geometry: dict, cameras) -> torch.Tensor:
    """[N] points a side for each surfel of `geometry` (SplatModel.geometry()): its largest sigma in pixels over the
    views that have it in front, at most half a pixel between points (the largest of GRIDS when even that is
    coarser)."""
    means = geometry["means"].detach()
    cameras = [cam.to(means.device, means.dtype) for cam in cameras]
    sigma = geometry["scales"].detach().max(-1).values
    most = torch.zeros_like(sigma)
    for cam in cameras:
        z = means @ cam.R.T[:, 2] + cam.t[2]
        focal = torch.maximum(cam.K[0, 0], cam.K[1, 1])
        most = torch.maximum(most, torch.where(z > 0, focal * sigma / z.clamp_min(1e-12), torch.zeros_like(z)))
    needed = 2 * RADIUS * most / 0.5
    sizes = torch.tensor(GRIDS, device=sigma.device)
    index = torch.searchsorted(sizes, needed.ceil().to(sizes.dtype)).clamp(max=len(GRIDS) - 1)
    return sizes[index]


def plane_points(geometry: dict, rows: torch.Tensor, grid: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(points [n,G,G,3] in world space, normals [n,3], u [G]) of surfels `rows` of `geometry`: u along columns, v
    along rows."""
    means, scales = geometry["means"].detach()[rows], geometry["scales"].detach()[rows]
    R = quat_to_rotmat(geometry["quats"].detach()[rows])
    u = ((torch.arange(grid, device=means.device, dtype=means.dtype) + 0.5) / grid * 2 - 1) * RADIUS
    tu, tv = R[..., 0] * scales[:, :1], R[..., 1] * scales[:, 1:]
    points = (means[:, None, None] + u[None, None, :, None] * tu[:, None, None]
              + u[None, :, None, None] * tv[:, None, None])
    return points, R[..., 2], u


def sample_photos(points: torch.Tensor, normals: torch.Tensor, centres: torch.Tensor, views, depths):
    """(colour [n,G,G,3], weight [n,G,G]) of the photos over the points: per point the mean over the views that
    see it, weighted by how squarely they face it (module docstring, step 1)."""
    n, G = points.shape[:2]
    colour = points.new_zeros(n, G, G, 3)
    weight = points.new_zeros(n, G, G)
    for (cam, photo), depth in zip(views, depths):
        local = points @ cam.R.T + cam.t
        z = local[..., 2]
        pixel = local @ cam.K.T
        x = pixel[..., 0] / z.clamp_min(1e-12)
        y = pixel[..., 1] / z.clamp_min(1e-12)
        H, W = photo.shape[:2]
        # pixel centres at half-integers: grid_sample's align_corners=False convention
        where = torch.stack([2 * x / W - 1, 2 * y / H - 1], -1).reshape(1, n * G, G, 2)
        inside = (z > 0) & (where[0].reshape(n, G, G, 2).abs() < 1).all(-1)
        seen = F.grid_sample(depth[None, None], where, mode="nearest", align_corners=False)[0, 0].reshape(n, G, G)
        ray = centres - cam.center.to(centres)
        facing = ((normals * ray).sum(-1).abs() / ray.norm(dim=-1).clamp_min(1e-12))  # [n]
        w = (inside & ((seen - z).abs() <= DEPTH_TOLERANCE * z)).to(points.dtype) * facing[:, None, None]
        w = w * (facing >= MIN_FACING)[:, None, None]
        rgb = F.grid_sample(photo.permute(2, 0, 1)[None], where, mode="bilinear", padding_mode="border",
                            align_corners=False)[0].reshape(3, n, G, G).permute(1, 2, 3, 0)
        colour += w[..., None] * rgb
        weight += w
    return colour / weight.clamp_min(1e-12)[..., None], weight


def pursue(colour: torch.Tensor, counted: torch.Tensor, u: torch.Tensor, count: int):
    """Matching pursuit of `count` waves in colour [n,G,G,3] where counted [n,G,G] (module docstring, step 2).
    Returns (vectors [n,count,2] cycles per sigma, phases [n,count] radians, amplitudes [n,count,3], cover [n]):
    colour ~ mean + sum_k a_k cos(2 pi k_k . (u, v) + phi_k)."""
    n, G = colour.shape[:2]
    window = torch.exp(-0.5 * (u[:, None] ** 2 + u[None, :] ** 2))  # [v,u]
    w = window * counted.to(colour.dtype)
    cover = w.sum((1, 2)) / window.sum()
    mean = (w[..., None] * colour).sum((1, 2)) / w.sum((1, 2)).clamp_min(1e-12)[..., None]
    residual = (colour - mean[:, None, None]) * counted[..., None]
    top = G / (4 * RADIUS)  # the grid's Nyquist frequency, cycles per sigma
    ks = torch.arange(-round(top / STEP), round(top / STEP) + 1, device=u.device, dtype=u.dtype) * STEP
    half = ks[ks >= 0]
    # exp(-2 pi i k u) over the grid: the windowed residual's spectrum on the candidate vectors (kx, ky >= 0)
    along_u = torch.polar(torch.ones(len(ks), G, device=u.device, dtype=u.dtype), -2 * math.pi * ks[:, None] * u)
    along_v = torch.polar(torch.ones(len(half), G, device=u.device, dtype=u.dtype), -2 * math.pi * half[:, None] * u)
    # k and -k are one wave: on the row ky = 0 only kx > 0
    allowed = torch.ones(len(half), len(ks), dtype=torch.bool, device=u.device)
    allowed[0, ks <= 0] = False
    vectors = colour.new_zeros(n, count, 2)
    phases = colour.new_zeros(n, count)
    amplitudes = colour.new_zeros(n, count, 3)
    rows = torch.arange(n, device=colour.device)
    for j in range(count):
        spectrum = torch.einsum("yv,nvuc,xu->nyxc", along_v, (w[..., None] * residual).to(along_u.dtype), along_u)
        energy = (spectrum.abs() ** 2).sum(-1).masked_fill(~allowed, -1.0)
        best = energy.reshape(n, -1).argmax(1)
        iy, ix = best // len(ks), best % len(ks)
        k = torch.stack([ks[ix], half[iy]], -1)  # [n,2]
        z = spectrum[rows, iy, ix]  # [n,3]: ~ (a/2) e^{i phi} x the window's weight
        phase = 0.5 * torch.angle((z * z).sum(-1))  # the phase of most energy over the channels (a_c may be < 0)
        wave = torch.cos(2 * math.pi * (k[:, 0, None, None] * u[None, None, :] + k[:, 1, None, None] * u[None, :, None])
                         + phase[:, None, None])  # [n,v,u]
        amplitude = (((w * wave)[..., None] * residual).sum((1, 2))
                     / (w * wave * wave).sum((1, 2)).clamp_min(1e-12)[:, None])
        residual = residual - amplitude[:, None, None] * wave[..., None] * counted[..., None]
        vectors[:, j], phases[:, j], amplitudes[:, j] = k, phase, amplitude
    return vectors, phases, amplitudes, cover


@torch.no_grad()
def fit_waves(net, optimizer, views, background, backend: str) -> dict:
    """Replace every surfel's waves by those the photos show on its plane (module docstring). views: (camera,
    photo [H,W,3] over `background`) pairs (the trainer passes VIEWS at most). Returns {"surfels_fitted",
    "surfels"}."""
    geometry = net.geometry()
    means = geometry["means"].detach()
    views = [(cam.to(means.device, means.dtype), photo.to(means)) for cam, photo in views]
    depths = []
    for cam, _ in views:
        out = net.render(cam, background=background, backend=backend)
        depths.append(torch.where(out.median_depth > 0, out.median_depth, out.depth).detach())
    counts = net.wave_slots()
    sizes = grid_sizes(geometry, [cam for cam, _ in views])
    fitted = torch.zeros(net.num_primitives, dtype=torch.bool, device=means.device)
    for grid in sizes.unique().tolist():
        rows_all = torch.nonzero((sizes == grid) & (counts > 0)).squeeze(1)
        per = max(1, CHUNK_POINTS // (grid * grid))
        for start in range(0, len(rows_all), per):
            rows = rows_all[start:start + per]
            points, normals, u = plane_points(geometry, rows, grid)
            colour, weight = sample_photos(points, normals, means[rows], views, depths)
            vectors, phases, amplitudes, cover = pursue(colour, weight > 0, u, int(counts[rows].max()))
            keep = cover >= MIN_COVER
            net.start_waves(rows[keep], vectors[keep], phases[keep], amplitudes[keep], optimizer)
            fitted[rows[keep]] = True
    return {"surfels_fitted": int(fitted.sum()), "surfels": net.num_primitives}
