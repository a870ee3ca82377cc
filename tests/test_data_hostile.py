"""Hostile datasets: lens calibrations that leave nothing to train on, NaN camera parameters, a file where the
undistorted copies go, a fisheye flag on a perspective model and masks a transforms file names but lacks are each
refused by name (or warned about with the fix), alike on the transforms.json and the COLMAP paths."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from splatzoo.data import load_scene
from splatzoo.data.camera_models import MIN_REGION, WARN_REGION, import_pycolmap, undistorted_region
from splatzoo.data.scene import MissingMaskError
from splatzoo.data.synthetic import synthetic_cameras
from splatzoo.errors import DataError

W, H = 96, 72
FX, FY, CX, CY = 80.0, 78.0, 49.0, 35.0


def lens(model: str, terms: dict):
    t = {k: terms.get(k, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
    params = ([FX, FY, CX, CY, t["k1"], t["k2"], t["k3"], t["k4"]] if model == "OPENCV_FISHEYE" else
              [FX, FY, CX, CY, t["k1"], t["k2"], t["p1"], t["p2"]])
    return import_pycolmap().Camera(model=model, width=W, height=H, params=params, camera_id=1)


def c2w_opengl(cam) -> list:
    return (torch.linalg.inv(cam.world_to_camera.double()).numpy() @ np.diag([1.0, -1, -1, 1])).tolist()


def write_capture(root: Path, model: str, terms: dict, n: int = 3, colmap: bool = False) -> Path:
    """n textured photos through one lens, as a transforms.json dataset or (colmap=True) a COLMAP one."""
    from splatzoo.data.colmap import write_model

    (root / "images").mkdir(parents=True)
    cams = synthetic_cameras("plain", n, W, H)
    rng = np.random.default_rng(0)
    names = [f"f{i}.png" for i in range(n)]
    for name in names:
        cv2.imwrite(str(root / "images" / name), (rng.random((H, W, 3)) * 255).astype(np.uint8))
    if colmap:
        points = rng.uniform(-0.3, 0.3, (20, 3))
        sparse = write_model(root / "sparse" / "0", cams, names, points, rng.uniform(0, 1, (20, 3)))
        rec = import_pycolmap().Reconstruction(sparse)
        distorted = lens(model, terms)
        for cam in rec.cameras.values():
            cam.model, cam.params = distorted.model, list(distorted.params)
        rec.write_binary(str(sparse))
        return root
    frames = [{"file_path": f"images/{name}", "transform_matrix": c2w_opengl(c)} for name, c in zip(names, cams)]
    meta = {"camera_model": model, "fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H, **terms,
            "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


ABSURD = [("OPENCV", {"k1": 1e6}), ("OPENCV", {"p1": 1e3, "p2": 1e3}),
          ("OPENCV_FISHEYE", {"k1": 1e3, "k2": 1e3, "k3": 1e3, "k4": 1e3}), ("OPENCV", {"k1": 1e300})]


@pytest.mark.parametrize("colmap", [False, True], ids=["transforms", "colmap"])
@pytest.mark.parametrize("model,terms", ABSURD, ids=["k1", "p1p2", "fisheye", "k1-huge"])
def test_a_lens_that_leaves_too_little_to_train_on_is_refused_by_name(tmp_path, model, terms, colmap, capsys):
    root = write_capture(tmp_path / "d", model, terms, colmap=colmap)
    w, h = undistorted_region(lens(model, terms))
    assert min(w / W, h / H) < MIN_REGION       # what pycolmap would crop to without its 0.2x floor
    with pytest.raises(DataError) as e:
        load_scene(root, test_every=0)
    msg = str(e.value)
    who = "camera 1 of" if colmap else "transforms.json: frame 0 (images/f0.png)"
    if colmap:
        assert "(used by 3 images, e.g. f0.png)" in msg
    assert who in msg, msg
    assert f"leaves a valid undistorted region of {w}x{h} px of its {W}x{H} photo" in msg, msg
    assert "too little to train on" in msg and "distortion coefficients are wrong" in msg
    assert ("Check its parameters; if SfM fitted them, re-run it" if colmap else
            "Check the distortion coefficients") in msg
    first = next(iter(terms))
    assert f"{first} {terms[first]:.4g}" in msg                    # the coefficient is named with its value
    # refused before anything was warped or written
    assert not (root / "undistorted").exists() and not (root / "undistorted-transforms").exists()
    assert "ghost rings" not in capsys.readouterr().err


@pytest.mark.parametrize("colmap", [False, True], ids=["transforms", "colmap"])
def test_strong_distortion_warns_with_the_fix_and_a_real_lens_does_not(tmp_path, colmap, capsys):
    strong = {"k1": 1.0}                       # corners pushed out 50%: no real lens, but something is left
    w, h = undistorted_region(lens("OPENCV", strong))
    assert MIN_REGION <= min(w / W, h / H) < WARN_REGION
    scene = load_scene(write_capture(tmp_path / "a", "OPENCV", strong, colmap=colmap), test_every=0)
    assert (scene.train[0].camera.width, scene.train[0].camera.height) == (w, h)
    err = capsys.readouterr().err
    assert "warning: " in err and f"leaves a valid undistorted region of {w}x{h} px of its {W}x{H} photo" in err
    assert "distortion coefficients are probably wrong" in err, err
    real = {"k1": -0.22, "k2": 0.05, "p1": 0.002, "p2": -0.001}
    load_scene(write_capture(tmp_path / "b", "OPENCV", real, colmap=colmap), test_every=0)
    assert "warning" not in capsys.readouterr().err


def test_non_finite_camera_parameters_are_refused_on_both_paths(tmp_path):
    for k, value in (("k1", float("nan")), ("p2", float("inf"))):
        root = write_capture(tmp_path / f"c{k}", "OPENCV", {k: value}, colmap=True)
        with pytest.raises(DataError, match=rf"camera 1 of .* its camera \(OPENCV\) has {k} {value}: parameters must "
                                            "be finite numbers; check its parameters"):
            load_scene(root, test_every=0)   # pycolmap itself would take a NaN term for zero: loaded as a pinhole
        root = write_capture(tmp_path / f"t{k}", "OPENCV", {k: value})
        with pytest.raises(DataError, match=rf"{k} is {value}, not a finite number \(a lens distortion coefficient; "
                                            "fix it"):
            load_scene(root, test_every=0)


def test_a_file_where_the_undistorted_copies_go_is_named(tmp_path):
    root = write_capture(tmp_path / "t", "OPENCV", {"k1": 0.05})
    (root / "undistorted-transforms").write_text("notes\n")
    with pytest.raises(DataError, match=r"undistorted-transforms is a file, but splatzoo keeps the undistorted copies "
                                        r".* move or delete that file"):
        load_scene(root, test_every=0)
    assert (root / "undistorted-transforms").read_text() == "notes\n"
    (root / "undistorted-transforms").unlink()
    (root / "undistorted-transforms").mkdir()
    (root / "undistorted-transforms" / "images").write_text("notes\n")
    with pytest.raises(DataError, match=r"undistorted-transforms/images is a file where splatzoo needs a folder; move "
                                        "or delete that file"):
        load_scene(root, test_every=0)
    root = write_capture(tmp_path / "c", "OPENCV", {"k1": 0.05}, colmap=True)
    (root / "undistorted").write_text("notes\n")
    with pytest.raises(DataError, match=r"undistorted is a file, but splatzoo keeps the undistorted copies .* move "
                                        "or delete that file"):
        load_scene(root, test_every=0)
    assert (root / "undistorted").read_text() == "notes\n"
    assert not [p.name for p in root.iterdir() if p.name.startswith(".undistorted")]


def test_an_older_splatzoo_s_whole_undistorted_copy_is_removed_and_nothing_else(tmp_path, monkeypatch, capsys):
    """COLMAP datasets were once undistorted as a whole (images/, sparse/, source.json); the per-photo copies replace
    that copy, in the dataset and, for a read-only dataset, in the cache, and leave other folders alone."""
    import splatzoo.data.undistort as undistort

    def older_copy(folder: Path, source: Path) -> None:
        (folder / "images").mkdir(parents=True)
        (folder / "sparse" / "0").mkdir(parents=True)
        (folder / "images" / "f0.png").write_bytes(b"old")
        (folder / "sparse" / "0" / "cameras.bin").write_bytes(b"old")
        (folder / "source.json").write_text(json.dumps({"stamp": "0" * 40, "from": str(source)}))

    root = write_capture(tmp_path / "d", "OPENCV", {"k1": 0.05}, colmap=True)
    older_copy(root / "undistorted", root)
    scene = load_scene(root, test_every=0)
    kept = sorted(p.relative_to(root / "undistorted").as_posix() for p in (root / "undistorted").rglob("*")
                  if p.is_file())
    assert len(kept) == 3 and all(undistort.STAMPED.fullmatch(k.split("/")[-1]) for k in kept), kept
    assert "removed 3 file(s) of an older undistorted copy" in capsys.readouterr().err
    assert sorted(str(v.path) for v in scene.train) == sorted(str(root / "undistorted" / k) for k in kept)

    cache = tmp_path / "cache"
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    other, access = tmp_path / "o", undistort.os.access
    monkeypatch.setattr(undistort.os, "access", lambda p, mode: Path(p) != other and access(p, mode))  # read-only
    other = write_capture(other, "OPENCV", {"k1": 0.05}, colmap=True)
    older_copy(cache / "splatzoo" / "undistorted" / "aaaaaaaaaaaaaaaa", other)   # this dataset's, from before
    older_copy(cache / "splatzoo" / "undistorted" / "bbbbbbbbbbbbbbbb", root)    # another dataset's
    (cache / "splatzoo" / "undistorted" / "cccccccccccccccc").mkdir()            # not the older layout's
    load_scene(other, test_every=0)
    left = sorted(p.name for p in (cache / "splatzoo" / "undistorted").iterdir())
    assert "aaaaaaaaaaaaaaaa" not in left and {"bbbbbbbbbbbbbbbb", "cccccccccccccccc"} < set(left) and len(left) == 3
    assert "removed 3 file(s)" in capsys.readouterr().err


def _edited(root: Path, edit) -> dict:
    """The transforms.json of `root` after `edit(meta)`, written back."""
    meta = json.loads((root / "transforms.json").read_text())
    edit(meta)
    (root / "transforms.json").write_text(json.dumps(meta))
    return meta


def _refusal(root: Path) -> str:
    with pytest.raises(DataError) as e:
        load_scene(root, test_every=0)
    return str(e.value)


def test_a_fisheye_flag_on_a_perspective_model_names_the_conflict(tmp_path):
    root = write_capture(tmp_path / "d", "OPENCV", {"k1": 0.05})
    meta = _edited(root, lambda m: m.update(is_fisheye=True))
    msg = _refusal(root)
    assert ("frame 0 is marked is_fisheye: true (at the top of the file) but its camera_model is OPENCV (at the top of "
            "the file), a perspective model; the two disagree") in msg, msg
    assert "set camera_model to OPENCV_FISHEYE" in msg and "remove is_fisheye or set it to false" in msg
    assert "cannot use" not in msg
    meta["frames"][1]["camera_model"] = "PINHOLE"
    meta["camera_model"] = "OPENCV_FISHEYE"
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"frame 1 is marked is_fisheye: true \(at the top of the file\) but its "
                                        r"camera_model is PINHOLE \(in the frame\)"):
        load_scene(root, test_every=0)


def test_a_fisheye_model_marked_not_fisheye_names_the_conflict(tmp_path):
    root = write_capture(tmp_path / "d", "OPENCV_FISHEYE", {"k1": 0.05})
    meta = _edited(root, lambda m: m["frames"][2].update(is_fisheye=False))
    msg = _refusal(root)
    assert ("frame 2 is marked is_fisheye: false (in the frame) but its camera_model is OPENCV_FISHEYE (at the top of "
            "the file), a fisheye model; the two disagree") in msg, msg
    assert "remove is_fisheye or set it to true" in msg and "set camera_model to OPENCV" in msg
    del meta["frames"][2]["is_fisheye"]
    meta["is_fisheye"] = True   # agreeing flags load
    (root / "transforms.json").write_text(json.dumps(meta))
    assert len(load_scene(root, test_every=0).train) == len(meta["frames"])


def test_masks_a_transforms_file_names_are_used_and_missing_ones_refused_unless_skipped(tmp_path):
    root = write_capture(tmp_path / "d", "PINHOLE", {}, n=4)
    meta = json.loads((root / "transforms.json").read_text())
    (root / "cutouts").mkdir()                 # not masks/: found through mask_path alone
    for i, frame in enumerate(meta["frames"]):
        frame["mask_path"] = f"cutouts/{i}.png"
        mask = np.zeros((H, W), np.uint8)
        mask[10:60, 20:80] = 255
        cv2.imwrite(str(root / "cutouts" / f"{i}.png"), mask)
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(root, test_every=0)     # masks="auto"
    assert all(v.use_mask and v.mask_path is not None for v in scene.train)
    assert 0.3 < float(scene.train[0].mask().mean()) < 0.7
    (root / "cutouts" / "2.png").unlink()
    with pytest.raises(MissingMaskError) as e:
        load_scene(root, test_every=0)
    msg = str(e.value)
    assert (f"1 of 4 frames name a mask (mask_path) that does not exist (also tried .png/.jpg/.jpeg): frame 2 "
            f"(images/f2.png): {root / 'cutouts' / '2.png'}") in msg, msg
    assert "--skip-missing" in msg
    scene = load_scene(root, test_every=0, skip_missing=True)
    assert [v.name for v in scene.train] == ["images/f0.png", "images/f1.png", "images/f3.png"]
    assert "transforms.json: skipped 1 frame whose masks are missing: images/f2.png (mask cutouts/2.png)" in scene.notes
    # with a masks/ folder too (where an incomplete folder is left out with a note), a named mask still must exist
    (root / "masks").mkdir()
    with pytest.raises(MissingMaskError):
        load_scene(root, test_every=0)
    # masks=False asks for none: mask_path is not looked at
    assert len(load_scene(root, test_every=0, masks=False).train) == 4


def test_a_folder_where_the_triangulation_cache_goes_is_named(tmp_path, capsys):
    from splatzoo.data.triangulate import CACHE_NAME

    root = write_capture(tmp_path / "d", "PINHOLE", {})
    (root / CACHE_NAME).mkdir()
    load_scene(root, test_every=0)
    err = capsys.readouterr().err
    assert f"warning: cannot keep the triangulated points in {root / CACHE_NAME}" in err, err
    assert "move or delete what is there" in err


def test_one_fold_warning_for_both_dataset_paths():
    """The COLMAP and transforms.json paths warn about a lens that folds back inside the photo with one text
    (camera_models.fold_warning), naming who and the fix each path gives."""
    import pycolmap

    from splatzoo.data.camera_models import fold_warning

    folding = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 100.0, 200, 200)
    folding.params = [100.0, 100.0, 100.0, -0.5]  # k1 = -0.5: the image turns back inside the photo
    text = fold_warning(folding, "camera 1 of sparse/0", "Re-run SfM")
    assert text is not None and text.startswith("camera 1 of sparse/0 (SIMPLE_RADIAL:") and "folds back" in text
    assert "ghost rings" in text and text.endswith("Re-run SfM")
    plain = pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", 100.0, 200, 200)
    assert fold_warning(plain, "frame_0001.png", "Check it") is None
