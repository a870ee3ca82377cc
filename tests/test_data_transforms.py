"""nerfstudio / instant-ngp transforms.json: lens distortion undistorted as the COLMAP path does (and matching it),
applied_transform / applied_scale, frames with missing images (skip_missing), and the keys splatzoo does not use."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from splatzoo.data import load_scene
from splatzoo.data.camera_models import import_pycolmap
from splatzoo.data.synthetic import synthetic_cameras
from splatzoo.errors import DataError

W, H = 96, 72
FX, FY, CX, CY = 80.0, 78.0, 49.0, 35.0
OPENCV = {"k1": -0.22, "k2": 0.05, "p1": 0.002, "p2": -0.001}
FISHEYE = {"k1": 0.05, "k2": -0.01, "k3": 0.004, "k4": -0.001}


def pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth colour pattern on the normalised image plane (z = 1): what an ideal pinhole camera sees."""
    return np.stack([0.5 + 0.4 * np.sin(9 * x + 1.3 * y), 0.5 + 0.4 * np.cos(7 * y - 2 * x),
                     0.5 + 0.3 * np.sin(5 * (x + y))], -1)


def photo(cam) -> np.ndarray:
    """uint8 [h,w,3]: `pattern` seen through pycolmap camera `cam` (any model), sampled at pixel centres."""
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    xy = np.asarray(cam.cam_from_img(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)))
    rgb = pattern(xy[:, 0], xy[:, 1]).reshape(cam.height, cam.width, 3)
    return (np.clip(np.nan_to_num(rgb), 0, 1) * 255 + 0.5).astype(np.uint8)   # NaN: a pixel no ray reaches


