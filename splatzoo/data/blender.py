"""Blender / NeRF-synthetic datasets: transforms_train.json + transforms_test.json (or one transforms.json).

Poses are camera-to-world in OpenGL axes (+y up, +z backwards); we flip the y and z camera axes to get
OpenCV. Intrinsics come from camera_angle_x (and camera_angle_y), or from fl_x/fl_y/cx/cy when given
(instant-ngp / nerfstudio style). RGBA images are composited over the scene background.

Initial points: the PLY named by the transforms file's ply_file_path (nerfstudio), else points3d.ply in the
dataset folder if present (x, y, z and optional red, green, blue). Without one (init_points="auto"), points are
triangulated from the training images and their known poses (data/triangulate.py: SIFT matches, poses held fixed;
cached in DATA/triangulated_points.npz), except for NeRF-synthetic-style objects (camera_angle_x, no fl_x, RGBA
images), which start from random points as the 3DGS protocol does. Random points are also the stated fallback when
triangulation fails or finds fewer than MIN_TRIANGULATED points (init_points="random" asks for them, "triangulate"
triangulates NeRF-synthetic-style data too): RANDOM_POINTS points with random colours (seeded, so loading twice
gives the same cloud) drawn uniformly in a cube around the point the cameras look at, of half-size
RANDOM_BOX_PER_DISTANCE x their mean distance to it: [-1.3, 1.3]^3 for the NeRF-synthetic scenes (cameras 4.03
from the origin), and the same proportion at any other scale. scene.notes says which start was taken and why.

nerfstudio / instant-ngp additions, all read at the top level or per frame (a frame's value wins):
- lens distortion: camera_model (nerfstudio: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV,
  OPENCV_FISHEYE; instant-ngp: is_fisheye) with k1, k2, k3, k4, p1, p2 (or nerfstudio's distortion_params list).
  Distorted photos are undistorted as the COLMAP path does (splatzoo.data.undistort: pycolmap's undistorter, the same
  PINHOLE camera, the same crop) into DATA/undistorted-transforms/ (masks and alpha too), once; later loads reuse the
  files. A projection that is not perspective (EQUIRECTANGULAR, ...) is refused by name, and so is a lens whose
  undistorted photos would keep under half the photo's width or height (a warning under 80%: camera_models.check_lens,
  as the COLMAP path).
- applied_transform / applied_scale: see _points_frame (how the point cloud is put in the frames' frame).
- frames whose image is missing stop loading with an error that names them and the skip_missing option
  (--skip-missing); with it they are left out and scene.notes says which. So do frames whose mask_path names a mask
  that does not exist, when masks are read (masks="auto" reads them when any frame names a mask_path).
- keys splatzoo does not use (aabb_scale, sharpen, depth_file_path, ...) are listed once in scene.notes.
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
from .scene import (DatasetFormat, MissingMaskError, Scene, View, camera_extent, check_cameras, find_mask,
                    image_has_alpha, image_size, mesh_path_of, scale_camera, split_views, target_scale)

RANDOM_POINTS = 10_000
MIN_TRIANGULATED = 100     # fewer triangulated points than this: random points instead
INIT_POINTS = ("auto", "triangulate", "random")
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
_TERM_HINT = " (a lens distortion coefficient; fix it, or remove it for a lens without that term)"


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


def _image_path(root: Path, file_path: str, where: Path) -> Path | None:
    """The image a frame names (trying .png/.jpg/.jpeg after a bare name, as NeRF-synthetic writes them), or None."""
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
    return None


# --- what a transforms file may hold ------------------------------------------------------------------------------

DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")   # nerfstudio's order, as in its distortion_params list
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "camera_model",
                   "is_fisheye", "distortion_params", *DISTORTION_KEYS)
USED_KEYS = frozenset({"frames", "ply_file_path", "applied_transform", "applied_scale", *_INTRINSIC_KEYS})
USED_FRAME_KEYS = frozenset({"file_path", "transform_matrix", "mask_path", *_INTRINSIC_KEYS})
# nerfstudio camera_model -> the COLMAP model its photos are undistorted with (None: a pinhole camera unless k/p are
# given, as nerfstudio reads any perspective camera with its distortion terms)
PERSPECTIVE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
FISHEYE_MODELS = ("OPENCV_FISHEYE",)
UNDISTORTED_DIR = "undistorted-transforms"


def _camera_model(frame: dict, meta: dict, where: Path, i: int) -> str:
    """PERSPECTIVE or FISHEYE for a frame, or a DataError naming a projection splatzoo cannot train on."""
    model = frame.get("camera_model", meta.get("camera_model"))
    fisheye = frame.get("is_fisheye", meta.get("is_fisheye"))
    if fisheye not in (None, True, False):
        raise DataError(f"{where}: frame {i}: is_fisheye must be true or false, not {fisheye!r:.60}")
    if model is None:
        return "FISHEYE" if fisheye else "PERSPECTIVE"
    if not isinstance(model, str):
        raise DataError(f"{where}: camera_model must be a name such as OPENCV, not {model!r:.60}")
    at = {k: "in the frame" if k in frame else "at the top of the file" for k in ("is_fisheye", "camera_model")}
    if model in PERSPECTIVE_MODELS and not fisheye:
        return "PERSPECTIVE"
    if model in PERSPECTIVE_MODELS:
        raise DataError(f"{where}: frame {i} is marked is_fisheye: true ({at['is_fisheye']}) but its camera_model is "
                        f"{model} ({at['camera_model']}), a perspective model; the two disagree. For a fisheye lens "
                        "set camera_model to OPENCV_FISHEYE (distortion k1..k4); otherwise remove is_fisheye or set "
                        "it to false")
    if model in FISHEYE_MODELS and fisheye is False:
        raise DataError(f"{where}: frame {i} is marked is_fisheye: false ({at['is_fisheye']}) but its camera_model is "
                        f"{model} ({at['camera_model']}), a fisheye model; the two disagree. For a fisheye lens remove "
                        "is_fisheye or set it to true; for a perspective lens set camera_model to OPENCV (or PINHOLE)")
    if model in FISHEYE_MODELS:
        return "FISHEYE"
    known = ", ".join(PERSPECTIVE_MODELS + FISHEYE_MODELS)
    kind = {"EQUIRECTANGULAR": " (a spherical 360-degree panorama)"}.get(model, "")
    raise DataError(f"{where}: frame {i} uses camera_model {model[:60]}{kind}, which splatzoo cannot use: training "
                    f"needs perspective images, and the camera models it can undistort are {known}. Cut panoramas "
                    "into perspective views first, or re-run SfM with one of those models")


def _distortion(frame: dict, meta: dict, where: Path, i: int) -> dict[str, float]:
    """k1, k2, k3, k4, p1, p2 of a frame (0 when absent): per-frame keys, else the file's keys, else nerfstudio's
    distortion_params list [k1, k2, k3, k4, p1, p2]."""
    terms = {}
    listed = frame.get("distortion_params", meta.get("distortion_params"))
    if listed is not None:
        if not (isinstance(listed, list) and len(listed) == 6 and all(_is_number(v) and _is_finite(v)
                                                                        for v in listed)):
            raise DataError(f"{where}: frame {i}: distortion_params must be 6 finite numbers [k1, k2, k3, k4, p1, "
                            f"p2], not {listed!r:.80}")
        terms = dict(zip(DISTORTION_KEYS, map(float, listed)))
    for key in DISTORTION_KEYS:
        value = _option(frame, meta, key, where, i, hint=_TERM_HINT)
        if value is not None:
            terms[key] = value
    return {k: terms.get(k, 0.0) for k in DISTORTION_KEYS}


def _colmap_camera(kind: str, terms: dict[str, float], fx, fy, cx, cy, w, h, where: Path, i: int):
    """The COLMAP camera that projects as this frame's lens does, or None for a pinhole camera (nothing to warp)."""
    from .camera_models import import_pycolmap

    k1, k2, k3, k4, p1, p2 = (terms[k] for k in DISTORTION_KEYS)
    if kind == "FISHEYE":
        if p1 or p2:
            raise DataError(f"{where}: frame {i} is a fisheye camera (OPENCV_FISHEYE) with p1/p2 = {p1:g}/{p2:g}; "
                            "that model has no tangential terms (k1..k4 only). Remove p1 and p2 or use OPENCV")
        model, params = "OPENCV_FISHEYE", [fx, fy, cx, cy, k1, k2, k3, k4]
    elif not any(terms.values()):
        return None
    elif k4:
        raise DataError(f"{where}: frame {i} gives k4 = {k4:g} for a perspective camera (an r^8 radial term), which "
                        "COLMAP's undistorter has no model for; refit the camera with k1, k2, k3, p1, p2 (OPENCV), "
                        "or mark it camera_model OPENCV_FISHEYE if it is a fisheye lens")
    elif k3:
        model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    else:
        model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    return import_pycolmap().Camera(model=model, width=w, height=h, params=params, camera_id=1)


