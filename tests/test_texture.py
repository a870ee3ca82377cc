"""The texture appearance kind (Surfels.texture [N,T,T,4]): rgb added to the colour, alpha times the opacity,
bilinear over (u, v) in [-TEXTURE_RADIUS, TEXTURE_RADIUS]^2 sigmas, clamped to the edge; prefiltered by the pixel
footprint when anti-aliased.

Known answers (a 1x1 texture is a colour offset and an opacity factor; zero alpha draws nothing; the texels land
where the convention puts them), every native backend against the reference in float64 (outputs and gradients under
one random cotangent), gradcheck, extremes, the valid range, and consistency across scales when anti-aliased.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
import torch

from splatzoo.errors import SplatzooError
from splatzoo.rasterizers import rasterize
from splatzoo.rasterizers.common import ANTIALIASED, SETTINGS
from splatzoo.testing import sphere_and_wall
from splatzoo.types import TEXTURE_RADIUS, Camera, Surfels
from test_native import EMULATED, FIELDS, _assert_outputs_close, _check_grads, _cotangent, _render_and_grads

D = torch.float64
SETTING_IDS = ["plain", "antialiased"]


def textured(s: Surfels, size: int, seed: int = 0, alpha=(0.3, 1.0), rgb: float = 0.4) -> Surfels:
    """s with a random texture of size x size texels: rgb in [-rgb, rgb], alpha in `alpha`."""
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(s.num, size, size, 4, generator=g, dtype=D)
    t[..., :3] = (2 * t[..., :3] - 1) * rgb
    t[..., 3] = alpha[0] + (alpha[1] - alpha[0]) * t[..., 3]
    s.texture = t.to(s.means.dtype)
    return s


def one_surfel(sigma_px: float = 10.0, width: int = 48, normal=(0.0, 0.0, -1.0), size: int = 4) -> tuple:
    cam = Camera.look_at((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), fov_deg=60.0, width=width, height=width)
    f = float(cam.K[0, 0])
    from splatzoo.geometry import normals_to_quats

    q = normals_to_quats(torch.tensor([normal], dtype=D))
    s = Surfels(torch.zeros(1, 3, dtype=D), q, torch.full((1, 2), sigma_px * 4.0 / f, dtype=D),
                torch.tensor([0.9], dtype=D), torch.tensor([[0.5, 0.4, 0.3]], dtype=D), torch.zeros(1, 0, 2, dtype=D),
                torch.zeros(1, 0, dtype=D), torch.zeros(1, 0, 3, dtype=D))
    return textured(s, size, seed=1), cam


# ---- the contract -------------------------------------------------------------------------------------------------

def test_no_texture_is_size_zero_and_the_header_uses_the_python_radius():
    s, _ = sphere_and_wall(5, 16, 16, 2)
    assert s.texture.shape == (5, 0, 0, 4) and s.texture_size == 0
    header = (Path(__file__).resolve().parents[1] / "splatzoo" / "csrc" / "surfel_math.h").read_text()
    found = re.search(r"constexpr double TEXTURE_RADIUS = ([0-9.e+-]+);", header)
    assert found and float(found.group(1)) == TEXTURE_RADIUS


def test_a_one_texel_texture_is_a_colour_offset_and_an_opacity_factor(any_backend):
    s, cam = sphere_and_wall(300, 40, 32, 2, seed=2, dtype=D)
    s = textured(s, 1, seed=3)
    plain = s.map(lambda t: t.clone())
    plain.texture = s.texture[:, :0, :0]
    plain.base_color = s.base_color + s.texture[:, 0, 0, :3]
    plain.opacities = s.opacities * s.texture[:, 0, 0, 3]
    for settings in (SETTINGS, ANTIALIASED):
        a = rasterize(s.to(any_backend.torch_device()), cam, backend=any_backend, settings=settings)
        b = rasterize(plain.to(any_backend.torch_device()), cam, backend=any_backend, settings=settings)
        for k in FIELDS:
            torch.testing.assert_close(getattr(a, k).cpu(), getattr(b, k).cpu(), rtol=0, atol=1e-9, msg=k)


def test_texels_land_where_the_convention_puts_them():
    """A face-on surfel, 10 px a sigma, with one bright texel: the brightest pixel is at that texel's centre,
    -R + (c + 1/2) 2R/T sigmas along u (image x) and likewise along v (image y, the camera's y is down)."""
    s, cam = one_surfel(sigma_px=10.0, width=96, size=6)
    s.texture.zero_()
    s.texture[..., 3] = 1.0
    r, c = 1, 4
    s.texture[0, r, c, 0] = 0.5
    out = rasterize(s, cam, backend="cpu")
    seen = out.alpha > 0.05
    red = torch.where(seen, out.rgb[..., 0] / out.alpha.clamp_min(1e-9) - 0.5, torch.zeros_like(out.alpha))
    y, x = divmod(int(red.argmax()), 96)
    assert 0.4 < float(red.max()) <= 0.5 + 1e-9  # the texel's value, bilinear within half a pixel of its centre
    step = 2 * TEXTURE_RADIUS / 6
    u, v = -TEXTURE_RADIUS + (c + 0.5) * step, -TEXTURE_RADIUS + (r + 0.5) * step
    # normals_to_quats((0, 0, -1)) gives t_u, t_v along the image axes, possibly flipped: either sign
    assert min(abs(x + 0.5 - 48 - 10 * u), abs(x + 0.5 - 48 + 10 * u)) < 1.01, (x, u)
    assert min(abs(y + 0.5 - 48 - 10 * v), abs(y + 0.5 - 48 + 10 * v)) < 1.01, (y, v)


def test_a_texture_of_zero_alpha_draws_nothing(any_backend):
    s, cam = sphere_and_wall(200, 32, 32, 2, seed=4)
    s = textured(s.to(dtype=D), 4, alpha=(0.0, 0.0)).to(dtype=torch.float32)
    for settings in (SETTINGS, ANTIALIASED):
        out = rasterize(s.to(any_backend.torch_device()), cam, backend=any_backend, settings=settings)
        assert out.alpha.abs().max() == 0 and out.rgb.abs().max() == 0


@pytest.mark.parametrize("channel,bad,match", [(3, float("nan"), r"Surfels\.texture contains NaN"),
                                               (3, 1.5, r"Surfels\.texture .*channel 3.*must lie in \[0, 1\]"),
                                               (3, -0.1, r"Surfels\.texture .*channel 3.*must lie in \[0, 1\]"),
                                               (0, 1e7, r"Surfels\.texture .*channel 0.*must lie in")])
def test_bad_textures_are_refused_naming_the_field(channel, bad, match):
    s, cam = one_surfel()
    s.texture[0, 1, 2, channel] = bad
    for backend in ("reference", "cpu"):
        with pytest.raises(SplatzooError, match=match):
            rasterize(s, cam, backend=backend)
    s.texture = torch.zeros(1, 2, 3, 4, dtype=D)  # not square
    with pytest.raises(SplatzooError, match=r"Surfels\.texture must have shape \[N,T,T,4\]"):
        rasterize(s, cam, backend="cpu")


# ---- every backend against the reference ----------------------------------------------------------------------------

@pytest.mark.parametrize("settings", [SETTINGS, ANTIALIASED], ids=SETTING_IDS)
@pytest.mark.parametrize("K,size", [(0, 4), (2, 3)])
def test_native_backends_match_the_reference_float64(native_backend, settings, K, size):
    n = 120 if native_backend.name == EMULATED else 300
    s, cam = sphere_and_wall(n, 40, 32, K, seed=7 + K, dtype=D, px_sigma=(0.5, 5.0))
    s = textured(s, size, seed=K)
    s.falloff[::3] = 0.3  # Beta kernels among them
    cot = _cotangent(32, 40, D, seed=5)
    ref, g_ref = _render_and_grads("reference", s, cam, cot, [0.1, 0.2, 0.3], settings=settings)
    nat, g_nat = _render_and_grads(native_backend, s, cam, cot, [0.1, 0.2, 0.3], settings=settings)
    for k in FIELDS:
        torch.testing.assert_close(getattr(nat, k), getattr(ref, k), rtol=0, atol=1e-9, msg=k)
    assert g_ref["texture"].abs().max() > 0
    _check_grads(g_ref, g_nat, rel_tol=1e-7, cos_tol=1 - 1e-12)


@pytest.mark.parametrize("settings", [SETTINGS, ANTIALIASED], ids=SETTING_IDS)
def test_native_backends_match_the_reference_float32(native_backend, settings):
    n, W, H = (150, 48, 40) if native_backend.name == EMULATED else (1000, 96, 80)
    s, cam = sphere_and_wall(n, W, H, 2, seed=21, dtype=D, px_sigma=(0.5, 5.0))
    s = textured(s, 8, seed=2).to(dtype=torch.float32)
    cot = _cotangent(H, W, torch.float32, seed=2)
    ref, g_ref = _render_and_grads("reference", s, cam, cot, [0.2, 0.4, 0.6], settings=settings)
    nat, g_nat = _render_and_grads(native_backend, s, cam, cot, [0.2, 0.4, 0.6], settings=settings)
    _assert_outputs_close(ref, nat, torch.float32)
    _check_grads(g_ref, g_nat)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
@pytest.mark.parametrize("settings", [SETTINGS, ANTIALIASED], ids=SETTING_IDS)
def test_gradcheck(backend, settings):
    """Finite differences through the texels, the geometry (the texture's slope moves u, v) and the opacity. Plain,
    not w.r.t. the means (the screen filter's switch is a step, see test_native)."""
    s, cam = sphere_and_wall(3, 8, 8, 1, seed=3, dtype=D, px_sigma=(2.0, 3.0))
    s = textured(s, 2, seed=4)
    s.opacities.fill_(0.6)
    s.means[:, 2] += 0.01 * torch.arange(3, dtype=D)
    fixed = {"falloff": s.falloff}
    if not settings.antialiased:
        fixed["means"] = s.means
    if backend == "reference":  # slow under finite differences: the texels and what moves (u, v) or the opacity
        fixed.update({k: getattr(s, k) for k in ("base_color", "wave_vectors", "wave_phases", "wave_amplitudes")})
    names = [k for k in s.tensors() if k not in fixed]
    inputs = [getattr(s, k).detach().clone().requires_grad_(True) for k in names]

    def f(*x):
        out = rasterize(Surfels(**dict(zip(names, x)), **fixed), cam, backend=backend, settings=settings)
        return tuple(getattr(out, k) * w for k, w in zip(FIELDS, (1.0, 0.7, 0.3, 0.2, 0.5, 2.0)))

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, nondet_tol=1e-12)


