"""Blender / NeRF-synthetic datasets: transforms_train.json + transforms_test.json (or one transforms.json).

Poses are camera-to-world in OpenGL axes (+y up, +z backwards); we flip the y and z camera axes to get
OpenCV. Intrinsics come from camera_angle_x (and camera_angle_y), or from fl_x/fl_y/cx/cy when given
(instant-ngp / nerfstudio style). RGBA images are composited over the scene background.

Initial points: points3d.ply in the dataset folder if present (x, y, z and optional red, green, blue);
otherwise RANDOM_POINTS points drawn uniformly in the box [-1.3, 1.3]^3 with random colours (seeded, so
loading twice gives the same cloud), the usual start for these object-centred scenes.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..errors import DataError
from ..types import Camera
from .scene import (DatasetFormat, Scene, View, camera_extent, find_mask, image_has_alpha, image_size, mesh_path_of,
                    scale_camera, split_views, target_scale)

RANDOM_POINTS = 10_000
RANDOM_BOX = 1.3
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def _read_json(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"cannot read {path}: {e}") from None
    except json.JSONDecodeError as e:
        raise DataError(f"{path} is not valid JSON (line {e.lineno}: {e.msg}); fix or re-export it") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise DataError(f"{path} has no 'frames' list; a Blender transforms file needs frames with file_path "
                        "and transform_matrix")
    if not meta["frames"]:
        raise DataError(f"{path} lists no frames; add frames or use another split file")
    return meta


def _image_path(root: Path, file_path: str, where: Path) -> Path:
    p = root / file_path
    if p.is_file():
        return p
    for ext in (".png", ".jpg", ".jpeg"):
        cand = p.with_name(p.name + ext)
        if cand.is_file():
            return cand
    raise DataError(f"image {p} (from {where}) does not exist (also tried .png/.jpg); restore it or remove the "
                    "frame from the transforms file")


def _views_from(root: Path, meta_path: Path, background, masks: bool, resolution, max_width) -> list[View]:
    meta = _read_json(meta_path)
    views = []
    size = None
    for i, frame in enumerate(meta["frames"]):
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise DataError(f"{meta_path}: frame {i} lacks file_path or transform_matrix")
        path = _image_path(root, frame["file_path"], meta_path)
        w, h = image_size(path)
        if size is None:
            size = (w, h, path)
        elif (w, h) != size[:2] and "w" not in frame and "fl_x" not in frame:
            raise DataError(f"images in {meta_path} differ in size: {size[2]} is {size[0]}x{size[1]} but {path} is "
                            f"{w}x{h}; a shared camera_angle_x needs one image size. Resize them to one size")
        get = lambda k, d=None: frame.get(k, meta.get(k, d))  # noqa: E731 (per-frame values override)
        if get("fl_x") is not None:
            fx = float(get("fl_x"))
            fy = float(get("fl_y", fx))
        elif get("camera_angle_x") is not None:
            fx = 0.5 * w / math.tan(0.5 * float(get("camera_angle_x")))
            fy = 0.5 * h / math.tan(0.5 * float(get("camera_angle_y"))) if get("camera_angle_y") else fx
        else:
            raise DataError(f"{meta_path} gives no focal length: add camera_angle_x (radians) or fl_x")
        if get("w") is not None and (int(get("w")), int(get("h", h))) != (w, h):
            fx *= w / float(get("w"))   # intrinsics written for another image size: rescale them
            fy *= h / float(get("h", h))
        cx = float(get("cx", w / 2)) * (w / float(get("w", w)))
        cy = float(get("cy", h / 2)) * (h / float(get("h", h)))
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0, 0, 0, 1]])
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise DataError(f"{meta_path}: frame {i} transform_matrix must be a finite 4x4 matrix")
        w2c = np.linalg.inv(c2w @ _OPENGL_TO_OPENCV)
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
        name = str(path.relative_to(root))
        cam = Camera(torch.from_numpy(w2c), torch.from_numpy(K), w, h, name)
        cam = scale_camera(cam, target_scale(w, h, resolution, max_width))
        mask_path = None
        if masks:
            mask_path = find_mask(root / "masks", name) if (root / "masks").is_dir() else None
            if mask_path is None and not image_has_alpha(path):
                raise DataError(f"masks requested but image {path} has no alpha channel and no mask in "
                                f"{root / 'masks'}; load without masks")
        views.append(View(camera=cam, name=name, path=path, mask_path=mask_path, use_mask=masks,
                          background=tuple(background)))
    return views


def read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """x, y, z (and red, green, blue if present) of a PLY vertex list, ascii or binary, no open3d needed."""
    types = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
    try:
        data = path.read_bytes()
        end = data.index(b"end_header") + len(b"end_header")
        end = data.index(b"\n", end) + 1
        header = data[:end].decode("ascii").splitlines()
        fmt = next(ln.split()[1] for ln in header if ln.startswith("format"))
        props, count, in_vertex = [], 0, False
        for ln in header:
            parts = ln.split()
            if parts[:1] == ["element"]:
                in_vertex = parts[1] == "vertex"
                if in_vertex:
                    count = int(parts[2])
                elif count and not props:
                    raise ValueError("vertex element must come first")
            elif parts[:1] == ["property"] and in_vertex:
                if parts[1] == "list":
                    raise ValueError("list properties on vertices are not supported")
                props.append((parts[2], types[parts[1]]))
        if fmt == "ascii":
            rows = data[end:].decode("ascii").split("\n")[:count]
            arr = np.array([[float(x) for x in r.split()[:len(props)]] for r in rows])
            table = {n: arr[:, i] for i, (n, _) in enumerate(props)}
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            dt = np.dtype([(n, order + t) for n, t in props])
            rec = np.frombuffer(data, dtype=dt, count=count, offset=end)
            table = {n: rec[n] for n, _ in props}
        xyz = np.stack([table["x"], table["y"], table["z"]], 1).astype(np.float32)
        rgb = None
        if all(k in table for k in ("red", "green", "blue")):
            rgb = np.stack([table["red"], table["green"], table["blue"]], 1).astype(np.float32)
            rgb = rgb / 255.0 if rgb.max() > 1.0 else rgb
        return xyz, rgb
    except (OSError, ValueError, KeyError, StopIteration, UnicodeDecodeError, IndexError) as e:
        raise DataError(f"cannot read points from {path} ({e}); it must be a PLY point cloud with x, y, z "
                        "vertex properties. Fix or delete it (random points are used without it)") from None


def load_blender(root, *, resolution: int | None = None, max_width: int | None = None, test_every: int = 8,
                 background=(0.0, 0.0, 0.0), masks: bool = False) -> Scene:
    """Read a Blender/NeRF-synthetic folder. With transforms_train.json the split comes from the files
    (transforms_test.json is the test set; test_every is ignored); a single transforms.json is split by
    test_every. See the module docstring for how initial points are chosen."""
    root = Path(root)
    train_file, test_file = root / "transforms_train.json", root / "transforms_test.json"
    if train_file.is_file():
        train = _views_from(root, train_file, background, masks, resolution, max_width)
        test = _views_from(root, test_file, background, masks, resolution, max_width) if test_file.is_file() else []
        train.sort(key=lambda v: v.name)
        test.sort(key=lambda v: v.name)
    else:
        views = _views_from(root, root / "transforms.json", background, masks, resolution, max_width)
        train, test = split_views(views, test_every, root)
    ply = next((p for p in (root / "points3d.ply", root / "points3D.ply") if p.is_file()), None)
    if ply is not None:
        xyz, rgb = read_ply_points(ply)
        if len(xyz) == 0:
            raise DataError(f"{ply} holds no points; delete it to start from random points")
        if rgb is None:
            rgb = np.full_like(xyz, 0.5)
    else:
        g = np.random.default_rng(0)
        xyz = (g.random((RANDOM_POINTS, 3)) * 2 - 1).astype(np.float32) * RANDOM_BOX
        rgb = g.random((RANDOM_POINTS, 3)).astype(np.float32)
    points, colors = torch.from_numpy(np.ascontiguousarray(xyz)), torch.from_numpy(np.ascontiguousarray(rgb))
    return Scene(name=root.resolve().name, root=root, train=train, test=test, points=points, colors=colors,
                 extent=camera_extent([v.camera for v in train], points), background=tuple(background),
                 mesh_path=mesh_path_of(root))


def is_blender(root: Path) -> bool:
    return (root / "transforms_train.json").is_file() or (root / "transforms.json").is_file()


# Before COLMAP: an instant-ngp / nerfstudio folder holds transforms.json next to an images/ folder.
FORMAT = DatasetFormat(
    "blender", is_blender, load_blender, priority=10,
    needs="transforms_train.json (and transforms_test.json) or one transforms.json, whose frames give each "
          "image's file_path and transform_matrix, with camera_angle_x or fl_x")
