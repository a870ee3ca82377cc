"""Data layer: COLMAP/Blender loading, undistortion, synthetic scenes, error messages and the data CLI."""
from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

# required dependencies (scripts/install.sh installs them): a missing one must fail the suite, not skip it
import cv2  # noqa: E402
import open3d  # noqa: E402,F401
import pycolmap  # noqa: E402

from splatzoo.data import View, load_scene  # noqa: E402
from splatzoo.data.colmap import write_model  # noqa: E402
from splatzoo.data.synthetic import (MeshScene, get_spec, make_synthetic_scene, render_mesh,  # noqa: E402
                                     synthetic_cameras)
from splatzoo.errors import DataError  # noqa: E402

VIEWS, W, H = 10, 80, 64


@pytest.fixture(scope="module")
def shirt(tmp_path_factory) -> Path:
    """A small synthetic COLMAP dataset (non-square on purpose, so width/height mix-ups show)."""
    return make_synthetic_scene("shirt", tmp_path_factory.mktemp("synth") / "shirt", views=VIEWS, width=W, height=H,
                                seed=3, points=800)


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _close(a: torch.Tensor, b: torch.Tensor, tol: float = 1e-6) -> bool:
    """Equal to `tol` relative to the magnitude (float32 cannot hold a 100 px focal length to 1e-6 absolute)."""
    a, b = a.double(), b.double()
    return bool(((a - b).abs() <= tol * torch.clamp(b.abs(), min=1.0)).all())


# --- round trips ---------------------------------------------------------------------------------------------

def test_synthetic_scene_layout(shirt):
    info = json.loads((shirt / "scene.json").read_text())
    assert info["name"] == "shirt" and info["views"] == VIEWS and (info["width"], info["height"]) == (W, H)
    for rel in ("images", "masks", "sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin",
                "mesh.ply"):
        assert (shirt / rel).exists(), rel
    assert len(list((shirt / "images").glob("*.png"))) == VIEWS
    assert not list(shirt.parent.glob(".*tmp*")), "temporary folders left behind"
    rec = pycolmap.Reconstruction(shirt / "sparse" / "0")
    assert rec.num_reg_images() == VIEWS and 300 <= rec.num_points3D() <= 800
    assert rec.compute_mean_track_length() >= 2


def test_colmap_binary_and_text_load_identically(shirt, tmp_path):
    text = _copy(shirt, tmp_path / "text")
    sparse = text / "sparse" / "0"
    rec = pycolmap.Reconstruction(sparse)
    for f in sparse.iterdir():
        f.unlink()
    rec.write_text(sparse)
    assert (sparse / "cameras.txt").is_file() and not (sparse / "cameras.bin").exists()

    sb, st = load_scene(shirt), load_scene(text)
    truth = {c.name: c for c in synthetic_cameras("shirt", VIEWS, W, H, seed=3)}
    assert [v.name for v in sb.views] == sorted(truth)
    assert len(sb.test) == 2 and len(sb.train) == VIEWS - 2          # index 0 and 8 of the sorted names
    for vb, vt in zip(sb.views, st.views):
        assert vb.name == vt.name
        assert vb.camera.world_to_camera.dtype == torch.float32 and vb.camera.K.dtype == torch.float32
        assert (vb.camera.width, vb.camera.height) == (W, H)
        true = truth[vb.name]
        for cam in (vb.camera, vt.camera):
            assert _close(cam.world_to_camera, true.world_to_camera)
            assert _close(cam.K, true.K)
        assert torch.equal(vb.camera.world_to_camera, vt.camera.world_to_camera)
        img = vb.image()
        assert img.dtype == torch.uint8 and img.shape == (H, W, 3)
        assert torch.equal(img, vt.image())
        disk = cv2.imread(str(shirt / "images" / vb.name))[:, :, ::-1]
        assert torch.equal(img, torch.from_numpy(disk.copy()))
        f = vb.image_float()
        assert f.dtype == torch.float32 and torch.allclose(f, img.float() / 255)
        assert torch.equal(vb.mask(), vt.mask())  # the dataset's masks/, read alike
    assert torch.equal(sb.points, st.points) and torch.equal(sb.colors, st.colors)
    assert sb.points.dtype == torch.float32 and sb.colors.min() >= 0 and sb.colors.max() <= 1
    centers = torch.stack([truth[n].center for n in sorted(truth) if n in {v.name for v in sb.train}])
    radius = float((centers - centers.mean(0)).norm(dim=1).max())
    assert math.isclose(sb.extent, 1.1 * radius, rel_tol=1e-5)
    assert sb.mesh_path == shirt / "mesh.ply"


