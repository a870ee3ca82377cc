"""The reference rasterizer: gradients (float64 gradcheck), known answers and numerical stability."""
import math

import pytest
import torch

from scenes import extreme_cases, random_scene, single_surfel
from splatzoo import Camera, Surfels, rasterize
from splatzoo.errors import ShapeError
from splatzoo.geometry import quat_to_rotmat
from splatzoo.rasterizers.reference import rasterize_reference

FIELDS = ["means", "quats", "scales", "opacities", "base_color", "wave_vectors", "wave_phases", "wave_amplitudes"]
OUTPUTS = ["rgb", "alpha", "depth", "median_depth", "normal", "distortion"]


@pytest.mark.parametrize("k", [0, 1, 4])
def test_gradcheck_every_output_every_field(k):
    s, cam = random_scene(8, k, width=8, height=8, seed=10 + k, dtype=torch.float64, pixel_sigma=(1.0, 2.5))
    s.means = s.means * 0.4  # pull the surfels into the 8x8 view so that they overlap
    inputs = [getattr(s, f).clone().requires_grad_(True) for f in FIELDS]

    def fn(*xs):
        out = rasterize_reference(Surfels(*xs), cam, background=torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
        return tuple(getattr(out, o) for o in OUTPUTS)

    outs = fn(*inputs)
    assert all(o.abs().sum() > 0 for o in outs[:4]), "scene too empty to test gradients"
    assert outs[5].abs().sum() > 0, "no overlapping surfels: distortion untested"
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, nondet_tol=0.0)


def test_gradcheck_the_beta_falloff():
    """The Beta kernel (1 - s rho/2)^(1/s): every field, the exponents among them (common.falloff)."""
    s, cam = random_scene(8, 1, width=8, height=8, seed=12, dtype=torch.float64, pixel_sigma=(1.0, 2.5))
    s.means = s.means * 0.4
    s.falloff = torch.tensor([0.05, 0.3, 0.9, 0.5, 0.02, 0.7, 0.2, 1.0], dtype=torch.float64)
    names = FIELDS + ["falloff"]
    inputs = [getattr(s, f).clone().requires_grad_(True) for f in names]

    def fn(*xs):
        out = rasterize_reference(Surfels(**dict(zip(names, xs))), cam)
        return tuple(getattr(out, o) for o in OUTPUTS)

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, nondet_tol=0.0)


def test_the_beta_falloff_profile_and_its_bounded_support():
    """A face-on surfel with falloff exponent s: alpha = o (1 - s r^2/2)^(1/s) at r sigmas, zero from r = sqrt(2/s)
    (the Gaussian as s -> 0), and a screen box no wider than that support."""
    from splatzoo.rasterizers.common import SETTINGS, project

    for s_exp in (0.5, 1.0, 1e-7):
        s, cam, sigma_px = _face_on(width=41, scale=0.1, opacity=0.8)
        s.falloff = torch.full_like(s.opacities, s_exp)
        out = rasterize(s, cam, backend="reference")
        c = 20
        r = ((torch.arange(41, dtype=torch.float64) + 0.5 - 20.5) / sigma_px).abs()
        if s_exp > 1e-3:
            profile = 0.8 * (1 - s_exp * r ** 2 / 2).clamp_min(0) ** (1 / s_exp)
        else:
            profile = 0.8 * torch.exp(-r ** 2 / 2)
        predicted = torch.where(profile >= 1 / 255, profile, torch.zeros_like(profile))
        assert torch.allclose(out.alpha[c].double(), predicted, atol=1e-5), s_exp
        box = project(s, cam, SETTINGS).boxes[0]
        half_width = float(box[2] - box[0]) / 2
        support = sigma_px * math.sqrt(2 / s_exp) if s_exp > 1e-3 else math.inf
        assert half_width <= support * 1.01 + 0.5


def _face_on(width, scale, opacity, k_vectors=(), dist=3.0, fov=40.0):
    cam = Camera.look_at([0.0, 0.0, -dist], [0.0, 0.0, 0.0], width=width, height=width, fov_deg=fov)
    s = single_surfel(normal=(0.0, 0.0, -1.0), scale=(scale, scale), opacity=opacity, k_vectors=k_vectors)
    return s, cam, float(cam.K[0, 0]) * scale / dist  # sigma in pixels