def _frame_path(frame, i: int, root: Path, meta_path: Path) -> str:
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
    return file_path


def _missing_mask(frame, root: Path, meta_path: Path, i: int) -> str | None:
    """The mask_path a frame names when no such file exists (also trying .png/.jpg/.jpeg after a bare name), else
    None."""
    given = frame.get("mask_path") if isinstance(frame, dict) else None
    if given is None:
        return None
    if not isinstance(given, str) or not given:
        raise DataError(f"{meta_path}: frame {i} mask_path must be a path relative to {root}, not {given!r:.60}")
    return given if _image_path(root, given, meta_path) is None else None


def names_masks(root) -> bool:
    """Whether a Blender-style dataset has masks to read when masks are "auto": a masks/ folder, or a transforms file
    whose frames name a mask_path (nerfstudio's per-frame masks, which may lie anywhere)."""
    root = Path(root)
    if (root / "masks").is_dir():
        return True
    train = root / "transforms_train.json"
    files = [train, root / "transforms_test.json"] if train.is_file() else [root / "transforms.json"]
    for path in files:
        try:
            frames = _read_json(path)["frames"] if path.is_file() else []
        except DataError:
            return False   # loading names what is wrong with the file
        if any(isinstance(f, dict) and f.get("mask_path") is not None for f in frames):
            return True
    return False