def test_points_lie_on_the_mesh_and_project_to_their_observations(shirt):
    import open3d as o3d

    scene = load_scene(shirt)
    mesh = o3d.t.io.read_triangle_mesh(str(scene.mesh_path))
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(mesh)
    dist = rc.compute_distance(o3d.core.Tensor(scene.points.numpy())).numpy()
    assert dist.max() < 1e-3
    rec = pycolmap.Reconstruction(shirt / "sparse" / "0")
    cams = {v.name: v.camera for v in scene.views}
    for im in list(rec.images.values())[:3]:
        cam = cams[im.name]
        for p in [p for p in im.points2D if p.has_point3D()][:20]:
            X = torch.tensor([*rec.points3D[p.point3D_id].xyz, 1.0], dtype=torch.float64)
            x = cam.K.double() @ (cam.world_to_camera.double() @ X)[:3]
            assert np.allclose((x[:2] / x[2]).numpy(), p.xy, atol=1e-3)


def test_resolution_max_width_masks_and_split(shirt):
    s2 = load_scene(shirt, resolution=2)
    v = s2.train[0]
    assert (v.camera.width, v.camera.height) == (W // 2, H // 2) and v.image().shape == (H // 2, W // 2, 3)
    full = load_scene(shirt)
    assert torch.allclose(v.camera.K[:2], full.train[0].camera.K[:2] / 2)
    s3 = load_scene(shirt, max_width=40)
    assert s3.train[0].camera.width == 40 and s3.train[0].image_float().shape == (32, 40, 3)
    sm = load_scene(shirt, masks=True)
    m = sm.train[0].mask()
    assert m.dtype == torch.float32 and m.shape == (H, W) and 0 <= m.min() and m.max() == 1 and m.mean() < 0.9
    s0 = load_scene(shirt, test_every=0)
    assert len(s0.train) == VIEWS and s0.test == []
    s4 = load_scene(shirt, test_every=4)
    assert [v.name for v in s4.test] == ["view_000.png", "view_004.png", "view_008.png"]


def test_prescaled_image_folder_is_used(shirt, tmp_path):
    d = _copy(shirt, tmp_path / "pyramid")
    (d / "images_2").mkdir()
    for p in (d / "images").iterdir():
        cv2.imwrite(str(d / "images_2" / p.name), cv2.resize(cv2.imread(str(p)), (W // 2, H // 2),
                                                                interpolation=cv2.INTER_AREA))
    s = load_scene(d, resolution=2)
    assert all(v.path.parent.name == "images_2" for v in s.views)
    assert s.train[0].image().shape == (H // 2, W // 2, 3)
    assert load_scene(d, resolution=4).train[0].path.parent.name == "images"   # no images_4: resized on load


def test_view_from_tensor_composites_rgba():
    from splatzoo.types import Camera

    cam = Camera(torch.eye(4), torch.tensor([[4.0, 0, 2], [0, 4, 1.5], [0, 0, 1]]), 4, 3, "tiny")
    rgba = torch.zeros(3, 4, 4)
    rgba[..., 0] = 1.0
    rgba[0, :, 3] = 1.0          # first row opaque red, the rest transparent
    v = View.from_tensor(cam, rgba, background=(0.0, 0.0, 1.0))
    f = v.image_float()
    assert torch.allclose(f[0, 0], torch.tensor([1.0, 0, 0])) and torch.allclose(f[1, 0], torch.tensor([0.0, 0, 1]))
    assert torch.equal(v.mask(), rgba[..., 3]) and v.image()[1, 0].tolist() == [0, 0, 255]


def test_view_without_cache_budget(shirt, monkeypatch):
    from splatzoo.data.scene import PIXEL_CACHE

    PIXEL_CACHE.clear()
    monkeypatch.setenv("SPLATZOO_IMAGE_CACHE_MB", "0")
    v = load_scene(shirt).train[0]
    assert torch.equal(v.image(), v.image())
    assert PIXEL_CACHE._used == 0


def test_synthetic_is_deterministic_and_textured(tmp_path):
    a = make_synthetic_scene("sweater", tmp_path / "a", views=3, width=48, height=48, seed=1, points=100)
    b = make_synthetic_scene("sweater", tmp_path / "b", views=3, width=48, height=48, seed=1, points=100)
    for name in ("view_000.png", "view_002.png"):
        assert (a / "images" / name).read_bytes() == (b / "images" / name).read_bytes()
    spec = get_spec("sweater")
    cam = synthetic_cameras("sweater", 8, 256, 256)[0]
    rgb, cov = render_mesh(MeshScene(spec.build()), cam)
    # High frequency content: many large vertical jumps between neighbouring pixels inside the object.
    inside = (cov[1:] == 1) & (cov[:-1] == 1)
    jump = np.abs(np.diff(rgb.mean(2), axis=0))[inside]
    assert (jump > 0.15).mean() > 0.1
    plain_rgb, _ = render_mesh(MeshScene(get_spec("plain").build()), cam)
    pj = np.abs(np.diff(plain_rgb.mean(2), axis=0))[inside]
    assert (pj > 0.15).mean() < 0.01


def test_every_scene_renders(tmp_path):
    from splatzoo.data.synthetic import SCENES

    assert {"sweater", "vest", "shirt", "boots", "plain"} <= set(SCENES)
    for name, spec in SCENES.items():
        mesh = MeshScene(spec.build())
        rgb, cov = render_mesh(mesh, synthetic_cameras(name, 4, 32, 32)[1])
        assert rgb.shape == (32, 32, 3) and 0.05 < cov.mean() <= 1 and np.isfinite(rgb).all()


# --- undistortion --------------------------------------------------------------------------------------------

def test_opencv_model_is_undistorted_and_loads_as_pinhole(tmp_path):
    """Images taken through a strongly distorted OPENCV camera, whose pixels store their own ideal (pinhole)
    ray coordinates as colour: after load_scene undistorts them, every pixel's colour must equal the ray of
    that pixel under the loaded PINHOLE K. Skipping or botching the undistortion is off by up to ~10 px."""
    n, w, h = 4, 96, 72
    params = [60.0, 62.0, 47.0, 37.0, -0.25, 0.05, 0.002, -0.001]
    dcam = pycolmap.Camera(model="OPENCV", width=w, height=h, params=params, camera_id=1)
    root = tmp_path / "distorted"
    (root / "images").mkdir(parents=True)
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    ideal = dcam.cam_from_img(np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)).reshape(h, w, 2)
    assert np.abs(ideal).max() < 1.2
    code = np.concatenate([0.5 + 0.4 * ideal, np.full((h, w, 1), 0.5)], 2)     # smooth: resamples exactly
    cams = synthetic_cameras("plain", n, w, h)
    (root / "masks").mkdir()
    for cam in cams:
        cv2.imwrite(str(root / "images" / cam.name), (code[:, :, ::-1] * 255 + 0.5).astype(np.uint8))
        cv2.imwrite(str(root / "masks" / cam.name), np.where(ideal[:, :, 0] > 0, 255, 0).astype(np.uint8))
    sparse = root / "sparse" / "0"
    write_model(sparse, cams, [c.name for c in cams], np.zeros((4, 3)), np.full((4, 3), 0.5))
    rec = pycolmap.Reconstruction(sparse)   # swap the PINHOLE camera for the distorted one
    rec.cameras[1].model = pycolmap.CameraModelId.OPENCV
    rec.cameras[1].params = params
    rec.write_binary(sparse)
    assert pycolmap.Reconstruction(sparse).cameras[1].model_name == "OPENCV"

    scene = load_scene(root, test_every=0)
    und = root / "undistorted"
    copies = {p: p.stat().st_mtime_ns for p in (und / "images").glob("*.png")}
    assert len(copies) == n
    truth = {c.name: c for c in cams}
    for v in scene.views:
        assert v.path.is_relative_to(und)
        assert _close(v.camera.world_to_camera, truth[v.name].world_to_camera)
        K = v.camera.K.double().numpy()
        img = v.image_float().numpy().astype(np.float64)
        assert img.shape == (v.camera.height, v.camera.width, 3)
        vy, vx = np.mgrid[0:v.camera.height, 0:v.camera.width] + 0.5
        want = np.stack([(vx - K[0, 2]) / K[0, 0], (vy - K[1, 2]) / K[1, 1]], 2)
        got = (img[:, :, :2] - 0.5) / 0.4
        valid = img.sum(2) > 0.1                   # pixels outside the source image are black
        assert valid.mean() > 0.8
        err_px = np.abs(got - want)[valid] * K[0, 0]
        assert err_px.mean() < 0.3 and np.percentile(err_px, 99) < 1.0, (err_px.mean(), err_px.max())
        raw = (code[:, :, :2] - 0.5) / 0.4       # what the distorted image claims, read as if pinhole
        plain_err = np.abs(raw - np.stack([(xs - params[2]) / params[0], (ys - params[3]) / params[1]], 2))
        assert plain_err.max() * params[0] > 5    # the distortion is large enough to matter
    masked = load_scene(root, test_every=0, masks=True)     # the masks are undistorted by the same map
    assert {p: p.stat().st_mtime_ns for p in (und / "images").glob("*.png")} == copies, "copies should be reused"
    v = masked.views[0]
    assert v.mask_path.is_relative_to(und)
    K = v.camera.K.double().numpy()
    right = (np.arange(v.camera.width) + 0.5 - K[0, 2]) / K[0, 0] > 0       # x_ideal > 0 in the pinhole image
    agree = ((v.mask().numpy() > 0.5) == right[None, :])[v.image_float().numpy().sum(2) > 0.1]
    assert agree.mean() > 0.97
    # A changed camera makes new copies (and removes the old ones).
    rec.cameras[1].params = [*params[:4], -0.2, 0.05, 0.002, -0.001]
    rec.write_binary(sparse)
    load_scene(root, test_every=0)
    remade = list((und / "images").glob("*.png"))
    assert len(remade) == n and not set(remade) & set(copies)


# --- Blender ---------------------------------------------------------------------------------------------------

def test_blender_dataset(tmp_path):
    name, n, w, h = "vest", 6, 40, 40
    mesh = MeshScene(get_spec(name).build())
    cams = synthetic_cameras(name, n, w, h)
    root = tmp_path / "blender"
    fov = 2 * math.atan(0.5 * w / float(cams[0].K[0, 0]))
    renders = {}
    for split, sel in (("train", cams[:4]), ("test", cams[4:])):
        (root / split).mkdir(parents=True)
        frames = []
        for i, cam in enumerate(sel):
            rgb, cov = render_mesh(mesh, cam)
            rgba = np.concatenate([rgb / np.maximum(cov, 1e-6)[..., None], cov[..., None]], 2)
            px = (np.clip(rgba, 0, 1) * 255 + 0.5).astype(np.uint8)
            cv2.imwrite(str(root / split / f"r_{i}.png"), px[:, :, [2, 1, 0, 3]])
            renders[f"{split}/r_{i}.png"] = (cam, px)
            c2w = torch.linalg.inv(cam.world_to_camera).numpy() @ np.diag([1.0, -1, -1, 1])  # OpenCV -> OpenGL
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
    scene = load_scene(root, background=(1.0, 1.0, 1.0), masks=True)
    assert len(scene.train) == 4 and len(scene.test) == 2
    assert scene.points.shape == (10_000, 3) and scene.points.abs().max() <= 1.3
    for v in scene.views:
        cam, px = renders[v.name]
        assert _close(v.camera.world_to_camera, cam.world_to_camera, 1e-5)
        assert _close(v.camera.K, cam.K, 1e-5)
        a = px[:, :, 3:].astype(np.float32) / 255
        want = px[:, :, :3].astype(np.float32) / 255 * a + (1 - a)
        assert np.abs(v.image_float().numpy() - want).max() < 2.5 / 255
        assert np.abs(v.mask().numpy() - a[:, :, 0]).max() < 1e-6
        assert v.image().dtype == torch.uint8
    # Poses survive the OpenGL -> OpenCV flip: the mesh centre projects into every image, in front.
    for v in scene.views:
        pc = v.camera.world_to_camera.double() @ torch.tensor([0.0, 0, 0, 1], dtype=torch.float64)
        x = v.camera.K.double() @ pc[:3]
        assert pc[2] > 0 and 0 < x[0] / x[2] < w and 0 < x[1] / x[2] < h


def test_single_transforms_json_uses_test_every(tmp_path):
    root = tmp_path / "ngp"
    (root / "images").mkdir(parents=True)
    frames = []
    for i, cam in enumerate(synthetic_cameras("plain", 9, 16, 12)):
        cv2.imwrite(str(root / "images" / f"{i:02d}.png"), np.full((12, 16, 3), 128, np.uint8))
        c2w = torch.linalg.inv(cam.world_to_camera).numpy() @ np.diag([1.0, -1, -1, 1])
        frames.append({"file_path": f"images/{i:02d}.png", "transform_matrix": c2w.tolist()})
    K = cam.K.double()
    meta = {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": 8.0, "cy": 6.0, "w": 16, "h": 12, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    s = load_scene(root, test_every=4)
    assert [v.name for v in s.test] == ["images/00.png", "images/04.png", "images/08.png"] and len(s.train) == 6
    assert _close(s.train[0].camera.K, cam.K)


def test_blender_errors(tmp_path):
    root = tmp_path / "bl"
    root.mkdir()
    (root / "transforms_train.json").write_text("{not json")
    with pytest.raises(DataError, match="not valid JSON"):
        load_scene(root)
    (root / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.7, "frames": [{"file_path": "./train/r_0", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(DataError, match=r"r_0.*does not exist"):
        load_scene(root)


# --- error messages ------------------------------------------------------------------------------------------

def test_missing_empty_and_unrecognised_folders(tmp_path):
    with pytest.raises(DataError, match=r"nope does not exist"):
        load_scene(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"empty.* is empty"):
        load_scene(tmp_path / "empty")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("hi")
    with pytest.raises(DataError, match=r"not a dataset.*splatzoo sfm"):
        load_scene(tmp_path / "junk")


def test_colmap_layout_errors(shirt, tmp_path):
    d = _copy(shirt, tmp_path / "noimages")
    shutil.rmtree(d / "images")
    with pytest.raises(DataError, match=r"no images/ folder"):
        load_scene(d)
    for f in (d / "sparse" / "0").iterdir():
        f.unlink()
    (d / "images").mkdir()
    with pytest.raises(DataError, match=r"images is empty"):
        load_scene(d)
    cv2.imwrite(str(d / "images" / "a.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(DataError, match=r"no sparse model.*splatzoo sfm"):
        load_scene(d)
    d2 = _copy(shirt, tmp_path / "missing")
    (d2 / "images" / "view_003.png").unlink()
    with pytest.raises(DataError, match=r"missing from .*view_003.png"):
        load_scene(d2)


def test_corrupt_images(shirt, tmp_path):
    d = _copy(shirt, tmp_path / "corrupt")
    (d / "images" / "view_002.png").write_bytes(b"this is not a png")
    with pytest.raises(DataError, match=r"view_002.png is unreadable or corrupt"):
        load_scene(d)
    d2 = _copy(shirt, tmp_path / "truncated")
    data = (d2 / "images" / "view_002.png").read_bytes()
    (d2 / "images" / "view_002.png").write_bytes(data[: len(data) // 2])   # header fine, pixels cut off
    with pytest.raises(DataError, match=r"view_002.png is truncated or damaged"):     # named when loading
        load_scene(d2, test_every=0)
    d3 = _copy(shirt, tmp_path / "damaged")
    scene = load_scene(d3, test_every=0, background="black")  # auto would decode (and cache) border samples
    (d3 / "images" / "view_002.png").write_bytes(data[:40] + bytes(len(data) - 40))   # zeroed after loading
    view = next(v for v in scene.views if v.name == "view_002.png")
    with pytest.raises(DataError, match=r"view_002.png is (unreadable or corrupt|truncated or damaged)"):
        view.image()


def test_image_size_mismatch_within_a_camera(shirt, tmp_path):
    d = _copy(shirt, tmp_path / "sizes")
    img = cv2.imread(str(d / "images" / "view_005.png"))
    cv2.imwrite(str(d / "images" / "view_005.png"), cv2.resize(img, (W // 2, H // 2)))
    with pytest.raises(DataError, match=r"differ in size.*view_005.png is 40x32"):
        load_scene(d)
    # Every image shrunk alike is fine: the intrinsics follow.
    for p in (d / "images").iterdir():
        cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), (W // 2, H // 2)))
    s = load_scene(d)
    assert s.train[0].camera.width == W // 2 and torch.allclose(s.train[0].camera.K[0, 0],
                                                                   load_scene(shirt).train[0].camera.K[0, 0] / 2)
    for p in (d / "images").iterdir():
        cv2.imwrite(str(p), np.zeros((H, W // 2, 3), np.uint8))
    with pytest.raises(DataError, match=r"different aspect ratio"):
        load_scene(d)


def test_model_without_points_or_registered_images(shirt, tmp_path):
    cams = synthetic_cameras("shirt", VIEWS, W, H, seed=3)
    d = _copy(shirt, tmp_path / "nopoints")
    shutil.rmtree(d / "sparse")
    write_model(d / "sparse" / "0", cams, [c.name for c in cams])
    with pytest.raises(DataError, match=r"no 3D points.*splatzoo sfm"):
        load_scene(d)
    shutil.rmtree(d / "sparse")
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[50, 50, 40, 32],
                                                    camera_id=1))
    (d / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(d / "sparse" / "0")
    with pytest.raises(DataError, match=r"no registered images"):
        load_scene(d)
    (d / "sparse" / "0" / "images.bin").write_bytes(b"\x01\x02")
    with pytest.raises(DataError, match=r"cannot read COLMAP model .*sparse/0"):
        load_scene(d)


def test_option_errors(shirt):
    with pytest.raises(DataError, match=r"test_every=1"):
        load_scene(shirt, test_every=1)
    with pytest.raises(DataError, match=r"resolution=3"):
        load_scene(shirt, resolution=3)
    with pytest.raises(DataError, match=r"masks requested.*no alpha channel"):
        load_scene(_no_masks(shirt), masks=True)


def _no_masks(shirt: Path) -> Path:
    d = shirt.parent / "nomasks"
    if not d.exists():
        shutil.copytree(shirt, d, ignore=shutil.ignore_patterns("masks"))
    return d


def test_unknown_scene_and_existing_output(tmp_path):
    with pytest.raises(DataError, match=r"unknown synthetic scene 'shrit'.*sweater, vest, shirt, boots, plain"
                                        r".*Did you mean 'shirt'"):
        make_synthetic_scene("shrit", tmp_path / "x")
    assert not (tmp_path / "x").exists()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(DataError, match=r"full already exists.*--overwrite"):
        make_synthetic_scene("vest", tmp_path / "full", views=2, width=16, height=16)
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"


def test_failure_leaves_nothing_half_written(tmp_path, monkeypatch):
    import splatzoo.data.synthetic as synthetic

    def boom(*a, **k):
        raise DataError("disk full (simulated)")
    monkeypatch.setattr(synthetic, "_write_mesh", boom)
    with pytest.raises(DataError, match="simulated"):
        make_synthetic_scene("vest", tmp_path / "out", views=2, width=16, height=16)
    assert list(tmp_path.iterdir()) == []


def test_sfm_input_errors(tmp_path):
    from splatzoo.data.sfm import run_sfm

    with pytest.raises(DataError, match=r"photos does not exist"):
        run_sfm(tmp_path / "photos", tmp_path / "out", progress=False)
    (tmp_path / "photos").mkdir()
    with pytest.raises(DataError, match=r"photos is empty"):
        run_sfm(tmp_path / "photos", tmp_path / "out", progress=False)
    cv2.imwrite(str(tmp_path / "photos" / "a.png"), np.zeros((8, 8, 3), np.uint8))
    (tmp_path / "photos" / "b.png").write_bytes(b"garbage")
    with pytest.raises(DataError, match=r"b.png is unreadable or corrupt"):
        run_sfm(tmp_path / "photos", tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


# --- CLI and imports ------------------------------------------------------------------------------------------

def test_cli_synth(tmp_path):
    from typer.testing import CliRunner

    from splatzoo.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["synth", "--list"])
    assert res.exit_code == 0
    for name in ("sweater", "vest", "shirt", "boots", "plain"):
        assert name in res.output
    out = tmp_path / "cli"
    res = runner.invoke(app, ["synth", "boots", "--out", str(out), "--views", "4", "--width", "32", "--height",
                              "24", "--seed", "2"])
    assert res.exit_code == 0, res.output
    assert "rendered 4/4" in res.output
    s = load_scene(out, test_every=0)
    assert len(s.train) == 4 and s.train[0].image().shape == (24, 32, 3)
    res = runner.invoke(app, ["synth", "nosuch", "--out", str(tmp_path / "y")])
    assert isinstance(res.exception, DataError) and "known scenes" in str(res.exception)
    res = runner.invoke(app, ["synth"])
    assert res.exit_code != 0 and "--list" in res.output


def test_cli_sfm_error_is_one_line(tmp_path):
    from typer.testing import CliRunner

    from splatzoo.cli import app

    res = CliRunner().invoke(app, ["sfm", str(tmp_path / "none"), "--out", str(tmp_path / "o")])
    assert isinstance(res.exception, DataError) and "does not exist" in str(res.exception)
    proc = subprocess.run([sys.executable, "-m", "splatzoo.cli", "sfm", str(tmp_path / "none"), "--out",
                           str(tmp_path / "o")], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.startswith("error: image folder") and "Traceback" not in proc.stderr


def test_import_splatzoo_stays_light():
    code = ("import sys, splatzoo, splatzoo.data, splatzoo.cli; "
            "print(sorted(m for m in ('open3d', 'pycolmap', 'cv2') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
