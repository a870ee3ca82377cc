"""Anti-aliased rendering (RasterSettings.pixel_filter > 0): the pixel footprint filters every surfel and wave.

Known answers (a wave far above the pixel Nyquist limit renders at the mean colour; magnified, the stripes come
back at the predicted period; a sub-pixel surfel keeps its coverage), consistency across scales, culling boxes that
never cut, and every native backend against the reference, outputs and gradients.
"""
from __future__ import annotations

import json
import math

import pytest
import torch

from splatzoo.rasterizers import common, rasterize
from splatzoo.rasterizers.common import ANTIALIASED, SETTINGS, RasterSettings
from splatzoo.rasterizers.reference import rasterize_reference
from splatzoo.testing import dense_overlap, sphere_and_wall
from splatzoo.types import Camera, Surfels
from test_native import EMULATED, FIELDS, _check_grads, _cotangent, _render_and_grads

D = torch.float64


def one_surfel(sigma_px: float, period_px: float, *, width: int = 64, amplitude: float = 0.4, opacity: float = 0.9,
               tilt_deg: float = 0.0):
    """One surfel at the image centre, sigma_px pixels across, with one wave of period_px pixels along u."""
    cam = Camera.look_at((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), fov_deg=60.0, width=width, height=width)
    f = float(cam.K[0, 0])
    scale = sigma_px * 4.0 / f
    k = 2 * math.pi * sigma_px / period_px  # radians per sigma: the period in pixels, face on
    t = math.radians(tilt_deg) / 2
    s = Surfels(torch.zeros(1, 3, dtype=D), torch.tensor([[math.cos(t), math.sin(t), 0.0, 0.0]], dtype=D),
                torch.full((1, 2), scale, dtype=D), torch.tensor([opacity], dtype=D),
                torch.tensor([[0.5, 0.4, 0.3]], dtype=D), torch.tensor([[[k, 0.0]]], dtype=D),
                torch.zeros(1, 1, dtype=D), torch.full((1, 1, 3), amplitude, dtype=D))
    return s, cam


def test_a_wave_above_nyquist_renders_at_the_mean_colour(any_backend):
    backend = any_backend
    s, cam = one_surfel(sigma_px=20.0, period_px=0.3)
    centre = (slice(24, 40), slice(24, 40))
    for settings, expect_flat in ((ANTIALIASED, True), (SETTINGS, False)):
        out = render(s, cam, backend, settings)
        colour = out.rgb[centre] / out.alpha[centre][..., None]
        spread = (colour - torch.tensor([0.5, 0.4, 0.3], dtype=D)).abs().max().item()
        if expect_flat:
            assert spread < 1e-6, f"anti-aliased: the colour strays {spread:.2e} from the mean"
        else:
            assert spread > 0.2, "unfiltered, the point-sampled wave should alias"


def test_the_same_wave_magnified_shows_stripes_at_the_predicted_period(any_backend):
    for period in (8.0, 5.0):
        s, cam = one_surfel(sigma_px=20.0, period_px=period)
        out = render(s, cam, any_backend, ANTIALIASED)
        row = (out.rgb[32, 16:48, 0] / out.alpha[32, 16:48])
        spectrum = torch.fft.rfft(row - row.mean()).abs()
        peak = int(spectrum[1:].argmax()) + 1
        assert abs(32 / peak - period) < 0.6, f"stripes of period {32 / peak:.2f} px, expected {period}"
        # the footprint's attenuation of this wave: exp(-pixel_filter (2 pi / period)^2 / 2) (face on, so J = I/sigma)
        gain = math.exp(-0.5 * common.PIXEL_FILTER * (2 * math.pi / period) ** 2)
        x = torch.arange(16, 48, dtype=D) + 0.5 - 32.0  # pixel centres, relative to the surfel's centre
        basis = torch.stack([torch.cos(2 * math.pi * x / period), torch.sin(2 * math.pi * x / period),
                             torch.ones_like(x)], 1)
        fit = torch.linalg.lstsq(basis, row[:, None]).solution[:, 0]
        measured = float(fit[:2].norm())
        assert abs(measured - 0.4 * gain) < 0.02 * 0.4 * gain, (measured, 0.4 * gain)


