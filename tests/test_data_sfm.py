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
    assert all(v.path.is_relative_to(out / "undistorted") for v in scene.views)
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


# --- which pairs are matched --------------------------------------------------------------------------------------

def test_auto_matching_chooses_by_count_and_names():
    from splatzoo.data.sfm import EXHAUSTIVE_MAX, choose_matching

    few = [f"IMG_{i:04d}.JPG" for i in range(EXHAUSTIVE_MAX)]
    assert choose_matching(few).strategy == "exhaustive"
    frames = [f"frame_{i:04d}.jpg" for i in range(EXHAUSTIVE_MAX + 1)]
    seq = choose_matching(frames)
    assert seq.strategy == "sequential" and "numbered in sequence" in seq.reason
    unpadded = [f"shot{i}.png" for i in range(60)]           # by number, not as text: shot2 before shot10
    assert choose_matching(unpadded).order[:3] == ["shot0.png", "shot1.png", "shot2.png"]
    rng = np.random.default_rng(0)
    unordered = [f"{''.join(rng.choice(list('abcdefgh'), 6))}.jpg" for _ in range(EXHAUSTIVE_MAX + 1)]
    assert choose_matching(unordered).strategy == "vocabtree"
    mixed = [f"a_{i}.jpg" for i in range(30)] + [f"b_{i}.jpg" for i in range(30)]
    assert choose_matching(mixed).strategy == "vocabtree"
    video = choose_matching(["frame_01.jpg", "frame_02.jpg", "frame_03.jpg"], video=True)
    assert (video.strategy, video.reason) == ("sequential", "frames of a video")
    assert choose_matching(unordered, "Exhaustive").strategy == "exhaustive"   # case does not matter
    assert choose_matching(frames, "vocabtree").strategy == "vocabtree"       # an explicit choice is kept


def test_unknown_matching_strategy_is_a_named_error(tmp_path):
    from typer.testing import CliRunner

    from splatzoo.cli import app
    from splatzoo.data.sfm import choose_matching
    from splatzoo.errors import DataError

    with pytest.raises(DataError, match="unknown matching strategy 'exhaustiv' \\(did you mean exhaustive\\?\\)"):
        choose_matching(["a.jpg", "b.jpg"], "exhaustiv")
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(2):
        _png(photos / f"p{i}.png", i)
    res = CliRunner().invoke(app, ["sfm", str(photos), "--out", str(tmp_path / "o"), "--matching", "sequentail"])
    assert isinstance(res.exception, DataError) and "did you mean sequential" in str(res.exception)
    assert not (tmp_path / "o").exists()


def _png(path, seed, size=64):
    from PIL import Image

    Image.fromarray(np.random.default_rng(seed).integers(0, 255, (size, size, 3), dtype=np.uint8)).save(path)


def test_spatial_matching_refuses_photos_without_gps(tmp_path):
    from PIL import Image

    from splatzoo.data import run_sfm
    from splatzoo.errors import DataError

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        _png(photos / f"p{i}.png", i)
    with pytest.raises(DataError, match="none of the 3 photos .* carries GPS"):
        run_sfm(photos, tmp_path / "o", matching="spatial", progress=False)
    exif = Image.Exif()
    exif.get_ifd(0x8825).update({1: "N", 2: (52.0, 31.0, 0.0), 3: "E", 4: (13.0, 24.0, 0.0), 5: 0, 6: 35.0})
    Image.open(photos / "p0.png").convert("RGB").save(photos / "p0.jpg", exif=exif)
    (photos / "p0.png").unlink()
    with pytest.raises(DataError, match="only 1 of 3 photos"):
        run_sfm(photos, tmp_path / "o", matching="spatial", progress=False)
    assert not (tmp_path / "o").exists()


def test_sequential_pairs_follow_the_order_given():
    from splatzoo.data.sfm import sequential_pairs

    pairs = sequential_pairs(list("abcdef"), overlap=2)
    assert pairs == [("a", "b"), ("a", "c"), ("b", "c"), ("b", "d"), ("c", "d"), ("c", "e"), ("d", "e"), ("d", "f"),
                     ("e", "f")]
    many = sequential_pairs(list(range(100)))       # next 10, and 2^k-th neighbours up to 512 ahead
    assert (0, 64) in many and (0, 11) not in many and len(many) == len(set(many))


@pytest.fixture(scope="module")
def orbit_db(tmp_path_factory):
    """SIFT features of 14 frames along an orbit, in a COLMAP database (no matches yet)."""
    from PIL import Image

    from splatzoo.data.colmap import quiet_colmap
    from splatzoo.data.video import orbit_frames

    root = tmp_path_factory.mktemp("orbit")
    (root / "images").mkdir()
    for cam, rgb in orbit_frames("boots", 14, 160, 120):
        Image.fromarray(rgb).save(root / "images" / cam.name)
    db = root / "database.db"
    opts = pycolmap.FeatureExtractionOptions()
    opts.use_gpu = False
    with quiet_colmap(2):
        pycolmap.extract_features(db, root / "images", camera_mode=pycolmap.CameraMode.SINGLE,
                                  extraction_options=opts, device=pycolmap.Device.cpu)
    return root


