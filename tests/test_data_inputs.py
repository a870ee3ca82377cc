"""Bad inputs are named: truncated images, camera models that cannot become pinhole images, and malformed Blender
transforms files each give a DataError that says which file, what is wrong and what to do."""
from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import torch

from splatzoo.data import load_scene
from splatzoo.data.camera_models import all_models, undistortable_models
from splatzoo.data.colmap import write_model
from splatzoo.data.scene import read_image
from splatzoo.data.synthetic import synthetic_cameras
from splatzoo.errors import DataError


def _photo(h=48, w=64, seed=0) -> np.ndarray:
    g = np.random.default_rng(seed)
    return cv2.GaussianBlur((g.random((h, w, 3)) * 255).astype(np.uint8), (5, 5), 1.5)


def _colmap_dataset(root: Path, n=3, w=64, h=48, ext=".png") -> tuple[Path, list]:
    cams = synthetic_cameras("plain", n, w, h)
    (root / "images").mkdir(parents=True)
    names = [Path(c.name).with_suffix(ext).name for c in cams]
    for i, name in enumerate(names):
        cv2.imwrite(str(root / "images" / name), _photo(h, w, i))
    write_model(root / "sparse" / "0", cams, names, np.zeros((4, 3)), np.full((4, 3), 0.5))
    return root, cams


def _set_camera(root: Path, model: str, params) -> None:
    sparse = root / "sparse" / "0"
    rec = pycolmap.Reconstruction(sparse)
    cam = pycolmap.Camera(model=model, width=rec.cameras[1].width, height=rec.cameras[1].height, params=list(params),
                          camera_id=1)
    rec.cameras[1].model = cam.model
    rec.cameras[1].params = list(cam.params)
    rec.write_binary(sparse)