def test_a_sub_pixel_surfel_keeps_its_coverage_and_mean_colour(any_backend):
    """Summed alpha of a surfel a fifth of a pixel across is its area times opacity, 2 pi sigma^2 o, less the tail
    below alpha_min (a fraction alpha_min / peak of a 2D Gaussian's mass, peak = o sigma^2 / (sigma^2 + f)), with a
    footprint f wide enough to be sampled at pixel centres. The screen filter instead shows a disc of about pi o."""
    backend = any_backend
    sigma, o, f = 0.2, 0.9, 0.5
    s, cam = one_surfel(sigma_px=sigma, period_px=0.05, width=16, opacity=o)
    out = render(s, cam, backend, RasterSettings(pixel_filter=f))
    peak = o * sigma ** 2 / (sigma ** 2 + f)
    area = o * 2 * math.pi * sigma ** 2 * (1 - SETTINGS.alpha_min / peak)
    assert abs(out.alpha.sum().item() - area) < 0.05 * area  # pixel-centre sampling of the cut-off tail
    seen = out.alpha > 0
    colour = out.rgb[seen] / out.alpha[seen][:, None]
    assert (colour - torch.tensor([0.5, 0.4, 0.3], dtype=D)).abs().max() < 1e-3
    unfiltered = render(s, cam, backend).alpha.sum().item()
    assert unfiltered > 8 * area


def render(s: Surfels, cam: Camera, backend, settings=SETTINGS):
    """Render on the backend's device; the outputs come back on the CPU."""
    out = rasterize(s.to(backend.torch_device()), cam, backend=backend, settings=settings)
    return type(out)(**{k: getattr(out, k).cpu() for k in FIELDS})


def _area_average(img: torch.Tensor, f: int) -> torch.Tensor:
    return torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], f)[0].permute(1, 2, 0)


@pytest.mark.parametrize("kernel", ["gaussian", "beta"])
def test_a_small_render_is_the_area_average_of_a_big_one(kernel):
    """Textured surfels with waves of up to ~1 cycle per pixel at 128 px: the 32 px anti-aliased render is close
    to the 4x4 average of the 128 px render; the unfiltered one is not. For every falloff (the Beta kernel is
    prefiltered as the footprint's gain times f at its q: an approximation, checked here)."""
    s, cam = sphere_and_wall(3000, 128, 128, K=4, seed=3, dtype=D, px_sigma=(2.0, 6.0))
    s.wave_vectors.mul_(4.0)
    s.opacities.fill_(0.95)
    if kernel == "beta":
        s.falloff = torch.rand(s.num, generator=torch.Generator().manual_seed(4), dtype=D)
    psnr = {}
    for name, st in (("aa", ANTIALIASED), ("plain", SETTINGS)):
        big = rasterize(s, cam, backend="cpu", settings=st).rgb
        small = rasterize(s, cam.scaled(0.25), backend="cpu", settings=st).rgb
        mse = ((small - _area_average(big, 4)) ** 2).mean().item()
        psnr[name] = -10 * math.log10(mse)
    assert psnr["aa"] > 30 and psnr["aa"] > psnr["plain"] + 5, psnr


@pytest.mark.parametrize("seed", [0, 13, 36])
def test_boxes_bound_a_filtered_surfel(monkeypatch, seed):
    """The culling boxes of the footprint-widened support are exact for surfels seen face on and trim at most a
    faint fringe of nearly edge-on ones: the reference, split into rectangles small enough that boxes decide what it
    shades where, against the same with boxes 300 pixels wider (where the reference shades every pixel)."""
    exact = common.screen_boxes

    def wide_boxes(*args, **kw):
        boxes, visible = exact(*args, **kw)
        return boxes + torch.tensor([-300.0, -300.0, 300.0, 300.0], dtype=boxes.dtype), visible

    cases = [(sphere_and_wall, {"px_sigma": (0.05, 0.5)}, 5e-3), (sphere_and_wall, {"px_sigma": (1.0, 6.0)}, 5e-3),
             (sphere_and_wall, {"px_sigma": (10.0, 60.0)}, 5e-3),
             (dense_overlap, {"px_sigma": (0.3, 8.0), "max_tilt_deg": 89.0}, 5e-3),
             (dense_overlap, {"px_sigma": (0.1, 20.0), "max_tilt_deg": 0.0}, 1e-12)]  # face on: exact
    for make, kw, tol in cases:
        s, cam = make(100, 32, 24, 1, seed=seed, dtype=D, **kw)
        s.opacities.fill_(1.0)
        tight = rasterize_reference(s, cam, settings=ANTIALIASED, pair_budget=64)
        with monkeypatch.context() as m:  # every box covers the image: however it splits, each pixel sees them all
            m.setattr(common, "screen_boxes", wide_boxes)
            wide = rasterize_reference(s, cam, settings=ANTIALIASED)
        assert (tight.alpha > 0).any()
        for k in ("rgb", "alpha"):
            err = (getattr(tight, k) - getattr(wide, k)).abs().max().item()
            assert err <= tol, (make.__name__, kw, k, err)


