"""The native tile rasterizers against the PyTorch reference, on every native backend: the C++ loops ("cpu"), the
CUDA kernels under the host emulation ("cuda-emulated", so CI runs the real kernel source) and, with a GPU, "cuda".

Forward outputs and gradients (one shared random cotangent on every output) on random realistic scenes, an exact
float64 comparison, gradcheck, extreme inputs, wave counts, settings, the camera-gradient policy, and build and
dispatch behaviour. The first test that needs the extension builds it (a minute or two on 2 cores; cached).
"""
from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
import warnings
from dataclasses import fields, replace
from pathlib import Path

import pytest
import torch

from conftest import backend_for_test
from splatzoo.errors import BackendUnavailableError, ShapeError, UnknownNameError
from splatzoo.geometry import normals_to_quats
from splatzoo.rasterizers import BACKENDS, native, rasterize, select_backend
from splatzoo.rasterizers.common import ANTIALIASED, SETTINGS, RasterSettings
from splatzoo.rasterizers.reference import rasterize_reference
from splatzoo.testing import sphere_and_wall as random_scene
from splatzoo.types import MAX_FALLOFF, MAX_PHASE, MAX_SCALE, MAX_WAVE_NUMBER, SURFEL_FIELDS, Camera, Surfels

CSRC = Path(__file__).resolve().parents[1] / "splatzoo" / "csrc"
FIELDS = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion")
# The emulated kernels run every GPU thread as a fiber on one core: they get smaller images than the real loops.
EMULATED = "cuda-emulated"


def _leaf(s: Surfels, device="cpu") -> Surfels:
    return s.to(device).map(lambda t: t.detach().clone().requires_grad_(True))


def _render_and_grads(backend, s: Surfels, cam, cot, bg=None, settings=SETTINGS):
    """Outputs and surfel gradients (on the CPU) of `backend` (a Backend, or "reference") for cotangent `cot`."""
    b = BACKENDS.get(backend) if isinstance(backend, str) else backend
    dev = b.torch_device()
    s = _leaf(s, dev)
    out = rasterize(s, cam, backend=b, background=bg, settings=settings)
    loss = sum((getattr(out, k) * cot[k].to(dev)).sum() for k in FIELDS)
    grads = torch.autograd.grad(loss, list(s.tensors().values()), allow_unused=True)
    out = type(out)(**{k: getattr(out, k).detach().cpu() for k in FIELDS})
    return out, {k: None if g is None else g.cpu() for k, g in zip(s.tensors(), grads)}


def _cotangent(H, W, dtype, seed=7):
    g = torch.Generator().manual_seed(seed)
    shapes = {"rgb": (H, W, 3), "normal": (H, W, 3)}
    return {k: torch.randn(shapes.get(k, (H, W)), generator=g, dtype=torch.float64).to(dtype) for k in FIELDS}


def _check_grads(g_ref, g_nat, rel_tol=1e-3, cos_tol=0.9999):
    """Each gradient must match in relative error AND in direction (cosine)."""
    for name, a in g_ref.items():
        b = g_nat[name]
        if a is None or a.numel() == 0:
            continue
        assert b is not None, f"no native gradient for {name}"
        assert torch.isfinite(b).all(), f"non-finite native gradient for {name}"
        a, b = a.double().flatten(), b.double().flatten()
        if a.norm() == 0:
            assert b.norm() <= 1e-12, f"gradient of {name}: reference is zero, native has norm {b.norm():.2e}"
            continue
        rel = ((a - b).norm() / a.norm()).item()
        cos = torch.nn.functional.cosine_similarity(a, b, dim=0).item()
        assert rel <= rel_tol and cos >= cos_tol, f"gradient of {name}: relative error {rel:.2e}, cosine {cos:.7f}"


def _assert_outputs_close(ref, nat, dtype, max_bad_fraction=1 / 2000, atol=1e-4):
    npix = ref.alpha.numel()
    for k in FIELDS:
        a, b = getattr(ref, k), getattr(nat, k)
        assert a.shape == b.shape and b.dtype == dtype, k
        assert torch.isfinite(b).all(), k
        err = (a - b).abs()
        if err.dim() == 3:
            err = err.amax(-1)
        # A (surfel, pixel) pair within float32 rounding of a discrete decision (alpha = alpha_min, T = t_min, ...)
        # may go either way in two float32 implementations; such pixels are rare (the float64 test below shows the
        # maths is identical). Everything else must agree to atol.
        bad = int((err > atol).sum())
        assert bad <= max(2, int(npix * max_bad_fraction)), f"{k}: {bad} pixels differ by more than {atol:g} (max {err.max():.2e})"


# ---- settings: one source ---------------------------------------------------------------------------------------

def test_settings_struct_has_every_field_of_raster_settings():
    C = native.load("cpu")
    python_fields = {f.name for f in fields(RasterSettings)} - {"tile"}
    assert set(C.SETTINGS_FIELDS) == python_fields
    assert C.TILE == SETTINGS.tile
    struct = native.settings_struct(C, SETTINGS)
    for name in python_fields:
        assert getattr(struct, name) == getattr(SETTINGS, name), name