# --- truncated images ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_truncated_image_is_named_when_the_scene_loads(tmp_path, ext):
    root, _ = _colmap_dataset(tmp_path / "d", ext=ext)
    victim = sorted((root / "images").iterdir())[1]
    whole = victim.read_bytes()
    victim.write_bytes(whole[: len(whole) // 2])         # the header survives: the size is still readable
    assert cv2.imread(str(victim)) is not None or ext == ".png"   # OpenCV decodes a cut JPEG as grey, silently
    kind = "JPEG data stops before its end-of-image marker" if ext == ".jpg" else "PNG data stops before its IEND"
    with pytest.raises(DataError, match=rf"image .*{victim.name} is truncated or damaged \(the {kind}.*Copy it again"):
        load_scene(root)
    with pytest.raises(DataError, match=rf"{victim.name} is truncated"):
        read_image(victim)                                # and again when a view is decoded
    # Padding or extra data after the end marker (some cameras append a trailer) is fine.
    victim.write_bytes(whole + b"\x00" * 7)
    load_scene(root)
    victim.write_bytes(whole + b"TRAILER" * 50)
    assert read_image(victim).shape == (48, 64, 3)


def test_truncated_image_during_blender_load(tmp_path):
    root = _blender(tmp_path / "b")
    img = root / "train" / "r_1.png"
    img.write_bytes(img.read_bytes()[:200])
    with pytest.raises(DataError, match=r"r_1.png is truncated"):
        load_scene(root)


# --- camera models ---------------------------------------------------------------------------------------------

def test_every_perspective_model_loads_and_equirectangular_is_named(tmp_path):
    root, _ = _colmap_dataset(tmp_path / "base")
    models = all_models()
    assert set(undistortable_models()) == set(models) - {"EQUIRECTANGULAR"}
    for model in models:
        d = tmp_path / model
        (d / "sparse" / "0").mkdir(parents=True)
        (d / "images").symlink_to(root / "images", target_is_directory=True)
        proto = pycolmap.Camera.create_from_model_name(1, model, 50.0, 64, 48)
        rec = pycolmap.Reconstruction(root / "sparse" / "0")
        rec.cameras[1].model = proto.model
        rec.cameras[1].params = list(proto.params)
        rec.write_binary(d / "sparse" / "0")
        if model == "EQUIRECTANGULAR":
            with pytest.raises(DataError) as e:
                load_scene(d, test_every=0)
            msg = str(e.value)
            assert "uses the EQUIRECTANGULAR camera model" in msg and "360-degree panorama" in msg
            assert f"pycolmap {pycolmap.__version__} undistorts only perspective models (SIMPLE_PINHOLE" in msg
            assert "--camera-model OPENCV" in msg and "only PINHOLE" not in msg
            continue
        scene = load_scene(d, test_every=0)
        assert len(scene.views) == 3 and scene.views[0].image().shape[2] == 3, model


@pytest.mark.parametrize("model,params", [
    ("FISHEYE", [120.0, 121.0, 48.0, 36.0]),               # no terms: pycolmap would copy it unwarped
    ("SIMPLE_RADIAL_FISHEYE", [120.0, 48.0, 36.0, 0.0]),    # zero terms: likewise
    ("SIMPLE_DIVISION", [60.0, 48.0, 36.0, -0.2]),
    ("SIMPLE_RADIAL", [60.0, 48.0, 36.0, 0.0]),             # zero terms: a pinhole camera, loaded directly
])
def test_undistorted_pixels_show_their_own_pinhole_rays(tmp_path, model, params):
    """Each pixel of the photos stores the ideal ray (x/z, y/z) of the camera model as colour: after loading, every
    pixel's colour must be the ray of that pixel under the loaded PINHOLE K."""
    w, h = 96, 72
    dcam = pycolmap.Camera(model=model, width=w, height=h, params=params, camera_id=1)
    root, cams = _colmap_dataset(tmp_path / "d", n=2, w=w, h=h)
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    ideal = dcam.cam_from_img(np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)).reshape(h, w, 2)
    scale = 0.45 / np.abs(ideal).max()
    code = np.concatenate([0.5 + scale * ideal, np.full((h, w, 1), 0.5)], 2)
    for p in (root / "images").iterdir():
        cv2.imwrite(str(p), (code[:, :, ::-1] * 255 + 0.5).astype(np.uint8))
    _set_camera(root, model, params)
    scene = load_scene(root, test_every=0)
    for v in scene.views:
        K = v.camera.K.double().numpy()
        img = v.image_float().numpy().astype(np.float64)
        vy, vx = np.mgrid[0:v.camera.height, 0:v.camera.width] + 0.5
        want = np.stack([(vx - K[0, 2]) / K[0, 0], (vy - K[1, 2]) / K[1, 1]], 2)
        got = (img[:, :, :2] - 0.5) / scale
        valid = img.sum(2) > 0.1
        assert valid.mean() > 0.7
        err_px = np.abs(got - want)[valid] * K[0, 0]
        assert err_px.mean() < 0.3 and np.percentile(err_px, 99) < 1.0, (model, err_px.mean(), err_px.max())


# --- Blender transforms ---------------------------------------------------------------------------------------

def _blender(root: Path, n: int = 2) -> Path:
    frames = []
    (root / "train").mkdir(parents=True)
    for i, cam in enumerate(synthetic_cameras("plain", n, 16, 12)):
        cv2.imwrite(str(root / "train" / f"r_{i}.png"), _photo(12, 16, i))
        c2w = torch.linalg.inv(cam.world_to_camera).numpy() @ np.diag([1.0, -1, -1, 1])
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": c2w.tolist()})
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    return root


def _edit(root: Path, change) -> Path:
    f = root / "transforms_train.json"
    meta = json.loads(f.read_text())
    change(meta)
    f.write_text(json.dumps(meta))
    return f


def _frame1(key, value):
    def change(meta):
        if value is KeyError:
            del meta["frames"][1][key]
        else:
            meta["frames"][1][key] = value
    return change


def _matrix(edit):
    def change(meta):
        m = np.asarray(meta["frames"][1]["transform_matrix"])
        meta["frames"][1]["transform_matrix"] = edit(m)
    return change


BAD_TRANSFORMS = {
    "singular": (_matrix(lambda m: (m * [[1, 1, 0, 1]] * [[1], [1], [1], [1]]).tolist()),
                 r"frame 1 transform_matrix is singular \(its 3x3 rotation part has determinant 0"),
    "nan": (_matrix(lambda m: [[float("nan") if (r, c) == (0, 3) else v for c, v in enumerate(row)]
                               for r, row in enumerate(m.tolist())]),
            r"frame 1 transform_matrix holds NaN or infinity"),
    "ragged": (_matrix(lambda m: [m[0].tolist(), m[1].tolist(), m[2, :3].tolist(), m[3].tolist()]),
               r"frame 1 transform_matrix must be 4 rows of 4 numbers .*lengths \[4, 4, 3, 4\]"),
    "flat": (_matrix(lambda m: m.ravel().tolist()), r"frame 1 transform_matrix must be a list of 4 rows"),
    "text entry": (_matrix(lambda m: [m[0].tolist(), [1, "a", 0, 0], m[2].tolist(), m[3].tolist()]),
                   r"frame 1 transform_matrix: row 1 holds 'a', not a number"),
    "scaled": (_matrix(lambda m: (m * [[2, 2, 2, 1]]).tolist()), r"frame 1 transform_matrix: its 3x3 part is not a "
                                                                   r"rotation"),
    "mirrored": (_matrix(lambda m: (m * [[-1, 1, 1, 1]]).tolist()), r"frame 1 transform_matrix is a reflection"),
    "bottom row": (_matrix(lambda m: [*m[:3].tolist(), [0, 0, 1, 1]]), r"the last row is \[0.0, 0.0, 1.0, 1.0\]"),
    "no matrix": (_frame1("transform_matrix", KeyError), r"frame 1 has no transform_matrix"),
    "null path": (_frame1("file_path", None), r"frame 1 has no file_path"),
    "no path": (_frame1("file_path", KeyError), r"frame 1 has no file_path"),
    "numeric path": (_frame1("file_path", 7), r"frame 1 file_path must be a string"),
    "frame not object": (lambda meta: meta["frames"].__setitem__(1, [1, 2]), r"frame 1 must be an object"),
    "zero angle": (lambda meta: meta.update(camera_angle_x=0), r"camera_angle_x is 0; it must be greater than 0"),
    "negative angle": (lambda meta: meta.update(camera_angle_x=-0.5), r"camera_angle_x is -0.5; it must be greater"),
    "degrees": (lambda meta: meta.update(camera_angle_x=40), r"camera_angle_x is 40; it must be less than 3.142 "
                                                             r"\(the field of view in radians"),
    "text angle": (lambda meta: meta.update(camera_angle_x="0.7"), r"camera_angle_x must be a number, not '0.7'"),
    "per-frame angle": (_frame1("camera_angle_x", float("inf")), r"frame 1: camera_angle_x is inf, not a finite"),
    "negative fl_x": (lambda meta: meta.update(fl_x=-10), r"fl_x is -10; it must be greater than 0"),
    "no focal": (lambda meta: meta.pop("camera_angle_x"), r"gives no focal length for frame 0"),
    "frames not list": (lambda meta: meta.update(frames={"a": 1}), r"'frames' must be a list of frames, not a JSON "
                                                                   r"object"),
    "no frames": (lambda meta: meta.pop("frames"), r"has no 'frames' list"),
}


@pytest.mark.parametrize("case", sorted(BAD_TRANSFORMS))
def test_malformed_blender_transforms(tmp_path, case):
    change, pattern = BAD_TRANSFORMS[case]
    root = _blender(tmp_path / "b")
    f = _edit(root, change)
    with pytest.raises(DataError, match=pattern) as e:
        load_scene(root)
    assert str(f) in str(e.value)


def test_blender_transforms_that_are_not_an_object(tmp_path):
    root = _blender(tmp_path / "b")
    (root / "transforms_train.json").write_text("[1, 2]")
    with pytest.raises(DataError, match=r"transforms_train.json must hold a JSON object with a 'frames' list, not a "
                                        r"list"):
        load_scene(root)


def test_valid_blender_variants_still_load(tmp_path):
    root = _blender(tmp_path / "b")
    _edit(root, _matrix(lambda m: m[:3].tolist()))            # 3x4 is accepted
    _edit(root, lambda meta: meta.update(camera_angle_y=None))  # null is as if absent
    scene = load_scene(root, test_every=0)
    assert len(scene.train) == 2
    assert math.isclose(float(scene.train[0].camera.K[0, 0]), 0.5 * 16 / math.tan(0.35), rel_tol=1e-5)


# --- cameras no photo can have ----------------------------------------------------------------------------------

def _colmap_with(tmp_path, edit) -> Path:
    """A 3-view COLMAP dataset whose cameras (a list of splatzoo Cameras) went through `edit` before writing."""
    root, cams = _colmap_dataset(tmp_path / "d")
    names = [Path(c.name).with_suffix(".png").name for c in cams]
    cams, names = edit(list(cams), names)
    write_model(root / "sparse" / "0", cams, names, np.zeros((4, 3)), np.full((4, 3), 0.5))
    return root


def _with_K(cam, **entries):
    K = cam.K.clone()
    for (i, j), value in ((IJ[k], v) for k, v in entries.items()):
        K[i, j] = value
    return dataclasses.replace(cam, K=K)


IJ = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}


