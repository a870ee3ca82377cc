"""Initial points for posed images without a point cloud: SIFT features matched between the images and triangulated
from the known cameras (pycolmap), in place of a random box.

The views' photos are written at their own size whatever size training uses (a longer side than LONG_SIDE pixels
downscaled to it, intrinsics scaled with them) into a temporary COLMAP workspace: fewer pixels give fewer features
(the fox gave 1,511 points from its photos at 1/8 size, 133x237, and 11,729 at 900x1600: BENCHMARKS.md). Features are
extracted (one PINHOLE camera per image, set to the known intrinsics) and matched: every pair for up to
EXHAUSTIVE_MAX images, beyond that each image with its NEIGHBOURS nearest cameras (by centre distance and viewing
direction: cameras far apart or looking away from each other see little in common). pycolmap's
point triangulator then triangulates and refines the points with the poses and intrinsics held fixed. Points seen by
fewer than MIN_TRACK images, with a mean reprojection error above MAX_ERROR_PX, or not finite are dropped.

The result is cached beside the dataset (CACHE_NAME, or under ~/.cache/splatzoo/triangulated/ when the dataset
folder is read-only), keyed by a stamp of the frames' names, image files, working sizes and poses and by their working
intrinsics (compared within float32 rounding, so loads at any training resolution share it), so a second load does
not triangulate again. A result with few or no points is cached too (the caller decides what is enough).
"""
from __future__ import annotations

import hashlib
import itertools
import math
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..io import say_progress as _say
from ..types import Camera
from .colmap import import_pycolmap, quiet_colmap
from .scene import View
from .sfm import image_ids, match_pairs

LONG_SIDE = 1600           # photos with a longer side than this are downscaled to it (for speed)
MAX_IMAGES = 200           # at most this many views (evenly spread over the list) are used
EXHAUSTIVE_MAX = 40        # up to this many images every pair is matched ...
NEIGHBOURS = 15            # ... beyond, each image with its nearest cameras
MIN_TRACK = 3              # a point must be seen in at least this many images
MAX_ERROR_PX = 2.0         # and reproject within this many pixels (at the working resolution) on average
CACHE_NAME = "triangulated_points.npz"
_VERSION = 2               # part of the cache stamp: bump when the method changes what it returns


def select_views(views: list[View], max_images: int = MAX_IMAGES) -> list[View]:
    """The views triangulation uses: all of them, or `max_images` spread evenly over the list."""
    if len(views) <= max_images:
        return list(views)
    keep = np.unique(np.linspace(0, len(views) - 1, max_images).round().astype(int))
    return [views[i] for i in keep]


def working_camera(view: View, long_side: int = LONG_SIDE) -> Camera:
    """The view's camera (float64) at the size of its photo (view.source_size), downscaled so its long side is at most
    `long_side`: the same camera whatever size the view is trained at."""
    import dataclasses

    import torch

    cam = view.camera
    w, h = view.source_size()
    shrink = min(1.0, long_side / max(w, h))
    width, height = max(1, round(w * shrink)), max(1, round(h * shrink))
    K = cam.K.double().clone()
    K[0] *= width / cam.width      # per axis, as the photo is resized: a training size rounds each side apart
    K[1] *= height / cam.height
    return dataclasses.replace(cam.to(dtype=torch.float64), K=K, width=width, height=height)


def _intrinsics(cams: list[Camera]) -> np.ndarray:
    """[N,4] fx, fy, cx, cy in float64."""
    return np.array([[float(c.K[0, 0]), float(c.K[1, 1]), float(c.K[0, 2]), float(c.K[1, 2])] for c in cams])