def test_face_on_surfel_renders_the_gaussian_profile():
    s, cam, sigma_px = _face_on(width=33, scale=0.1, opacity=0.8)
    out = rasterize(s, cam, backend="reference")
    c = 16  # pixel 16's centre is 16.5 = cx
    assert out.alpha[c, c].item() == pytest.approx(0.8, abs=1e-6)
    assert out.rgb[c, c, 0].item() == pytest.approx(0.8 * 0.5, abs=1e-6)
    assert out.depth[c, c].item() == pytest.approx(3.0, abs=1e-5)
    dx = torch.arange(33, dtype=torch.float64) + 0.5 - 16.5
    predicted = 0.8 * torch.exp(-dx ** 2 / (2 * sigma_px ** 2))
    predicted = torch.where(predicted >= 1 / 255, predicted, torch.zeros_like(predicted))
    assert torch.allclose(out.alpha[c].double(), predicted, atol=1e-5)
    # half width at half maximum, read off the row by linear interpolation
    row = out.alpha[c, c:].double()
    i = int((row < 0.4).nonzero()[0])
    hwhm = (i - 1) + (row[i - 1] - 0.4) / (row[i - 1] - row[i])
    assert hwhm.item() == pytest.approx(sigma_px * math.sqrt(2 * math.log(2)), rel=0.02)
    # normal faces the camera (camera looks along +z, so the normal is -z)
    assert torch.allclose(out.normal[c, c], torch.tensor([0.0, 0.0, -0.8]), atol=1e-5)


def test_gabor_wave_shows_predicted_stripe_period():
    freq = 1.5  # cycles per sigma
    s, cam, sigma_px = _face_on(width=65, scale=0.4, opacity=0.99, k_vectors=[(2 * math.pi * freq, 0.0)], fov=60.0)
    s.wave_amplitudes = torch.full((1, 1, 3), 0.4)
    out = rasterize(s, cam, backend="reference")
    c = 32
    # sample along the image axis that the surfel's u axis projects onto
    t_u = quat_to_rotmat(s.quats)[0, :, 0] @ cam.R.T.float()
    rgb, alpha = (out.rgb[c], out.alpha[c]) if abs(t_u[0]) > abs(t_u[1]) else (out.rgb[:, c], out.alpha[:, c])
    color = (rgb / alpha.clamp_min(1e-8)[:, None])[:, 0].double()
    dx = torch.arange(65, dtype=torch.float64) + 0.5 - 32.5
    # local u runs along +x or -x depending on the rotation: cos is even, so the profile is the same
    predicted = 0.5 + 0.4 * torch.cos(2 * math.pi * freq * dx / sigma_px)
    inside = alpha > 0.05
    assert inside.sum() > 20
    assert torch.allclose(color[inside], predicted[inside], atol=1e-4)
    # stripe period in pixels from the spacing of the colour's upward mean crossings
    period_px = sigma_px / freq
    sig = (color - 0.5)[inside].numpy()
    xs = dx[inside].numpy()
    ups = [xs[i] - sig[i] * (xs[i + 1] - xs[i]) / (sig[i + 1] - sig[i]) for i in range(len(sig) - 1)
           if sig[i] < 0 <= sig[i + 1]]
    assert len(ups) >= 2
    measured = (ups[-1] - ups[0]) / (len(ups) - 1)
    assert measured == pytest.approx(period_px, rel=0.01)


