"""Waves fitted to the photos (training/wave_fit.py, beta-gabor's fit_waves): the pursuit finds waves exactly on
its grid, the photos are sampled where a view sees the surfel, a fit recovers the stripes a rendered surfel shows,
hidden surfels keep their waves, plain photos give no waves, and a run fits once at its fraction."""
import json
import math

import pytest
import torch

import splatzoo
from splatzoo import Camera
from splatzoo.geometry import normals_to_quats
from splatzoo.training import wave_fit


def grid(size: int) -> torch.Tensor:
    return ((torch.arange(size, dtype=torch.float32) + 0.5) / size * 2 - 1) * wave_fit.RADIUS


def waves_on(u: torch.Tensor, vectors, phases, amplitudes) -> torch.Tensor:
    """[G,G,3] sum_k a_k cos(2 pi k_k . (u, v) + phi_k), u along columns and v along rows."""
    out = torch.zeros(len(u), len(u), 3)
    for k, phi, a in zip(vectors, phases, amplitudes):
        t = 2 * math.pi * (k[0] * u[None, :] + k[1] * u[:, None]) + phi
        out += torch.cos(t)[..., None] * torch.as_tensor(a)
    return out


def test_pursuit_finds_waves_on_its_grid_with_their_phases_and_colours():
    u = grid(32)
    vectors = [(1.5, 0.25), (-0.5, 2.0)]  # on the STEP grid, ky >= 0
    phases = [0.7, -2.1]
    amplitudes = [(0.3, -0.2, 0.1), (0.1, 0.12, -0.05)]
    colour = torch.tensor([0.4, 0.5, 0.6]) + waves_on(u, vectors, phases, amplitudes)
    v, phi, a, cover = wave_fit.pursue(colour[None], torch.ones(1, 32, 32, dtype=torch.bool), u, 3)
    assert float(cover) == pytest.approx(1.0)
    assert v[0, :2].tolist() == [list(vectors[0]), list(vectors[1])]  # the stronger wave first
    fitted = waves_on(u, v[0, :2], phi[0, :2], a[0, :2])
    assert (fitted - (colour - colour.mean((0, 1)))).abs().max() < 0.02
    assert a[0, 2].abs().max() < 0.01  # a third wave finds nothing left
    # where nothing is counted nothing is fitted and the cover says so
    counted = torch.zeros(1, 32, 32, dtype=torch.bool)
    counted[0, :, :4] = True
    *_, cover = wave_fit.pursue(colour[None], counted, u, 1)
    assert float(cover) < 0.05


def plane_model(n_side=3, size=0.25, seed=0):
    """beta-gabor surfels side by side on the plane z = 0 (centres 4 sigmas apart), facing -z, opaque, with two
    known waves each."""
    xs = torch.linspace(-1.0, 1.0, n_side)
    pts = torch.stack(torch.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)
    points = torch.cat([pts, torch.zeros(len(pts), 1)], 1)
    model = splatzoo.create_model("beta-gabor", points, torch.full((len(pts), 3), 0.5), n_waves=2)
    with torch.no_grad():
        model.quats.copy_(normals_to_quats(torch.tensor([[0.0, 0.0, -1.0]]).expand(len(pts), 3)))
        model.log_scales.fill_(math.log(size))
        model.logit_opacity.fill_(6.0)
        model.falloff_logit.fill_(-8.0)  # near the Gaussian
        model.wave_freqs.copy_(torch.tensor([[1.25, 0.5], [0.0, 0.75]]).expand(len(pts), 2, 2))
        model.wave_phases.copy_(torch.tensor([0.4, 2.0]).expand(len(pts), 2))
        model.wave_weights.copy_(torch.tensor([[0.25, -0.15, 0.05], [0.1, 0.1, -0.2]]).expand(len(pts), 2, 3))
    return model


def cameras(count=5, distance=4.0, size=48):
    out = []
    for i in range(count):
        angle = (i - (count - 1) / 2) * 0.25
        eye = [distance * math.sin(angle), 0.3 * math.cos(3 * angle), -distance * math.cos(angle)]
        out.append(Camera.look_at(eye, [0.0, 0.0, 0.0], width=size, height=size, fov_deg=45.0))
    return out


def photos_of(model, cams, background):
    with torch.no_grad():
        return [(cam, model.render(cam, background=background, backend="cpu").rgb) for cam in cams]


def render_error(model, views, background) -> float:
    with torch.no_grad():
        return sum(float(((model.render(c, background=background, backend="cpu").rgb - p) ** 2).mean())
                   for c, p in views) / len(views)


