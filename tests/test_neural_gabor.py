"""neural-gabor: the per-surfel sine network, as the rasterizers draw it (through the wave kind)."""
from __future__ import annotations

import math

import pytest
import torch

import splatzoo
from splatzoo.errors import ShapeError
from splatzoo.training.densify import split_rows
from splatzoo.types import Camera


def _model(n=1, seed=0, **options):
    gen = torch.Generator().manual_seed(seed)
    pts = torch.randn(n, 3, generator=gen) * 0.2
    cols = torch.rand(n, 3, generator=gen)
    model = splatzoo.create_model("neural-gabor", pts, cols, seed=seed, **options)
    with torch.no_grad():  # a strong pattern: the start's hidden units are colourless
        model.net_w2.copy_(0.4 * (2 * torch.rand(model.net_w2.shape, generator=gen) - 1))
        model.net_b2.fill_(0.5)
    return model


def _pixel_uv(camera: Camera, mean, scale) -> torch.Tensor:
    """(u, v) [H,W,2] where each pixel's centre ray meets the plane z = mean_z of an axis-aligned surfel."""
    H, W = camera.height, camera.width
    j, i = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    pix = torch.stack([i + 0.5, j + 0.5, torch.ones_like(i)], -1)
    c2w = camera.camera_to_world.double()
    dirs = (pix @ torch.linalg.inv(camera.K.double()).T) @ c2w[:3, :3].T
    eye = camera.center.double()
    t = (mean[2] - eye[2]) / dirs[..., 2]
    hit = eye + t[..., None] * dirs
    return (hit[..., :2] - mean[:2]) / scale


def test_starts_as_its_2dgs_surfel():
    """Colourless hidden units at the start: a new model renders what 2DGS renders from the same points and seed."""
    gen = torch.Generator().manual_seed(5)
    pts, cols = torch.randn(40, 3, generator=gen) * 0.3, torch.rand(40, 3, generator=gen)
    neural = splatzoo.create_model("neural-gabor", pts, cols, seed=5)
    plain = splatzoo.create_model("2dgs", pts, cols, seed=5)
    assert float(neural.net_w2.detach().abs().max()) == 0.0  # colourless units...
    assert float(neural.net_w1.detach().abs().max()) > 0     # ... whose waves can still grow
    cam = Camera.look_at([0.4, 0.3, -2.5], [0.0, 0.0, 0.0], width=40, height=40, fov_deg=40)
    with torch.no_grad():
        a, b = neural.render(cam, backend="cpu"), plain.render(cam, backend="cpu")
    assert float(b.alpha.max()) > 0.5
    assert torch.allclose(a.rgb, b.rgb, atol=1e-5) and torch.allclose(a.alpha, b.alpha, atol=1e-6)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_rendered_colour_is_the_network_at_the_hit(backend):
    """One opaque surfel facing the camera: each pixel's colour over black, divided by its alpha, is the network
    evaluated as written at the pixel ray's hit (u, v) and the view direction."""
    model = _model(seed=3, view_dependent=True).double()
    model.antialias = False
    with torch.no_grad():
        model.means.zero_()
        model.quats.copy_(torch.tensor([[1.0, 0, 0, 0]]))
        model.log_scales.fill_(math.log(0.4))
        model.logit_opacity.fill_(6.0)
    cam = Camera.look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], width=48, height=48, fov_deg=30)
    with torch.no_grad():
        out = model.render(cam, background=0.0, backend=backend)
        uv = _pixel_uv(cam, model.means[0].double(), 0.4)
        want = model.network_color(uv.reshape(1, -1, 2), cam)[0].reshape(48, 48, 3)
    solid = out.alpha > 0.5
    assert int(solid.sum()) > 200
    got = out.rgb / out.alpha[..., None]
    assert torch.allclose(got[solid], want[solid], atol=1e-6 if backend == "reference" else 2e-4)
    assert float(want[solid].std()) > 0.05  # the pattern is there to be matched