# ---- the surfel fields: one table ----------------------------------------------------------------------------------

def test_the_shipped_field_header_is_generated_from_the_table():
    """csrc/surfel_fields.h is what splatzoo/rasterizers/fields.py makes of the Surfels declarations."""
    from splatzoo.rasterizers import fields as field_header

    assert field_header.HEADER.read_text() == field_header.header_text(), (
        "csrc/surfel_fields.h is stale: run python -m splatzoo.rasterizers.fields")
    assert field_header.main(["--check"]) == 0


def test_the_extension_takes_the_fields_of_the_table():
    from splatzoo.types import SURFEL_FIELDS

    C = native.load("cpu")
    assert tuple(C.SURFEL_FIELDS) == tuple(f.name for f in SURFEL_FIELDS) == native.SURFEL_FIELDS
    assert [f.name for f in SURFEL_FIELDS][:3] == ["means", "quats", "scales"]
    assert {f.role for f in SURFEL_FIELDS} == {"geometry", "opacity", "appearance"}
    # a build whose table differs (a header not regenerated after a field was added) is refused, naming the fix
    class Stale:
        SURFEL_FIELDS = native.SURFEL_FIELDS[:-1]

    with pytest.raises(BackendUnavailableError, match="python -m splatzoo.rasterizers.fields"):
        native._check_fields(Stale)


def _bindings(backend, cam: Camera):
    """The extension a native backend calls, with its device, its `emulated` flag and `cam` as the bindings take it
    (KR, Kt and the eye, float32 on that device)."""
    C = native.load("cuda" if backend.name == "cuda" else "cpu")
    dev = backend.torch_device()
    cam = cam.to("cpu", torch.float64)
    KR, Kt, eye = ((cam.K @ cam.R).float().to(dev), (cam.K @ cam.t).float().to(dev), cam.center.float().to(dev))
    return C, dev, backend.name == "cuda-emulated", (KR, Kt, eye)


@pytest.mark.parametrize("name", [f.name for f in SURFEL_FIELDS])
def test_the_extension_checks_every_field_by_name(native_backend, name):
    """Below Surfels.validate, the bindings check each field's shape from the table and name it (every build: an
    error raised in the extension must reach Python as an exception, not end the process)."""
    s, cam = random_scene(10, 16, 16, 2, seed=1)
    C, dev, emulated, camera = _bindings(native_backend, cam)
    tensors = {k: t.to(dev) for k, t in s.tensors().items()}
    tensors[name] = tensors[name][:-1] if name != "means" else tensors[name][:, :2]
    with pytest.raises(RuntimeError, match=name):
        C.render(native.settings_struct(C, SETTINGS), list(tensors.values()), None, *camera, 16, 16, emulated)


def test_bad_settings_are_refused():
    from splatzoo.errors import SplatzooError

    for bad in ({"near": -1.0}, {"alpha_min": 0.5, "alpha_max": 0.4}, {"t_min": float("nan")}):
        with pytest.raises(SplatzooError):
            RasterSettings(**bad)
    s, cam = random_scene(20, 16, 16, 0, seed=1)
    with pytest.raises(BackendUnavailableError, match="tiles of 16"):
        rasterize(s, cam, backend="cpu", settings=RasterSettings(tile=8))


def test_non_default_settings_reach_every_backend(native_backend):
    """Settings flow through the seam: a render with other near plane, alpha limits, t_min and filter matches the
    reference with the same settings, and differs from the default render."""
    settings = RasterSettings(near=3.6, alpha_max=0.9, alpha_min=0.02, t_min=0.05, filter_inv_sq=1.0, far=50.0)
    s, cam = random_scene(150, 40, 32, 2, seed=8, dtype=torch.float64)
    cot = _cotangent(32, 40, torch.float64)
    ref, g_ref = _render_and_grads("reference", s, cam, cot, settings=settings)
    nat, g_nat = _render_and_grads(native_backend, s, cam, cot, settings=settings)
    for k in FIELDS:
        torch.testing.assert_close(getattr(nat, k), getattr(ref, k), rtol=0, atol=1e-9, msg=k)
    _check_grads(g_ref, g_nat, rel_tol=1e-7, cos_tol=1 - 1e-12)
    default = _render_and_grads(native_backend, s, cam, cot)[0]
    assert (default.alpha - nat.alpha).abs().max() > 0.05


# ---- against the reference --------------------------------------------------------------------------------------

@pytest.mark.parametrize("n,K", [(2000, 0), (1000, 1), (2000, 4), (600, 8)])
def test_matches_reference_float32(native_backend, n, K):
    W = H = 128
    if native_backend.name == EMULATED:
        n, W, H = n // 10, 48, 40
    s, cam = random_scene(n, W, H, K, seed=11 * n + K)
    bg = [0.2, 0.4, 0.6]
    cot = _cotangent(H, W, torch.float32, seed=K)
    ref, g_ref = _render_and_grads("reference", s, cam, cot, bg)
    nat, g_nat = _render_and_grads(native_backend, s, cam, cot, bg)
    _assert_outputs_close(ref, nat, torch.float32)
    _check_grads(g_ref, g_nat)