def test_a_fit_recovers_the_stripes_rendered_surfels_show():
    background = torch.full((3,), 0.5)
    truth = plane_model()
    views = photos_of(truth, cameras(), background)
    model = plane_model()
    with torch.no_grad():  # scrambled waves
        g = torch.Generator().manual_seed(1)
        model.wave_freqs.uniform_(0, 1, generator=g)
        model.wave_phases.uniform_(0, 6, generator=g)
        model.wave_weights.uniform_(-0.05, 0.05, generator=g)
    before = render_error(model, views, background)
    params = [model.wave_freqs, model.wave_phases, model.wave_weights]
    optimizer = torch.optim.Adam([{"params": [p]} for p in params], lr=1e-2)
    for p in params:
        p.grad = torch.ones_like(p)
    optimizer.step()  # moments to restart
    record = wave_fit.fit_waves(model, optimizer, views, background, "cpu")
    assert record == {"surfels_fitted": 9, "surfels": 9}
    after = render_error(model, views, background)
    assert after < 0.4 * before, (before, after)
    # every surfel finds both waves exactly (on the grid), with their phases (mod pi) and their colours' directions;
    # the amplitudes come out smaller: the photos show each stripe through the surfel's falloff, alpha < 1 off centre
    for i in range(9):
        for k, phase, colour in ((truth.wave_freqs[i, j], truth.wave_phases[i, j], truth.wave_weights[i, j])
                                 for j in range(2)):
            j = int((model.wave_freqs[i] - k).norm(dim=-1).argmin())
            assert torch.equal(model.wave_freqs[i, j], k), (i, model.wave_freqs[i])
            assert math.sin((model.wave_phases[i, j] - phase).item()) == pytest.approx(0, abs=0.05)
            cos = torch.nn.functional.cosine_similarity(model.wave_weights[i, j].detach(), colour.detach(), dim=0)
            assert abs(float(cos)) > 0.97, (i, j, float(cos))
    for p in params:
        assert optimizer.state[p]["exp_avg"][4].abs().max() == 0


def test_hidden_and_edge_on_surfels_keep_their_waves_and_plain_photos_give_none():
    background = torch.full((3,), 0.5)
    model = plane_model(n_side=1, size=1.0)
    hidden = plane_model(n_side=1, size=0.2)
    with torch.no_grad():
        hidden.means.add_(torch.tensor([0.0, 0.0, 0.5]))  # behind the front surfel in every view
    both = splatzoo.create_model("beta-gabor", torch.zeros(3, 3), torch.full((3, 3), 0.5), n_waves=2)
    with torch.no_grad():
        for name, p in both.named_parameters():
            p[:1].copy_(getattr(model, name))
            p[1:2].copy_(getattr(hidden, name))
            p[2:].copy_(getattr(hidden, name))
        both.means[2] = torch.tensor([5.0, 0.0, 0.0])  # off every photo
        both.quats[2] = normals_to_quats(torch.tensor([[1.0, 0.0, 0.0]]))[0]  # and edge-on
    plain = [(cam, torch.full((48, 48, 3), 0.5)) for cam in cameras()]
    old = {name: getattr(both, name).detach().clone() for name in ("wave_freqs", "wave_phases", "wave_weights")}
    assert wave_fit.fit_waves(both, None, plain, background, "cpu") == {"surfels_fitted": 1, "surfels": 3}
    assert both.wave_weights[0].abs().max() < 1e-4  # a plain photo: no wave worth a colour
    for name, value in old.items():
        assert torch.equal(getattr(both, name)[1:], value[1:]), name


def test_a_surfel_s_grid_resolves_half_a_pixel_up_to_the_largest():
    model = plane_model(n_side=2)
    with torch.no_grad():
        model.log_scales.copy_(torch.log(torch.tensor([1e-4, 0.08, 0.15, 10.0]))[:, None].expand(4, 2))
    sizes = wave_fit.grid_sizes(model.geometry(), cameras(1))
    focal = float(cameras(1)[0].K[0, 0])
    assert sizes.tolist() == [8, 16, 32, 64], (sizes, focal)
    with torch.no_grad():
        model.means[:, 2] = -10.0  # behind the camera: nothing to resolve
    assert wave_fit.grid_sizes(model.geometry(), cameras(1)).tolist() == [8] * 4


