"""The background behind the surfels: given or found in the images (auto), or random per training step."""
import numpy as np
import pytest
import torch

from splatzoo import Camera
from splatzoo.data import load_scene
from splatzoo.data.background import choose_background, parse_background
from splatzoo.data.scene import View
from splatzoo.errors import SplatzooError
from splatzoo.runs import train
from splatzoo.training import TrainConfig


@pytest.fixture(scope="module")
def white_scene(tmp_path_factory):
    from splatzoo.data.synthetic import make_synthetic_scene

    return make_synthetic_scene("plain", tmp_path_factory.mktemp("white") / "data", views=10, width=40, height=40,
                                background=(1.0, 1.0, 1.0))


def test_parse():
    assert parse_background(None) == "auto" and parse_background("Random") == "random"
    assert parse_background("white") == (1.0, 1.0, 1.0) and parse_background("black") == (0.0, 0.0, 0.0)
    assert parse_background("255, 0, 51") == (1.0, 0.0, 0.2)
    assert parse_background("0.5,0.25,1") == (0.5, 0.25, 1.0) and parse_background([0, 1, 0]) == (0.0, 1.0, 0.0)
    for bad in ("pink", "1,2", "-1,0,0", "300,0,0", "nan,0,0", [1, 2, 3, 4]):
        with pytest.raises(SplatzooError, match="background"):
            parse_background(bad)


@pytest.fixture(scope="module")
def white_scene_without_masks(white_scene, tmp_path_factory):
    import shutil

    copy = tmp_path_factory.mktemp("white-unmasked") / "data"
    shutil.copytree(white_scene, copy, ignore=shutil.ignore_patterns("masks"))
    return copy


def test_auto_finds_a_white_backdrop(white_scene_without_masks, tmp_path):
    white_scene = white_scene_without_masks  # (random needs alpha or masks)
    scene = load_scene(white_scene)
    assert scene.background == (1.0, 1.0, 1.0) and not scene.random_background
    assert "white" in scene.background_note and all(v.background == (1.0, 1.0, 1.0) for v in scene.views)
    assert load_scene(white_scene, background="black").background == (0.0, 0.0, 0.0)
    from splatzoo.data.synthetic import make_synthetic_scene

    black = make_synthetic_scene("plain", tmp_path / "black", views=6, width=40, height=40)
    assert load_scene(black).background == (0.0, 0.0, 0.0)
    grey = make_synthetic_scene("plain", tmp_path / "grey", views=6, width=40, height=40,
                                background=(0.5, 0.25, 0.75))
    assert np.allclose(load_scene(grey).background, (0.5, 0.25, 0.75), atol=0.01)
    with pytest.raises(SplatzooError, match="alpha.*or masks"):
        load_scene(white_scene, background="random")


def test_masks_replace_the_backdrop_exactly(tmp_path):
    """A photo over white with its mask, its backdrop replaced by black, is the same scene shot over black."""
    from splatzoo.data.synthetic import make_synthetic_scene

    white = load_scene(make_synthetic_scene("sweater", tmp_path / "w", views=4, width=48, height=48,
                                            background=(1.0, 1.0, 1.0)))
    black = load_scene(make_synthetic_scene("sweater", tmp_path / "b", views=4, width=48, height=48), masks=False)
    for w, b in zip(white.views, black.views):
        replaced = w.image_float(background=(0.0, 0.0, 0.0))
        assert (replaced - b.image_float()).abs().max() <= 1.5 / 255   # the two 8-bit roundings
        assert torch.equal(w.image_float(background=(1.0, 1.0, 1.0)), w.image_float())


def test_random_with_masks_replaces_the_backdrop(white_scene, white_scene_without_masks, tmp_path):
    """--background random over a white backdrop with masks: a new colour behind the object each step (through the
    masks), the model renders over white; auto keeps the backdrop fixed (masks are read, for eval's opacity)."""
    scene = load_scene(white_scene, background="random")
    assert scene.background == (1.0, 1.0, 1.0) and scene.random_background and scene.masked_backdrop
    assert "masks" in scene.background_note and "white" in scene.background_note
    auto = load_scene(white_scene)
    assert not auto.random_background and all(v.use_mask for v in auto.views)
    assert not load_scene(white_scene, masks=False).train[0].use_mask
    with pytest.raises(SplatzooError, match="alpha.*or masks"):
        load_scene(white_scene_without_masks, background="random")
    cfg = TrainConfig(iterations=6, backend="cpu", num_primitives=200, densify=False)
    run = train(white_scene, "2dgs", {}, cfg, tmp_path / "random", progress=False, evaluate_at_end=True,
                scene_options={"background": "random"})
    assert run.model.background == (1.0, 1.0, 1.0)
    assert 0 <= run.metrics["object_alpha"] <= 1  # eval measures the opacity inside the masks
    from splatzoo.runs import Run

    assert Run(tmp_path / "random").record()["scene"]["random_background"] is True


def test_random_needs_one_backdrop_colour_to_replace(tmp_path):
    img = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    views = _views(img)
    for v in views:
        v.use_mask, v.mask_path = True, tmp_path / "m.png"
    with pytest.raises(SplatzooError, match="backdrop of one colour"):
        choose_background("random", views, None)