@pytest.mark.parametrize("K", [0, 4])
@pytest.mark.parametrize("name", [EMULATED, "cuda"])
def test_agrees_with_the_cpu_backend(name, K):
    """The CUDA kernels (real or emulated) against the C++ backend on the same float32 inputs: outputs to 1e-4 (but
    for rare pixels on a float32 threshold), gradients by the relative-and-cosine rule."""
    native_backend = backend_for_test(name)
    n, W, H = (2000, 128, 96) if name == "cuda" else (200, 48, 40)
    s, cam = random_scene(n, W, H, K, seed=31 + K)
    cot = _cotangent(H, W, torch.float32, seed=3)
    cpu, g_cpu = _render_and_grads("cpu", s, cam, cot, [0.3, 0.2, 0.1])
    nat, g_nat = _render_and_grads(native_backend, s, cam, cot, [0.3, 0.2, 0.1])
    _assert_outputs_close(cpu, nat, torch.float32)
    _check_grads(g_cpu, g_nat)


@pytest.mark.parametrize("kernel", ["gaussian", "beta"])
def test_matches_reference_float64_exactly(native_backend, kernel):
    s, cam = random_scene(400, 48, 40, 3, seed=5, dtype=torch.float64)
    if kernel == "beta":  # a mix: Gaussians, Beta kernels from nearly Gaussian to the tightest
        s.falloff = torch.rand(s.num, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
        s.falloff[::4] = 0.0
        s.falloff[1::9] = 1e-6
        s.falloff[2::9] = MAX_FALLOFF
    cot = _cotangent(40, 48, torch.float64)
    ref, g_ref = _render_and_grads("reference", s, cam, cot, [0.1, 0.1, 0.1])
    nat, g_nat = _render_and_grads(native_backend, s, cam, cot, [0.1, 0.1, 0.1])
    for k in FIELDS:
        torch.testing.assert_close(getattr(nat, k), getattr(ref, k), rtol=0, atol=1e-9, msg=k)
    _check_grads(g_ref, g_nat, rel_tol=1e-7, cos_tol=1 - 1e-12)


@pytest.mark.parametrize("kernel", ["gaussian", "beta"])
def test_gradcheck_float64(native_backend, kernel):
    """The hand-written backward of the whole native render (projection, culling, sort, tile loop), by finite
    differences. Not w.r.t. the means: a small move of a mean moves the boundary where the screen filter takes over
    (there the surfel is seen as its centre, a step in colour), in the reference as well; the means' gradient is
    checked against the reference's autograd in test_matches_reference_float64_exactly."""
    s, cam = random_scene(6, 12, 10, 2, seed=3, dtype=torch.float64, px_sigma=(2.0, 3.0))
    s = s.to(native_backend.torch_device())
    s.opacities.fill_(0.6)
    if kernel == "beta":  # falloff exponents inside (0, 1]: finite differences stay in the valid range
        s.falloff = torch.tensor([0.02, 0.3, 1e-3, 0.9, 0.1, 0.5], dtype=torch.float64, device=s.means.device)
    means = s.means.detach()
    fixed = {"falloff": s.falloff} if kernel == "gaussian" else {}  # 0 is the range's edge
    names = [name for name in s.tensors() if name != "means" and name not in fixed]
    inputs = [getattr(s, n).detach().clone().requires_grad_(True) for n in names]

    def f(*x):
        out = rasterize(Surfels(means, **dict(zip(names, x)), **fixed), cam, backend=native_backend)
        return tuple(getattr(out, k) * w for k, w in zip(FIELDS, (1.0, 0.7, 0.3, 0.2, 0.5, 2.0)))

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, nondet_tol=1e-12)


def test_dispatch_by_name():
    s, cam = random_scene(50, 32, 32, 1, seed=2)
    a = rasterize(s, cam, backend="cpu")
    b = rasterize(s, cam, backend="reference")
    torch.testing.assert_close(a.rgb, b.rgb, atol=1e-4, rtol=0)


# ---- extremes ---------------------------------------------------------------------------------------------------

def _one(means, normal, scales, opac=0.9, K=0, freq=0.0, dtype=torch.float32):
    n = means.shape[0]
    q = normals_to_quats(torch.as_tensor(normal, dtype=torch.float64).reshape(-1, 3).expand(n, 3))
    wv = torch.zeros(n, K, 2, dtype=torch.float64)
    if K:
        ang = torch.linspace(0, math.pi, K, dtype=torch.float64)
        wv = 2 * math.pi * freq * torch.stack([torch.cos(ang), torch.sin(ang)], -1).expand(n, K, 2)
    s = Surfels(torch.as_tensor(means, dtype=torch.float64), q, torch.as_tensor(scales, dtype=torch.float64).expand(n, 2),
                torch.as_tensor(opac, dtype=torch.float64).expand(n).clone(), torch.full((n, 3), 0.5, dtype=torch.float64),
                wv.clone(), torch.full((n, K), 0.3, dtype=torch.float64), torch.full((n, K, 3), 0.4, dtype=torch.float64))
    return s.to(dtype=dtype)