def _mask_of(frame: dict, root: Path, name: str, meta_path: Path, i: int) -> Path | None:
    """The frame's mask: nerfstudio's per-frame mask_path, else masks/<name> (see find_mask)."""
    given = frame.get("mask_path")
    if given is not None:
        if not isinstance(given, str) or not given:
            raise DataError(f"{meta_path}: frame {i} mask_path must be a path relative to {root}, not {given!r:.60}")
        found = _image_path(root, given, meta_path)
        if found is None:
            raise DataError(f"{meta_path}: frame {i} names the mask {root / given} (mask_path), which does not "
                            "exist; restore it or load without masks")
        return found
    return find_mask(root / "masks", name) if (root / "masks").is_dir() else None


class _Loaded:
    """What reading one transforms file found besides its views: skipped frames and keys splatzoo does not use."""

    def __init__(self, meta_path: Path, meta: dict):
        self.meta_path, self.meta = meta_path, meta
        self.skipped: list[str] = []
        self.skipped_masks: list[str] = []   # frames left out because the mask they name is missing
        self.ignored = sorted(k for k in meta if k not in USED_KEYS)
        self.ignored_per_frame: dict[str, int] = {}
        self.distorted = 0


def _frame_images(root: Path, meta_path: Path, frames: list, found: _Loaded, skip_missing: bool) -> list:
    """Each frame's image (None for those missing, which then go to found.skipped); a DataError when images are
    missing and skip_missing is not given, or when none exists."""
    paths = [_image_path(root, _frame_path(f, i, root, meta_path), meta_path) for i, f in enumerate(frames)]
    missing = [i for i, path in enumerate(paths) if path is None]
    if missing:
        names = [str(root / frames[i]["file_path"]) for i in missing]
        listing = ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
        if len(missing) == len(frames):
            raise DataError(f"{meta_path}: none of its {len(frames)} frames' images exists (image {names[0]} does not "
                            "exist; also tried .png/.jpg/.jpeg); restore the images or fix the file_path entries")
        if not skip_missing:
            raise DataError(f"{meta_path}: {len(missing)} of {len(frames)} frames name an image that does not exist "
                            f"(also tried .png/.jpg/.jpeg): image {listing}. Restore them, remove those frames from "
                            "the transforms file, or pass --skip-missing (load_scene(..., skip_missing=True)) to "
                            "train without them")
        found.skipped = [str(Path(frames[i]["file_path"])) for i in missing]
    return paths


