"""beta-gabor: per-surfel wave counts (0 to 8) and per-surfel Beta falloffs on one surfel, held to the reference in
float64, by finite differences, and at the extremes of both choices; in both colour forms of its waves (residual: one
shared colour difference a surfel; per-wave: an RGB amplitude a wave)."""
import math

import pytest
import torch

import splatzoo
from scenes import random_scene
from splatzoo import Surfels, rasterize
from splatzoo.types import MAX_FALLOFF

FIELDS = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion")


COLOR_PARAMS = ["residual", "per-wave", "per-wave, free directions"]


def beta_gabor(n=48, seed=0, color_param="residual"):
    """A beta-gabor model whose surfels hold every wave count from 0 to 8 and falloffs from the Gaussian's
    neighbourhood to the tightest kernel."""
    _, cam = random_scene(1, 0, 40, 32, seed=seed, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    free = color_param.endswith(", free directions")
    model = splatzoo.create_model("beta-gabor", d / d.norm(dim=1, keepdim=True), torch.rand(n, 3, generator=g),
                                  color_param=color_param.split(",")[0], free_directions=free,
                                  fit_waves=0.3 if free else 0.0)
    model = model.double()
    with torch.no_grad():
        model.logit_opacity.fill_(0.5)
        model.log_scales.fill_(math.log(0.15))
        if model.per_wave:
            model.wave_weights.uniform_(-0.06, 0.06, generator=g)
        else:
            model.color_diff.uniform_(-0.4, 0.4, generator=g)
        model.wave_freqs.uniform_(0.05, 0.6, generator=g)
        if free:  # directions off the fan
            model.wave_freqs[..., 1].uniform_(-0.4, 0.4, generator=g)
        model.falloff_logit.copy_(torch.linspace(-12, 12, n, dtype=torch.float64))  # s from ~6e-6 to MAX_FALLOFF
        remove = torch.arange(8)[None] >= (torch.arange(n) % 9)[:, None]           # 0..8 waves a surfel
        model.prune_waves(0.0, remove=remove)
    assert set(model.wave_counts.tolist()) == set(range(9))
    return model, cam


@pytest.mark.parametrize("color_param", COLOR_PARAMS)
def test_float64_native_equals_the_reference_with_gradients(color_param):
    model, cam = beta_gabor(color_param=color_param)
    with torch.no_grad():
        s = model.surfels(cam)
    assert s.falloff is not None and s.wave_counts is not None
    assert float(s.falloff.min()) < 1e-4 and float(s.falloff.max()) > 0.99 * MAX_FALLOFF
    outs, grads = {}, {}
    for backend in ("reference", "cpu"):
        model.zero_grad()
        out = model.render(cam, backend=backend)
        (out.rgb.sum() + 0.5 * out.alpha.sum() + 0.1 * out.depth.sum()).backward()
        outs[backend] = out
        grads[backend] = {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}
    for k in FIELDS:
        torch.testing.assert_close(getattr(outs["cpu"], k).detach(), getattr(outs["reference"], k).detach(),
                                   rtol=0, atol=1e-9, msg=k)
    assert outs["cpu"].alpha.max() > 0.3, "the scene draws little"
    assert set(grads["cpu"]) == set(grads["reference"]) >= {"falloff_logit", "wave_weights", "wave_freqs",
                                                             "wave_phases", "color_base"}
    assert ("color_diff" in grads["cpu"]) == (color_param == "residual")
    for k, g in grads["reference"].items():
        torch.testing.assert_close(grads["cpu"][k], g, rtol=1e-6, atol=1e-9, msg=k)
    # a surfel's unused wave slots take no gradient
    unused = torch.arange(model.wave_weights.shape[1])[None] >= model.wave_counts[:, None]
    assert grads["cpu"]["wave_weights"][unused].abs().max() == 0


def test_gradcheck_of_mixed_wave_counts_and_falloffs():
    """Finite differences of the native render w.r.t. the falloffs and the waves of surfels with 0 to 8 waves."""
    model, cam = beta_gabor(n=9, seed=4)
    with torch.no_grad():
        s = model.surfels(cam)
        s.falloff = torch.linspace(0.02, 0.9, 9, dtype=torch.float64)  # inside (0, 1]: differences stay valid
    names = ("falloff", "wave_amplitudes", "wave_phases", "wave_vectors", "opacities")
    fixed = {k: v for k, v in s.tensors().items() if k not in names}

    def f(*xs):
        out = rasterize(Surfels(**fixed, **dict(zip(names, xs)), wave_counts=s.wave_counts), cam, backend="cpu")
        return out.rgb, out.alpha, out.depth

    inputs = [getattr(s, k).detach().clone().requires_grad_(True) for k in names]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, nondet_tol=1e-12)


@pytest.mark.parametrize("color_param", COLOR_PARAMS[1:])
def test_gradcheck_of_per_wave_colours_through_the_model(color_param):
    """Finite differences of the native render w.r.t. the model's own per-wave parameters: each wave's RGB amplitude,
    frequency (free directions: its 2D vector) and phase, and the base colour, on surfels with 0 to 8 waves."""
    model, cam = beta_gabor(n=9, seed=4, color_param=color_param)
    names = ("wave_weights", "wave_freqs", "wave_phases", "color_base")
    assert model.wave_weights.shape[-1] == 3 and model.wave_freqs.dim() == (3 if model.free_directions else 2)

    class Rendered(torch.nn.Module):  # the model's render as a module call, for functional_call
        def __init__(self):
            super().__init__()
            self.model = model

        def forward(self):
            out = self.model.render(cam, backend="cpu")
            return out.rgb, out.alpha

    module = Rendered()

    def f(*xs):
        return torch.func.functional_call(module, {f"model.{k}": x for k, x in zip(names, xs)}, ())

    inputs = [getattr(model, k).detach().clone().requires_grad_(True) for k in names]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, nondet_tol=1e-12)