@pytest.mark.parametrize("entries, message", [
    ({"fx": 1e-300}, "focal fx = 0 px"),  # rounded to 0 on the way
    ({"fy": 1e-3}, "focal fy = 0.001"),
    ({"fx": 1e12}, "focal fx = 1e"),
    ({"cx": 1e9}, "principal point at (1e"),
    ({"cy": -500.0}, "principal point"),
])
def test_colmap_intrinsics_no_photo_has_are_named(tmp_path, entries, message):
    root = _colmap_with(tmp_path, lambda cams, names: ([_with_K(cams[0], **entries)] + cams[1:], names))
    with pytest.raises(DataError, match=re.escape(message)):
        load_scene(root)


def test_duplicate_names_and_broken_rotations_are_named(tmp_path):
    root = _colmap_with(tmp_path, lambda cams, names: (cams, [names[0], names[0], names[2]]))
    with pytest.raises(DataError, match="two views are named"):
        load_scene(root)
    root = _blender(tmp_path / "b", n=2)
    _edit(root, _matrix(lambda m: (m @ np.diag([1.0, 2, 1, 1])).tolist()))  # a column of length 2: a shear
    with pytest.raises(DataError, match="not a rotation"):
        load_scene(root)
    _edit(root, _frame1("transform_matrix", (np.eye(4) * np.diag([1.0, 1, 1, 1])).tolist()))
    load_scene(root)  # an identity pose is fine