def test_start_waves_sets_only_a_surfel_s_own_waves_and_needs_free_directions():
    model = plane_model(n_side=2)
    model.prune_waves(0.0, remove=torch.tensor([[False, True], [False, False], [True, True], [False, False]]))
    assert model.wave_slots().tolist() == [1, 2, 0, 2]
    before = model.wave_freqs.detach().clone()
    rows = torch.tensor([0, 1, 2])
    model.start_waves(rows, torch.full((3, 2, 2), 3.0), torch.zeros(3, 2), torch.ones(3, 2, 3))
    assert model.wave_freqs[0, 0].tolist() == [3.0, 3.0] and torch.equal(model.wave_freqs[0, 1], before[0, 1])
    assert (model.wave_freqs[1] == 3.0).all() and torch.equal(model.wave_freqs[2:], before[2:])
    fan = splatzoo.create_model("gabor", torch.rand(2, 3), torch.rand(2, 3))
    with pytest.raises(splatzoo.SplatzooError, match="free directions"):
        fan.start_waves(torch.tensor([0]), torch.ones(1, 1, 2), torch.zeros(1, 1), torch.ones(1, 1, 3))


def test_fit_waves_is_beta_gabor_s_and_refused_where_it_cannot_apply(tmp_path):
    pts, cols = torch.rand(20, 3), torch.rand(20, 3)
    model = splatzoo.create_model("beta-gabor", pts, cols)
    assert model.config.fit_waves == 0.3 and model.wave_fit_step(1500) == 450
    for name in ("gabor", "gabor-adaptive", "2dgs", "beta"):
        assert splatzoo.create_model(name, pts, cols).wave_fit_step(1500) is None, name
    path = tmp_path / "old.pt"
    splatzoo.save_model(model, path)
    ckpt = torch.load(path, weights_only=True)
    del ckpt["config"]["fit_waves"]
    torch.save(ckpt, path)
    assert splatzoo.load_model(path).config.fit_waves == 0.0  # written before the option: trained without a fit
    for bad, message in ((1.0, "fit_waves is a fraction of the run in [0, 1)"), (-0.1, "got -0.1"),
                         (float("nan"), "fit_waves expects a finite float, got nan")):
        with pytest.raises((ValueError, TypeError)) as e:
            splatzoo.create_model("beta-gabor", pts, cols, fit_waves=bad)
        assert message in str(e.value), str(e.value)
    with pytest.raises(ValueError, match="needs free directions"):
        splatzoo.create_model("beta-gabor", pts, cols, free_directions=False)
    with pytest.raises(ValueError, match="a colour a wave"):
        splatzoo.create_model("gabor-adaptive", pts, cols, fit_waves=0.5)
    assert splatzoo.create_model("beta-gabor", pts, cols, free_directions=False, fit_waves=0).wave_fit_step(10) is None


def test_a_run_fits_once_at_its_fraction_and_never_with_fit_waves_0(tmp_path):
    from splatzoo.data import load_scene
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    data = make_synthetic_scene("sweater", tmp_path / "data", views=6, width=32, height=32)
    scene = load_scene(data)
    cfg = TrainConfig(iterations=20, backend="cpu", num_primitives=60, log_every=5, eval_every=20, seed=1,
                      densify=False)
    train(scene, "beta-gabor", {"fit_waves": 0.5}, cfg, tmp_path / "run", progress=False)
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    fits = [r for r in log if "wave_fit" in r]
    assert len(fits) == 1 and fits[0]["iteration"] == 10, fits
    assert 0 < fits[0]["wave_fit"]["surfels_fitted"] <= fits[0]["wave_fit"]["surfels"] == 60
    train(scene, "beta-gabor", {"fit_waves": 0.0}, cfg, tmp_path / "plain", progress=False)
    assert not any("wave_fit" in line for line in (tmp_path / "plain" / "train_log.jsonl").read_text().splitlines())


def test_surfels_at_the_extremes_leave_every_parameter_finite():
    """The largest and smallest scales, a surfel at a camera's centre, one edge-on to every view, and one behind them
    all: the fit runs, and what it sets (or leaves) is finite."""
    from splatzoo.types import MAX_SCALE

    background = torch.full((3,), 0.5)
    model = plane_model(n_side=3)
    views = photos_of(plane_model(n_side=3), cameras(), background)
    cam = views[2][0]
    with torch.no_grad():
        model.log_scales[0] = math.log(MAX_SCALE)
        model.log_scales[1] = math.log(1e-9)
        model.means[2] = cam.center.float()
        model.quats[3] = normals_to_quats(torch.tensor([[1.0, 0.0, 0.0]]))[0]
        model.means[4, 2] = -50.0
    record = wave_fit.fit_waves(model, None, views, background, "cpu")
    assert 0 < record["surfels_fitted"] < 9
    for name, p in model.named_parameters():
        assert torch.isfinite(p).all(), name