def test_view_direction_moves_the_phases_only():
    model = _model(n=4, seed=1, view_dependent=True)
    a = Camera.look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], dtype=torch.float32)
    b = Camera.look_at([2.0, 0.5, -2.0], [0.0, 0.0, 0.0], dtype=torch.float32)
    sa, sb = model.surfels(a), model.surfels(b)
    assert torch.equal(sa.wave_vectors, sb.wave_vectors) and torch.equal(sa.wave_amplitudes, sb.wave_amplitudes)
    assert not torch.allclose(sa.wave_phases, sb.wave_phases)
    still = _model(n=4, seed=1, view_dependent=False)
    assert torch.equal(still.surfels(a).wave_phases, still.surfels(b).wave_phases)


def test_every_network_parameter_learns():
    model = _model(n=20, seed=2, view_dependent=True)
    model.antialias = True
    cam = Camera.look_at([0.0, 0.0, -2.0], [0.0, 0.0, 0.0], width=32, height=32, dtype=torch.float32)
    model.render(cam, backend="cpu").rgb.square().sum().backward()
    for name in ("net_w1", "net_b1", "net_w2", "net_b2"):
        g = getattr(model, name).grad
        assert g is not None and torch.isfinite(g).all() and float(g.abs().sum()) > 0, name
    # the view weights learn too (through the phases)
    assert float(model.net_w1.grad[..., 2:].abs().sum()) > 0


def test_split_children_show_their_parents_pattern():
    """A child's network at its own (u', v') equals the parent's at offsets + (u', v') / shrink (same view)."""
    model = _model(n=3, seed=4)
    params = {k: v.detach() for k, v in model.per_primitive().items()}
    idx = torch.tensor([0, 1, 2, 0, 1, 2])
    children = split_rows(model, params, idx, torch.Generator().manual_seed(0))
    child = _model(n=6, seed=4)
    child.replace_parameters(children)
    cam = Camera.look_at([0.5, 0.2, -3.0], [0.0, 0.0, 0.0], dtype=torch.float32)
    # the same world points: recover each child's offset from its centre, in the parent's frame and sigmas
    parent_scale = torch.exp(params["log_scales"][idx])
    from splatzoo.geometry import quat_to_rotmat

    R = quat_to_rotmat(params["quats"][idx])
    offsets = ((children["means"] - params["means"][idx])[:, None, :] @ R[:, :, :2]).squeeze(1) / parent_scale
    uv = torch.randn(6, 9, 2, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        got = child.network_color(uv, cam)
        parent = _model(n=6, seed=4, view_dependent=False)
        parent.replace_parameters({k: v[idx] for k, v in params.items()})
        want = parent.network_color(offsets[:, None, :] + uv / 1.6, cam)
    assert torch.allclose(got, want, atol=1e-5)


def test_size_and_options():
    model = _model(n=10, view_dependent=True)
    assert model.size_bytes() == 10 * (3 + 2 + 4 + 1 + 6 * 5 + 6 + 6 * 3 + 3) * 4  # 57 network numbers at H = 6
    assert _model(n=10).size_bytes() == 10 * (10 + 6 * 2 + 6 + 6 * 3 + 3) * 4  # no view weights stored
    assert model.densify_strategy == "frequency"
    with pytest.raises(ShapeError, match="hidden"):
        _model(hidden=0)
    with pytest.raises(ShapeError, match="omega"):
        _model(omega=-1.0)
    assert _model(hidden=3).net_w1.shape == (1, 3, 2)


def test_amplitude_penalty_is_gabors_sparse_waves():
    model = _model(n=10)
    want = model.config.amplitude_l1 * 2000 / 10 * float(model.net_w2.detach().abs().sum())
    assert math.isclose(float(model.regulariser().detach()), want, rel_tol=1e-6)
    assert _model(n=10, amplitude_l1=0.0).regulariser() is None
    with pytest.raises(ShapeError, match="amplitude_l1"):
        _model(amplitude_l1=-1.0)