def _drop_missing_masks(root: Path, meta_path: Path, frames: list, paths: list, found: _Loaded,
                        skip_missing: bool) -> list:
    """`paths` without the frames whose mask_path names a mask that does not exist (they go to found.skipped_masks):
    a mask the file names is part of the frame, so missing, it stops loading as a missing image does, unless
    skip_missing is given and other frames are left."""
    present = sum(p is not None for p in paths)
    named = {i: _missing_mask(frames[i], root, meta_path, i) for i in range(len(frames)) if paths[i] is not None}
    lacking = {i: m for i, m in named.items() if m is not None}
    if lacking:
        shown = [f"frame {i} ({frames[i]['file_path']}): {root / m}" for i, m in list(lacking.items())[:5]]
        listing = ", ".join(shown) + (f" and {len(lacking) - 5} more" if len(lacking) > 5 else "")
        if not skip_missing or len(lacking) == present:
            raise MissingMaskError(
                f"{meta_path}: {len(lacking)} of {len(frames)} frames name a mask (mask_path) that does not exist "
                f"(also tried .png/.jpg/.jpeg): {listing}. Restore the masks or fix those frames' mask_path"
                + ("" if skip_missing else ", or pass --skip-missing (load_scene(..., skip_missing=True)) to train "
                                            "without those frames"))
        found.skipped_masks = [f"{frames[i]['file_path']} (mask {m})" for i, m in lacking.items()]
        paths = [None if i in lacking else p for i, p in enumerate(paths)]
    return paths


def _intrinsics(frame: dict, meta: dict, meta_path: Path, i: int, w: int, h: int):
    """The frame's focal lengths and principal point (fx, fy, cx, cy) in pixels of its w x h image: from fl_x/fl_y
    or camera_angle_x/_y, cx/cy, rescaled when given for another image size (w, h)."""
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
        fx *= w / fw   # intrinsics written for another image size: rescale them (distortion terms are unitless)
        fy *= h / fh
    cx = (get("cx") if get("cx") is not None else fw / 2) * (w / fw)
    cy = (get("cy") if get("cy") is not None else fh / 2) * (h / fh)
    return fx, fy, cx, cy


def _frame_mask(frame: dict, root: Path, name: str, path: Path, meta_path: Path, i: int) -> Path | None:
    """The frame's mask file when masks are asked for (None: the image's alpha channel); a DataError when there
    is neither."""
    mask_path = _mask_of(frame, root, name, meta_path, i)
    if mask_path is None and not image_has_alpha(path):
        raise DataError(f"masks requested but image {path} has no alpha channel and no mask in "
                        f"{root / 'masks'}; load without masks")
    return mask_path