def test_the_header_uses_the_python_footprint_constants():
    """The culling constants are written twice (common.py and csrc/surfel_math.h, which has no Python): equal."""
    import re
    from pathlib import Path

    header = (Path(common.__file__).parent.parent / "csrc" / "surfel_math.h").read_text()
    for name, value in (("FOOTPRINT_PAD", common.FOOTPRINT_PAD), ("FOOTPRINT_PAD_PX", common.FOOTPRINT_PAD_PX),
                        ("LINEAR_LIMIT", common.LINEAR_LIMIT)):
        found = re.search(rf"constexpr double {name} = ([0-9.e+-]+);", header)
        assert found and float(found.group(1)) == value, name


@pytest.mark.parametrize("K", [0, 3])
def test_native_backends_match_the_reference_exactly(native_backend, K):
    s, cam = sphere_and_wall(400, 48, 40, K, seed=5 + K, dtype=D, px_sigma=(0.2, 3.0))
    cot = _cotangent(40, 48, D)
    ref, g_ref = _render_and_grads("reference", s, cam, cot, [0.1, 0.1, 0.1], settings=ANTIALIASED)
    nat, g_nat = _render_and_grads(native_backend, s, cam, cot, [0.1, 0.1, 0.1], settings=ANTIALIASED)
    for k in FIELDS:
        torch.testing.assert_close(getattr(nat, k), getattr(ref, k), rtol=0, atol=1e-9, msg=k)
    _check_grads(g_ref, g_nat, rel_tol=1e-7, cos_tol=1 - 1e-12)


def test_native_backends_match_the_reference_float32(native_backend):
    from test_native import _assert_outputs_close

    n, W, H = (150, 48, 40) if native_backend.name == EMULATED else (1200, 96, 80)
    s, cam = sphere_and_wall(n, W, H, 4, seed=19, px_sigma=(0.3, 4.0))
    cot = _cotangent(H, W, torch.float32, seed=2)
    ref, g_ref = _render_and_grads("reference", s, cam, cot, [0.2, 0.4, 0.6], settings=ANTIALIASED)
    nat, g_nat = _render_and_grads(native_backend, s, cam, cot, [0.2, 0.4, 0.6], settings=ANTIALIASED)
    _assert_outputs_close(ref, nat, torch.float32)
    _check_grads(g_ref, g_nat)


@pytest.mark.parametrize("kernel", ["gaussian", "beta"])
def test_gradcheck_including_the_means(native_backend, kernel):
    """Filtered, nothing switches between the hit and the screen filter, so even the means pass finite
    differences (test_native's gradcheck leaves them out). The Gaussian falloff (exponent 0, the edge of its
    range) is held; the Beta kernel's exponents are checked too."""
    s, cam = sphere_and_wall(6, 12, 10, 2, seed=3, dtype=D, px_sigma=(0.5, 3.0))
    s = s.to(native_backend.torch_device())
    s.opacities.fill_(0.6)
    s.means[:, 2] += 0.01 * torch.arange(6, dtype=D, device=s.means.device)  # no two at one depth: a tie's order flips under a step
    if kernel == "beta":
        s.falloff = torch.tensor([0.02, 0.3, 1e-3, 0.9, 0.1, 0.5], dtype=D, device=s.means.device)
    fixed = {"falloff": s.falloff} if kernel == "gaussian" else {}
    names = [k for k in s.tensors() if k not in fixed]
    inputs = [getattr(s, k).detach().clone().requires_grad_(True) for k in names]

    def f(*x):
        out = rasterize(Surfels(**dict(zip(names, x)), **fixed), cam, backend=native_backend, settings=ANTIALIASED)
        return tuple(getattr(out, k) * w for k, w in zip(FIELDS, (1.0, 0.7, 0.3, 0.2, 0.5, 2.0)))

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, nondet_tol=1e-12)


# ---- training with it, evaluating at other scales -----------------------------------------------------------------

@pytest.fixture(scope="module")
def small_data(tmp_path_factory):
    from splatzoo.data.synthetic import make_synthetic_scene

    return make_synthetic_scene("sweater", tmp_path_factory.mktemp("data") / "sweater", views=8, width=48, height=48)


