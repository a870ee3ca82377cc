"""Conformance of every registered model (built-ins and installed plugins), driven by list_models()."""
import pytest
import torch

import splatzoo
from splatzoo import Camera, rasterize
from splatzoo.errors import ShapeError, UnknownNameError
from splatzoo.models.base import ModelOptionError


def point_cloud(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    pts = d / d.norm(dim=1, keepdim=True)
    return pts, torch.rand(n, 3, generator=g)


CAM = Camera.look_at([0.0, 0.0, -3.5], [0.0, 0.0, 0.0], width=32, height=32, fov_deg=45.0)


@pytest.mark.parametrize("name", splatzoo.list_models())
def test_model_conformance(name, tmp_path):
    pts, cols = point_cloud()
    model = splatzoo.create_model(name, pts, cols, seed=1)
    assert model.num_primitives == 64
    with torch.no_grad():  # make every surfel clearly visible so that every parameter can get a gradient
        model.logit_opacity.fill_(1.0)
        # a start may hold zeros whose partners get no gradient until they move (neural-gabor's colourless hidden
        # units hold their wave vectors still at the first step): give all-zero parameters small values
        gen = torch.Generator().manual_seed(3)
        for p in model.parameters():
            if p.numel() and float(p.abs().max()) == 0:
                p.copy_(0.01 * torch.randn(p.shape, generator=gen))
    out = rasterize(model.surfels(CAM), CAM, backend="reference")
    target = torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(2))
    loss = (out.rgb - target).abs().mean() + out.depth.mean() * 1e-3 + out.normal.sum() * 1e-3
    assert torch.isfinite(loss)
    loss.backward()
    for pname, p in model.named_parameters():
        if p.numel() == 0:
            continue
        assert p.grad is not None and p.grad.abs().sum() > 0, f"{name}: no gradient reaches {pname}"
    path = tmp_path / f"{name}.pt"
    splatzoo.save_model(model, path)
    loaded = splatzoo.load_model(path)
    assert type(loaded) is type(model) and loaded.config == model.config
    with torch.no_grad():
        a = rasterize(model.surfels(CAM), CAM, backend="reference")
        b = rasterize(loaded.surfels(CAM), CAM, backend="reference")
    for k, v in a.tensors().items():
        assert torch.equal(v, getattr(b, k)), k


def test_model_render_image_only_is_the_same_picture_without_autograd():
    pts, cols = point_cloud()
    model = splatzoo.create_model("gabor", pts, cols, seed=1)
    full = model.render(CAM, backend="cpu")
    image = model.render(CAM, backend="cpu", image_only=True)
    assert torch.equal(image.rgb, full.rgb.detach()) and image.depth is None and image.rgb.grad_fn is None


@pytest.mark.parametrize("name", ["2dgs", "gabor"])
def test_parameters_beyond_the_valid_range_render_with_finite_gradients(name):
    """A crafted or diverged log-scale of 88 (exp overflows float) or a wave frequency of 1e20 is held at the valid
    range by the parametrisation (types.MAX_SCALE, MAX_WAVE_NUMBER): the model renders on every backend with finite
    gradients instead of NaN everywhere."""
    from splatzoo.types import MAX_SCALE, MAX_WAVE_NUMBER

    pts, cols = point_cloud()
    model = splatzoo.create_model(name, pts, cols, seed=1)
    with torch.no_grad():
        model.log_scales[0] = 88.0
        if name == "gabor":
            model.wave_freqs[1] = 1e20
    s = model.surfels(CAM)
    assert float(s.scales.detach().max()) == pytest.approx(MAX_SCALE, rel=1e-4)
    assert s.wave_vectors.numel() == 0 or float(s.wave_vectors.detach().abs().max()) <= MAX_WAVE_NUMBER
    for backend in ("reference", "cpu"):
        model.zero_grad()
        out = model.render(CAM, backend=backend)
        (out.rgb.sum() + out.alpha.sum()).backward()
        for pname, p in model.named_parameters():
            assert p.grad is None or torch.isfinite(p.grad).all(), f"{backend}: gradient of {pname} not finite"