def _views_from(root: Path, meta_path: Path, background, masks: bool, resolution, max_width,
                skip_missing: bool = False) -> tuple[list[View], _Loaded]:
    """The views of one transforms file (undistorted where a lens asks for it, scaled to the resolution asked) and
    what else reading it found."""
    meta = _read_json(meta_path)
    found = _Loaded(meta_path, meta)
    frames = meta["frames"]
    paths = _frame_images(root, meta_path, frames, found, skip_missing)
    if masks:
        paths = _drop_missing_masks(root, meta_path, frames, paths, found, skip_missing)
    views = []
    lenses = []   # (index in views, COLMAP camera of the photo, the frame in words) for the frames whose photos must
    #               be undistorted
    size = None
    for i, frame in enumerate(frames):
        path = paths[i]
        if path is None:
            continue
        for key in frame:
            if key not in USED_FRAME_KEYS:
                found.ignored_per_frame[key] = found.ignored_per_frame.get(key, 0) + 1
        c2w = _pose(frame, meta_path, i)
        w, h = image_size(path)
        if size is None:
            size = (w, h, path)
        elif (w, h) != size[:2] and "w" not in frame and "w" not in meta and "fl_x" not in frame:
            # (intrinsics written for a stated size w, h are rescaled to each image: a downscaled copy is fine)
            raise DataError(f"images in {meta_path} differ in size: {size[2]} is {size[0]}x{size[1]} but {path} is "
                            f"{w}x{h}; a shared camera_angle_x needs one image size. Resize them to one size")
        fx, fy, cx, cy = _intrinsics(frame, meta, meta_path, i, w, h)
        lens = _colmap_camera(_camera_model(frame, meta, meta_path, i), _distortion(frame, meta, meta_path, i),
                              fx, fy, cx, cy, w, h, meta_path, i)
        w2c = np.linalg.inv(c2w @ _OPENGL_TO_OPENCV)
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
        name = str(path.relative_to(root))
        mask_path = _frame_mask(frame, root, name, path, meta_path, i) if masks else None
        if lens is not None:
            lenses.append((len(views), lens, f"{meta_path}: frame {i} ({name})"))
        cam = Camera(torch.from_numpy(w2c), torch.from_numpy(K), w, h, name)
        views.append(View(camera=cam, name=name, path=path, mask_path=mask_path, use_mask=masks,
                          background=tuple(background)))
    if lenses:
        # the checks load_scene makes (in float32, as training sees them), before any photo is warped
        check_cameras([View(camera=scale_camera(v.camera, 1.0), name=v.name) for v in views], meta_path)
        _undistort_views(root, views, lenses)
        found.distorted = len(lenses)
    for v in views:
        v.camera = scale_camera(v.camera, target_scale(v.camera.width, v.camera.height, resolution, max_width))
    return views, found


# --- undistortion ------------------------------------------------------------------------------------------------

_LENS_FIX = (f"check the distortion coefficients ({', '.join(DISTORTION_KEYS)} or distortion_params): they are "
             "unitless, for image coordinates divided by the focal length (typically |k1| < 0.5 and |p1|, |p2| < 0.01)")