@pytest.mark.parametrize("color_param", COLOR_PARAMS)
@pytest.mark.parametrize("extreme", ["no waves", "all waves", "gaussian", "tightest"])
def test_extremes_render_finite_and_as_their_limits(extreme, color_param):
    """No waves is the beta surfel; the falloff's limit s -> 0 is the gabor surfel; the tightest kernel draws
    nothing beyond its support."""
    model, cam = beta_gabor(n=27, seed=2, color_param=color_param)
    with torch.no_grad():
        if extreme == "no waves":
            model.prune_waves(math.inf)
        elif extreme == "gaussian":
            model.falloff_logit.fill_(-40.0)
        elif extreme == "tightest":
            model.falloff_logit.fill_(40.0)
    out = model.render(cam, backend="cpu")
    for k in FIELDS:
        assert torch.isfinite(getattr(out, k)).all(), k
    s = model.surfels(cam)
    if extreme == "no waves":
        beta = splatzoo.create_model("beta", model.means.detach().float(), torch.rand(27, 3)).double()
        with torch.no_grad():
            for k in ("means", "log_scales", "quats", "logit_opacity", "falloff_logit"):
                getattr(beta, k).copy_(getattr(model, k))
            beta.sh_dc.copy_(((model.color_base - 0.5) / 0.28209479177387814)[:, None])
        torch.testing.assert_close(out.rgb, beta.render(cam, backend="cpu").rgb, rtol=0, atol=1e-9)
    if extreme == "gaussian":
        plain = Surfels(**{k: v for k, v in s.tensors().items() if k != "falloff"}, wave_counts=s.wave_counts)
        torch.testing.assert_close(out.rgb, rasterize(plain, cam, backend="cpu").rgb, rtol=0, atol=1e-9)
    if extreme == "tightest":
        assert float(s.falloff.detach().min()) == pytest.approx(MAX_FALLOFF)


def test_a_file_from_before_free_directions_loads_with_the_fan(tmp_path):
    """A beta-gabor file whose stored config has no free_directions (written before the option existed, when every
    wave had one frequency along the fan) loads as the fan, not as today's default."""
    model = splatzoo.create_model("beta-gabor", torch.rand(20, 3), torch.rand(20, 3), free_directions=False,
                                  fit_waves=0)
    path = tmp_path / "old.pt"
    splatzoo.save_model(model, path)
    ckpt = torch.load(path, weights_only=True)
    del ckpt["config"]["free_directions"]
    torch.save(ckpt, path)
    back = splatzoo.load_model(path)
    assert back.config.free_directions is False and back.wave_freqs.shape == model.wave_freqs.shape
    assert splatzoo.create_model("beta-gabor", torch.rand(2, 3), torch.rand(2, 3)).config.free_directions is True


def test_waves_learn_at_ten_times_gabor_s_rate_and_old_files_keep_theirs(tmp_path):
    """beta-gabor's wave vectors and phases train at wave_lr = 1e-2 (gabor and gabor-adaptive keep 1e-3, and the
    amplitudes theirs); a file written before the option existed was trained at 1e-3 and loads so; a rate that is not
    one is refused by name."""
    from splatzoo.models.gabor import WAVE_LR

    def rates(model):
        return {g["name"]: g["lr"] for g in model.optim_groups(1.0) if g["name"].startswith("wave_")}

    pts, cols = torch.rand(20, 3), torch.rand(20, 3)
    model = splatzoo.create_model("beta-gabor", pts, cols)
    assert model.config.wave_lr == 1e-2 == 10 * WAVE_LR
    assert rates(model) == {"wave_weights": 1e-3, "wave_freqs": 1e-2, "wave_phases": 1e-2}
    for name in ("gabor", "gabor-adaptive"):
        assert set(rates(splatzoo.create_model(name, pts, cols)).values()) == {WAVE_LR} == {1e-3}
    assert rates(splatzoo.create_model("beta-gabor", pts, cols, wave_lr=3e-3))["wave_phases"] == 3e-3
    path = tmp_path / "old.pt"
    splatzoo.save_model(model, path)
    ckpt = torch.load(path, weights_only=True)
    del ckpt["config"]["wave_lr"]
    torch.save(ckpt, path)
    assert set(rates(splatzoo.load_model(path)).values()) == {1e-3}
    for bad, message in ((0, "wave_lr must be a learning rate in (0, 1], got 0"), (2.0, "in (0, 1], got 2.0"),
                         (-1e-3, "in (0, 1], got -0.001"), (float("nan"), "wave_lr expects a finite float, got nan")):
        with pytest.raises((ValueError, TypeError)) as e:   # ShapeError, or ModelOptionError for a non-number
            splatzoo.create_model("beta-gabor", pts, cols, wave_lr=bad)
        assert message in str(e.value), str(e.value)
