"""The `baked` export: a gabor model with strong waves fitted into plain constant-colour 2dgs splats."""
from __future__ import annotations

import math

import pytest
import torch

from splatzoo import Camera, SplatzooError, create_model, load_ply
from splatzoo.bake import BakeOptions, bake_model, bake_options, export_baked, waves_dropped
from splatzoo.export import save_ply
from splatzoo.metrics import psnr


def _striped_gabor(seed: int = 0):
    """25 surfels on a plane facing -z, each with one strong wave (about 1.5 periods across its +-2 sigma)."""
    g = torch.Generator().manual_seed(seed)
    xs = torch.linspace(-0.8, 0.8, 5)
    pts = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    points = torch.cat([pts, torch.zeros(pts.shape[0], 1)], 1)
    colors = 0.3 + 0.4 * torch.rand(points.shape[0], 3, generator=g)
    model = create_model("gabor", points, colors, n_waves=1)
    with torch.no_grad():
        model.quats.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(points.shape[0], 4))
        model.log_scales.fill_(math.log(0.2))
        model.logit_opacity.fill_(3.0)
        model.color_diff.copy_(0.35 * torch.sign(torch.randn(points.shape[0], 3, generator=g)))
        model.wave_weights.fill_(1.0)
        model.wave_freqs.copy_(0.3 + 0.1 * torch.rand(points.shape[0], 1, generator=g))
        model.wave_phases.copy_(6.0 * torch.rand(points.shape[0], 1, generator=g))
    return model


def _cameras(n: int = 6, size: int = 48) -> list[Camera]:
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = [0.6 * math.cos(a), 0.6 * math.sin(a), -3.0]
        cams.append(Camera.look_at(eye, [0.0, 0.0, 0.0], fov_deg=40.0, width=size, height=size, name=f"c{i}"))
    return cams


FAST = dict(steps=120, views=12, eval_views=4)


@pytest.fixture(scope="module")
def baked():
    model = _striped_gabor()
    cams = _cameras()
    out, report = bake_model(model, cams, BakeOptions(max_splats=8 * model.num_primitives, **FAST))
    return model, cams, out, report


def test_bake_beats_dropping_the_waves(baked):
    model, cams, out, report = baked
    assert out.name == "2dgs" and out.config.sh_degree == 0
    assert report["splats"] == out.num_primitives <= 8 * model.num_primitives
    # the fit improves on its start, and the result is far closer to the gabor render than the waves-dropped model
    assert report["bake_db"] > report["start_db"] + 1.0
    assert report["bake_db"] > report["plain_db"] + 5.0, report
    # the same, on the fitting cameras themselves, measured here independently of the report
    for cam in cams[:2]:
        ref = model.render(cam, image_only=True).rgb
        dropped = model.render(cam, image_only=True, surfels=waves_dropped(model)(cam)).rgb
        assert psnr(out.render(cam, image_only=True).rgb, ref) > psnr(dropped, ref) + 5.0


def test_max_splats_is_respected():
    model = _striped_gabor(1)
    out, report = bake_model(model, _cameras(3), BakeOptions(max_splats=50, steps=5, views=3, eval_views=1))
    assert out.num_primitives <= 50 and report["max_splats"] == 50
    # fewer splats than surfels: the most opaque surfels are kept, one splat each
    out, _ = bake_model(model, _cameras(3), BakeOptions(max_splats=20, steps=0, views=3, eval_views=1))
    assert out.num_primitives == 20


def test_baked_model_saves_and_reloads(baked, tmp_path):
    _, cams, out, _ = baked
    path = save_ply(out, tmp_path / "baked.ply")
    back = load_ply(path)
    assert back.name == "2dgs" and back.num_primitives == out.num_primitives
    back.antialias, back.background = out.antialias, out.background
    a, b = out.render(cams[0], image_only=True).rgb, back.render(cams[0], image_only=True).rgb
    assert torch.allclose(a, b, atol=1e-5)


def test_plain_model_passes_through():
    plain = create_model("2dgs", torch.zeros(4, 3), torch.full((4, 3), 0.5))
    out, report = bake_model(plain, _cameras(2), BakeOptions(steps=5))
    assert out is plain and report["splats"] == 4


def test_view_dependent_colour_is_kept():
    model = create_model("gabor", torch.rand(20, 3), torch.rand(20, 3), n_waves=2, sh_degree=1)
    with torch.no_grad():
        model.sh_rest.normal_(0, 0.1)
        model.logit_opacity.fill_(2.0)
    out, _ = bake_model(model, _cameras(2, 24), BakeOptions(steps=2, views=2, eval_views=1))
    assert out.config.sh_degree == 1 and out.sh_rest.shape[1:] == (3, 3)
    assert out.sh_rest.abs().sum() > 0


def test_export_baked_writes_a_ply_from_a_model_file(tmp_path):
    from splatzoo import save_model

    model = _striped_gabor(2)
    src = tmp_path / "gabor.pt"
    save_model(model, src)
    messages = []
    path = export_baked(src, tmp_path / "baked.ply", progress=messages.append, steps="10", views="4",
                        eval_views="2", max_splats="100")
    back = load_ply(path)
    assert back.name == "2dgs" and 0 < back.num_primitives <= 100
    assert any("bake error" in m and "dB" in m for m in messages)


@pytest.mark.parametrize("bad", [dict(max_splats=0), dict(max_splats=-5), dict(max_splats="0"), dict(steps=-1),
                                 dict(views=0), dict(jitter=2.0), dict(scale=0), dict(max_splats="many"),
                                 dict(colour=3)])
def test_bad_options_are_refused(bad, tmp_path):
    with pytest.raises(SplatzooError):
        bake_options(**bad)
    with pytest.raises(SplatzooError):
        export_baked(tmp_path / "missing.pt", tmp_path / "out.ply", **bad)


def test_bad_options_refused_by_bake_model():
    with pytest.raises(SplatzooError, match="max_splats"):
        bake_model(_striped_gabor(), _cameras(2), BakeOptions(max_splats=0))
    with pytest.raises(SplatzooError, match="max_splats"):
        bake_model(_striped_gabor(), _cameras(2), BakeOptions(max_splats=-3))


def test_export_baked_refuses_a_non_ply_target(tmp_path):
    with pytest.raises(SplatzooError, match=r"\.ply"):
        export_baked(tmp_path / "x.pt", tmp_path / "out.pt")