def _undistort_views(root: Path, views: list[View], lenses: list) -> None:
    """Point each distorted view at the undistorted copy of its photo (and mask) and at the PINHOLE camera it was
    warped to (splatzoo.data.undistort, as the COLMAP path does)."""
    from .undistort import DistortedPhoto, undistort_photos

    photos = [DistortedPhoto(views[i].path, lens, who, views[i].mask_path) for i, lens, who in lenses]
    for (i, _, _), copy in zip(lenses, undistort_photos(root, UNDISTORTED_DIR, photos, _LENS_FIX)):
        view = views[i]
        view.camera = Camera(view.camera.world_to_camera, torch.from_numpy(copy.K), copy.width, copy.height,
                             view.camera.name)
        view.path, view.mask_path = copy.path, copy.mask


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
                 background=(0.0, 0.0, 0.0), masks: bool = False, skip_missing: bool = False,
                 init_points: str = "auto") -> Scene:
    """Read a Blender/NeRF-synthetic folder. With transforms_train.json the split comes from the files
    (transforms_test.json is the test set; test_every is ignored); a single transforms.json is split by
    test_every. skip_missing: leave out frames whose image (or, with masks, whose mask_path) does not exist
    (scene.notes lists them) instead of stopping with an error. init_points (used only without a point cloud):
    "auto", "triangulate" or "random". See the module docstring for lens distortion and how initial points are
    chosen."""
    if init_points not in INIT_POINTS:
        raise DataError(f"init_points={init_points!r:.60}: choose one of {', '.join(INIT_POINTS)}")
    root = Path(root)
    train_file, test_file = root / "transforms_train.json", root / "transforms_test.json"
    options = (background, masks, resolution, max_width, skip_missing)
    if train_file.is_file():
        train, loaded = _views_from(root, train_file, *options)
        found = [loaded]
        test = []
        if test_file.is_file():
            test, loaded = _views_from(root, test_file, *options)
            found.append(loaded)
        train.sort(key=lambda v: v.name)
        test.sort(key=lambda v: v.name)
    else:
        views, loaded = _views_from(root, root / "transforms.json", *options)
        found = [loaded]
        train, test = split_views(views, test_every, root)
    notes = _notes(found)
    meta_path = train_file if train_file.is_file() else root / "transforms.json"
    meta = found[0].meta
    ply = _named_ply(root, meta_path, meta)
    if ply is None:
        ply = next((p for p in (root / "points3d.ply", root / "points3D.ply") if p.is_file()), None)
    applied = _applied(meta, meta_path)
    if applied is not None:
        notes.append(applied[2])
    if ply is not None:
        xyz, rgb = read_ply_points(ply)
        if len(xyz) == 0:
            raise DataError(f"{ply} holds no points; delete it to start from random points")
        if rgb is None:
            rgb = np.full_like(xyz, 0.5)
        if applied is not None:
            xyz, note = _points_frame(xyz, applied, [v.camera for v in train + test], ply.name)
            notes.append(note)
    else:
        xyz, rgb, note = _initial_points(root, train, [v.camera for v in train + test], meta, init_points)
        notes.append(note)
    if (root / "dataparser_transforms.json").is_file():
        notes.append("dataparser_transforms.json (the frame a nerfstudio model was trained in) is not applied: "
                     "splatzoo trains in the frame of the transforms file's own poses")
    points, colors = torch.from_numpy(np.ascontiguousarray(xyz)), torch.from_numpy(np.ascontiguousarray(rgb))
    return Scene(name=root.resolve().name, root=root, train=train, test=test, points=points, colors=colors,
                 extent=camera_extent([v.camera for v in train], points), background=tuple(background),
                 mesh_path=mesh_path_of(root), notes=notes)


def _notes(found: list[_Loaded]) -> list[str]:
    """What loading skipped, undistorted and ignored, once per transforms file."""
    notes = []
    for f in found:
        name = f.meta_path.name
        if f.skipped:
            listing = ", ".join(f.skipped[:10]) + (f", ... ({len(f.skipped) - 10} more)" if len(f.skipped) > 10 else "")
            notes.append(f"{name}: skipped {len(f.skipped)} frame{'s' if len(f.skipped) > 1 else ''} whose images are "
                         f"missing: {listing}")
        if f.skipped_masks:
            listing = ", ".join(f.skipped_masks[:10]) + (f", ... ({len(f.skipped_masks) - 10} more)"
                                                         if len(f.skipped_masks) > 10 else "")
            notes.append(f"{name}: skipped {len(f.skipped_masks)} frame{'s' if len(f.skipped_masks) > 1 else ''} "
                         f"whose masks are missing: {listing}")
        if f.distorted:
            notes.append(f"{name}: {f.distorted} frame(s) have lens distortion: training on undistorted copies of "
                         f"their photos (pinhole cameras, as COLMAP's undistorter makes them) in {UNDISTORTED_DIR}/")
        ignored = [k[:40] for k in f.ignored]
        ignored += [f"{k[:40]} (in {n} frame{'s' if n > 1 else ''})" for k, n in sorted(f.ignored_per_frame.items())]
        if ignored:
            shown = ", ".join(ignored[:20]) + (f", ... ({len(ignored) - 20} more)" if len(ignored) > 20 else "")
            notes.append(f"{name}: ignored {len(ignored)} key{'s' if len(ignored) > 1 else ''} that splatzoo does not "
                         f"use: {shown}")
    return notes