def stamp(views: list[View], cams: list[Camera]) -> str:
    """What a triangulation is made from, but for the intrinsics (compared apart, see _read_cache): each view's name,
    image file (path, size, time) or pixels, working size (cams) and pose, and the method's settings."""
    h = hashlib.sha1(f"v{_VERSION}|{MIN_TRACK}|{MAX_ERROR_PX}|{NEIGHBOURS}".encode())
    for v, cam in zip(views, cams):
        h.update(f"|{v.name}|{cam.width}x{cam.height}|{v.background}".encode())
        h.update(np.round(cam.world_to_camera.double().numpy(), 7).tobytes())
        if v.pixels is not None:
            h.update(np.ascontiguousarray(v.pixels).tobytes())
        elif v.path is not None:
            try:
                st = Path(v.path).stat()
                h.update(f"{Path(v.path).resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
            except OSError:
                h.update(str(v.path).encode())
    return h.hexdigest()[:16]


def cache_file(folder) -> Path:
    """Where the triangulation of the dataset in `folder` is kept: folder/CACHE_NAME, or a per-dataset file under
    ~/.cache/splatzoo/triangulated/ (XDG_CACHE_HOME) when the folder is not writable."""
    folder = Path(folder)
    if os.access(folder, os.W_OK):
        return folder / CACHE_NAME
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "splatzoo" / "triangulated"
    return cache / hashlib.sha1(str(folder.resolve()).encode()).hexdigest()[:16] / CACHE_NAME


def _read_cache(path: Path, key: str, intrinsics: np.ndarray):
    """The cached points and colours when the stamp matches and so do the intrinsics, within float32 rounding: a view
    loaded at 1/8 size and scaled back to its photo's size differs from one loaded at 1/4 in the last bits."""
    try:
        with np.load(path, allow_pickle=False) as f:
            if str(f["stamp"]) != key:
                return None
            cached = f["intrinsics"]
            if cached.shape != intrinsics.shape or not np.allclose(cached, intrinsics, rtol=1e-5, atol=1e-3):
                return None
            points, colors = f["points"].astype(np.float32), f["colors"].astype(np.float32)
    except (OSError, KeyError, ValueError, EOFError):
        return None   # absent, stale or damaged: triangulate again
    if points.ndim != 2 or points.shape[1:] != (3,) or colors.shape != points.shape:
        return None
    return points, colors


def _write_cache(path: Path, key: str, intrinsics: np.ndarray, points: np.ndarray, colors: np.ndarray) -> str | None:
    """Write atomically (a temporary file, then rename). A cache that cannot be written is only a lost speed-up, but
    one lost at every load: returns why, for the caller to say."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".npz")
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, stamp=np.array(key), intrinsics=intrinsics, points=points, colors=colors)
            os.replace(tmp, path)
        finally:
            Path(tmp).unlink(missing_ok=True)
    except OSError as e:
        return e.strerror or str(e)
    return None


def neighbour_pairs(cameras: list[Camera], k: int = NEIGHBOURS) -> list[tuple[int, int]]:
    """(i, j) index pairs, i < j: each camera with the k others nearest to it, by centre distance (relative to the
    cameras' spread) plus a penalty for turning away (1 - cos of the angle between viewing directions); cameras whose
    directions differ by more than 90 degrees are not paired."""
    import torch

    c = torch.stack([cam.center.double() for cam in cameras]).numpy()
    d = torch.stack([cam.R[2].double() for cam in cameras]).numpy()
    radius = float(np.linalg.norm(c - c.mean(0), axis=1).max()) or 1.0
    dist = np.linalg.norm(c[:, None] - c[None], axis=2) / radius
    cos = np.clip(d @ d.T, -1, 1)
    cost = dist + 2.0 * (1.0 - cos)
    cost[cos < 0] = np.inf
    np.fill_diagonal(cost, np.inf)
    pairs = set()
    for i in range(len(cameras)):
        for j in np.argsort(cost[i])[:k]:
            if np.isfinite(cost[i, j]):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _write_images(views: list[View], cams: list[Camera], folder: Path) -> list[str]:
    """Each view's image at its working camera's size as folder/00000.png, ... (written by pycolmap itself: OpenCV's
    PNG writer and pycolmap's bundled zlib can clash in one process)."""
    pycolmap = import_pycolmap()
    folder.mkdir(parents=True)
    names = []
    for i, (v, cam) in enumerate(zip(views, cams)):
        px = v.image_at(cam.width, cam.height).numpy()   # uint8 [H,W,3], transparency over its background
        name = f"{i:05d}.png"
        if not pycolmap.Bitmap.from_array(np.ascontiguousarray(px)).write(str(folder / name), False):
            raise DataError(f"cannot write a working copy of {v.name} for triangulation in {folder}")
        names.append(name)
    return names


def _extract(db: Path, images: Path, names: list[str], num_threads: int, say) -> None:
    pycolmap = import_pycolmap()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    extract = pycolmap.FeatureExtractionOptions()
    extract.num_threads = num_threads
    extract.use_gpu = False
    chunk = max(16, math.ceil(len(names) / 5))
    t0 = time.perf_counter()
    for start in range(0, len(names), chunk):
        part = names[start:start + chunk]
        pycolmap.extract_features(db, images, image_names=part, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                                  reader_options=reader, extraction_options=extract, device=pycolmap.Device.cpu)
        if len(names) > chunk:
            say(f"      features of {start + len(part)}/{len(names)} images, {time.perf_counter() - t0:.0f} s so far")


def _reconstruction(db_path: Path, cams: list[Camera], names: list[str]):
    """A pycolmap Reconstruction of the known cameras and poses under the database's image and camera ids (the
    database's cameras are set to the known intrinsics first), with no points."""
    pycolmap = import_pycolmap()
    rec = pycolmap.Reconstruction()
    by_name = dict(zip(names, cams))
    db = pycolmap.Database.open(str(db_path))
    try:
        images = db.read_all_images()
        for im in images:
            cam = by_name[im.name]
            K = cam.K.double().numpy()
            colmap_cam = pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                                         params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=im.camera_id)
            db.update_camera(colmap_cam)
            rec.add_camera_with_trivial_rig(colmap_cam)
            image = pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id)
            w2c = cam.world_to_camera.double().numpy()
            rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
    finally:
        db.close()
    return rec


def _filtered(rec) -> tuple[np.ndarray, np.ndarray]:
    pts, cols = [], []
    for p in rec.points3D.values():
        if p.track.length() < MIN_TRACK or not (p.error <= MAX_ERROR_PX):
            continue
        xyz = np.asarray(p.xyz, dtype=np.float64)
        if not np.isfinite(xyz).all():
            continue
        pts.append(xyz)
        cols.append(np.asarray(p.color, dtype=np.float64) / 255.0)
    if not pts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    return np.asarray(pts, np.float32), np.clip(np.asarray(cols, np.float32), 0, 1)


def triangulate_points(views: list[View], *, max_images: int = MAX_IMAGES, long_side: int = LONG_SIDE,
                       cache_dir=None, progress=None, num_threads: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Points [M,3] float32 and colours [M,3] float32 in [0,1] triangulated from the views' images and known cameras.

    max_images: use at most this many views (spread evenly). The photos are used at their own size (not the views'
    training size), downscaled to `long_side` pixels on their longer side when larger (intrinsics follow).
    cache_dir: the dataset folder; the result is kept there (see cache_file) and reused while the views are
    unchanged. progress: True prints steps to stderr, a callable receives each message. Raises DataError when
    pycolmap fails; too few textured, overlapping images give few or no points instead (not an error).
    """
    say = _say(progress)
    views = select_views(views, max_images)
    if len(views) < 2:
        raise DataError(f"triangulation needs at least 2 posed images, got {len(views)}")
    cams = [working_camera(v, long_side) for v in views]
    key, intrinsics = stamp(views, cams), _intrinsics(cams)
    cache = cache_file(cache_dir) if cache_dir is not None else None
    if cache is not None:
        hit = _read_cache(cache, key, intrinsics)
        if hit is not None:
            say(f"initial points: reusing {len(hit[0])} triangulated points from {cache}")
            return hit
    pycolmap = import_pycolmap()
    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="splatzoo-triangulate-"))
    try:
        images = work / "images"
        say(f"initial points: triangulating from the known poses of {len(views)} images "
            f"({cams[0].width}x{cams[0].height}) ...")
        names = _write_images(views, cams, images)
        db = work / "database.db"
        try:
            with quiet_colmap(2):
                pycolmap.set_random_seed(0)
                say(f"      [1/3] SIFT features of {len(names)} images")
                _extract(db, images, names, num_threads, say)
                ids = image_ids(db)
                index = {n: i for i, n in enumerate(names)}
                if len(views) <= EXHAUSTIVE_MAX:
                    pairs = list(itertools.combinations(range(len(names)), 2))
                    how = "every pair"
                else:
                    pairs = neighbour_pairs(cams)
                    how = f"each image with its {NEIGHBOURS} nearest cameras"
                by_index = {index[n]: i for n, i in ids.items()}
                id_pairs = [(by_index[a], by_index[b]) for a, b in pairs if a in by_index and b in by_index]
                say(f"      [2/3] matching {len(id_pairs)} image pairs ({how})")

                match_pairs(db, id_pairs, work / "match", num_threads=num_threads)
                say("      [3/3] triangulating with the poses held fixed")
                rec = _reconstruction(db, cams, names)
                options = pycolmap.IncrementalPipelineOptions()
                options.num_threads = num_threads
                out = work / "model"
                out.mkdir()
                rec = pycolmap.triangulate_points(rec, db, images, out, clear_points=True, options=options,
                                                  refine_intrinsics=False)
                rec.extract_colors_for_all_images(str(images))
        except DataError:
            raise
        except Exception as e:   # pycolmap reports failures as RuntimeError / ValueError with its own message
            raise DataError(f"triangulation failed: {e}") from None
        points, colors = _filtered(rec)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    say(f"      {len(points)} points (of {rec.num_points3D()} triangulated: seen in at least {MIN_TRACK} images, "
        f"within {MAX_ERROR_PX:g} px) in {time.perf_counter() - t0:.1f} s")
    if cache is not None:
        failed = _write_cache(cache, key, intrinsics, points, colors)
        if failed:
            say(f"warning: cannot keep the triangulated points in {cache} ({failed}), so every load triangulates "
                "again; make that path a writable file (move or delete what is there)")
    return points, colors