# ---- extremes ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["edge-on", "tiny", "huge", "beyond-the-edge"])
def test_extremes_agree_with_the_reference(native_backend, case):
    """Edge-on, sub-pixel and image-filling textured surfels, and one seen only beyond its texels (clamp to edge):
    finite, and every backend equal to the reference in float64."""
    normal = (math.sin(math.radians(89.99)), 0.0, -math.cos(math.radians(89.99))) if case == "edge-on" else (
        0.3, 0.2, -1.0)
    sigma = {"tiny": 1e-3, "huge": 1e3}.get(case, 6.0)
    s, cam = one_surfel(sigma_px=sigma, width=32, normal=normal, size=5)
    if case == "beyond-the-edge":
        s.opacities.fill_(1.0)
        s.falloff.fill_(0.01)  # a wide Beta support, beyond the texels' 3 sigmas
    cot = _cotangent(32, 32, D, seed=9)
    for settings in (SETTINGS, ANTIALIASED):
        ref, g_ref = _render_and_grads("reference", s, cam, cot, settings=settings)
        nat, g_nat = _render_and_grads(native_backend, s, cam, cot, settings=settings)
        for k in FIELDS:
            assert torch.isfinite(getattr(nat, k)).all(), k
            torch.testing.assert_close(getattr(nat, k), getattr(ref, k), rtol=0, atol=1e-9, msg=k)
        for k, g in g_nat.items():
            assert g is None or torch.isfinite(g).all(), k
        _check_grads(g_ref, g_nat, rel_tol=1e-6, cos_tol=1 - 1e-10)