def _check_finite(backend, s, cam, single_layer=False):
    out, grads = _render_and_grads(backend, s, cam, _cotangent(cam.height, cam.width, s.means.dtype))
    for k in FIELDS:
        v = getattr(out, k)
        assert v.shape[:2] == (cam.height, cam.width)
        assert torch.isfinite(v).all(), f"non-finite {k}"
    assert (out.alpha >= 0).all() and (out.alpha <= 1 - SETTINGS.t_min + 1e-6).all()
    if single_layer:
        assert (out.alpha <= SETTINGS.alpha_max + 1e-6).all()
    for k, g in grads.items():
        assert g is None or torch.isfinite(g).all(), f"non-finite gradient of {k}"
    return out


def _cam(w=64, h=48):
    return Camera.look_at((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), fov_deg=60.0, width=w, height=h)


def _same_as_reference_float64(backend, s, cam, atol=1e-7):
    ref = rasterize_reference(s.to(dtype=torch.float64), cam)
    nat = _render_and_grads(backend, s.to(dtype=torch.float64), cam, _cotangent(cam.height, cam.width, torch.float64))[0]
    for k in FIELDS:
        torch.testing.assert_close(getattr(nat, k), getattr(ref, k), atol=atol, rtol=0, msg=k)


@pytest.mark.parametrize("angle_deg", [0.0, 60.0, 85.0, 89.9, 89.999, 90.0])
def test_extreme_edge_on(native_backend, angle_deg):
    a = math.radians(angle_deg)
    normal = [math.sin(a), 0.0, -math.cos(a)]
    s = _one(torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.1, 0.5]]), normal, [0.2, 0.1], K=2, freq=3.0)
    out = _check_finite(native_backend, s, _cam())
    _same_as_reference_float64(native_backend, s, _cam())  # float64: both sides are accurate, even edge-on
    assert out.alpha.max() > 0  # seen at least through the screen-space filter


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1.0, 1e3])
def test_extreme_scales(native_backend, scale):
    s = _one(torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.2, 1.0]]), [0.3, 0.2, -1.0], [scale, scale * 0.5], K=1, freq=1.0)
    _check_finite(native_backend, s, _cam())


@pytest.mark.parametrize("freq", [10.0, MAX_WAVE_NUMBER / (2 * math.pi)])
def test_extreme_frequencies(native_backend, freq):
    s = _one(torch.tensor([[0.0, 0.0, 0.0]]), [0.0, 0.0, -1.0], [0.5, 0.5], K=4, freq=freq)
    _check_finite(native_backend, s, _cam(), single_layer=True)


@pytest.mark.parametrize("opac", [0.0, 1.0])
def test_extreme_opacity(native_backend, opac):
    s, cam = random_scene(300, 48, 48, 2, seed=4)
    s.opacities.fill_(opac)
    out = _check_finite(native_backend, s, cam)
    if opac == 0.0:
        assert out.alpha.abs().max() == 0
    else:  # opaque surfels stop pixels early (transmittance floor): the emulated kernels' block vote path
        assert out.alpha.max() > 0.999


# ---- the valid ranges: every backend gives the same answer up to each field's bound (types.py), none beyond it ----

def _agree_with_reference(backend, s, cam, settings, atol=1e-4):
    cot = _cotangent(cam.height, cam.width, torch.float32)
    ref, g_ref = _render_and_grads("reference", s, cam, cot, settings=settings)
    nat, g_nat = _render_and_grads(backend, s, cam, cot, settings=settings)
    _assert_outputs_close(ref, nat, torch.float32, atol=atol)
    # the scales as a model sees them, through their log (d/d log s = s d/ds): for a surfel far wider than the image
    # dL/ds is float noise of size ~1/s in every backend
    g_ref["scales"], g_nat["scales"] = g_ref["scales"] * s.scales, g_nat["scales"] * s.scales
    # every gradient agrees to a fraction of the largest; those that are not vanishingly small (such as the waves'
    # where the footprint averages them away) also in relative error and direction
    largest = max(float(g.abs().max()) for g in g_ref.values() if g is not None and g.numel())
    for name, a in g_ref.items():
        if a is not None and a.numel():
            assert float((a - g_nat[name]).abs().max()) <= 1e-3 * largest, name
    _check_grads({k: g for k, g in g_ref.items() if g is not None and float(g.abs().max()) > 1e-3 * largest}, g_nat)
    return ref