@pytest.mark.parametrize("name", splatzoo.list_models())
def test_model_render_uses_its_own_settings(name, tmp_path):
    """model.render is the one render call: the model's raster settings (the pixel-footprint filter it was trained
    with) and its background, kept through save and load; a camera in float64 is taken to the model's dtype."""
    from splatzoo.rasterizers.common import ANTIALIASED, SETTINGS

    pts, cols = point_cloud()
    model = splatzoo.create_model(name, pts, cols, seed=1)
    with torch.no_grad():
        model.logit_opacity.fill_(1.0)
    cam = CAM.scaled(0.25)  # 8x8: a surfel under a pixel, where the filter changes the picture most
    cam32 = cam.to(dtype=torch.float32)
    for antialias, settings in ((False, SETTINGS), (True, ANTIALIASED)):
        model.antialias = antialias
        out = model.render(cam, backend="reference")
        assert out.rgb.dtype == torch.float32 and out.rgb.requires_grad
        want = rasterize(model.surfels(cam32), cam32, backend="reference", settings=settings)
        for k, v in want.tensors().items():
            assert torch.equal(v, getattr(out, k)), (antialias, k)
    plain = rasterize(model.surfels(cam32), cam32, backend="reference").rgb
    assert not torch.equal(out.rgb, plain), "the filter should change an 8x8 render of 64 surfels"
    model.background = (0.25, 0.5, 1.0)
    path = tmp_path / "m.pt"
    splatzoo.save_model(model, path)
    loaded = splatzoo.load_model(path)
    assert loaded.background == (0.25, 0.5, 1.0) and loaded.antialias
    with torch.no_grad():
        a, b = model.render(cam, backend="reference"), loaded.render(cam, backend="reference")
        black = loaded.render(cam, backend="reference", background=0.0)
    assert torch.equal(a.rgb, b.rgb)
    empty = b.alpha < 0.5
    assert empty.any() and torch.allclose(b.rgb - black.rgb, (1 - b.alpha)[..., None] * torch.tensor([0.25, 0.5, 1.0]))


def test_gabor_residual_maps_to_the_wave_bank():
    """The default: c0 = color_base, a_i = w_i d (d = color_diff); it starts as the 2DGS surfel with the release's
    waves around it (d = half the point colour, w = 0.1 U(0,1))."""
    pts, cols = point_cloud(5)
    m = splatzoo.create_model("gabor", pts, cols, n_waves=4)
    assert m.config.color_param == "residual"
    s = m.surfels(CAM)
    assert torch.equal(s.base_color, cols) and torch.equal(m.color_diff, cols / 2)
    w = m.wave_weights
    assert torch.equal(s.wave_amplitudes, w[..., None] * m.color_diff[:, None])
    assert w.min() >= 0 and w.max() <= 0.1 and w.std() > 0.01
    groups = {g["name"]: g["lr"] for g in m.optim_groups(1.0)}
    two = {g["name"]: g["lr"] for g in splatzoo.create_model("2dgs", pts, cols).optim_groups(1.0)}
    assert groups["color_base"] == pytest.approx(two["sh_dc"] * 0.28209479177387814)  # 2DGS's pace, colour units
    with pytest.raises(ShapeError, match="color_param=paper"):
        splatzoo.create_model("gabor", init="surfel")


def test_gabor_paper_maps_to_the_wave_bank():
    """c0 = (sum w)(cA + cB)/2, a_i = w_i (cA - cB)/2, k_i = 2 pi f_i (cos i pi/N, sin i pi/N)."""
    pts, cols = point_cloud(5)
    m = splatzoo.create_model("gabor", pts, cols, n_waves=4, color_param="paper")
    s = m.surfels(CAM)
    w, f = m.wave_weights, m.wave_freqs
    assert torch.allclose(s.base_color, w.sum(1, keepdim=True) * (m.color_a + m.color_b) / 2)
    assert torch.allclose(s.wave_amplitudes, w[..., None] * ((m.color_a - m.color_b) / 2)[:, None])
    angle = torch.tensor([0, 1, 2, 3]) * torch.pi / 4
    assert torch.allclose(s.wave_vectors[..., 0], 2 * torch.pi * f * angle.cos(), atol=1e-6)
    assert torch.allclose(s.wave_vectors[..., 1], 2 * torch.pi * f * angle.sin(), atol=1e-6)
    # the paper's formula, evaluated directly at a local point
    u, v = 0.3, -0.7
    theta = 2 * torch.pi * f * (angle.cos() * u + angle.sin() * v) + m.wave_phases
    paper = (w[..., None] * (m.color_a[:, None] * (1 + theta.cos()[..., None]) / 2
                             + m.color_b[:, None] * (1 - theta.cos()[..., None]) / 2)).sum(1)
    bank = s.base_color + (s.wave_amplitudes * (s.wave_vectors[..., 0] * u + s.wave_vectors[..., 1] * v
                                                + s.wave_phases).cos()[..., None]).sum(1)
    assert torch.allclose(paper, bank, atol=1e-6)