def test_pair_plans_for_each_strategy(orbit_db, tmp_path, monkeypatch):
    from splatzoo.data import sfm
    from splatzoo.data.scene import list_images

    names = list_images(orbit_db / "images")
    db = orbit_db / "database.db"
    messages = []

    def plan(matching, **kw):
        choice = sfm.choose_matching(names, matching, video=kw.pop("video", False))
        return sfm.plan_pairs(choice, db, tmp_path / "work", say=messages.append, **kw)

    choice, pairs = plan("exhaustive")
    assert len(pairs) == 14 * 13 // 2
    choice, pairs = plan("sequential")
    ids = sfm.image_ids(db)
    rank = {ids[str(n)]: k for k, n in enumerate(sorted(names))}
    gaps = sorted({abs(rank[a] - rank[b]) for a, b in pairs})
    assert {1, 2, 10} <= set(gaps)
    assert any("loop closure" in m for m in messages)         # a vocabulary tree was built and queried
    assert (tmp_path / "work" / "vocab_tree.bin").is_file()
    tree = tmp_path / "work" / "vocab_tree.bin"
    choice, pairs = plan("vocabtree", vocab_tree=tree)        # a given tree is used as it is
    assert choice.strategy == "vocabtree" and 0 < len(pairs) <= 14 * 13 // 2

    # a pycolmap that cannot build a tree: vocabtree asked is a named error that says how to give one; auto falls back
    def cannot_build(*a, **k):
        raise sfm.VocabTreeError("this pycolmap cannot build a vocabulary tree; pass --vocab-tree PATH")
    monkeypatch.setattr(sfm, "build_vocab_tree", cannot_build)
    with pytest.raises(sfm.VocabTreeError, match="--vocab-tree PATH"):
        plan("vocabtree")
    messages.clear()
    choice, pairs = sfm.plan_pairs(sfm.MatchingChoice("vocabtree", "many photos", sorted(map(str, names)), "auto"),
                                   db, tmp_path / "work", say=messages.append)
    assert choice.strategy == "sequential"                    # numbered names: in their order (else exhaustive)
    assert any("note: no vocabulary tree" in m and "matching sequential instead" in m for m in messages)
    choice, pairs = plan("sequential", video=True)           # sequential goes on without loop closure
    assert choice.strategy == "sequential" and any("without loop closure" in m for m in messages)
    with pytest.raises(sfm.VocabTreeError, match="is not a file"):
        plan("vocabtree", vocab_tree=tmp_path / "nowhere.bin")


def test_matching_a_pair_list_with_spaces_in_names(orbit_db, tmp_path):
    """COLMAP's pair lists are 'name1 name2' lines: photos whose names hold spaces go by an alias while matching."""
    from splatzoo.data import sfm

    db = tmp_path / "database.db"
    shutil.copy(orbit_db / "database.db", db)
    d = pycolmap.Database.open(str(db))
    names_before = {}
    for im in d.read_all_images():
        im.name = im.name.replace("_", " ")
        names_before[im.image_id] = im.name
        d.update_image(im)
    d.close()
    ids = sorted(names_before)
    sfm.match_pairs(db, [(ids[0], ids[1]), (ids[1], ids[2])], tmp_path / "work")
    d = pycolmap.Database.open(str(db))
    try:
        assert {im.image_id: im.name for im in d.read_all_images()} == names_before
        assert d.num_verified_image_pairs() == 2
    finally:
        d.close()


def test_spatial_matching_pairs_photos_by_their_gps(tmp_path):
    from PIL import Image

    from splatzoo.data import sfm
    from splatzoo.data.colmap import quiet_colmap

    (tmp_path / "images").mkdir()
    for i in range(3):   # a few metres apart
        exif = Image.Exif()
        exif.get_ifd(0x8825).update({1: "N", 2: (52.0, 31.0, 0.1 * i), 3: "E", 4: (13.0, 24.0, 0.0), 5: 0, 6: 35.0})
        _png(tmp_path / "p.png", i, 96)
        Image.open(tmp_path / "p.png").save(tmp_path / "images" / f"p{i}.jpg", exif=exif)
    sfm.check_spatial(tmp_path / "images", ["p0.jpg", "p1.jpg", "p2.jpg"])
    opts = pycolmap.FeatureExtractionOptions()
    opts.use_gpu = False
    with quiet_colmap(2):
        pycolmap.extract_features(tmp_path / "db.db", tmp_path / "images", extraction_options=opts,
                                  device=pycolmap.Device.cpu)
    choice, pairs = sfm.plan_pairs(sfm.choose_matching(["p0.jpg", "p1.jpg", "p2.jpg"], "spatial"), tmp_path / "db.db",
                                   tmp_path / "work")
    assert choice.strategy == "spatial" and len(pairs) == 3