@pytest.mark.parametrize("settings", [SETTINGS, ANTIALIASED], ids=["plain", "antialiased"])
@pytest.mark.parametrize("fov_deg", [50.0, 0.05])
def test_backends_agree_at_the_largest_scale(native_backend, settings, fov_deg):
    """Surfels at MAX_SCALE cover the image alike in every backend, with the same gradients, for a short and a very
    long focal length (anti-aliased, the native products of such a surfel's footprint used to overflow float: it
    vanished there while the reference drew it)."""
    cam = Camera.look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), width=24, height=24, fov_deg=fov_deg)
    s = _one(torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.05, 0.5]]), [0.3, 0.2, -1.0], [MAX_SCALE, MAX_SCALE / 2], K=1,
             freq=1.0)
    ref = _agree_with_reference(native_backend, s, cam, settings)
    assert ref.alpha.min() > 0.9


@pytest.mark.parametrize("settings", [SETTINGS, ANTIALIASED], ids=["plain", "antialiased"])
def test_backends_agree_at_the_highest_wave_number(native_backend, settings):
    s = _one(torch.tensor([[0.0, 0.0, 0.0], [0.2, -0.1, 0.4]]), [0.3, 0.2, -1.0], [0.5, 0.3], K=3,
             freq=MAX_WAVE_NUMBER / (2 * math.pi))
    s.wave_phases = torch.full_like(s.wave_phases, MAX_PHASE)
    # unfiltered, the float phases of 1e3 radians per sigma are good to ~3e-4 (the bound's reason); filtered, such
    # waves are averaged away
    _agree_with_reference(native_backend, s, _cam(32, 24), settings, atol=2e-3)


@pytest.mark.parametrize("fov_deg", [50.0, 0.05])
@pytest.mark.parametrize("offset", [1e4, 1e6])
def test_backends_agree_far_from_the_origin(native_backend, offset, fov_deg):
    """A scene far from the origin seen from close by: the surfels' camera coordinates cancel large world coordinates
    against the camera's translation, and every backend accumulates them in double (in float the backends' rounding
    differed by up to 12% of a pixel's alpha at 1e6)."""
    cam = Camera.look_at((offset, offset, offset - 3.0), (offset, offset, offset), width=24, height=24, fov_deg=fov_deg)
    d = torch.tensor([[0.0, 0.0, 0.0], [0.25, -0.125, 0.5]], dtype=torch.float64)
    s = _one(d + offset, [0.3, 0.2, -1.0], [0.3, 0.2], K=1, freq=1.0)
    ref = _agree_with_reference(native_backend, s, cam, SETTINGS)
    assert ref.alpha.max() > 0.5


@pytest.mark.parametrize("field,value", [("scales", -0.1), ("scales", 1e13), ("opacities", 2.0), ("opacities", -0.5),
                                         ("wave_vectors", 1e20), ("wave_phases", 1e5), ("means", 1e13),
                                         ("base_color", -1e7), ("wave_amplitudes", 1e7), ("quats", 1e30)])
def test_values_outside_a_fields_range_are_refused_by_name(field, value):
    s = _one(torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.2, 1.0]]), [0.3, 0.2, -1.0], [0.2, 0.1], K=2, freq=1.0)
    t = getattr(s, field).clone()
    t.view(-1)[0] = value
    setattr(s, field, t)
    lo, hi = next(f.valid for f in SURFEL_FIELDS if f.name == field)
    with pytest.raises(ShapeError, match=rf"Surfels\.{field} \(.*\) must lie in {re.escape(f'[{lo:g}, {hi:g}]')}.*1 "
                                         r"value\(s\) lie outside"):
        rasterize(s, _cam(), backend="reference")
    t.view(-1)[0] = float("nan")
    with pytest.raises(ShapeError, match=rf"Surfels\.{field} contains NaN"):
        rasterize(s, _cam(), backend="cpu")


@pytest.mark.parametrize("settings", [SETTINGS, ANTIALIASED], ids=["plain", "antialiased"])
def test_an_image_only_render_has_the_full_renders_pixels(any_backend, settings):
    """rasterize(..., image_only=True), the render to look at: rgb and alpha bit for bit those of the full render (the
    same blend), the other outputs None, nothing differentiable, on every backend."""
    s, cam = random_scene(800, 48, 40, 4, seed=3)
    s.wave_counts = torch.randint(0, 5, (s.num,), generator=torch.Generator().manual_seed(1))
    dev = any_backend.torch_device()
    s = s.to(dev)
    full = rasterize(s, cam, backend=any_backend, background=(0.2, 0.4, 0.6), settings=settings)
    leaves = s.map(lambda t: t.clone().requires_grad_(True))
    image = rasterize(leaves, cam, backend=any_backend, background=(0.2, 0.4, 0.6), settings=settings,
                      image_only=True)
    assert torch.equal(image.rgb, full.rgb) and torch.equal(image.alpha, full.alpha)
    assert image.depth is None and image.normal is None and image.distortion is None
    assert not image.rgb.requires_grad and set(image.tensors()) == {"rgb", "alpha"}


