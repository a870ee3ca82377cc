"""A model's render settings (anti-aliasing, background) are its own, changed in one place and kept in its files; and
a model recoloured for display (compare's surfels row, the viewer's surfels, waves and frequency modes) is drawn as
opaque as the model itself, whatever its member: a Beta falloff and a texture's alpha are kept."""
import pytest
import torch

from splatzoo import Camera, SplatzooError, create_model
from splatzoo.compare import random_color_surfels
from splatzoo.display import random_colors, recolored
from splatzoo.models.base import RenderSettings
from splatzoo.rasterizers import available_backends
from splatzoo.types import Surfels
from splatzoo.zoo import model_from_checkpoint

MEMBERS = ["2dgs", "gabor", "beta", "beta-gabor", "textured", "neural-gabor"]
SHAPED = {"beta", "beta-gabor", "textured"}  # members whose opacity is more than geometry and peak opacity


def _member(name: str):
    """`name` with 40 surfels in front of the camera, their falloff or texture alpha varied per surfel and texel."""
    g = torch.Generator().manual_seed(0)
    n = 40
    model = create_model(name, (torch.rand(n, 3, generator=g) - 0.5) * 0.8, torch.rand(n, 3, generator=g))
    with torch.no_grad():
        model.logit_opacity.fill_(2.0)
        for key, p in model.named_parameters():
            if key in ("falloff_logit", "texture_alpha_logit"):
                p.copy_(torch.randn(p.shape, generator=g) * 2)
    return model


def _camera() -> Camera:
    return Camera.look_at([0.0, 0.0, -2.5], [0.0, 0.0, 0.0], width=40, height=40, dtype=torch.float32)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
@pytest.mark.parametrize("name", MEMBERS)
def test_a_recoloured_render_keeps_the_models_alpha(name, backend):
    if backend not in available_backends():  # asked here, not at collection: asking builds the native extension
        pytest.skip(f"the {backend} backend cannot run here")
    model, cam = _member(name), _camera()
    with torch.no_grad():
        own = model.render(cam, backend=backend)
        shapes = random_color_surfels(model, cam)  # compare's surfels row
        flat = model.render(cam, backend=backend, surfels=shapes)
        assert own.alpha.max() > 0.5
        torch.testing.assert_close(flat.alpha, own.alpha, atol=1e-6, rtol=0)
        # the viewer's modes recolour through the same function, with other colours
        mine = model.render(cam, backend=backend, surfels=recolored(model.surfels(cam), random_colors(40, 3)))
        torch.testing.assert_close(mine.alpha, own.alpha, atol=1e-6, rtol=0)
        assert shapes.num_waves == 0 and not torch.equal(flat.rgb, own.rgb)
        if name in SHAPED:  # rebuilt from five fields, as recolouring once was, the member draws another alpha
            s = model.surfels(cam)
            five = Surfels.constant_color(s.means, s.quats, s.scales, s.opacities, shapes.base_color)
            assert (model.render(cam, backend=backend, surfels=five).alpha - own.alpha).abs().max() > 1e-3


def test_render_settings_are_set_in_one_place_and_kept_in_the_checkpoint():
    model = create_model("2dgs", torch.zeros(3, 3), torch.full((3, 3), 0.5))
    assert model.render_settings == RenderSettings() and not model.antialias and model.background is None
    assert model.set_render_settings(antialias=True, background=[1, 1, 1]) is model
    assert model.render_settings == RenderSettings(True, (1.0, 1.0, 1.0))
    model.background = None  # assigning an attribute sets the render setting too
    assert model.render_settings == RenderSettings(True, None)
    back = model_from_checkpoint(model.checkpoint())
    assert back.render_settings == model.render_settings
    other = create_model("gabor", torch.zeros(2, 3), torch.full((2, 3), 0.5))
    assert other.set_render_settings(back.render_settings, background=(0, 0.5, 1)).render_settings == \
        RenderSettings(True, (0.0, 0.5, 1.0))
    for bad in ({"antialias": "yes"}, {"background": (1, 2)}, {"background": (0, float("nan"), 0)},
                {"background": "white"}):
        with pytest.raises(SplatzooError, match="render setting"):
            model.set_render_settings(**bad)
    assert model.render_settings == RenderSettings(True, None)  # a refused change changes nothing