@pytest.mark.parametrize("case", extreme_cases(), ids=lambda c: c[0])
def test_stability_at_the_extremes(case, any_backend):
    name, s, cam = case
    if cam.width * cam.height > 100_000 and any_backend.name in ("reference", "cuda-emulated"):
        cam = cam.scaled(0.25)  # the slow backends take the full-HD case at 480x270
    dev = any_backend.torch_device()
    inputs = {f: getattr(s, f).clone().to(dev).requires_grad_(True) for f in FIELDS + ["falloff"]}
    out = rasterize(Surfels(**inputs), cam, backend=any_backend)
    for o in OUTPUTS:
        v = getattr(out, o)
        assert v.shape[:2] == (cam.height, cam.width), o
        assert torch.isfinite(v).all(), f"{name}: {o} not finite"
    assert out.alpha.min() >= 0
    limit = 0.99 + 1e-6 if s.num <= 1 else 1 - 1e-4 + 1e-6
    assert out.alpha.max() <= limit
    g = torch.Generator().manual_seed(0)
    loss = sum((getattr(out, o) * torch.randn(getattr(out, o).shape, generator=g).to(dev)).sum() for o in OUTPUTS)
    loss.backward()  # every backend's render is differentiable, even one that draws nothing
    grads = {f: t.grad if t.grad is not None else torch.zeros_like(t) for f, t in inputs.items() if t.numel()}
    for f, g in grads.items():
        assert inputs[f].grad is not None and torch.isfinite(g).all(), f"{name}: gradient of {f} missing or not finite"
    if float(out.alpha.detach().max()) == 0:  # nothing drawn: nothing to learn, the same in every backend
        for f, g in grads.items():
            assert (g == 0).all(), f"{name}: a render that draws nothing has a gradient for {f}"


def test_near_plane_culls_and_behind_camera_is_invisible():
    cases = dict((n, (s, c)) for n, s, c in extreme_cases())
    for name in ("inside_near", "at_camera", "behind"):
        s, cam = cases[name]
        assert rasterize(s, cam, backend="reference").alpha.max() == 0, name
    s, cam = cases["tilt0"]
    assert rasterize(s, cam, backend="reference").alpha.max() > 0.5


def test_occlusion_order_front_to_back():
    front = single_surfel(center=(0.0, 0.0, -1.0), opacity=0.9, color=(1.0, 0.0, 0.0))
    back = single_surfel(center=(0.0, 0.0, 1.0), opacity=0.9, color=(0.0, 1.0, 0.0))
    cam = Camera.look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], width=9, height=9, fov_deg=40.0)
    both = Surfels(*[torch.cat([getattr(back, f), getattr(front, f)]) for f in FIELDS])
    out = rasterize(both, cam, backend="reference")
    # the front surfel (listed second) is composited first
    assert out.rgb[4, 4].tolist() == pytest.approx([0.9, 0.1 * 0.9, 0.0], abs=1e-5)
    assert out.median_depth[4, 4].item() == pytest.approx(2.0, abs=1e-4)
    assert out.depth[4, 4].item() == pytest.approx((0.9 * 2 + 0.09 * 4) / 0.99, abs=1e-4)
    m = lambda z: 100 / 99.8 * (1 - 0.2 / z)  # noqa: E731
    assert out.distortion[4, 4].item() == pytest.approx(0.9 * 0.09 * (m(4) - m(2)) ** 2, rel=1e-4)


def test_chunking_does_not_change_the_result():
    s, cam = random_scene(300, 4, width=40, height=30, seed=5)
    a = rasterize_reference(s, cam)
    b = rasterize_reference(s, cam, pair_budget=2000)
    for o in OUTPUTS:
        assert torch.allclose(getattr(a, o), getattr(b, o), atol=1e-6), o


def test_a_few_thousand_surfels_at_128_fit_in_memory():
    s, cam = random_scene(3000, 4, width=128, height=128, seed=6)
    out = rasterize(s, cam, backend="reference")
    assert out.alpha.mean() > 0.3


def test_bad_input_is_named():
    s, cam = random_scene(4, 1)
    with pytest.raises(ShapeError, match="scales"):
        rasterize(Surfels(s.means, s.quats, s.scales[:, :1], s.opacities, s.base_color, s.wave_vectors,
                          s.wave_phases, s.wave_amplitudes), cam, backend="reference")
    bad = s.means.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ShapeError, match="NaN"):
        rasterize(Surfels(bad, *[getattr(s, f) for f in FIELDS[1:]]), cam, backend="reference")
    with pytest.raises(Exception, match="unknown rasterizer backend 'refrence'.*reference"):
        rasterize(s, cam, backend="refrence")