def test_near_plane_and_behind_camera(native_backend):
    # camera at z = -4 looking +z: camera depth = z + 4
    near = SETTINGS.near
    z = torch.tensor([-4.0 + near, -4.0 + near * 0.999, -4.0 + near * 1.001, -4.0, -5.0, -4.1, -3.7, -3.9])
    means = torch.stack([torch.linspace(-0.05, 0.05, 8), torch.zeros(8), z], 1).double()
    s = _one(means, [0.2, 0.1, -1.0], [0.3, 0.3], K=1, freq=2.0)
    out = _check_finite(native_backend, s, _cam())
    _same_as_reference_float64(native_backend, s, _cam())
    assert (out.depth[out.alpha > 0] >= near - 1e-6).all()


def test_extreme_image_sizes(native_backend):
    sizes = [(1, 1), (37, 5)] + ([] if native_backend.name == EMULATED else [(1920, 1080)])
    s, _ = random_scene(500, 64, 64, 2, seed=9)
    for w, h in sizes:
        cam = Camera.look_at((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), fov_deg=60.0, width=w, height=h)
        out = _check_finite(native_backend, s, cam)
        if w * h < 1000:
            ref = rasterize_reference(s, cam)
            torch.testing.assert_close(out.rgb, ref.rgb, atol=1e-4, rtol=0)


def test_no_surfels(native_backend):
    dev = native_backend.torch_device()
    s = Surfels.empty(3).to(dev).map(lambda t: t.requires_grad_(True))
    out = rasterize(s, _cam(), backend=native_backend, background=[0.5, 0.5, 0.5])
    assert torch.equal(out.rgb.cpu(), torch.full((48, 64, 3), 0.5))
    assert out.alpha.abs().max() == 0
    out.rgb.sum().backward()  # an empty render still back-propagates
    # all invisible: behind the camera
    s2 = _one(torch.tensor([[0.0, 0.0, -6.0]]), [0.0, 0.0, -1.0], [0.3, 0.3])
    out2, grads = _render_and_grads(native_backend, s2, _cam(), _cotangent(48, 64, torch.float32))
    assert out2.alpha.abs().max() == 0 and all(g is None or (g == 0).all() for g in grads.values())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_wave_counts_match_reference(native_backend, dtype):
    """Per-surfel wave counts: values and gradients as the reference; unused waves get exactly zero gradient."""
    s, cam = random_scene(300, 48, 40, 4, seed=5, dtype=dtype)
    s.wave_counts = torch.randint(0, 5, (s.num,), generator=torch.Generator().manual_seed(1), dtype=torch.int32)
    cot = _cotangent(40, 48, dtype)
    ref, g_ref = _render_and_grads("reference", s, cam, cot)
    nat, g_nat = _render_and_grads(native_backend, s, cam, cot)
    atol = 1e-9 if dtype == torch.float64 else 1e-4
    for k in FIELDS:
        torch.testing.assert_close(getattr(nat, k), getattr(ref, k), atol=atol, rtol=0, msg=k)
    exact = dtype == torch.float64
    _check_grads(g_ref, g_nat, rel_tol=1e-7 if exact else 1e-3, cos_tol=1 - 1e-12 if exact else 0.9999)
    unused = torch.arange(4)[None] >= s.wave_counts[:, None]
    for name in ("wave_vectors", "wave_phases", "wave_amplitudes"):
        assert g_nat[name][unused].abs().max() == 0, name
    # all counts 0 renders exactly as K = 0
    s.wave_counts.zero_()
    flat = Surfels(s.means, s.quats, s.scales, s.opacities, s.base_color, s.wave_vectors[:, :0], s.wave_phases[:, :0],
                   s.wave_amplitudes[:, :0])
    cot = _cotangent(40, 48, dtype)
    assert torch.equal(_render_and_grads(native_backend, s, cam, cot)[0].rgb,
                       _render_and_grads(native_backend, flat, cam, cot)[0].rgb)


def test_bad_wave_counts_are_refused(native_backend):
    s, cam = random_scene(20, 16, 16, 2, seed=1)
    s.wave_counts = torch.full((s.num,), 3, dtype=torch.int32)  # K = 2
    with pytest.raises(ShapeError, match="wave_counts must lie in"):
        rasterize(s.to(native_backend.torch_device()), cam, backend=native_backend)


# ---- determinism and the camera-gradient policy -----------------------------------------------------------------

def test_gradients_are_repeatable(native_backend):
    """The C++ backward sums per-(surfel, tile) rows in a fixed order: bitwise repeatable. The CUDA backward adds
    per-warp sums with atomics, so its order (and last bits) may vary on a GPU; the emulation runs blocks in order."""
    s, cam = random_scene(300, 48, 40, 2, seed=6)
    cot = _cotangent(40, 48, torch.float32)
    a = _render_and_grads(native_backend, s, cam, cot)
    b = _render_and_grads(native_backend, s, cam, cot)
    for k in FIELDS:
        assert torch.equal(getattr(a[0], k), getattr(b[0], k)), k  # the forward is deterministic everywhere
    for k, g in a[1].items():
        if native_backend.name == "cuda":
            torch.testing.assert_close(b[1][k], g, rtol=1e-4, atol=1e-6)
        else:
            assert torch.equal(b[1][k], g), k