def test_baselines_are_settings_of_the_bank():
    pts, cols = point_cloud(6)
    a = splatzoo.create_model("baseline-a", pts, cols)
    assert a.surfels(CAM).num_waves == 1
    b = splatzoo.create_model("baseline-b", pts, cols, n_waves=3)
    sb = b.surfels(CAM)
    assert sb.num_waves == 3 and torch.all(sb.wave_vectors[..., 1] == 0)
    c = splatzoo.create_model("baseline-c", pts, cols)
    assert torch.all(c.surfels(CAM).wave_phases == 0)
    assert "wave_phases" not in dict(c.named_parameters())


def test_2dgs_spherical_harmonics_are_view_dependent():
    pts, cols = point_cloud(8)
    m = splatzoo.create_model("2dgs", pts, cols, sh_degree=3)
    assert m.sh_rest.shape == (8, 15, 3)
    with torch.no_grad():
        m.sh_rest.normal_(0, 0.3)
    other = Camera.look_at([3.5, 0.0, 0.0], [0.0, 0.0, 0.0], width=32, height=32)
    assert not torch.allclose(m.surfels(CAM).base_color, m.surfels(other).base_color)
    flat = splatzoo.create_model("2dgs", pts, cols)
    assert torch.allclose(flat.surfels(CAM).base_color, cols, atol=1e-6)


def test_options_and_names_are_checked():
    with pytest.raises(UnknownNameError, match="'gabr'.*Did you mean 'gabor'"):
        splatzoo.create_model("gabr")
    with pytest.raises(ModelOptionError, match="n_wave.*n_waves"):
        splatzoo.create_model("gabor", n_wave=3)
    with pytest.raises(ShapeError, match="sh_degree"):
        splatzoo.create_model("2dgs", sh_degree=5)
    with pytest.raises(ShapeError, match="n_waves"):
        splatzoo.create_model("gabor", n_waves=0)
    with pytest.raises(ShapeError, match="points"):
        splatzoo.create_model("gabor", torch.zeros(5, 2))
    assert splatzoo.create_model("gabor", n_waves="8").config.n_waves == 8


