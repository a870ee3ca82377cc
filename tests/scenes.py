"""Scenes shared by the rasterizer tests: random realistic ones and the extreme cases every backend must survive."""
from __future__ import annotations

import math

import torch

from splatzoo import Camera, Surfels
from splatzoo.types import MAX_FALLOFF, MAX_SCALE, MAX_WAVE_NUMBER
from splatzoo.geometry import normals_to_quats


def random_scene(n: int = 200, k: int = 0, width: int = 32, height: int = 32, seed: int = 0,
                 dtype=torch.float32, pixel_sigma: tuple[float, float] = (1.0, 4.0)) -> tuple[Surfels, Camera]:
    """Surfels scattered over a sphere of radius 1 seen from distance 4, about `pixel_sigma` pixels across,
    oriented near the sphere normal, with moderate opacity and colours that stay positive."""
    g = torch.Generator().manual_seed(seed)
    cam = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], width=width, height=height, fov_deg=40.0, dtype=dtype)
    focal = float(cam.K[0, 0])
    dirs = torch.randn(n, 3, generator=g, dtype=dtype)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    means = dirs * (0.8 + 0.2 * torch.rand(n, 1, generator=g, dtype=dtype))
    normals = dirs + 0.3 * torch.randn(n, 3, generator=g, dtype=dtype)
    quats = normals_to_quats(normals)
    quats = quats * (0.5 + torch.rand(n, 1, generator=g, dtype=dtype))  # unnormalised on purpose
    lo, hi = pixel_sigma
    sigma_px = lo + (hi - lo) * torch.rand(n, 2, generator=g, dtype=dtype)
    scales = sigma_px * 4.0 / focal
    opac = 0.2 + 0.6 * torch.rand(n, generator=g, dtype=dtype)
    base = 0.3 + 0.5 * torch.rand(n, 3, generator=g, dtype=dtype)
    vec = (2 * math.pi) * (0.2 + 1.5 * torch.rand(n, k, 2, generator=g, dtype=dtype) - 0.75)
    phase = 2 * math.pi * torch.rand(n, k, generator=g, dtype=dtype)
    amp = (0.25 / max(k, 1)) * (torch.rand(n, k, 3, generator=g, dtype=dtype) * 2 - 1)
    return Surfels(means, quats, scales, opac, base, vec, phase, amp), cam


def single_surfel(normal=(0.0, 0.0, -1.0), scale=(0.2, 0.2), opacity=0.8, center=(0.0, 0.0, 0.0),
                  k_vectors=(), color=(0.5, 0.5, 0.5), dtype=torch.float32) -> Surfels:
    n = torch.tensor([normal], dtype=dtype)
    q = normals_to_quats(n)
    K = len(k_vectors)
    vec = torch.tensor(list(k_vectors), dtype=dtype).reshape(1, K, 2)
    return Surfels(torch.tensor([center], dtype=dtype), q, torch.tensor([scale], dtype=dtype),
                   torch.tensor([opacity], dtype=dtype), torch.tensor([color], dtype=dtype), vec,
                   torch.zeros(1, K, dtype=dtype), torch.full((1, K, 3), 0.3, dtype=dtype))


def extreme_cases(dtype=torch.float32) -> list[tuple[str, Surfels, Camera]]:
    """Cases at the edges of the maths: every backend must give finite outputs and gradients here."""
    cam = Camera.look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], width=24, height=24, fov_deg=50.0, dtype=dtype)
    cases = []
    for deg in (0, 30, 60, 85, 89, 89.99, 90):
        a = math.radians(deg)
        cases.append((f"tilt{deg}", single_surfel((math.sin(a), 0.0, -math.cos(a)), dtype=dtype), cam))
    for s in (1e-6, 1e-3, 1.0, 1e3):
        cases.append((f"scale{s:g}", single_surfel(scale=(s, s), dtype=dtype), cam))
    cases.append(("needle", single_surfel(scale=(1e-6, 1.0), dtype=dtype), cam))
    for f in (1.0, 100.0):
        w = 2 * math.pi * f
        cases.append((f"freq{f:g}", single_surfel(k_vectors=[(w, 0.0), (0.0, w), (w, w)], dtype=dtype), cam))
    w = MAX_WAVE_NUMBER  # the highest wave number a surfel may have (types.py)
    cases.append(("freq_max", single_surfel(k_vectors=[(w, 0.0), (0.0, w), (-w, w)], dtype=dtype), cam))
    cases.append(("scale_max", single_surfel(scale=(MAX_SCALE, MAX_SCALE), dtype=dtype), cam))
    for name, s_exp in (("beta_tiny", 1e-9), ("beta_max", MAX_FALLOFF)):  # the Beta falloff at its range's ends
        one = single_surfel(k_vectors=[(3.0, 1.0)], dtype=dtype)
        one.falloff = torch.full_like(one.opacities, s_exp)
        cases.append((name, one, cam))
    for o in (0.0, 1.0):
        cases.append((f"opacity{o:g}", single_surfel(opacity=o, dtype=dtype), cam))
    # the camera is at z = -3 looking along +z: depth = z + 3
    for name, z in (("at_near", -2.8), ("inside_near", -2.9), ("at_camera", -3.0), ("behind", -4.0)):
        cases.append((name, single_surfel(center=(0.0, 0.0, z), scale=(0.5, 0.5), dtype=dtype), cam))
    cases.append(("crossing_camera_plane", single_surfel(normal=(1.0, 0.0, 0.0), center=(0.0, 0.0, -3.0),
                                                         scale=(1.0, 1.0), dtype=dtype), cam))
    cases.append(("negative_color", single_surfel(color=(-1.0, 0.2, 2.0), k_vectors=[(3.0, 0.0)], dtype=dtype), cam))
    one = Camera.look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], width=1, height=1, fov_deg=50.0, dtype=dtype)
    cases.append(("image1x1", single_surfel(dtype=dtype), one))
    hd = Camera.look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], width=1920, height=1080, fov_deg=50.0, dtype=dtype)
    s, _ = random_scene(20, 2, seed=3, dtype=dtype)
    cases.append(("image1920x1080", s, hd))
    cases.append(("empty", Surfels.empty(0, dtype=dtype), cam))
    cases.append(("empty_k4", Surfels.empty(4, dtype=dtype), cam))
    dense, _ = random_scene(300, 1, seed=4, dtype=dtype)
    dense.opacities = torch.ones_like(dense.opacities)  # drives transmittance to the early stop
    cases.append(("opaque_stack", dense, cam))
    return cases