def test_no_backend_propagates_camera_gradients(any_backend):
    s, cam = random_scene(100, 32, 24, 1, seed=2)
    w2c = cam.world_to_camera.clone().requires_grad_(True)
    K = cam.K.clone().requires_grad_(True)
    cam = replace(cam, world_to_camera=w2c, K=K)
    dev = any_backend.torch_device()
    s = s.to(dev).map(lambda t: t.requires_grad_(True))
    out = rasterize(s, cam, backend=any_backend)
    (out.rgb.sum() + out.depth.sum()).backward()
    assert w2c.grad is None and K.grad is None
    assert s.means.grad is not None and s.means.grad.abs().sum() > 0


# ---- the backend registry ---------------------------------------------------------------------------------------

def test_backend_registry_names_and_errors():
    assert {"reference", "cpu", "cuda", "cuda-emulated"} <= set(BACKENDS.names())
    with pytest.raises(UnknownNameError, match="Did you mean 'cuda'"):
        select_backend("cudaa")
    b = select_backend("cuda-emulated")
    assert b.device == "cpu" and b.test_only and b.auto_rank is None
    with pytest.raises(BackendUnavailableError, match="move them"):
        select_backend("cpu", torch.device("meta"))


def test_auto_falls_back_to_the_cpu_backend_when_the_cuda_build_fails(monkeypatch):
    """On a GPU machine whose CUDA build fails, "auto" must pick the C++ CPU backend (and say why), not the slow
    reference."""
    from splatzoo import rasterizers

    def broken():
        raise BackendUnavailableError("could not build the native cuda rasterizer: nvcc failed")

    cuda = BACKENDS.get("cuda")
    monkeypatch.setattr(BACKENDS._entries["cuda"], "spec", replace(cuda, check=broken))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(rasterizers, "_warned", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        chosen = select_backend("auto")
    assert chosen.name == "cpu" and chosen.torch_device().type == "cpu"
    assert any("nvcc failed" in str(w.message) for w in caught)


# ---- build and import behaviour ---------------------------------------------------------------------------------

def test_import_does_not_build_or_load():
    code = ("import sys, splatzoo; bad = [m for m in sys.modules if m.startswith('splatzoo_cpu') or "
            "m.startswith('splatzoo_cuda') or m == 'torch.utils.cpp_extension']; print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_collection_does_not_build_the_extension(tmp_path):
    env = {**__import__("os").environ, "SPLATZOO_EXTENSIONS_DIR": str(tmp_path / "ext")}
    r = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", str(Path(__file__).parent)],
                       capture_output=True, text=True, timeout=300, env=env, cwd=Path(__file__).parents[1])
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert not (tmp_path / "ext").exists(), "collecting the tests built the native extension"


def test_build_failures_say_what_to_install(monkeypatch, tmp_path):
    monkeypatch.setattr(native, "CSRC", tmp_path / "nowhere")
    with pytest.raises(BackendUnavailableError, match="sources are missing"):
        native._build("cpu")
    monkeypatch.setattr(native, "CSRC", CSRC)
    from torch.utils import cpp_extension

    def no_ninja():
        raise RuntimeError("Ninja is required to load C++ extensions")

    monkeypatch.setattr(cpp_extension, "verify_ninja_availability", no_ninja)
    with pytest.raises(BackendUnavailableError, match="pip install ninja"):
        native._build("cpu")
    if torch.version.cuda is None:
        with pytest.raises(BackendUnavailableError, match="no CUDA support"):
            native._build("cuda")
        assert not BACKENDS.get("cuda").available()


def _find_nvcc():
    found = shutil.which("nvcc")
    if found:
        return found
    for p in ("/usr/local/cuda/bin/nvcc", "/usr/local/bin/nvcc"):
        if Path(p).is_file():
            return p
    return None


def test_cuda_sources_compile(tmp_path):
    """nvcc accepts the kernels (the emulated backend runs the same source on the host)."""
    nvcc = _find_nvcc()
    if nvcc is None:
        pytest.skip("nvcc is not installed")
    cmd = [nvcc, "-c", "-O3", "-std=c++17", "-arch=sm_90", "-DSPLATZOO_WITH_CUDA", "-Xcompiler", "-Wall",
           str(CSRC / "rasterize_cuda.cu"), "-o", str(tmp_path / "rasterize_cuda.o")]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-4000:]
    assert (tmp_path / "rasterize_cuda.o").stat().st_size > 0