def test_import_is_light():
    import subprocess
    import sys

    code = ("import sys, splatzoo; heavy = [m for m in ('open3d', 'pycolmap', 'cv2', 'splatzoo.rasterizers.native', "
            "'kornia', 'skimage') if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_gabor_surfel_init_starts_as_the_2dgs_surfel():
    """init=surfel: the base colour is the point colour (as 2DGS starts) and every wave starts small."""
    import splatzoo
    from splatzoo.models.gabor import INIT_OFFSET

    torch.manual_seed(0)
    pts, cols = torch.randn(300, 3), torch.rand(300, 3)
    cam = splatzoo.Camera.look_at([0, 0, -4], [0, 0, 0], width=32, height=32)
    gabor = splatzoo.create_model("gabor", pts, cols, n_waves=4, color_param="paper", init="surfel")
    s = gabor.surfels(cam)
    assert torch.allclose(s.base_color, cols, atol=1e-6)
    assert s.wave_amplitudes.abs().max() <= INIT_OFFSET / 4 + 1e-7 and s.wave_amplitudes.abs().max() > 0
    paper = splatzoo.create_model("gabor", pts, cols, n_waves=4, color_param="paper").surfels(cam)
    assert paper.base_color.max() < 0.25  # the release's dark start: (sum w)(cA + cB)/2 with sum w ~ 0.2


def test_files_from_before_color_param_mean_the_paper_model():
    """Configs recorded before an option existed are read with what they meant (stored_defaults), not today's
    default: a gabor checkpoint, PLY header or run record without color_param is the paper's parametrisation."""
    from splatzoo.zoo import model_from_checkpoint, stored_config

    assert stored_config("gabor", {"n_waves": 4}) == {"color_param": "paper", "wave_l1": 0.0,
                                                      "wave_l1_per_count": False, "n_waves": 4}
    assert stored_config("gabor", {"color_param": "residual"})["color_param"] == "residual"
    # a residual model from before the sparse-wave default trained (and resumes) without the penalty
    assert stored_config("gabor", {"color_param": "residual"})["wave_l1"] == 0.0
    assert stored_config("gabor", {"color_param": "residual", "wave_l1": 3e-6})["wave_l1"] == 3e-6
    # and one from before wave_l1_per_count had the same strength at any count
    assert stored_config("gabor", {"color_param": "residual", "wave_l1": 3e-6})["wave_l1_per_count"] is False
    assert stored_config("2dgs", {"sh_degree": 1}) == {"sh_degree": 1}
    assert stored_config("no-such-model", {"x": 1}) == {"x": 1}  # the caller reports the unknown name
    pts, cols = point_cloud(7)
    paper = splatzoo.create_model("gabor", pts, cols, color_param="paper")
    ck = paper.checkpoint()
    del ck["config"]["color_param"]
    back = model_from_checkpoint(ck)
    assert back.config.color_param == "paper"
    assert torch.equal(back.surfels(CAM).base_color, paper.surfels(CAM).base_color)


def test_nearest_neighbour_distance_matches_brute_force():
    """The KD-tree initial scales equal the all-pairs answer, duplicates (distance 0) included."""
    from splatzoo.models.base import nearest_neighbour_distance

    g = torch.Generator().manual_seed(0)
    pts = torch.randn(500, 3, generator=g, dtype=torch.float64)
    pts[10] = pts[11]  # a duplicate
    d = torch.cdist(pts, pts)
    d.fill_diagonal_(float("inf"))
    want = d.topk(3, largest=False).values.mean(1)
    got = nearest_neighbour_distance(pts)
    assert got.dtype == pts.dtype and torch.allclose(got, want, rtol=1e-12, atol=1e-12)
    assert torch.equal(nearest_neighbour_distance(pts[:1]), torch.ones(1, dtype=torch.float64))
    two = nearest_neighbour_distance(torch.tensor([[0.0, 0, 0], [3.0, 4, 0]]))  # k shrinks to N - 1
    assert torch.allclose(two, torch.tensor([5.0, 5.0]))


@pytest.mark.parametrize("name, param, hidden, visible, message", [
    # every opacity below 1/255 (a diverged run, an edited file)
    ("beta", "logit_opacity", -20.0, (3,), "logit_opacity: every one of its 64 surfels has an opacity below 1/255"),
    # opacities that pass, but texture alphas at zero everywhere
    ("textured", "texture_alpha_logit", -30.0, (5, 0, 1), "texture_alpha_logit: every one of the 64 surfels"),
])
def test_a_model_that_draws_nothing_is_refused_on_load(tmp_path, name, param, hidden, visible, message):
    """Nothing renders and nothing can be learned: loading names the parameter instead of producing black images and a
    training that stands still. One visible surfel (or one texel of one surfel) is a model."""
    from splatzoo.errors import SplatzooError

    pts, cols = point_cloud()
    model = splatzoo.create_model(name, pts, cols, seed=1)
    with torch.no_grad():
        getattr(model, param).fill_(hidden)
    splatzoo.save_model(model, tmp_path / "model.pt")
    with pytest.raises(SplatzooError, match=message):
        splatzoo.load_model(tmp_path / "model.pt")
    with torch.no_grad():
        getattr(model, param)[visible] = 0.0
    splatzoo.save_model(model, tmp_path / "model.pt")
    assert splatzoo.load_model(tmp_path / "model.pt").num_primitives == 64
