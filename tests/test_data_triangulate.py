"""Posed images without a point cloud: initial points triangulated from the known poses, cached, with random points
only as a stated fallback."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from splatzoo.data import load_scene
from splatzoo.data.blender import MIN_TRIANGULATED, load_blender
from splatzoo.data.triangulate import CACHE_NAME, neighbour_pairs, triangulate_points
from splatzoo.data.synthetic import synthetic_cameras


def c2w_opengl(cam) -> list:
    return (torch.linalg.inv(cam.world_to_camera.double()).numpy() @ np.diag([1.0, -1, -1, 1])).tolist()


def as_nerfstudio(colmap_root: Path, out: Path) -> Path:
    """The synthetic COLMAP dataset's images and true cameras as a nerfstudio transforms.json, no point cloud."""
    info = json.loads((colmap_root / "scene.json").read_text())
    (out / "images").mkdir(parents=True)
    frames = []
    for c in info["cameras"]:
        (out / "images" / c["name"]).write_bytes((colmap_root / "images" / c["name"]).read_bytes())
        w2c = torch.tensor(c["world_to_camera"], dtype=torch.float64)
        frames.append({"file_path": f"images/{c['name']}",
                       "transform_matrix": (torch.linalg.inv(w2c).numpy() @ np.diag([1.0, -1, -1, 1])).tolist()})
    K = info["cameras"][0]["K"]
    meta = {"camera_model": "PINHOLE", "fl_x": K[0][0], "fl_y": K[1][1], "cx": K[0][2], "cy": K[1][2],
            "w": info["width"], "h": info["height"], "frames": frames}
    (out / "transforms.json").write_text(json.dumps(meta))
    return out


@pytest.fixture(scope="module")
def boots(tmp_path_factory):
    from splatzoo.data.synthetic import make_synthetic_scene

    base = tmp_path_factory.mktemp("tri")
    colmap = make_synthetic_scene("boots", base / "colmap", views=12, width=192, height=192, points=50)
    return colmap, as_nerfstudio(colmap, base / "ns")


def test_points_are_triangulated_on_the_surface_and_cached(boots):
    o3d = pytest.importorskip("open3d")
    colmap, data = boots
    t0 = time.perf_counter()
    scene = load_scene(data, test_every=0)
    first = time.perf_counter() - t0
    notes = [n for n in scene.notes if n.startswith("initial points")]
    assert notes and "triangulated from the known poses (12 images)" in notes[0], scene.notes
    assert not any("random points" in n for n in scene.notes)
    P, C = scene.points.numpy(), scene.colors.numpy()
    assert len(P) >= MIN_TRIANGULATED and P.dtype == np.float32 and C.shape == P.shape
    assert np.isfinite(P).all() and C.min() >= 0 and C.max() <= 1 and C.std() > 0.02   # real colours, not one grey
    mesh = o3d.t.io.read_triangle_mesh(str(colmap / "mesh.ply"))
    rays = o3d.t.geometry.RaycastingScene()
    rays.add_triangles(mesh)
    dist = rays.compute_distance(o3d.core.Tensor(P)).numpy()
    size = float(np.ptp(mesh.vertex.positions.numpy(), axis=0).max())   # the object and its floor: about 3
    assert np.median(dist) < 0.005 * size, np.median(dist)               # measured 0.0009 (size 3.0)
    assert np.percentile(dist, 90) < 0.03 * size, np.percentile(dist, 90)
    assert (data / CACHE_NAME).is_file()

    t0 = time.perf_counter()
    again = load_scene(data, test_every=0)
    assert torch.equal(again.points, scene.points) and torch.equal(again.colors, scene.colors)
    assert time.perf_counter() - t0 < max(0.5, first / 2)
    # a changed pose is a different dataset: triangulated again, not read from the stale cache
    meta = json.loads((data / "transforms.json").read_text())
    meta["frames"][0]["transform_matrix"][0][3] += 0.01
    (data / "transforms.json").write_text(json.dumps(meta))
    try:
        moved = load_scene(data, test_every=0)
        assert not torch.equal(moved.points, scene.points)
    finally:
        meta["frames"][0]["transform_matrix"][0][3] -= 0.01
        (data / "transforms.json").write_text(json.dumps(meta))


