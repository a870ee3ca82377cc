"""SfM results are checked before use: folding distortion, a focal length far from the prior, implausible distortion,
a blown-up undistorted canvas and few registered photos are caught; an implausible fit is retried with a simpler
camera; a known camera (model and focal length) can be given; the report (numbers, a picture from above) is written."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pycolmap
import pytest

from splatzoo.data import load_scene, make_synthetic_scene, run_sfm
from splatzoo.data.camera_models import projection_profile
from splatzoo.data.colmap import write_model
from splatzoo.data.sfm_checks import check_reconstruction, write_report_png
from splatzoo.data.synthetic import synthetic_cameras
from splatzoo.errors import DataError

GUESS = "the usual guess 1.2 x max(width, height)"


def _reconstruction(tmp_path, model: str, params, n=12, size=256):
    """A reconstruction of `n` cameras around a cloud of points, with the given camera model."""
    cams = synthetic_cameras("plain", n, size, size)
    rng = np.random.default_rng(0)
    pts = rng.normal(scale=0.4, size=(300, 3))
    tracks = []
    for p in pts:
        track = []
        for vi, c in enumerate(cams):
            x = c.K.double().numpy() @ (c.world_to_camera.double().numpy()[:3] @ np.append(p, 1))
            if x[2] > 0 and 0 <= x[0] / x[2] < size and 0 <= x[1] / x[2] < size:
                track.append((vi, x[:2] / x[2]))
        tracks.append(track)
    sparse = tmp_path / "sparse"
    write_model(sparse, cams, [c.name for c in cams], pts, np.full((300, 3), 0.5), tracks)
    rec = pycolmap.Reconstruction(sparse)
    proto = pycolmap.Camera(model=model, width=size, height=size, params=list(params), camera_id=1)
    rec.cameras[1].model = proto.model
    rec.cameras[1].params = list(proto.params)
    return rec


def test_checks_fire_on_a_folding_fit(tmp_path):
    # What SfM returned on 256 px renders of a striped torus without EXIF: focal 99 px (true 230), k1 -0.14.
    rec = _reconstruction(tmp_path, "SIMPLE_RADIAL", [99.0, 128.0, 128.0, -0.14])
    prof = projection_profile(rec.cameras[1])
    r = math.sqrt(1 / (3 * 0.14))                      # where r (1 + k r^2) stops growing
    assert prof["fold_px"] == pytest.approx(99 * r * (1 - 0.14 * r * r), rel=0.01)
    check = check_reconstruction(rec, {1: (307.2, GUESS)}, num_images=30)
    found = {f.what: f for f in check.findings}
    assert {"fold", "focal", "canvas", "registered"} <= {f.what for f in check.implausible}
    assert "folds back 102 px from the image centre, inside the photo (whose corners are 181 px away)" \
        in found["fold"].message
    assert "focal length found, 99 px, is 0.32x the prior 307 px" in found["focal"].message
    assert "256x256 photos into 512x512 images (4.0x the area)" in found["canvas"].message
    assert "only 12 of 30 photos" in found["registered"].message
    text = "\n".join(check.lines())
    assert "focal 99.0 px, prior 307.2 px" in text and "k -0.14" in text and "folds back 102 px" in text
    png = write_report_png(rec, check, tmp_path / "report.png", title="a bad fit")
    img = cv2.imread(str(png))
    assert img is not None and img.shape[1] > 800 and img.std() > 10


def test_checks_pass_a_good_fit_and_flag_strong_distortion(tmp_path):
    good = check_reconstruction(_reconstruction(tmp_path / "a", "SIMPLE_RADIAL", [351.0, 128.0, 128.0, 0.007]),
                                {1: (307.2, GUESS)}, num_images=12)
    assert not good.implausible, good.findings
    assert good.cameras[0].corner_distortion == pytest.approx(0.007 * (181 / 351) ** 2, rel=0.05)
    # k1 -0.35 at f 300: the distortion peaks 195 px from the centre, past the corners (181 px): no fold, but the
    # corners move inward by 20 %
    strong = check_reconstruction(_reconstruction(tmp_path / "b", "SIMPLE_RADIAL", [300.0, 128.0, 128.0, -0.35]),
                                  {1: (307.2, GUESS)}, num_images=12)
    assert [f.what for f in strong.implausible] == ["distortion"]
    assert "corners by -20% of their distance from the centre (implausible" in strong.implausible[0].message
    # past the corners it folds
    folds = check_reconstruction(_reconstruction(tmp_path / "c", "SIMPLE_RADIAL", [300.0, 128.0, 128.0, -0.6]),
                                 {1: (307.2, GUESS)}, num_images=12)
    assert "fold" in [f.what for f in folds.implausible]


def test_sfm_option_errors(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for i, size in enumerate([(32, 24), (32, 24), (24, 32)]):
        cv2.imwrite(str(photos / f"{i}.png"), np.full((*size, 3), 100, np.uint8))
    with pytest.raises(DataError, match=r"unknown camera model 'OPENCV_FISH' \(did you mean OPENCV_FISHEYE\?\).*"
                                        r"SIMPLE_PINHOLE \(no distortion\)"):
        run_sfm(photos, tmp_path / "out", camera_model="OPENCV_FISH", progress=False)
    with pytest.raises(DataError, match=r"EQUIRECTANGULAR cannot be undistorted into pinhole images"):
        run_sfm(photos, tmp_path / "out", camera_model="equirectangular", progress=False)
    with pytest.raises(DataError, match=r"focal=-5: give the focal length in pixels"):
        run_sfm(photos, tmp_path / "out", focal=-5, progress=False)
    with pytest.raises(DataError, match=r"photos of one size, but .*photos holds several \(24x32, 32x24\)"):
        run_sfm(photos, tmp_path / "out", focal=30, progress=False)
    assert not (tmp_path / "out").exists()


# --- SfM on renders of fine repeated texture without EXIF ------------------------------------------------------

VIEWS, SIZE = 20, 128


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    data = make_synthetic_scene("boots", tmp_path_factory.mktemp("sfm") / "boots", views=VIEWS, width=SIZE,
                                height=SIZE, points=50)
    true_focal = float(synthetic_cameras("boots", VIEWS, SIZE, SIZE)[0].K[0, 0])
    return data / "images", true_focal


def test_implausible_fit_is_retried_with_a_simpler_camera(renders, tmp_path):
    images, true_focal = renders
    # Twelve parameters on 128 px photos: the mapper overfits into a distortion that folds inside the photo.
    with pytest.raises(DataError, match=r"cannot be used: the fitted FULL_OPENCV distortion folds back .*"
                                        r"--camera-model SIMPLE_PINHOLE.*nothing was written"):
        run_sfm(images, tmp_path / "no-retry", camera_model="FULL_OPENCV", retry=False, progress=False,
                num_threads=1)
    assert not (tmp_path / "no-retry").exists()

    messages = []
    # one thread: the mapper is then repeatable (with several its fits differ from run to run)
    res = run_sfm(images, tmp_path / "out", camera_model="FULL_OPENCV", progress=messages.append, num_threads=1)
    said = "\n".join(messages)
    assert "the FULL_OPENCV fit looks implausible (" in said  # folding, or another implausible sign
    assert "mapping again with SIMPLE_PINHOLE" in said and "kept the SIMPLE_PINHOLE fit" in said
    assert res.retried and res.camera_model == "SIMPLE_PINHOLE" and not res.check.implausible
    assert res.check.cameras[0].focal == pytest.approx(true_focal, rel=0.03)
    assert res.num_registered >= 0.7 * VIEWS
    report = json.loads((tmp_path / "out" / "sfm_report.json").read_text())
    assert report["retried"] and report["camera_model_asked"] == "FULL_OPENCV"
    assert report["cameras"][0]["model"] == "SIMPLE_PINHOLE"
    assert cv2.imread(str(tmp_path / "out" / "sfm_report.png")) is not None
    cams = pycolmap.Reconstruction(tmp_path / "out" / "sparse" / "0").cameras
    assert {c.model_name for c in cams.values()} == {"SIMPLE_PINHOLE"}
    assert len(load_scene(tmp_path / "out", test_every=0).views) == res.num_registered


def test_known_camera(renders, tmp_path):
    images, true_focal = renders
    messages = []
    res = run_sfm(images, tmp_path / "out", camera_model="simple_pinhole", focal=0.9 * true_focal,
                  progress=messages.append)
    cam = res.check.cameras[0]
    assert cam.model == "SIMPLE_PINHOLE" and cam.prior_source == "given"
    assert cam.prior == pytest.approx(0.9 * true_focal)
    # held: the mapping does not refine a given focal away (even a wrong one: the user knows the lens, or not)
    assert cam.focal == pytest.approx(0.9 * true_focal, rel=1e-9) and not res.retried
    assert any(f"prior {0.9 * true_focal:.1f} px (given)" in m for m in messages)


def test_loading_a_folding_model_warns(tmp_path, capsys):
    rec = _reconstruction(tmp_path / "m", "SIMPLE_RADIAL", [99.0, 128.0, 128.0, -0.14], n=3)
    root = tmp_path / "data"
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(root / "sparse" / "0")
    (root / "images").mkdir()
    for im in rec.images.values():
        cv2.imwrite(str(root / "images" / im.name), np.full((256, 256, 3), 90, np.uint8))
    scene = load_scene(root, test_every=0)
    err = capsys.readouterr().err
    assert "warning: camera 1 of" in err and "folds back 102 px from the image centre" in err
    assert "--camera-model SIMPLE_PINHOLE" in err
    assert (scene.views[0].camera.width, scene.views[0].camera.height) == (512, 512)