def _applied(meta: dict, where: Path) -> tuple[np.ndarray, float, str] | None:
    """(applied_transform as 4x4, applied_scale, a note) when the transforms file records them, else None."""
    T, s = meta.get("applied_transform"), meta.get("applied_scale")
    if T is None and s is None:
        return None
    M = np.eye(4)
    if T is not None:
        ok = (isinstance(T, list) and len(T) in (3, 4) and all(isinstance(r, list) and len(r) == 4 for r in T)
              and all(_is_number(v) and _is_finite(v) for r in T for v in r))
        if not ok:
            raise DataError(f"{where}: applied_transform must be 3 (or 4) rows of 4 finite numbers, not {T!r:.80}")
        M[:len(T)] = np.asarray(T, dtype=np.float64)
        if not np.allclose(M[3], [0, 0, 0, 1]) or abs(np.linalg.det(M[:3, :3])) < 1e-9:
            raise DataError(f"{where}: applied_transform {T!r:.80} is not an invertible affine transform")
    scale = 1.0
    if s is not None:
        if not (_is_number(s) and _is_finite(s) and s > 0):
            raise DataError(f"{where}: applied_scale must be a number greater than 0, not {s!r:.60}")
        scale = float(s)
    said = []
    if T is not None:
        said.append("applied_transform " + str(np.round(M[:3], 4).tolist()))
    if s is not None:
        said.append(f"applied_scale {scale:g}")
    return M, scale, (f"{where.name} records {' and '.join(said)} (how its frames were made from the original "
                      "capture); its camera poses are used as they are, in that transformed frame")