def test_random_points_on_request_and_for_nerf_synthetic_style(boots, tmp_path):
    _, data = boots
    scene = load_blender(data, test_every=0, init_points="random")
    assert len(scene.points) == 10_000 and any("init_points='random'" in n for n in scene.notes)
    with pytest.raises(Exception, match="init_points"):
        load_blender(data, init_points="sfm")
    # camera_angle_x and RGBA images: the 3DGS protocol's random start, unless triangulation is asked for
    import cv2

    nerf = tmp_path / "nerf"
    (nerf / "train").mkdir(parents=True)
    meta = json.loads((data / "transforms.json").read_text())
    frames = []
    for i, f in enumerate(meta["frames"]):
        rgb = cv2.imread(str(data / f["file_path"]))
        rgba = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], 2)
        cv2.imwrite(str(nerf / "train" / f"r_{i}.png"), rgba)
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": f["transform_matrix"]})
    angle = 2 * np.arctan(0.5 * meta["w"] / meta["fl_x"])
    (nerf / "transforms_train.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    scene = load_blender(nerf)
    assert len(scene.points) == 10_000 and any("NeRF-synthetic-style" in n for n in scene.notes), scene.notes
    scene = load_blender(nerf, init_points="triangulate")
    assert len(scene.points) >= MIN_TRIANGULATED
    assert any("triangulated from the known poses (12 images)" in n for n in scene.notes), scene.notes


def test_untextured_views_fall_back_to_random_points_with_the_reason(tmp_path):
    import cv2

    root = tmp_path / "flat"
    (root / "images").mkdir(parents=True)
    frames = []
    for i, cam in enumerate(synthetic_cameras("plain", 2, 64, 64)):
        cv2.imwrite(str(root / "images" / f"f{i}.png"), np.full((64, 64, 3), (40, 120, 200), np.uint8))
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": c2w_opengl(cam)})
    K = synthetic_cameras("plain", 2, 64, 64)[0].K
    (root / "transforms.json").write_text(json.dumps({"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "w": 64,
                                                      "h": 64, "frames": frames}))
    scene = load_scene(root, test_every=0)
    assert len(scene.points) == 10_000
    note = next(n for n in scene.notes if n.startswith("initial points"))
    assert "triangulation found only 0 points" in note and "random points" in note, note
    # the cube is sized to the cameras: about 1.3 / 4.03 of their distance to what they look at (2.8 here)
    half = float((scene.points.max(0).values - scene.points.min(0).values).max()) / 2
    assert 0.7 < half < 1.1, half


def test_neighbour_pairs_link_nearby_cameras_looking_alike():
    cams = synthetic_cameras("sweater", 60, 32, 32)
    pairs = neighbour_pairs(cams, k=8)
    assert all(i < j for i, j in pairs) and len(pairs) < 60 * 59 / 2 / 3
    linked = {i for p in pairs for i in p}
    assert linked == set(range(60))
    centres = torch.stack([c.center for c in cams]).double()
    d = [float((centres[i] - centres[j]).norm()) for i, j in pairs]
    all_d = torch.cdist(centres, centres)
    assert np.median(d) < float(all_d[all_d > 0].median())   # nearer than a random pair


def test_triangulate_points_needs_two_views(boots):
    _, data = boots
    scene = load_scene(data, test_every=0)
    with pytest.raises(Exception, match="at least 2"):
        triangulate_points(scene.train[:1])


def test_points_are_triangulated_at_the_photos_size_whatever_the_training_size(boots, capsys):
    from splatzoo.data.scene import PIXEL_CACHE
    from splatzoo.data.triangulate import working_camera

    _, data = boots
    (data / CACHE_NAME).unlink(missing_ok=True)
    PIXEL_CACHE.clear()
    small = load_scene(data, test_every=0, resolution=4)          # trained at 48x48
    assert small.train[0].camera.width == 48
    assert "triangulating from the known poses of 12 images (192x192)" in capsys.readouterr().err
    # the photos were read at their own size without filling the cache that training reads from
    assert not [k for k in PIXEL_CACHE._items if k[2] != 48]
    assert all((c.width, c.height) == (192, 192) for c in (working_camera(v) for v in small.train))
    assert [(c.width, c.height) for c in (working_camera(v, 100) for v in small.train[:1])] == [(100, 100)]
    # one triangulation for every training size
    full = load_scene(data, test_every=0, resolution=1)
    assert "reusing" in capsys.readouterr().err
    assert torch.equal(full.points, small.points) and torch.equal(full.colors, small.colors)
    # at the training size (what was done before) far fewer points are found
    at_48, _ = triangulate_points(small.train, long_side=48)
    assert len(at_48) < 0.5 * len(small.points), (len(at_48), len(small.points))