def _views(image: np.ndarray, n: int = 4) -> list[View]:
    cam = Camera.look_at([0, 0, -3], [0, 0, 0], width=image.shape[1], height=image.shape[0])
    return [View.from_tensor(cam, torch.from_numpy(image), f"v{i}") for i in range(n)]


def test_auto_keeps_a_colour_the_scene_is_made_of():
    """White borders that most points share are a white wall of the scene, not a backdrop."""
    img = np.full((32, 32, 3), 255, np.uint8)
    img[8:24, 8:24] = (200, 30, 30)
    colour, random, note = choose_background("auto", _views(img), torch.ones(100, 3))
    assert colour == (0.0, 0.0, 0.0) and "part of the scene" in note
    colour, _, note = choose_background("auto", _views(img), torch.tensor([[0.8, 0.1, 0.1]] * 100))
    assert colour == (1.0, 1.0, 1.0)
    noisy = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    colour, _, note = choose_background("auto", _views(noisy), None)
    assert colour == (0.0, 0.0, 0.0) and "no common colour" in note


def test_no_flag_trains_as_the_right_explicit_one(white_scene, tmp_path):
    """On a white backdrop (with masks), auto is white: the same run, bit for bit, as --background white."""
    cfg = TrainConfig(iterations=15, backend="cpu", num_primitives=300, densify=False)
    auto = train(white_scene, "gabor", {}, cfg, tmp_path / "auto", progress=False, evaluate_at_end=False).model
    white = train(white_scene, "gabor", {}, cfg, tmp_path / "white", progress=False, evaluate_at_end=False,
                  scene_options={"background": "white"}).model
    for k, v in auto.state_dict().items():
        assert torch.equal(v, white.state_dict()[k]), k
    from splatzoo.runs import Run

    record = Run(tmp_path / "auto").record()
    assert record["scene_options"]["background"] == "auto" and "white" in record["scene"]["background_note"]
    assert Run(tmp_path / "white").record()["scene_options"]["background"] == [1.0, 1.0, 1.0]
    # the trained model renders over its backdrop by default, from Python as in every command
    loaded = Run(tmp_path / "auto").model()
    assert auto.background == loaded.background == (1.0, 1.0, 1.0)


def test_random_background_changes_every_step():
    """random: behind a transparent pixel the target shows a new colour each step (and the render the same one)."""
    from splatzoo.data.scene import Scene
    from splatzoo.training.trainer import Trainer
    from splatzoo.zoo import make_config

    rgba = np.zeros((24, 24, 4), np.uint8)
    rgba[6:18, 6:18] = (200, 40, 40, 255)
    views = _views(rgba, 3)
    colour, random, _ = choose_background("random", views, None)
    assert random and colour == (0.0, 0.0, 0.0)
    pts = torch.randn(200, 3) * 0.3
    scene = Scene("rgba", None, views, [], pts, torch.rand(200, 3), 3.0, colour, random_background=True)
    trainer = Trainer.start(scene, "2dgs", make_config("2dgs"), TrainConfig(iterations=10, backend="cpu", densify=False),
                            "cpu", torch.device("cpu"))
    corners = []
    for step in (1, 2):
        target = trainer._loss(views[0], step).target
        corners.append(target[0, 0])
        assert torch.allclose(target[12, 12], torch.tensor([200, 40, 40]) / 255, atol=1e-6)
    assert not torch.allclose(corners[0], corners[1])
    assert trainer.net.background is None  # no backdrop was learned: it renders over black unless told
    again = trainer._loss(views[0], 1).target
    assert torch.equal(again[0, 0], corners[0])  # the same step draws the same colour (ranks, resume)


def test_cli_names_a_bad_background(white_scene, tmp_path):
    from typer.testing import CliRunner

    from splatzoo.cli import app

    result = CliRunner().invoke(app, ["train", str(white_scene), "--out", str(tmp_path / "r"), "--background",
                                      "pink", "--iterations", "2"])
    assert result.exit_code != 0 and "auto, black, white" in str(result.exception or result.output)
    assert not (tmp_path / "r").exists()


def test_large_photos_are_downscaled_unless_asked(tmp_path):
    """Photos wider than 1600 px train at 1600 px by default (and say so); --resolution 1 keeps full size."""
    import cv2

    from splatzoo.data.colmap import write_model

    cams = [Camera.look_at([np.sin(a) * 3, 0.3, -np.cos(a) * 3], [0, 0, 0], width=2000, height=1000,
                           name=f"v{i}.png", dtype=torch.float64) for i, a in enumerate(np.linspace(0, 1, 3))]
    (tmp_path / "images").mkdir()
    for c in cams:
        cv2.imwrite(str(tmp_path / "images" / c.name), np.full((1000, 2000, 3), 90, np.uint8))
    write_model(tmp_path / "sparse" / "0", cams, [c.name for c in cams], np.random.default_rng(0).normal(size=(50, 3)))
    scene = load_scene(tmp_path, test_every=0)
    assert (scene.train[0].camera.width, scene.train[0].camera.height) == (1600, 800)
    assert any("2000 px wide" in n and "--resolution 1" in n for n in scene.notes)
    full = load_scene(tmp_path, test_every=0, resolution=1)
    assert full.train[0].camera.width == 2000 and not any("px wide" in n for n in full.notes)
    assert load_scene(tmp_path, test_every=0, max_width=500).train[0].camera.width == 500