def lens(model: str, terms: dict, w=W, h=H):
    pycolmap = import_pycolmap()
    t = {k: terms.get(k, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
    params = ([FX, FY, CX, CY, t["k1"], t["k2"], t["k3"], t["k4"]] if model == "OPENCV_FISHEYE" else
              [FX, FY, CX, CY, t["k1"], t["k2"], t["p1"], t["p2"]])
    return pycolmap.Camera(model=model, width=w, height=h, params=params, camera_id=1)


def c2w_opengl(cam) -> list:
    return (torch.linalg.inv(cam.world_to_camera.double()).numpy() @ np.diag([1.0, -1, -1, 1])).tolist()


def write_capture(root: Path, model: str = "OPENCV", terms: dict | None = None, n: int = 3, **top) -> Path:
    """A transforms.json dataset: n views of `pattern` through one distorted lens."""
    terms = OPENCV if terms is None else terms
    (root / "images").mkdir(parents=True)
    cam = lens(model, terms)
    img = photo(cam)
    frames = []
    for i, c in enumerate(synthetic_cameras("plain", n, W, H)):
        cv2.imwrite(str(root / "images" / f"f{i}.png"), img[:, :, ::-1])
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": c2w_opengl(c)})
    meta = {"camera_model": model, "fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H, **terms,
            "frames": frames, **top}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def expected(view) -> np.ndarray:
    """What the view's own (pinhole) camera sees of `pattern`, float [h,w,3]."""
    K = view.camera.K.double().numpy()
    u, v = np.meshgrid(np.arange(view.camera.width) + 0.5, np.arange(view.camera.height) + 0.5)
    return np.clip(pattern((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]), 0, 1)


@pytest.mark.parametrize("model,terms", [("OPENCV", OPENCV), ("OPENCV_FISHEYE", FISHEYE)])
def test_distorted_photos_are_undistorted_to_the_pinhole_camera_colmap_makes(tmp_path, model, terms, capsys):
    root = write_capture(tmp_path / "d", model, terms)
    scene = load_scene(root, test_every=0, background="black")
    pinhole = import_pycolmap().undistort_camera(import_pycolmap().UndistortCameraOptions(), lens(model, terms))
    for view in scene.train:
        K = view.camera.K.double().numpy()
        assert (view.camera.width, view.camera.height) == (pinhole.width, pinhole.height)
        assert np.allclose(K, pinhole.calibration_matrix(), rtol=1e-6)
        got = psnr(view.image_float().numpy(), expected(view))
        assert got > 32, "the loaded image is the undistorted one"
    assert "undistorting 3 image(s)" in capsys.readouterr().err
    assert any("3 frame(s) have lens distortion" in n for n in scene.notes)
    # the bug this replaces: the photo read as if it were pinhole with the distorted camera's K
    raw = cv2.imread(str(root / "images" / "f0.png"))[:, :, ::-1] / 255.0
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    assert psnr(raw, np.clip(pattern((u - CX) / FX, (v - CY) / FY), 0, 1)) < got - 8
    # a second load reuses the undistorted copies
    again = load_scene(root, test_every=0, background="black")
    assert "undistorting" not in capsys.readouterr().err
    assert [v.path for v in again.train] == [v.path for v in scene.train]
    # a changed photo is undistorted again (its copy's name carries what it was made from)
    cv2.imwrite(str(root / "images" / "f1.png"), np.zeros((H, W, 3), np.uint8))
    third = load_scene(root, test_every=0, background="black")
    assert "undistorting 1 image(s)" in capsys.readouterr().err
    assert float(third.train[1].image_float().max()) == 0.0
    assert len(list((root / "undistorted-transforms" / "images").glob("f1.*.png"))) == 1


def test_per_frame_intrinsics_masks_and_alpha_are_warped_too(tmp_path):
    root = write_capture(tmp_path / "d", n=2)
    meta = json.loads((root / "transforms.json").read_text())
    # frame 1 at half size with its own intrinsics written for the full size (w, h): rescaled, then undistorted
    small = cv2.resize(cv2.imread(str(root / "images" / "f1.png")), (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(root / "images" / "f1.png"), small)
    alpha = np.zeros((H, W), np.uint8)
    alpha[10:60, 20:80] = 255
    rgba = np.dstack([cv2.imread(str(root / "images" / "f0.png")), alpha])
    cv2.imwrite(str(root / "images" / "f0.png"), rgba)
    (root / "m").mkdir()
    cv2.imwrite(str(root / "m" / "mask1.png"), np.full((H // 2, W // 2), 255, np.uint8))
    meta["frames"][1]["mask_path"] = "m/mask1.png"
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(root, test_every=0, background="black", masks=True)
    v0, v1 = scene.train
    assert v1.camera.width < v0.camera.width and abs(v1.camera.K[0, 0] * 2 - v0.camera.K[0, 0]) < 1e-3
    assert psnr(v1.image_float().numpy(), expected(v1)) > 27
    m0 = v0.mask().numpy()
    assert 0.3 < m0.mean() < 0.9 and m0[0, 0] == 0 and m0[m0.shape[0] // 2, m0.shape[1] // 2] == 1
    assert v1.mask().numpy().min() > 0.99


def test_zero_terms_load_directly_and_unknown_projections_are_refused(tmp_path):
    plain = load_scene(write_capture(tmp_path / "p", "OPENCV", {}), test_every=0)
    assert plain.train[0].path.parent.name == "images"
    assert np.allclose(plain.train[0].camera.K.double().numpy(), [[FX, 0, CX], [0, FY, CY], [0, 0, 1]])
    with pytest.raises(DataError, match=r"camera_model EQUIRECTANGULAR \(a spherical 360-degree panorama\), which "
                                        r"splatzoo cannot use.*OPENCV_FISHEYE"):
        load_scene(write_capture(tmp_path / "e", "EQUIRECTANGULAR", {}))
    with pytest.raises(DataError, match=r"k4 = 0.01 for a perspective camera"):
        load_scene(write_capture(tmp_path / "k4", "OPENCV", {**OPENCV, "k4": 0.01}))
    text = write_capture(tmp_path / "s", "OPENCV", {})
    meta = json.loads((text / "transforms.json").read_text())
    meta["frames"][0]["k1"] = "0.1"
    (text / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"frame 0: k1 must be a number, not '0.1' \(a lens distortion"):
        load_scene(text)
    # instant-ngp's is_fisheye and nerfstudio's distortion_params list
    ngp = write_capture(tmp_path / "ngp", "OPENCV_FISHEYE", FISHEYE)
    meta = json.loads((ngp / "transforms.json").read_text())
    del meta["camera_model"]
    meta.update(is_fisheye=True, aabb_scale=16)
    (ngp / "transforms.json").write_text(json.dumps(meta))
    fisheye = load_scene(ngp, test_every=0)
    assert psnr(fisheye.train[0].image_float().numpy(), expected(fisheye.train[0])) > 32
    listed = write_capture(tmp_path / "l", "OPENCV", OPENCV)
    meta = json.loads((listed / "transforms.json").read_text())
    for key in OPENCV:
        del meta[key]
    meta["distortion_params"] = [OPENCV["k1"], OPENCV["k2"], 0, 0, OPENCV["p1"], OPENCV["p2"]]
    (listed / "transforms.json").write_text(json.dumps(meta))
    view = load_scene(listed, test_every=0).train[0]
    assert psnr(view.image_float().numpy(), expected(view)) > 32


def test_missing_images_stop_loading_unless_skipped(tmp_path):
    root = write_capture(tmp_path / "d", "OPENCV", {}, n=5)
    (root / "images" / "f1.png").unlink()
    (root / "images" / "f3.png").unlink()
    with pytest.raises(DataError, match=r"2 of 5 frames name an image that does not exist.*f1.png, .*f3.png.*"
                                        r"--skip-missing"):
        load_scene(root)
    scene = load_scene(root, skip_missing=True, test_every=0)
    assert [v.name for v in scene.train] == ["images/f0.png", "images/f2.png", "images/f4.png"]
    assert "transforms.json: skipped 2 frames whose images are missing: images/f1.png, images/f3.png" in scene.notes
    for name in ("f0", "f2", "f4"):
        (root / "images" / f"{name}.png").unlink()
    with pytest.raises(DataError, match=r"none of its 5 frames' images exists"):
        load_scene(root, skip_missing=True)
    with pytest.raises(DataError, match=r"skip_missing='yes' must be true or false"):
        load_scene(root, skip_missing="yes")


def test_keys_splatzoo_does_not_use_are_named_once_with_counts(tmp_path):
    root = write_capture(tmp_path / "d", "OPENCV", {}, n=3, aabb_scale=16, sharpen=0.0)
    meta = json.loads((root / "transforms.json").read_text())
    for i, f in enumerate(meta["frames"]):
        f["colmap_im_id"] = i
    meta["frames"][0]["sharpness"] = 40.0
    (root / "transforms.json").write_text(json.dumps(meta))
    notes = [n for n in load_scene(root, test_every=0).notes if "ignored" in n]
    assert notes == ["transforms.json: ignored 4 keys that splatzoo does not use: aabb_scale, sharpen, colmap_im_id "
                     "(in 3 frames), sharpness (in 1 frame)"]
    clean = write_capture(tmp_path / "c", "OPENCV", OPENCV)
    assert not [n for n in load_scene(clean, test_every=0).notes if "ignored" in n]


def _ply(path: Path, xyz: np.ndarray) -> None:
    rgb = np.full((len(xyz), 3), 200, np.uint8)
    lines = ["ply", "format ascii 1.0", f"element vertex {len(xyz)}", "property float x", "property float y",
             "property float z", "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    lines += [f"{p[0]:.7f} {p[1]:.7f} {p[2]:.7f} {c[0]} {c[1]} {c[2]}" for p, c in zip(xyz, rgb)]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("ply_frame", ["poses", "original"])
def test_applied_transform_and_scale_put_points_and_poses_in_one_frame(tmp_path, ply_frame):
    """The capture in its original frame A; transforms.json in frame B = s * T(A), as ns-process-data writes it
    (applied_transform T, applied_scale s). The point cloud, in B (nerfstudio's convention) or in A, must come out
    in B: where the loaded cameras see it where the original cameras saw the original points."""
    rng = np.random.default_rng(0)
    cams = synthetic_cameras("plain", 6, W, H)
    from splatzoo.geometry import look_at_point

    centre = look_at_point(cams).numpy()
    pts_a = centre + rng.uniform(-0.3, 0.3, (200, 3))
    angle = math.radians(30)
    T = np.array([[0, 1, 0, 4.0], [1, 0, 0, -3.0], [0, 0, -1, 2.0]], dtype=np.float64)
    T[:3, :3] = T[:3, :3] @ np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0],
                                      [0, 0, 1]])
    s = 0.5

    def to_b(p):
        return s * (p @ T[:3, :3].T + T[:3, 3])
    root = tmp_path / "d"
    (root / "images").mkdir(parents=True)
    frames = []
    for i, cam in enumerate(cams):
        c2w_a = torch.linalg.inv(cam.world_to_camera.double()).numpy()
        c2w_b = np.eye(4)
        c2w_b[:3, :3] = T[:3, :3] @ c2w_a[:3, :3]
        c2w_b[:3, 3] = to_b(c2w_a[:3, 3])
        cv2.imwrite(str(root / "images" / f"f{i}.png"), np.full((H, W, 3), 128, np.uint8))
        frames.append({"file_path": f"images/f{i}.png",
                       "transform_matrix": (c2w_b @ np.diag([1.0, -1, -1, 1])).tolist()})
    # nerfstudio multiplies the points (not the poses) by applied_scale: a cloud in B is written at 1/s
    _ply(root / "sparse_pc.ply", to_b(pts_a) / s if ply_frame == "poses" else pts_a)
    meta = {"fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H, "frames": frames,
            "ply_file_path": "sparse_pc.ply", "applied_transform": T.tolist(), "applied_scale": s}
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(root, test_every=0)
    assert np.allclose(scene.points.double().numpy(), to_b(pts_a), atol=1e-5)
    def project(w2c, K, p):
        q = p @ w2c[:3, :3].T + w2c[:3, 3]
        return (q @ K.T)[:, :2] / q[:, 2:]
    for view, cam in zip(scene.train, cams):   # each camera sees each point where it saw it in frame A
        K = cam.K.double().numpy()
        at = project(view.camera.world_to_camera.double().numpy(), K, scene.points.double().numpy())
        assert np.abs(at - project(cam.world_to_camera.double().numpy(), K, pts_a)).max() < 1e-3
    said = " | ".join(scene.notes)
    assert "records applied_transform" in said and "applied_scale 0.5" in said
    assert ("original capture's frame" in said) == (ply_frame == "original")


def test_cli_skip_missing_for_train_and_eval(tmp_path):
    from typer.testing import CliRunner

    from splatzoo.cli import app

    root = write_capture(tmp_path / "d", "OPENCV", OPENCV, n=5)
    (root / "images" / "f2.png").unlink()
    runner = CliRunner()
    run = tmp_path / "run"
    base = ["train", str(root), "--model", "2dgs", "--iterations", "4", "--num-primitives", "50", "--backend", "cpu",
            "--no-densify", "--test-every", "2", "--out", str(run)]
    r = runner.invoke(app, base)
    assert isinstance(r.exception, DataError) and "or pass --skip-missing" in str(r.exception)
    r = runner.invoke(app, base + ["--skip-missing"])
    assert r.exit_code == 0, r.output
    assert "skipped 1 frame whose images are missing: images/f2.png" in r.output
    assert json.loads((run / "config.json").read_text())["scene_options"]["skip_missing"] is True
    (root / "images" / "f3.png").unlink()     # the run recorded skip_missing: eval leaves this one out too
    r = runner.invoke(app, ["eval", str(run), "--backend", "cpu", "--lpips-net", "alex"])
    assert r.exit_code == 0, r.output
    assert "skipped 2 frames whose images are missing: images/f2.png, images/f3.png" in r.output


def write_both(colmap_root: Path, ns_root: Path, photos: list[np.ndarray], cams, distorted, points: np.ndarray,
               colors: np.ndarray) -> None:
    """One capture written twice: a COLMAP model (images/ + sparse/0 with the distorted camera) and a nerfstudio
    transforms.json (same photos, fl_x.. and k1, k2, p1, p2, ply_file_path)."""
    from splatzoo.data.colmap import write_model

    for root in (colmap_root, ns_root):
        (root / "images").mkdir(parents=True)
        for cam, px in zip(cams, photos):
            cv2.imwrite(str(root / "images" / cam.name), px[:, :, ::-1])
    sparse = write_model(colmap_root / "sparse" / "0", cams, [c.name for c in cams], points, colors)
    rec = import_pycolmap().Reconstruction(sparse)
    for cam in rec.cameras.values():
        cam.model, cam.params = distorted.model, list(distorted.params)
    rec.write_binary(str(sparse))
    fx, fy, cx, cy, k1, k2, p1, p2 = distorted.params
    frames = [{"file_path": f"images/{c.name}", "transform_matrix": c2w_opengl(c)} for c in cams]
    rgb = (np.clip(colors, 0, 1) * 255 + 0.5).astype(np.uint8)
    lines = ["ply", "format ascii 1.0", f"element vertex {len(points)}", "property float x", "property float y",
             "property float z", "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    lines += [f"{p[0]:.8f} {p[1]:.8f} {p[2]:.8f} {c[0]} {c[1]} {c[2]}" for p, c in zip(points, rgb)]
    (ns_root / "sparse_pc.ply").write_text("\n".join(lines) + "\n")
    meta = {"camera_model": "OPENCV", "w": distorted.width, "h": distorted.height, "fl_x": fx, "fl_y": fy, "cx": cx,
            "cy": cy, "k1": k1, "k2": k2, "p1": p1, "p2": p2, "frames": frames, "ply_file_path": "sparse_pc.ply"}
    (ns_root / "transforms.json").write_text(json.dumps(meta, indent=1))


def test_the_same_capture_loads_alike_from_colmap_and_from_transforms_json(tmp_path):
    import dataclasses

    cams = [dataclasses.replace(c, name=f"v{i}.png") for i, c in enumerate(synthetic_cameras("plain", 4, W, H))]
    distorted = lens("OPENCV", OPENCV)
    photos = [np.roll(photo(distorted), 7 * i, axis=1) for i in range(len(cams))]
    rng = np.random.default_rng(1)
    points, colors = rng.uniform(-0.3, 0.3, (50, 3)), rng.uniform(0, 1, (50, 3))
    write_both(tmp_path / "colmap", tmp_path / "ns", photos, cams, distorted, points, colors)
    a = load_scene(tmp_path / "colmap", test_every=0, background="black")
    b = load_scene(tmp_path / "ns", test_every=0, background="black")
    assert [v.name for v in a.train] == [Path(v.name).name for v in b.train]
    for va, vb in zip(a.train, b.train):
        ca, cb = va.camera, vb.camera
        assert (ca.width, ca.height) == (cb.width, cb.height) and ca.width != W
        for x, y in ((ca.K, cb.K), (ca.world_to_camera, cb.world_to_camera)):
            assert torch.allclose(x.double(), y.double(), rtol=1e-4, atol=1e-4 * float(x.abs().max()))
        # the same warp (pycolmap's undistorter): the same pixels, give or take rounding
        assert (va.image().int() - vb.image().int()).abs().max() <= 1
    assert torch.allclose(a.points, b.points, atol=1e-5) and torch.allclose(a.colors, b.colors, atol=1 / 255)
    assert abs(a.extent - b.extent) < 1e-4 * a.extent
    said = load_scene(tmp_path / "colmap", test_every=0, skip_missing=True).notes
    assert "skip_missing does not apply to colmap datasets: their reader leaves out no frames" in said
