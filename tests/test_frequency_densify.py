"""--strategy frequency: band maps put a sinusoid in its band, the back-projection is each surfel's blending-weighted
mean error, a step grows by at most 5% within the budget with the opacity correction and decay, and training with it
grows the count, stays finite and resumes exactly; "auto" takes the model's own strategy."""
import json
import math

import pytest
import torch

import splatzoo
from splatzoo import Camera
from splatzoo.data import load_scene
from splatzoo.errors import SplatzooError
from splatzoo.models.base import inverse_sigmoid
from splatzoo.runs import train
from splatzoo.training import TrainConfig, frequency
from splatzoo.training.frequency import (BANDS, back_project, band_energy, band_magnitudes, densify_step,
                                         stacked_opacity, weight_surfels)
from splatzoo.training.trainer import Trainer, check_optimizer_state, resolve_strategy


def stripes(n: int, cycles_per_pixel: float) -> torch.Tensor:
    x = torch.arange(n, dtype=torch.float32)
    row = 0.5 + 0.3 * torch.cos(2 * math.pi * cycles_per_pixel * x)
    return row[None, :, None].expand(n, n, 3)  # grey: luma is the value itself


@pytest.mark.parametrize("band", [0, 1, 2])
def test_a_sinusoid_lands_in_its_band(band):
    lo, hi = BANDS[band]
    # radius = |f| / max |f|, max |f| = sqrt(2) / 2 cycles per pixel: the band's middle, on a 64-pixel period grid
    k = round((lo + hi) / 2 * math.sqrt(0.5) * 64)
    m = band_magnitudes(stripes(64, k / 64))
    assert m.shape == (3, 64, 64)
    means = m.mean((1, 2))
    wave = (stripes(64, k / 64)[..., 0] - 0.5).abs().mean()
    assert float(means[band]) == pytest.approx(float(wave), rel=1e-4)  # the band-pass is the wave itself
    assert float(torch.cat([means[:band], means[band + 1:]]).max()) < 1e-5
    # a size the FFT pads (47 -> 48): the band still holds nearly all of it
    means = band_magnitudes(stripes(47, k / 64)).mean((1, 2))
    assert float(means[band]) > 3 * float(torch.cat([means[:band], means[band + 1:]]).max())
    maps = band_energy(torch.stack([stripes(47, k / 64), torch.full((47, 47, 3), 0.5)]))
    assert maps.shape == (2, 3, 47, 47) and float(maps.min()) >= 0 and float(maps.max()) <= 1
    assert float(maps[0, band].max()) > 0.5 and float(maps[1].abs().max()) == 0  # a flat image has no detail


def tiny_model(name: str, n: int = 8):
    g = torch.Generator().manual_seed(1)
    m = splatzoo.create_model(name, torch.randn(n, 3, generator=g) * 0.3, torch.rand(n, 3, generator=g))
    with torch.no_grad():
        m.log_scales += 1.0
        m.logit_opacity += 2.0
        if name == "textured":  # an alpha that varies over the surfel must shape the weights
            m.texture_alpha_logit.copy_(torch.randn(m.texture_alpha_logit.shape, generator=g))
    return m