def test_an_antialiased_run_keeps_the_filter_and_eval_scores_smaller_renders(small_data, tmp_path):
    """`train --antialias`: recorded, kept in the model file, and used by every render of the model; `eval --scale`
    writes per-scale metrics against area-averaged images and the model's own full-size render."""
    from typer.testing import CliRunner

    from splatzoo.cli import app
    from splatzoo.zoo import load_model

    runner = CliRunner()
    run = tmp_path / "run"
    r = runner.invoke(app, ["train", str(small_data), "--model", "gabor", "--iterations", "10", "--num-primitives",
                            "120", "--backend", "cpu", "--antialias", "--out", str(run)])
    assert r.exit_code == 0, r.output
    assert json.loads((run / "config.json").read_text())["train"]["antialias"] is True
    model = load_model(run / "model.pt")
    assert model.antialias and model.raster_settings == ANTIALIASED
    cam = Camera.look_at((0.0, -1.0, -3.0), (0.0, 0.0, 0.0), width=40, height=40).to(dtype=torch.float32)
    bg = torch.zeros(3)
    filtered = rasterize(model.surfels(cam), cam, backend="cpu", background=bg, settings=ANTIALIASED).rgb
    plain = rasterize(model.surfels(cam), cam, backend="cpu", background=bg).rgb
    with torch.no_grad():
        shown = model.render(cam, background=bg, backend="cpu").image()
    assert torch.equal(shown, filtered.detach().clamp(0, 1)) and not torch.equal(shown, plain.detach().clamp(0, 1))

    r = runner.invoke(app, ["eval", str(run), "--scale", "0.5,0.25", "--backend", "cpu"])
    assert r.exit_code == 0, r.output
    assert "vs own full-size render" in r.output
    scales = json.loads((run / "metrics.json").read_text())["scales"]
    assert list(scales) == ["0.5", "0.25"]
    assert scales["0.5"]["resolution"] == [24, 24] and scales["0.25"]["resolution"] == [12, 12]
    for entry in scales.values():
        assert math.isfinite(entry["psnr"]) and entry["consistency_psnr"] > 25, entry

    for bad in ("2", "0", "x", ""):
        r = runner.invoke(app, ["eval", str(run), "--scale", bad])
        assert r.exit_code != 0 and "--scale" in r.output + str(r.exception), (bad, r.output)


def test_a_crafted_antialias_entry_is_refused(tmp_path):
    from splatzoo.errors import SplatzooError
    from splatzoo.zoo import create_model, model_from_checkpoint

    model = create_model("2dgs", torch.rand(20, 3), torch.rand(20, 3))
    ck = model.checkpoint()
    assert "antialias" not in ck and not model_from_checkpoint(ck).antialias  # older files load unchanged
    model.antialias = True
    assert model_from_checkpoint(model.checkpoint()).antialias
    with pytest.raises(SplatzooError, match="antialias"):
        model_from_checkpoint({**ck, "antialias": "yes"})


def test_ply_export_keeps_the_filter(tmp_path):
    from splatzoo.export import load_ply, save_ply
    from splatzoo.zoo import create_model

    model = create_model("gabor", torch.rand(20, 3), torch.rand(20, 3))
    assert not load_ply(save_ply(model, tmp_path / "plain.ply")).antialias
    model.antialias = True
    back = load_ply(save_ply(model, tmp_path / "aa.ply"))
    assert back.antialias and back.raster_settings == ANTIALIASED


def test_wave_blur_of_a_nearly_edge_on_surfel_is_finite_in_float():
    """A surfel seen nearly edge on has a huge, nearly singular centre footprint S (here ~1e8): det(I + S) cancels
    to 0 or below in float32, and the blur came out infinite (a training run on the reference backend hit it). It
    is computed in double, as the native backends do."""
    from splatzoo.rasterizers.reference import waves_blur

    T = torch.tensor([[1.1553786, -6.0863771, 93.766815], [0.78580368, -2.3110452, 25.974388],
                      [-0.062161319, -0.055025149, 2.8617098]])[None]
    centre = torch.tensor([[32.76601, 9.0765276]])
    blur = torch.stack(waves_blur(T, centre, ANTIALIASED))
    exact = torch.stack(waves_blur(T.double(), centre.double(), ANTIALIASED))
    assert blur.dtype == torch.float32 and torch.isfinite(blur).all()
    assert torch.allclose(blur.double(), exact, atol=1e-6)
    assert 0 <= blur[0] <= 1 and 0 <= blur[2] <= 1  # I - P with P = (I + S)^-1 positive definite