def _visible(xyz: np.ndarray, cameras: list[Camera]) -> float:
    """How much of the point cloud the cameras see: the mean, over points, of the fraction of cameras that have the
    point in front of them and inside their image (points of a real capture are each seen by several)."""
    if not len(xyz) or not cameras:
        return 0.0
    pts = xyz[np.random.default_rng(0).choice(len(xyz), min(len(xyz), 2000), replace=False)].astype(np.float64)
    cams = cameras[:: max(1, len(cameras) // 50)]
    seen = np.zeros(len(pts))
    for cam in cams:
        w2c, K = cam.world_to_camera.double().numpy(), cam.K.double().numpy()
        p = pts @ w2c[:3, :3].T + w2c[:3, 3]
        with np.errstate(all="ignore"):
            uv = (p @ K.T)[:, :2] / p[:, 2:3]
        seen += (p[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height)
    return float(seen.mean() / len(cams))


def _points_frame(xyz: np.ndarray, applied, cameras: list[Camera], ply_name: str) -> tuple[np.ndarray, str]:
    """The point cloud in the frame of the transforms file's poses, and a note saying how it got there.

    Assumption (nerfstudio's own reading of its format): `ns-process-data` writes the point cloud with
    applied_transform already applied, in the frame of the poses, and nerfstudio's dataparser multiplies the points,
    but not the poses, by applied_scale. So the points are taken as they are, times applied_scale. A point cloud
    written in the original capture's frame instead (older nerfstudio, other tools) is recognised by the cameras:
    when far more of its points are in view once applied_scale x applied_transform is applied to them, that is used.
    """
    M, scale, _ = applied
    as_nerfstudio = (xyz.astype(np.float64) * scale).astype(np.float32)
    original = (scale * (xyz.astype(np.float64) @ M[:3, :3].T + M[:3, 3])).astype(np.float32)
    seen_ns, seen_orig = _visible(as_nerfstudio, cameras), _visible(original, cameras)
    if seen_orig > max(2 * seen_ns, seen_ns + 0.25):
        return original, (f"{ply_name} is in the original capture's frame (the cameras see {100 * seen_orig:.0f}% of "
                          "its points after applying applied_transform and applied_scale to them, "
                          f"{100 * seen_ns:.0f}% without): applied them to the points")
    return as_nerfstudio, (f"{ply_name} is taken to be in the poses' frame, as ns-process-data writes it (the cameras "
                           f"see {100 * seen_ns:.0f}% of its points)"
                           + (f"; scaled by applied_scale {scale:g}, as nerfstudio does" if scale != 1 else ""))


def _named_ply(root: Path, meta_path: Path, meta: dict) -> Path | None:
    """The point cloud the transforms file names (nerfstudio's ply_file_path, relative to the dataset), if any."""
    name = meta.get("ply_file_path")
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


def _nerf_synthetic_style(meta: dict, train: list[View]) -> bool:
    """A NeRF-synthetic-style object dataset: a field of view (camera_angle_x) rather than fl_x, and transparent
    (RGBA) images."""
    frames = [f for f in meta.get("frames", []) if isinstance(f, dict)]
    has_fl = meta.get("fl_x") is not None or any(f.get("fl_x") is not None for f in frames)
    if has_fl or meta.get("camera_angle_x") is None or not train:
        return False
    v = train[0]
    if v.pixels is not None:
        return v.pixels.shape[2] == 4
    return v.path is not None and image_has_alpha(v.path)


def _initial_points(root: Path, train: list[View], cameras: list[Camera], meta: dict,
                    init_points: str) -> tuple[np.ndarray, np.ndarray, str]:
    """Initial points of a dataset without a point cloud (see the module docstring): triangulated from the known poses,
    else random points with a note saying why."""
    import sys

    from .triangulate import select_views, triangulate_points

    if init_points == "random":
        return _random_points(cameras, "no point cloud and init_points='random'")
    if init_points == "auto" and _nerf_synthetic_style(meta, train):
        return _random_points(cameras, "no point cloud (points3d.ply or the transforms file's ply_file_path); a "
                                       "NeRF-synthetic-style object (camera_angle_x, transparent images) starts as the "
                                       "3DGS protocol does (init_points='triangulate' triangulates instead)")
    if len(train) < 2:
        return _random_points(cameras, f"no point cloud, and {len(train)} training image is too few to triangulate")
    try:
        xyz, rgb = triangulate_points(train, cache_dir=root,
                                      progress=lambda msg: print(f"splatzoo: {msg}", file=sys.stderr, flush=True))
    except DataError as e:
        return _random_points(cameras, f"initial points: {e}")
    if len(xyz) < MIN_TRIANGULATED:
        return _random_points(cameras, f"initial points: triangulation found only {len(xyz)} points (fewer than "
                                       f"{MIN_TRIANGULATED}; the images may lack texture or overlap)")
    return xyz, rgb, (f"initial points: {len(xyz)} triangulated from the known poses "
                      f"({len(select_views(train))} images)")


def _random_points(cameras: list[Camera], why: str = "no point cloud (points3d.ply or the transforms file's "
                                                         "ply_file_path)") -> tuple[np.ndarray, np.ndarray, str]:
    """RANDOM_POINTS seeded random points and colours in a cube around what the cameras look at, sized to them."""
    from ..geometry import look_at_point

    centre = look_at_point(cameras) if len(cameras) > 1 else torch.zeros(3, dtype=torch.float64)
    distance = float(torch.stack([(c.center.double() - centre).norm() for c in cameras]).mean())
    half = RANDOM_BOX_PER_DISTANCE * distance if math.isfinite(distance) and distance > 0 else 1.3
    g = np.random.default_rng(0)
    xyz = ((g.random((RANDOM_POINTS, 3)) * 2 - 1) * half + centre.numpy()).astype(np.float32)
    rgb = g.random((RANDOM_POINTS, 3)).astype(np.float32)
    where = ", ".join(f"{x:.3g}" for x in centre.tolist())
    return xyz, rgb, (f"{why}: starting from {RANDOM_POINTS} random points in a cube of half-size {half:.3g} around "
                      f"({where}), what the cameras look at")


def is_blender(root: Path) -> bool:
    return (root / "transforms_train.json").is_file() or (root / "transforms.json").is_file()


# Before COLMAP: an instant-ngp / nerfstudio folder holds transforms.json next to an images/ folder.
FORMAT = DatasetFormat(
    "blender", is_blender, load_blender, priority=10, has_masks=names_masks,
    needs="transforms_train.json (and transforms_test.json) or one transforms.json, whose frames give each "
          "image's file_path and transform_matrix, with camera_angle_x or fl_x")