@pytest.mark.parametrize("name", ["2dgs", "gabor", "textured"])
def test_back_projection_is_the_blending_weighted_mean_error(name):
    m = tiny_model(name)
    cam = Camera.look_at((0, 0, -3), (0, 0, 0), width=20, height=16)
    errors = torch.rand(3, 16, 20, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        surfels = m.surfels(cam.to(dtype=torch.float32))
        # brute force: surfel j alone coloured 1 renders its blending weight w_j(p) in every pixel
        weights = torch.stack([m.render(cam, background=0.0, backend="reference",
                                        surfels=weight_surfels(surfels, torch.eye(m.num_primitives)[j, :, None]
                                                               .expand(-1, 3).contiguous())).rgb[..., 0]
                               for j in range(m.num_primitives)])
        # the weights are the model's own: they add up to its alpha
        alpha = m.render(cam, background=0.0, backend="reference").alpha
        assert torch.allclose(weights.sum(0), alpha, atol=1e-6)
    assert bool((weights.sum((1, 2)) > 0.1).all())
    want = torch.einsum("nhw,khw->nk", weights, errors) / weights.sum((1, 2))[:, None]
    for backend in ("reference", "cpu"):
        got = back_project(m, cam, errors, backend)
        assert torch.allclose(got, want, atol=2e-6), backend
    # a surfel behind the camera draws nothing: its error is 0
    with torch.no_grad():
        m.means[0] = torch.tensor([0.0, 0.0, -10.0])
    got = back_project(m, cam, errors[:1], "reference")
    assert got.shape == (m.num_primitives, 1) and float(got[0, 0]) == 0 and bool((got[1:] > 0).all())


def model_and_optimizer(n=100, scale=0.001):
    g = torch.Generator().manual_seed(0)
    m = splatzoo.create_model("2dgs", torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g))
    with torch.no_grad():
        m.log_scales.fill_(math.log(scale))
        m.logit_opacity.copy_(inverse_sigmoid(torch.linspace(0.2, 0.9, n)))
    opt = torch.optim.Adam(m.optim_groups(1.0), lr=0.0, eps=1e-15)
    for p in m.parameters():
        p.grad = torch.ones_like(p)
    opt.step()  # moments for every row
    return m, opt


def step_with_errors(m, opt, errors, monkeypatch, **kw):
    monkeypatch.setattr(frequency, "primitive_errors", lambda *a, **k: errors.clone())
    args = dict(scene_extent=1.0, budget=1000, generator=torch.Generator().manual_seed(0), min_opacity=0.0)
    return densify_step(m, opt, [], **{**args, **kw})


def test_a_step_clones_the_worst_within_5_percent_and_corrects_opacity(monkeypatch):
    m, opt = model_and_optimizer()
    before = torch.sigmoid(m.logit_opacity.detach()).clone()
    errors = torch.linspace(0, 0.05, 100)  # 80 reach 0.01; the 5 worst are the last 5
    out = step_with_errors(m, opt, errors, monkeypatch, opacity_decay=0.0)
    assert out == {"cloned": 5, "split": 0, "pruned": 0, "primitives": 105}
    o = torch.sigmoid(m.logit_opacity.detach())
    want = stacked_opacity(before[95:])
    assert torch.allclose(o[95:100], want, atol=1e-6) and torch.allclose(o[100:], want, atol=1e-6)
    assert torch.allclose((1 - o[100:]) ** 2, 1 - before[95:], atol=1e-6)  # the pair lets through what one did
    assert torch.allclose(o[:95], before[:95], atol=1e-6)
    assert torch.equal(m.means.detach()[100:], m.means.detach()[95:100])
    check_optimizer_state(opt, 1)
    state = opt.state[m.logit_opacity]
    assert state["exp_avg"].shape == (105,) and bool((state["exp_avg"][95:] == 0).all())
    assert bool((state["exp_avg"][:95] != 0).all())
    assert all(p is q for p, q in zip([g["params"][0] for g in opt.param_groups], m.parameters()))
    # the budget wins over the 5%
    out = step_with_errors(m, opt, torch.linspace(0, 0.05, 105), monkeypatch, budget=107, opacity_decay=0.0)
    assert out["primitives"] == 107 and out["cloned"] == 2
    out = step_with_errors(m, opt, torch.linspace(0, 0.05, 107), monkeypatch, budget=107)
    assert out["primitives"] == 107 and out["cloned"] == 0  # at the budget nothing happens, not even the decay


