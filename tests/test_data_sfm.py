"""End-to-end SfM: `splatzoo sfm` on rendered views of a synthetic scene recovers the true cameras."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import open3d  # noqa: E402,F401  (required: a missing dependency fails rather than skips)
import pycolmap  # noqa: E402,F401

from splatzoo.data import load_scene, make_synthetic_scene, similarity_align, synthetic_cameras  # noqa: E402

VIEWS, SIZE = 20, 256


def _centres_error(views, truth) -> tuple[float, float]:
    """Largest camera-centre error after a similarity alignment, and the radius of the true centres."""
    est = np.array([v.camera.center.double().numpy() for v in views])
    true = np.array([truth[v.name].center.double().numpy() for v in views])
    s, R, t = similarity_align(est, true)
    err = np.linalg.norm(s * est @ R.T + t - true, axis=1)
    all_true = np.array([c.center.double().numpy() for c in truth.values()])
    return float(err.max()), float(np.linalg.norm(all_true - all_true.mean(0), axis=1).max())


def test_similarity_align_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    a = rng.normal(size=3)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    dst = 2.5 * src @ R.T + a
    s, R2, t = similarity_align(src, dst)
    assert np.isclose(s, 2.5) and np.allclose(R2, R) and np.allclose(t, a)


@pytest.mark.slow
def test_cli_sfm_registers_synthetic_views(tmp_path):
    from typer.testing import CliRunner

    from splatzoo.cli import app

    data = make_synthetic_scene("boots", tmp_path / "render", views=VIEWS, width=SIZE, height=SIZE, points=200)
    out = tmp_path / "sfm"
    res = CliRunner().invoke(app, ["sfm", str(data / "images"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "[3/3] incremental mapping" in res.output and "registered" in res.output
    scene = load_scene(out, test_every=0)            # SIMPLE_RADIAL: goes through the undistortion path
    assert (out / "undistorted" / "sparse").is_dir()
    assert len(scene.views) >= 0.9 * VIEWS
    assert scene.points.shape[0] > 500
    truth = {c.name: c for c in synthetic_cameras("boots", VIEWS, SIZE, SIZE)}
    err, radius = _centres_error(scene.views, truth)
    assert err < 0.02 * radius, (err, radius)


@pytest.mark.slow
def test_synth_with_sfm_aligns_to_the_true_frame(tmp_path):
    out = make_synthetic_scene("boots", tmp_path / "boots", views=12, width=192, height=192, sfm=True)
    info = json.loads((out / "scene.json").read_text())
    assert info["poses"] == "sfm" and info["sfm"]["registered"] >= 11
    scene = load_scene(out, test_every=0)
    truth = {c.name: c for c in synthetic_cameras("boots", 12, 192, 192)}
    # Already in the mesh's frame: compare without any further alignment.
    err = max(float((v.camera.center.double() - truth[v.name].center).norm()) for v in scene.views)
    assert err < 0.02 * info["radius"]
    assert scene.mesh_path is not None


@pytest.mark.slow
def test_sfm_in_place_adds_a_model_next_to_the_images(tmp_path):
    from splatzoo.data import run_sfm
    from splatzoo.errors import DataError

    data = make_synthetic_scene("boots", tmp_path / "d", views=10, width=160, height=160, points=100)
    for p in (data / "sparse", data / "masks", data / "mesh.ply", data / "scene.json"):
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    (data / "notes").mkdir()
    with pytest.raises(DataError, match="notes is empty"):
        run_sfm(data / "notes", data, progress=False)
    messages = []
    # one thread: COLMAP's multi-threaded mapping is not deterministic, and now and then registers 8 of these 10
    res = run_sfm(data / "images", data, progress=messages.append, num_threads=1)
    assert res.num_registered >= 9 and (data / "sparse" / "0" / "points3D.bin").is_file()
    assert sorted(p.name for p in data.iterdir()) == ["database.db", "images", "notes", "sfm_report.json",
                                                     "sfm_report.png", "sparse"]
    assert any("registered" in m for m in messages)
    with pytest.raises(DataError, match="already exists"):
        run_sfm(data / "images", data, progress=False)


def test_a_given_focal_is_held_in_every_pass(tmp_path):
    """`--focal F` fixes the focal length: SfM does not refine it away in the first mapping pass."""
    from splatzoo.data import run_sfm

    data = make_synthetic_scene("boots", tmp_path / "d", views=12, width=160, height=160, points=100)
    true_f = float(synthetic_cameras("boots", 12, 160, 160)[0].K[0, 0])
    given = round(true_f * 1.05, 1)  # a little off, as a focal from a spec sheet is
    res = run_sfm(data / "images", tmp_path / "out", progress=False, num_threads=1, focal=given,
                  camera_model="SIMPLE_PINHOLE")
    rec = pycolmap.Reconstruction(tmp_path / "out" / "sparse" / "0")
    assert res.num_registered >= 8
    for cam in rec.cameras.values():
        assert abs(cam.mean_focal_length() - given) < 1e-6, (cam.mean_focal_length(), given)