def test_cuda_emulation_primitives(tmp_path):
    """The host emulation itself: barriers, warp collectives, atomics, early exits, and deadlock detection."""
    cxx = shutil.which("g++") or shutil.which("c++")
    if cxx is None:
        pytest.fail("no C++ compiler: install g++")
    src = Path(__file__).parent / "csrc" / "test_cuda_emulation.cpp"
    exe = tmp_path / "test_cuda_emulation"
    r = subprocess.run([cxx, "-O2", "-std=c++17", f"-I{CSRC}", str(src), "-o", str(exe)], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-4000:]
    r = subprocess.run([str(exe)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]


def test_an_installed_package_carries_the_native_sources(tmp_path):
    """A regular (non-editable) install must ship splatzoo/csrc, or the native backend is gone for pip users."""
    src = tmp_path / "src"
    shutil.copytree(CSRC.parents[1], src, ignore=shutil.ignore_patterns(".*", "runs", "build", "*.egg-info",
                                                                      "__pycache__", ".pytest_cache", "tests"))
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--no-warn-script-location", "--target", str(target), str(src)], check=True)
    shipped = sorted(p.name for p in (target / "splatzoo" / "csrc").iterdir())
    assert shipped == sorted(p.name for p in CSRC.iterdir() if p.is_file())


def test_gpu_backend_fixture_skips_only_for_want_of_a_gpu():
    if torch.cuda.is_available():
        assert backend_for_test("cuda").name == "cuda"
    else:
        with pytest.raises(pytest.skip.Exception):
            backend_for_test("cuda")


def test_builds_are_announced_and_a_cached_library_is_imported_never_rebuilt(monkeypatch, tmp_path, capsys):
    """Every build says so on stderr (a damaged cached library says why it is built again); a library already built
    is imported as it is, without ninja, which could rebuild it from file times and relink it under a process that
    has it loaded."""
    from torch.utils import cpp_extension

    monkeypatch.setenv("SPLATZOO_EXTENSIONS_DIR", str(tmp_path))
    built, sentinel = [], object()

    def fake_load(name, build_directory, **kw):
        Path(build_directory, f"{name}.so").write_bytes(b"")  # as a build cut short leaves it
        built.append(name)
        return object()

    def fake_import(name, path):
        if not path.read_bytes():
            raise ImportError(f"{path}: file too short")
        return sentinel

    monkeypatch.setattr(cpp_extension, "load", fake_load)
    monkeypatch.setattr(native, "_import_built", fake_import)
    native._build("cpu")
    err = capsys.readouterr().err
    assert "building the C++ rasterizer" in err and "built the C++ rasterizer in" in err
    native._build("cpu")  # the empty library does not load: built again, and the reason said
    err = capsys.readouterr().err
    assert "could not be loaded (ImportError" in err and "building the C++ rasterizer" in err and len(built) == 2
    Path(tmp_path, built[0], f"{built[0]}.so").write_bytes(b"a finished build")
    assert native._build("cpu") is sentinel  # cached: imported without a word and without ninja
    assert capsys.readouterr().err == "" and len(built) == 2


def test_the_build_cache_is_keyed_by_the_compiler_and_ninja(monkeypatch):
    """Two ninjas (a venv's and the system's) record different command hashes and rebuilt each other's library,
    silently, each time the other ran: each gets a build of its own."""
    a = native._build_name("cpu")
    monkeypatch.setattr(native, "_compiler_id", lambda kind: "c++ (another compiler) 99.1")
    assert native._build_name("cpu") != a
    monkeypatch.undo()
    assert native._build_name("cpu") == a
    assert "ninja" in native._ninja_id() and any(ch.isdigit() for ch in native._ninja_id())
    monkeypatch.setattr(native, "_ninja_id", lambda: "/usr/bin/ninja 1.11.1")
    b = native._build_name("cpu")
    monkeypatch.setattr(native, "_ninja_id", lambda: "/venv/bin/ninja 1.13.0.git.kitware.jobserver-pipe-1")
    assert native._build_name("cpu") not in (a, b)


def _too_large_camera() -> Camera:
    return Camera.look_at((0.0, 0.0, -1e6), (0.0, 0.0, 0.0), width=1 << 20, height=1 << 20, dtype=torch.float32)


def test_a_camera_too_large_to_index_is_refused_not_a_crash(any_backend):
    """A 2^20 x 2^20 camera (a hostile viewer client's, say) overflowed the 32-bit tile count in the binning and
    crashed the process; every backend refuses it by name, before allocating."""
    s, _ = random_scene(50, 16, 16, 2, seed=3)
    with pytest.raises(ShapeError, match="pixels per image"):
        rasterize(s, _too_large_camera(), backend=any_backend)


def test_the_bindings_refuse_a_camera_too_large_to_index(native_backend):
    """The bindings check the image size too, for callers below rasterize()."""
    s, _ = random_scene(50, 16, 16, 2, seed=3)
    C, dev, emulated, camera = _bindings(native_backend, _too_large_camera())
    fields = [t.to(dev) for t in s.tensors().values()]
    with pytest.raises(RuntimeError, match="2\\^31 - 1 pixels"):
        C.render(native.settings_struct(C, SETTINGS), fields, None, *camera, 1 << 20, 1 << 20, emulated)