def test_a_step_splits_large_ones_decays_opacity_and_prunes(monkeypatch):
    m, opt = model_and_optimizer(scale=0.5)
    before = torch.sigmoid(m.logit_opacity.detach()).clone()
    parent_scales = torch.exp(m.log_scales.detach()[50])
    errors = torch.zeros(100)
    errors[[10, 50]] = 0.02  # two candidates, each split in two
    out = step_with_errors(m, opt, errors, monkeypatch, min_opacity=0.3)
    o = torch.sigmoid(m.logit_opacity.detach())
    survivors = (before - 0.001 >= 0.3) & (torch.arange(100) != 10) & (torch.arange(100) != 50)
    assert out["split"] == 2 and out["cloned"] == 0
    # children of opacity 1 - sqrt(1 - o) - 0.001 all survive the step that made them, even under min_opacity
    kept = stacked_opacity(before[[10, 50]]) - 0.001
    assert bool((kept < 0.3).any())  # one pair is below it
    assert out["primitives"] == int(survivors.sum()) + 2 * kept.numel()
    assert torch.allclose(o[:int(survivors.sum())], before[survivors] - 0.001, atol=1e-6)
    assert torch.allclose(o[int(survivors.sum()):], kept.repeat(2), atol=1e-6)
    assert torch.allclose(torch.exp(m.log_scales.detach()[-1]), parent_scales / 1.6)
    check_optimizer_state(opt, 1)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from splatzoo.data.synthetic import make_synthetic_scene

    return load_scene(make_synthetic_scene("sweater", tmp_path_factory.mktemp("data") / "sweater", views=6,
                                           width=32, height=32))


def test_training_with_frequency_grows_stays_finite_and_resumes_exactly(tiny_scene, tmp_path):
    cfg = TrainConfig(iterations=30, num_primitives=80, max_primitives=200, strategy="frequency", densify_from=0,
                      densify_interval=5, densify_views=3, log_every=5, backend="cpu", checkpoint_minutes=0)
    full = train(tiny_scene, "2dgs", {}, cfg, tmp_path / "full", progress=False, evaluate_at_end=False)
    log = [json.loads(x) for x in (tmp_path / "full" / "train_log.jsonl").read_text().splitlines()]
    counts = [r["num_primitives"] for r in log if "num_primitives" in r]
    assert counts[-1] > 80 and all(b <= min(200, math.floor(a * 1.05)) for a, b in zip([80] + counts, counts))
    assert all(math.isfinite(r["loss"]) for r in log if "loss" in r)
    assert all(bool(torch.isfinite(p).all()) for p in full.model.parameters())
    train(tiny_scene, "2dgs", {}, cfg, tmp_path / "part", progress=False, evaluate_at_end=False, stop_after=12)
    resumed = train(tiny_scene, "2dgs", {}, None, tmp_path / "part", resume=True, progress=False,
                    evaluate_at_end=False)
    a, b = full.model.state_dict(), resumed.model.state_dict()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_auto_takes_the_models_strategy(tiny_scene):
    from splatzoo.zoo import make_config

    assert TrainConfig().strategy == "auto"
    trainer = Trainer.start(tiny_scene, "2dgs", make_config("2dgs"), TrainConfig(iterations=10, num_primitives=20),
                            "cpu", torch.device("cpu"))
    assert trainer.strategy == "adc" and not trainer.frequency and not trainer.mcmc
    m = splatzoo.create_model("neural-gabor", torch.randn(4, 3), torch.rand(4, 3))
    assert resolve_strategy("auto", m) == "frequency" and resolve_strategy("mcmc", m) == "mcmc"
    m.densify_strategy = "gsplat"
    with pytest.raises(SplatzooError, match="gsplat"):
        resolve_strategy("auto", m)
    with pytest.raises(SplatzooError, match="densify_views"):
        TrainConfig(densify_views=0).validate()


def test_the_separable_box_mean_is_the_window_mean():
    import torch.nn.functional as F

    from splatzoo.training.frequency import _box

    x = torch.rand(2, 3, 37, 53, generator=torch.Generator().manual_seed(4))
    for k in (3, 17):
        want = F.avg_pool2d(x, k, stride=1, padding=k // 2, count_include_pad=False)
        assert torch.allclose(_box(x, k), want, atol=1e-6)
