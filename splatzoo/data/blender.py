"""Blender / NeRF-synthetic datasets: transforms_train.json + transforms_test.json (or one transforms.json).

Poses are camera-to-world in OpenGL axes (+y up, +z backwards); we flip the y and z camera axes to get
OpenCV. Intrinsics come from camera_angle_x (and camera_angle_y), or from fl_x/fl_y/cx/cy when given
(instant-ngp / nerfstudio style). RGBA images are composited over the scene background.

Initial points: the PLY named by the transforms file's ply_file_path (nerfstudio), else points3d.ply in the
dataset folder if present (x, y, z and optional red, green, blue); otherwise, as a stated fallback, RANDOM_POINTS
points with random colours (seeded, so loading twice gives the same cloud) drawn uniformly in a cube around the point
the cameras look at, of half-size RANDOM_BOX_PER_DISTANCE x their mean distance to it: [-1.3, 1.3]^3 for the
NeRF-synthetic scenes (cameras 4.03 from the origin), and the same proportion at any other scale.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..errors import DataError
from ..io import ply_type_name, read_ply_vertices
from ..types import Camera
from .scene import (DatasetFormat, Scene, View, camera_extent, find_mask, image_has_alpha, image_size, mesh_path_of,
                    scale_camera, split_views, target_scale)

RANDOM_POINTS = 10_000
RANDOM_BOX_PER_DISTANCE = 1.3 / 4.0311  # NeRF-synthetic's [-1.3, 1.3]^3 box for its cameras 4.03 from the origin
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def _read_json(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"cannot read {path}: {e}") from None
    except json.JSONDecodeError as e:
        raise DataError(f"{path} is not valid JSON (line {e.lineno}: {e.msg}); fix or re-export it") from None
    except RecursionError:
        raise DataError(f"{path} nests its JSON too deeply to be a transforms file; fix or re-export it") from None
    if not isinstance(meta, dict):
        raise DataError(f"{path} must hold a JSON object with a 'frames' list, not a {_json_type(meta)}; a Blender "
                        "transforms file is {\"camera_angle_x\": ..., \"frames\": [...]}")
    if "frames" not in meta:
        raise DataError(f"{path} has no 'frames' list; a Blender transforms file needs frames with file_path "
                        "and transform_matrix")
    if not isinstance(meta["frames"], list):
        raise DataError(f"{path}: 'frames' must be a list of frames, not a {_json_type(meta['frames'])}")
    if not meta["frames"]:
        raise DataError(f"{path} lists no frames; add frames or use another split file")
    return meta


def _json_type(value) -> str:
    return {dict: "JSON object", list: "list", str: "string", bool: "boolean", type(None): "null"}.get(
        type(value), "number")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_finite(value) -> bool:
    """A number that a float64 holds and that is not NaN or infinity (JSON integers can be any size)."""
    return abs(value) <= 1.7976931348623157e308 and math.isfinite(value)


def _option(frame: dict, meta: dict, key: str, where: str, i: int, *, positive: bool = False,
            below: float | None = None, hint: str = "") -> float | None:
    """A per-frame value (or, failing that, the file's), checked: a finite number, > 0 if `positive`, < `below`.
    Absent or null: None."""
    if frame.get(key) is not None:
        value, at = frame[key], f"{where}: frame {i}"
    elif meta.get(key) is not None:
        value, at = meta[key], where
    else:
        return None
    if not _is_number(value):
        raise DataError(f"{at}: {key} must be a number, not {value!r:.60}{hint}")
    if not _is_finite(value):
        raise DataError(f"{at}: {key} is {str(value)[:40]}, not a finite number{hint}")
    if positive and value <= 0:
        raise DataError(f"{at}: {key} is {value}; it must be greater than 0{hint}")
    if below is not None and value >= below:
        raise DataError(f"{at}: {key} is {value}; it must be less than {below:.4g}{hint}")
    return float(value)


_ANGLE_HINT = " (the field of view in radians, between 0 and pi; 40 degrees is 0.698)"


def _pose(frame: dict, where: str, i: int) -> np.ndarray:
    """The frame's camera-to-world matrix as 4x4 float64, or a DataError saying what is wrong with it."""
    at = f"{where}: frame {i} transform_matrix"
    m = frame.get("transform_matrix")
    if m is None:
        raise DataError(f"{where}: frame {i} has no transform_matrix (its 4x4 camera-to-world matrix); add it or "
                        "remove the frame")
    if not isinstance(m, list) or not all(isinstance(row, list) for row in m):
        raise DataError(f"{at} must be a list of 4 rows of 4 numbers, not {m!r:.60}")
    lengths = [len(row) for row in m]
    if lengths not in ([4, 4, 4, 4], [4, 4, 4]):
        raise DataError(f"{at} must be 4 rows of 4 numbers (or 3 rows of 4); its rows have lengths {lengths}")
    for r, row in enumerate(m):
        bad = next((v for v in row if not _is_number(v)), "ok")
        if bad != "ok":
            raise DataError(f"{at}: row {r} holds {bad!r:.40}, not a number")
    if not all(_is_finite(v) for row in m for v in row):
        raise DataError(f"{at} holds NaN or infinity (or a number too large for a float); re-export the camera poses")
    c2w = np.asarray(m, dtype=np.float64)
    if c2w.shape == (3, 4):
        c2w = np.vstack([c2w, [0, 0, 0, 1]])
    if not np.allclose(c2w[3], [0, 0, 0, 1], atol=1e-6):
        raise DataError(f"{at}: the last row is {c2w[3].tolist()}, not [0, 0, 0, 1]; it is not a camera pose")
    R = c2w[:3, :3]
    det = float(np.linalg.det(R))
    if abs(det) < 1e-6:
        raise DataError(f"{at} is singular (its 3x3 rotation part has determinant {det:.3g}); the camera has no "
                        "orientation. Re-export the camera poses")
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > 1e-3:
        raise DataError(f"{at}: its 3x3 part is not a rotation (columns not unit length and perpendicular: off by "
                        f"{err:.3g}); remove any scale from the cameras and re-export")
    if det < 0:
        raise DataError(f"{at} is a reflection (determinant {det:.3g}), not a rotation; the camera axes must be "
                        "right-handed. Re-export the camera poses")
    return c2w


def _image_path(root: Path, file_path: str, where: Path) -> Path:
    p = root / file_path
    try:
        if p.is_file():
            return p
        for ext in (".png", ".jpg", ".jpeg"):
            cand = p.with_name(p.name + ext)
            if cand.is_file():
                return cand
    except OSError as e:  # a name longer than the file system allows, ...
        raise DataError(f"image path {str(p)[:120]}... (from {where}) cannot be looked up ({e.strerror or e}); "
                        "fix the frame's file_path") from None
    raise DataError(f"image {p} (from {where}) does not exist (also tried .png/.jpg); restore it or remove the "
                    "frame from the transforms file")


def _views_from(root: Path, meta_path: Path, background, masks: bool, resolution, max_width) -> list[View]:
    meta = _read_json(meta_path)
    views = []
    size = None
    for i, frame in enumerate(meta["frames"]):
        if not isinstance(frame, dict):
            raise DataError(f"{meta_path}: frame {i} must be an object with file_path and transform_matrix, not "
                            f"{frame!r:.60}")
        file_path = frame.get("file_path")
        if file_path is None or file_path == "":
            raise DataError(f"{meta_path}: frame {i} has no file_path (the image's path relative to {root}); add it "
                            "or remove the frame")
        if not isinstance(file_path, str):
            raise DataError(f"{meta_path}: frame {i} file_path must be a string (a path relative to {root}), not "
                            f"{file_path!r:.60}")
        c2w = _pose(frame, meta_path, i)
        path = _image_path(root, file_path, meta_path)
        w, h = image_size(path)
        if size is None:
            size = (w, h, path)
        elif (w, h) != size[:2] and "w" not in frame and "fl_x" not in frame:
            raise DataError(f"images in {meta_path} differ in size: {size[2]} is {size[0]}x{size[1]} but {path} is "
                            f"{w}x{h}; a shared camera_angle_x needs one image size. Resize them to one size")

        def get(key, **check):  # per-frame values override the file's
            return _option(frame, meta, key, meta_path, i, **check)
        fx, fy = get("fl_x", positive=True), get("fl_y", positive=True)
        angle_x = get("camera_angle_x", positive=True, below=math.pi, hint=_ANGLE_HINT)
        angle_y = get("camera_angle_y", positive=True, below=math.pi, hint=_ANGLE_HINT)
        if fx is not None:
            fy = fy if fy is not None else fx
        elif angle_x is not None:
            fx = 0.5 * w / math.tan(0.5 * angle_x)
            fy = 0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None else fx
        else:
            raise DataError(f"{meta_path} gives no focal length for frame {i}: add camera_angle_x (radians) or fl_x")
        fw, fh = get("w", positive=True), get("h", positive=True)
        fw, fh = fw or w, fh or h
        if (fw, fh) != (w, h):
            fx *= w / fw   # intrinsics written for another image size: rescale them
            fy *= h / fh
        cx = (get("cx") if get("cx") is not None else fw / 2) * (w / fw)
        cy = (get("cy") if get("cy") is not None else fh / 2) * (h / fh)
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
    """x, y, z (float32 [N,3]) and, if present, red, green, blue (float32 [N,3] in [0,1]) of a PLY vertex list, ASCII or
    binary, no open3d needed. Positions must be float or double properties; colours may be integers (uchar: 0..255)
    or floats (0..1, or 0..255). The file is read by splatzoo.io.read_ply_vertices: its counts must match its body."""
    fix = "Fix or delete it (random points are used without it)"
    arr, _ = read_ply_vertices(path, fix=fix, error=DataError)
    names = arr.dtype.names
    missing = [k for k in ("x", "y", "z") if k not in names]
    if missing:
        raise DataError(f"cannot read points from {path}: it has no {', '.join(missing)} vertex properties; a point "
                        f"cloud is a PLY with x, y, z vertex properties. {fix}")
    for k in ("x", "y", "z"):
        if arr.dtype[k].kind != "f":
            raise DataError(f"{path}: {k} is stored as {ply_type_name(arr.dtype[k])}; point positions are float or "
                            f"double properties. {fix}")
    xyz = np.stack([arr["x"], arr["y"], arr["z"]], 1).astype(np.float64)
    if not np.isfinite(xyz).all() or np.abs(xyz).max(initial=0) > np.finfo(np.float32).max:
        bad = int(np.count_nonzero(~np.isfinite(xyz).all(1) | (np.abs(xyz) > np.finfo(np.float32).max).any(1)))
        raise DataError(f"{path}: {bad} point(s) have a non-finite or out-of-range position (NaN, infinity or beyond "
                        f"float32); the file is damaged. {fix}")
    rgb = None
    if all(k in names for k in ("red", "green", "blue")):
        rgb = np.stack([arr["red"], arr["green"], arr["blue"]], 1).astype(np.float64)
        kinds = {arr.dtype[k].kind for k in ("red", "green", "blue")}
        if kinds <= {"u", "i"}:  # integer colours span their type: uchar 0..255, ushort 0..65535
            rgb = rgb / max(np.iinfo(arr.dtype[k]).max for k in ("red", "green", "blue"))
        elif rgb.size and np.isfinite(rgb).all() and rgb.max() > 1.0:
            rgb = rgb / 255.0
        if not np.isfinite(rgb).all() or (rgb.size and (rgb.min() < 0 or rgb.max() > 1)):
            raise DataError(f"{path}: its colours (red, green, blue) are not all in 0..255 (integers) or 0..1 "
                            f"(floats); the file is damaged. {fix}")
    return xyz.astype(np.float32), None if rgb is None else rgb.astype(np.float32)


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
    notes = []
    ply = _named_ply(root, train_file if train_file.is_file() else root / "transforms.json")
    if ply is None:
        ply = next((p for p in (root / "points3d.ply", root / "points3D.ply") if p.is_file()), None)
    if ply is not None:
        xyz, rgb = read_ply_points(ply)
        if len(xyz) == 0:
            raise DataError(f"{ply} holds no points; delete it to start from random points")
        if rgb is None:
            rgb = np.full_like(xyz, 0.5)
    else:
        xyz, rgb, note = _random_points([v.camera for v in train + test])
        notes.append(note)
    points, colors = torch.from_numpy(np.ascontiguousarray(xyz)), torch.from_numpy(np.ascontiguousarray(rgb))
    return Scene(name=root.resolve().name, root=root, train=train, test=test, points=points, colors=colors,
                 extent=camera_extent([v.camera for v in train], points), background=tuple(background),
                 mesh_path=mesh_path_of(root), notes=notes)


def _named_ply(root: Path, meta_path: Path) -> Path | None:
    """The point cloud the transforms file names (nerfstudio's ply_file_path, relative to the dataset), if any."""
    name = _read_json(meta_path).get("ply_file_path")
    if name is None:
        return None
    if not isinstance(name, str) or not name:
        raise DataError(f"{meta_path}: ply_file_path must be a path relative to {root}, not {name!r:.60}")
    path = root / name
    try:
        found = path.is_file()
    except OSError as e:
        raise DataError(f"{meta_path}: ply_file_path {name[:120]!r} cannot be looked up ({e.strerror or e})") from None
    if not found:
        raise DataError(f"{meta_path} names the point cloud {path} (ply_file_path), which does not exist; restore it "
                        "or remove the key to start from random points")
    return path


def _random_points(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray, str]:
    """RANDOM_POINTS seeded random points and colours in a cube around what the cameras look at, sized to them."""
    from ..geometry import look_at_point

    centre = look_at_point(cameras) if len(cameras) > 1 else torch.zeros(3, dtype=torch.float64)
    distance = float(torch.stack([(c.center.double() - centre).norm() for c in cameras]).mean())
    half = RANDOM_BOX_PER_DISTANCE * distance if math.isfinite(distance) and distance > 0 else 1.3
    g = np.random.default_rng(0)
    xyz = ((g.random((RANDOM_POINTS, 3)) * 2 - 1) * half + centre.numpy()).astype(np.float32)
    rgb = g.random((RANDOM_POINTS, 3)).astype(np.float32)
    where = ", ".join(f"{x:.3g}" for x in centre.tolist())
    return xyz, rgb, (f"no point cloud (points3d.ply or the transforms file's ply_file_path): starting from "
                      f"{RANDOM_POINTS} random points in a cube of half-size {half:.3g} around ({where}), what the "
                      "cameras look at")


def is_blender(root: Path) -> bool:
    return (root / "transforms_train.json").is_file() or (root / "transforms.json").is_file()


# Before COLMAP: an instant-ngp / nerfstudio folder holds transforms.json next to an images/ folder.
FORMAT = DatasetFormat(
    "blender", is_blender, load_blender, priority=10,
    needs="transforms_train.json (and transforms_test.json) or one transforms.json, whose frames give each "
          "image's file_path and transform_matrix, with camera_angle_x or fl_x")