# ---- anti-aliasing -----------------------------------------------------------------------------------------------

def _area_average(img: torch.Tensor, f: int) -> torch.Tensor:
    return torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], f)[0].permute(1, 2, 0)


def test_a_small_render_is_the_area_average_of_a_big_one():
    """Textured surfels of 8x8 texels, 2-6 px a sigma at 128 px (texels down to 1.5 px): the 32 px anti-aliased
    render (the texture prefiltered) is close to the 4x4 average of the 128 px render; the unfiltered one is not."""
    s, cam = sphere_and_wall(2000, 128, 128, 0, seed=3, dtype=D, px_sigma=(2.0, 6.0))
    s = textured(s, 8, seed=5, alpha=(0.5, 1.0), rgb=0.5)
    s.opacities.fill_(0.95)
    psnr = {}
    for name, st in (("aa", ANTIALIASED), ("plain", SETTINGS)):
        big = rasterize(s, cam, backend="cpu", settings=st).rgb
        small = rasterize(s, cam.scaled(0.25), backend="cpu", settings=st).rgb
        mse = ((small - _area_average(big, 4)) ** 2).mean().item()
        psnr[name] = -10 * math.log10(mse)
    assert psnr["aa"] > 30 and psnr["aa"] > psnr["plain"] + 5, psnr


# ---- the textured model -----------------------------------------------------------------------------------------

def test_the_textured_model_starts_as_its_2dgs_surfel_and_learns_its_texture():
    import splatzoo
    from test_models import CAM, point_cloud

    pts, cols = point_cloud()
    plain = splatzoo.create_model("2dgs", pts, cols, seed=1)
    model = splatzoo.create_model("textured", pts, cols, seed=1, texture_size=8)
    assert model.config.texture_size == 8 and model.texture().shape == (64, 8, 8, 4)
    with torch.no_grad():
        plain.logit_opacity.fill_(1.0)
        model.logit_opacity.fill_(1.0)
        a, b = plain.render(CAM, backend="cpu"), model.render(CAM, backend="cpu")
    # alpha_tex starts at sigmoid(4.6) = 0.99: the render is the 2DGS one but for that 1%
    assert (a.rgb - b.rgb).abs().max() < 0.02 and (a.alpha - b.alpha).abs().max() < 0.01
    # a few steps towards a striped target change the texels (and make them differ within a surfel)
    target = (torch.arange(32) // 2 % 2).float()[None, :, None].expand(32, 32, 3)
    opt = torch.optim.Adam([{"params": g["params"], "lr": g["lr"]} for g in model.optim_groups(1.0)])
    for _ in range(5):
        opt.zero_grad()
        ((model.render(CAM, backend="cpu").rgb - target) ** 2).mean().backward()
        opt.step()
    assert model.summary()["texture_rgb_rms"] > 1e-3
    with pytest.raises(SplatzooError, match="texture_size"):
        splatzoo.create_model("textured", pts, cols, texture_size=0)