def test_blender_subnormal_focal_is_named(tmp_path):
    root = _blender(tmp_path / "b", n=2)
    _edit(root, lambda meta: meta.update(fl_x=5e-324, fl_y=5e-324, w=16, h=12))
    with pytest.raises(DataError, match="focal fx = 0 px"):  # a float64 > 0 that float32 makes 0
        load_scene(root)


def test_colmap_camera_sizes_that_do_not_fit_the_images(tmp_path):
    big = lambda cams, names: ([dataclasses.replace(c, width=20000, height=15000) for c in cams], names)  # noqa: E731
    with pytest.raises(DataError, match="more than 64x smaller"):
        load_scene(_colmap_with(tmp_path / "a", big))
    root = _colmap_with(tmp_path / "b", lambda cams, names: (cams, names))
    rec = pycolmap.Reconstruction(root / "sparse" / "0")
    rec.cameras[1].width = 0
    rec.write_binary(root / "sparse" / "0")
    with pytest.raises(DataError, match="is 0x48; a camera needs a size of at least 1x1"):
        load_scene(root)


def _png_header_only(w: int, h: int) -> bytes:
    """A PNG whose header claims w x h over a body of a few bytes (a crafted decompression bomb)."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * 10)) + chunk(b"IEND", b""))


def test_crafted_transforms_and_huge_image_headers_are_named(tmp_path):
    """A JSON nesting bomb, a file_path longer than the file system allows, and a PNG header claiming 20000x20000
    (over PIL's decompression-bomb limit, as a real 400 MP photo is): DataErrors that name the file, no traceback."""
    root = _blender(tmp_path / "b", n=2)
    (root / "transforms_train.json").write_text('{"frames": ' + "[" * 100000 + "]" * 100000 + "}")
    with pytest.raises(DataError, match="nests its JSON too deeply"):
        load_scene(root)
    root = _blender(tmp_path / "c", n=2)
    _edit(root, _frame1("file_path", "./train/" + "a" * 5000))
    with pytest.raises(DataError, match="cannot be looked up"):
        load_scene(root)
    root = _blender(tmp_path / "d", n=2)
    for i in range(2):
        (root / "train" / f"r_{i}.png").write_bytes(_png_header_only(20000, 20000))
    # the header is read (a real photo can be this large); the body then fails to decode, and says so
    with pytest.raises(DataError, match="r_0.png is unreadable or corrupt"):
        load_scene(root)


def test_transforms_point_cloud_and_random_start_follow_the_cameras(tmp_path):
    """nerfstudio's ply_file_path is the initial point cloud; without any, the random start is a cube around what
    the cameras look at, sized to their distance (NeRF-synthetic's [-1.3, 1.3]^3 at 4.03), and it is said."""
    from splatzoo.geometry import look_at_point

    root = _blender(tmp_path / "b", n=3)
    scene = load_scene(root)
    cams = [v.camera for v in scene.views]
    centre = look_at_point(cams).float()
    distance = float(torch.stack([(c.center.double() - centre.double()).norm() for c in cams]).mean())
    half = (scene.points - centre).abs().max()
    assert abs(float(half) - 1.3 / 4.0311 * distance) < 0.01 * distance
    assert any("random points" in n for n in scene.notes)
    # the same capture ten times larger starts from a cloud ten times larger
    big = _blender(tmp_path / "big", n=3)
    _edit(big, lambda meta: [f.update(transform_matrix=(np.asarray(f["transform_matrix"]) @ np.diag([1, 1, 1, 1.0])
                                                         * np.array([[1, 1, 1, 10]] * 3 + [[0, 0, 0, 1]])).tolist())
                             for f in meta["frames"]])
    assert float((load_scene(big).points - centre * 10).abs().max()) == pytest.approx(10 * float(half), rel=0.01)
    # a named cloud wins, and a missing one is named
    pts = np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], np.float32)
    ply = root / "sparse_pc.ply"
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\nproperty float x\nproperty float y\n" \
             "property float z\nend_header\n"
    ply.write_bytes(header.encode() + pts.tobytes())
    _edit(root, lambda meta: meta.update(ply_file_path="sparse_pc.ply"))
    scene = load_scene(root)
    assert torch.allclose(scene.points, torch.from_numpy(pts)) and not any("random" in n for n in scene.notes)
    _edit(root, lambda meta: meta.update(ply_file_path="gone.ply"))
    with pytest.raises(DataError, match="gone.ply \\(ply_file_path\\), which does not exist"):
        load_scene(root)
