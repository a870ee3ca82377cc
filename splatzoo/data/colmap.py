"""COLMAP datasets: images/ + sparse/0/ (binary or text), read with pycolmap.

PINHOLE and SIMPLE_PINHOLE cameras (and other models with every distortion term zero) load directly. The photos of
any other perspective model (SIMPLE_RADIAL, OPENCV, division, fisheye, ...) are undistorted once with pycolmap into
DATA/undistorted/ (with their masks; splatzoo.data.undistort, as the transforms.json path does) and those copies are
used from then on; a copy is made again when its photo or camera changes. Non-perspective models (EQUIRECTANGULAR) are
an error that names them; see camera_models.py.
"""
from __future__ import annotations

import struct
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from ..errors import DataError
from ..types import Camera
from .camera_models import (PINHOLE_MODELS, check_finite, check_undistortable, import_pycolmap, is_pinhole,
                            pinhole_K)
from .scene import (DatasetFormat, Scene, View, camera_extent, find_mask, image_has_alpha, image_size, list_images,
                    mesh_path_of, scale_camera, split_views, target_scale)

__all__ = ["PINHOLE_MODELS", "import_pycolmap", "quiet_colmap", "find_sparse_dir", "is_colmap", "read_model",
           "load_colmap", "write_model", "FORMAT"]
MODEL_FILES = ("cameras", "images", "points3D")
UNDISTORTED_DIR = "undistorted"


MAX_DOWNSCALE = 64  # images may be a uniformly downscaled copy of those a COLMAP camera describes, up to this factor


def find_sparse_dir(root: Path) -> Path | None:
    """sparse/0/, sparse/ or the folder itself, whichever holds cameras.bin or cameras.txt."""
    for cand in (root / "sparse" / "0", root / "sparse", root):
        if (cand / "cameras.bin").is_file() or (cand / "cameras.txt").is_file():
            return cand
    return None


def is_colmap(root: Path) -> bool:
    """A COLMAP layout: a sparse model (sparse/0/, sparse/ or the folder itself), or images/ or sparse/ folders
    (then load_colmap says what is missing)."""
    return find_sparse_dir(root) is not None or (root / "images").is_dir() or (root / "sparse").is_dir()


def read_model(sparse: Path):
    """pycolmap.Reconstruction of a text or binary model, or a DataError that names the folder."""
    pycolmap = import_pycolmap()

    missing = [n for n in MODEL_FILES if not (sparse / f"{n}.bin").is_file() and not (sparse / f"{n}.txt").is_file()]
    if missing:
        raise DataError(f"COLMAP model {sparse} lacks {', '.join(m + '.bin/.txt' for m in missing)}; "
                        "re-export the model from COLMAP (File > Export model) or re-run `splatzoo sfm`")
    if all((sparse / f"{n}.bin").is_file() for n in MODEL_FILES):  # what pycolmap reads then
        for name in BINARY_LAYOUTS:
            if (sparse / f"{name}.bin").is_file():
                check_binary_file(sparse / f"{name}.bin")
    try:
        return pycolmap.Reconstruction(sparse)
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError on truncated files
        raise DataError(f"cannot read COLMAP model {sparse}: {e}. The files may be truncated or corrupt; "
                        "re-export the model or re-run `splatzoo sfm`") from None


# --- the binary model's layout, walked before pycolmap reads it ----------------------------------------------------
# pycolmap trusts the counts in a binary model: a count damaged into billions makes it reserve gigabytes or loop on a
# stream that has ended (minutes, then std::bad_alloc), and a cut-off image name makes it read forever. So each file is
# walked here first, with every count checked against the bytes that are left: layouts as COLMAP writes them
# (src/colmap/scene/reconstruction_io_binary.cc).

_POSE = 7 * 8  # quaternion (w, x, y, z) and translation, doubles


def _camera_param_counts() -> dict[int, int]:
    pycolmap = import_pycolmap()
    counts = {}
    for name, model_id in pycolmap.CameraModelId.__members__.items():
        if name != "INVALID":
            counts[int(model_id.value)] = len(pycolmap.Camera.create_from_model_name(1, name, 1.0, 1, 1).params)
    return counts


class _Reader:
    """Little-endian values from `data`, each read checked against the end: a DataError names the file."""

    def __init__(self, path: Path, data: bytes):
        self.path, self.data, self.at = path, data, 0

    def damaged(self, problem: str) -> DataError:
        return DataError(f"cannot read COLMAP model {self.path.parent}: {self.path.name} is damaged or truncated "
                         f"({problem}); re-export the model from COLMAP (File > Export model) or re-run `splatzoo sfm`")

    def skip(self, size: int, what: str) -> None:
        if size > len(self.data) - self.at:
            raise self.damaged(f"{what} needs {size} bytes at byte {self.at} but only {len(self.data) - self.at} are "
                               "left")
        self.at += size

    def read(self, fmt: str, what: str):
        size = struct.calcsize("<" + fmt)
        start = self.at
        self.skip(size, what)
        values = struct.unpack_from("<" + fmt, self.data, start)
        return values[0] if len(values) == 1 else values

    def count(self, fmt: str, what: str, item_size: int) -> int:
        """A count of items of at least `item_size` bytes each, which must fit in what is left of the file."""
        n = self.read(fmt, f"the number of {what}")
        if n * item_size > len(self.data) - self.at:
            raise self.damaged(f"it declares {n} {what} of at least {item_size} bytes but only "
                               f"{len(self.data) - self.at} bytes follow")
        return n

    def name(self, what: str) -> None:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise self.damaged(f"{what} runs to the end of the file without its terminating zero byte")
        try:
            self.data[self.at:end].decode("utf-8")
        except UnicodeDecodeError:
            raise self.damaged(f"{what} {self.data[self.at:end][:60]!r} is not UTF-8 text") from None
        self.at = end + 1

    def done(self) -> None:
        if self.at != len(self.data):
            raise self.damaged(f"{len(self.data) - self.at} bytes follow the last entry it declares; a count is wrong")


def _walk_cameras(r: _Reader) -> None:
    params = _camera_param_counts()
    for i in range(r.count("Q", "cameras", 24)):
        _, model_id = r.read("Ii", f"camera {i + 1}'s id and model")
        if model_id not in params:
            raise r.damaged(f"camera {i + 1} has camera model id {model_id}, which COLMAP does not know")
        r.skip(16 + 8 * params[model_id], f"camera {i + 1}'s size and parameters")


def _walk_images(r: _Reader) -> None:
    for i in range(r.count("Q", "images", 4 + _POSE + 4 + 1 + 8)):
        r.skip(4 + _POSE + 4, f"image {i + 1}'s id, pose and camera id")
        r.name(f"image {i + 1}'s name")
        r.skip(r.count("Q", f"2D points of image {i + 1}", 24) * 24, f"image {i + 1}'s 2D points")


def _walk_points(r: _Reader) -> None:
    # a tight loop: a model can hold millions of points
    n, data, at, end = r.count("Q", "3D points", 8 + 24 + 3 + 8 + 8), r.data, r.at, len(r.data)
    track_length = struct.Struct("<Q").unpack_from
    for i in range(n):
        at += 8 + 24 + 3 + 8  # id, position, colour, error
        if at + 8 > end:
            raise r.damaged(f"3D point {i + 1} of {n} runs past the end of the file")
        at += 8 + 8 * track_length(data, at)[0]
        if at > end:
            raise r.damaged(f"the track of 3D point {i + 1} runs past the end of the file")
    r.at = at


def _walk_rigs(r: _Reader) -> None:
    for i in range(r.count("Q", "rigs", 8)):
        r.skip(4, f"rig {i + 1}'s id")
        sensors = r.count("I", f"sensors of rig {i + 1}", 8)
        if sensors:
            r.skip(8, f"rig {i + 1}'s reference sensor")
        for j in range(max(sensors - 1, 0)):
            r.skip(8, f"sensor {j + 2} of rig {i + 1}")
            if r.read("B", f"whether sensor {j + 2} of rig {i + 1} has a pose"):
                r.skip(_POSE, f"the pose of sensor {j + 2} of rig {i + 1}")


def _walk_frames(r: _Reader) -> None:
    for i in range(r.count("Q", "frames", 8 + _POSE + 4)):
        r.skip(8 + _POSE, f"frame {i + 1}'s ids and pose")
        r.skip(r.count("I", f"data ids of frame {i + 1}", 16) * 16, f"frame {i + 1}'s data ids")


BINARY_LAYOUTS = {"rigs": _walk_rigs, "cameras": _walk_cameras, "frames": _walk_frames, "images": _walk_images,
                  "points3D": _walk_points}


def check_binary_file(path: Path) -> None:
    """A DataError naming `path` when the binary model file's counts do not match its bytes (see above)."""
    try:
        data = path.read_bytes()
    except OSError as e:
        raise DataError(f"cannot read COLMAP model {path.parent}: {path.name} ({e.strerror or e})") from None
    r = _Reader(path, data)
    BINARY_LAYOUTS[path.stem](r)
    r.done()


def quiet_colmap(level: int = 1):
    """Silence pycolmap's log lines below `level` (glog: 1 = warnings, 2 = errors) for the duration of a call;
    our own progress messages say what is happening."""
    import contextlib

    pycolmap = import_pycolmap()

    @contextlib.contextmanager
    def cm():
        old = pycolmap.logging.minloglevel
        pycolmap.logging.minloglevel = max(old, level)
        try:
            yield
        finally:
            pycolmap.logging.minloglevel = old
    return cm()


_LENS_FIX = ("check its parameters; if SfM fitted them, re-run it with `splatzoo sfm IMAGES --out DATA --camera-model "
             "SIMPLE_PINHOLE`")


def _camera_in_words(cid: int, registered, sparse: Path) -> str:
    names = sorted(im.name for im in registered if im.camera_id == cid)
    return f"camera {cid} of {sparse} (used by {len(names)} image{'s' if len(names) > 1 else ''}, e.g. {names[0]})"


def _check_distorted_sizes(model, distorted: list[int], cam_scale, registered, images_dir: Path) -> None:
    """A distorted camera's photos are undistorted at the camera's own size: a downscaled copy of them is refused."""
    for cid in distorted:
        if cid in cam_scale:
            cam = model.cameras[cid]
            name = next(im.name for im in registered if im.camera_id == cid)
            w, h = image_size(images_dir / name)
            raise DataError(f"image {images_dir / name} is {w}x{h}, a downscaled copy of the {cam.width}x{cam.height} "
                            f"photos of COLMAP camera {cid}, which has lens distortion: its photos are undistorted at "
                            "the camera's own size. Use the full-size photos (load at a lower --resolution instead)")


def _undistort(root: Path, model, registered, images_dir: Path, distorted: list[int], masks_dir: Path | None,
               masks: bool, sparse: Path) -> dict:
    """image name -> the UndistortedPhoto of each image whose camera is distorted (with its mask when masks are asked
    for; splatzoo.data.undistort)."""
    from .undistort import DistortedPhoto, undistort_photos

    chosen = sorted((im for im in registered if im.camera_id in distorted), key=lambda im: im.name)
    who = {cid: _camera_in_words(cid, registered, sparse) for cid in distorted}
    photos = []
    for im in chosen:
        path = images_dir / im.name
        mask = _mask_of(im.name, path, masks_dir, root) if masks else None
        photos.append(DistortedPhoto(path, model.cameras[im.camera_id], who[im.camera_id], mask))
    return {im.name: copy for im, copy in zip(chosen, undistort_photos(root, UNDISTORTED_DIR, photos, _LENS_FIX))}


def _locate_dataset(root: Path) -> tuple[Path, Path]:
    """images/ and the sparse model folder of a COLMAP dataset, or a DataError that says which is missing."""
    images_dir = root / "images"
    if not images_dir.is_dir():
        raise DataError(f"COLMAP dataset {root} has no images/ folder; put the photos in {images_dir} "
                        "(next to sparse/0/)")
    if not list_images(images_dir):
        raise DataError(f"image folder {images_dir} is empty (no .png/.jpg files); copy the photos there")
    sparse = find_sparse_dir(root)
    if sparse is None:
        raise DataError(f"COLMAP dataset {root} has no sparse model (sparse/0/cameras.bin or .txt); "
                        f"run `splatzoo sfm {images_dir} --out {root}` to make one")
    return images_dir, sparse


def _read_registered(sparse: Path):
    """The model and its registered images (those with a pose); a DataError when it has no such image or no
    3D point."""
    model = read_model(sparse)
    registered = [im for im in model.images.values() if im.has_pose]
    if not registered:
        raise DataError(f"COLMAP model {sparse} has no registered images (none has a pose); SfM failed on "
                        "these photos: take more overlapping photos of a textured subject and re-run `splatzoo sfm`")
    if model.num_points3D() == 0:
        raise DataError(f"COLMAP model {sparse} has no 3D points, so there is nothing to initialise surfels "
                        "from; re-run `splatzoo sfm` (or COLMAP point_triangulator) to triangulate points")
    return model, registered


def _check_photos(registered, images_dir: Path, sparse: Path) -> None:
    """Every photo must be present and whole before undistortion reads it: it would copy a gap or decode a cut-off
    JPEG as grey without a word."""
    missing = [im.name for im in registered if not (images_dir / im.name).is_file()]
    if missing:
        raise DataError(f"{len(missing)} image(s) named in {sparse} are missing from {images_dir} "
                        f"(e.g. {', '.join(missing[:3])}); restore them or re-run SfM on the images you have")
    for im in registered:
        image_size(images_dir / im.name)


def _check_camera_sizes(model, registered, images_dir: Path, sparse: Path):
    """Each image's size, and the (x, y) scale of each camera whose images are a uniformly downscaled copy; a
    DataError when an image does not match its camera's size: a stray crop or rotated photo would shift every
    pixel."""
    sizes = {im.name: image_size(images_dir / im.name) for im in registered}
    by_camera: dict[int, set] = defaultdict(set)
    for im in registered:
        by_camera[im.camera_id].add(sizes[im.name])
    cam_scale: dict[int, tuple[float, float]] = {}
    for cid, found in by_camera.items():
        cam = model.cameras[cid]
        if len(found) > 1:
            examples = {s: next(im.name for im in registered if im.camera_id == cid and sizes[im.name] == s)
                        for s in found}
            listing = ", ".join(f"{n} is {w}x{h}" for (w, h), n in sorted(examples.items(), key=lambda x: x[1]))
            raise DataError(f"images of camera {cid} in {images_dir} differ in size ({listing}); COLMAP camera "
                            f"{cid} is {cam.width}x{cam.height}. Resize them all to one size or re-run SfM "
                            "with one camera per image size")
        (w, h), = found
        if cam.width < 1 or cam.height < 1:
            raise DataError(f"COLMAP camera {cid} in {sparse} is {cam.width}x{cam.height}; a camera needs a size of at "
                            "least 1x1 (a damaged cameras file?)")
        if max(cam.width / w, cam.height / h) > MAX_DOWNSCALE:
            raise DataError(f"COLMAP camera {cid} is {cam.width}x{cam.height} but its images are {w}x{h}: more than "
                            f"{MAX_DOWNSCALE}x smaller, too far for a downscaled copy of the photos it was made from; "
                            "use those photos, or fix the camera's size")
        if (w, h) != (cam.width, cam.height):
            sx, sy = w / cam.width, h / cam.height
            # A uniformly downscaled copy of the images is fine (intrinsics scale with it); anything else is not.
            if abs(sx - sy) * max(cam.width, cam.height) > 1.0:
                name = next(im.name for im in registered if im.camera_id == cid)
                raise DataError(f"image {images_dir / name} is {w}x{h} but COLMAP camera {cid} is "
                                f"{cam.width}x{cam.height} (a different aspect ratio); use the images the model "
                                "was made from, or re-run SfM on these")
            cam_scale[cid] = (sx, sy)
    return sizes, cam_scale


def _world_to_camera(im, sparse: Path) -> np.ndarray:
    """The image's 4x4 world-to-camera matrix; a DataError when its pose is broken."""
    pose = im.cam_from_world()
    w2c = np.eye(4)
    w2c[:3, :4] = np.asarray(pose.matrix(), dtype=np.float64)
    # COLMAP stores the quaternion as written; a zero one becomes the identity rotation without a word
    quat = np.asarray(pose.rotation.quat, dtype=np.float64)
    length = float(np.linalg.norm(quat))
    if not (np.isfinite(w2c).all() and abs(length - 1) <= 1e-3):
        raise DataError(f"COLMAP model {sparse}: image {im.name} has a broken pose (its rotation quaternion "
                        f"{quat[[3, 0, 1, 2]].tolist()} (w, x, y, z) has length {length:.3g}, not 1, or its "
                        "translation is not finite); re-export the model from COLMAP or re-run `splatzoo sfm`")
    return w2c


def _image_path(name: str, images_dir: Path, resolution_dir: Path | None, cam: Camera) -> Path:
    """The image file to read: a pre-shrunk copy (Mip-NeRF 360 layout) when there is one of the camera's size."""
    path = images_dir / name
    if resolution_dir is not None and (resolution_dir / name).is_file():
        # Pre-shrunk copies (Mip-NeRF 360 layout) decode faster; accept them when they have the right size.
        rw, rh = image_size(resolution_dir / name)
        if abs(rw - cam.width) <= 1 and abs(rh - cam.height) <= 1:
            path = resolution_dir / name
    return path


def _mask_of(name: str, path: Path, masks_dir: Path | None, root: Path) -> Path | None:
    """The mask file of a view when masks are asked for (None: the image's alpha channel); a DataError when there
    is neither."""
    mask_path = find_mask(masks_dir, name) if masks_dir is not None else None
    if mask_path is None and not image_has_alpha(path):
        tried = ", ".join(dict.fromkeys([name, name + ".png", Path(name).stem + ".png"]))
        raise DataError(f"masks requested but image {path} has no alpha channel and no mask file in "
                        f"{root / 'masks'} (looked for {tried}); add masks or load without masks")
    return mask_path


def _build_views(root: Path, sparse: Path, model, registered, sizes, cam_scale, undistorted: dict, images_dir: Path,
                 resolution_dir: Path | None, masks_dir: Path | None, *, resolution, max_width, masks: bool,
                 background) -> list[View]:
    """One View per registered image, in name order, with its camera scaled to the asked resolution; an image in
    `undistorted` (name -> UndistortedPhoto) is its undistorted copy with the PINHOLE camera it was warped to."""
    views = []
    for im in sorted(registered, key=lambda im: im.name):
        copy = undistorted.get(im.name)
        if copy is not None:
            K, (w, h) = copy.K.copy(), (copy.width, copy.height)
        else:
            K, (w, h) = pinhole_K(model.cameras[im.camera_id]), sizes[im.name]
            if im.camera_id in cam_scale:
                sx, sy = cam_scale[im.camera_id]
                K[0] *= sx
                K[1] *= sy
        w2c = _world_to_camera(im, sparse)
        cam = Camera(torch.from_numpy(w2c), torch.from_numpy(K), w, h, im.name)
        cam = scale_camera(cam, target_scale(w, h, resolution, max_width))
        if copy is not None:
            path, mask_path = copy.path, copy.mask
        else:
            path = _image_path(im.name, images_dir, resolution_dir, cam)
            mask_path = _mask_of(im.name, path, masks_dir, root) if masks else None
        views.append(View(camera=cam, name=im.name, path=path, mask_path=mask_path, use_mask=masks,
                          background=tuple(background)))
    return views


def _read_points(model, sparse: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """The model's 3D points (float32) and their colours in [0, 1]; a DataError when a position is not finite or
    does not fit float32."""
    ids = sorted(model.points3D.keys())
    xyz64 = np.array([model.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    bad = ~(np.isfinite(xyz64) & (np.abs(xyz64) <= np.finfo(np.float32).max)).all(1)
    if bad.any():
        raise DataError(f"COLMAP model {sparse}: {int(bad.sum())} 3D point(s) have a non-finite or out-of-range "
                        f"position (e.g. point {ids[int(np.flatnonzero(bad)[0])]}); the points file is damaged. "
                        "Re-export the model from COLMAP or re-run `splatzoo sfm`")
    xyz = xyz64.astype(np.float32)
    rgb = np.array([model.points3D[i].color for i in ids], dtype=np.float32).reshape(-1, 3) / 255.0
    return torch.from_numpy(xyz), torch.from_numpy(rgb)


def load_colmap(root, *, resolution: int | None = None, max_width: int | None = None, test_every: int = 8,
                background=(0.0, 0.0, 0.0), masks: bool = False) -> Scene:
    """Read a COLMAP dataset folder: images/ (or images_<n>/ for resolution n) and sparse/0/."""
    root = Path(root)
    images_dir, sparse = _locate_dataset(root)
    model, registered = _read_registered(sparse)
    masks_dir = root / "masks" if (root / "masks").is_dir() else None

    _check_photos(registered, images_dir, sparse)
    used = sorted({im.camera_id for im in registered})
    for cid in used:
        check_undistortable(model.cameras[cid], sparse)
        # pycolmap takes a NaN distortion term for zero
        check_finite(model.cameras[cid], _camera_in_words(cid, registered, sparse), _LENS_FIX)
    distorted = [cid for cid in used if not is_pinhole(model.cameras[cid])]
    sizes, cam_scale = _check_camera_sizes(model, registered, images_dir, sparse)
    _check_distorted_sizes(model, distorted, cam_scale, registered, images_dir)
    undistorted = _undistort(root, model, registered, images_dir, distorted, masks_dir, masks, sparse)
    # pre-shrunk copies (images_<n>/) are read only for a dataset without distortion
    resolution_dir = root / f"images_{resolution}" if resolution in (2, 4, 8) and not distorted else None
    views = _build_views(root, sparse, model, registered, sizes, cam_scale, undistorted, images_dir, resolution_dir,
                         masks_dir, resolution=resolution, max_width=max_width, masks=masks, background=background)
    points, colors = _read_points(model, sparse)
    train, test = split_views(views, test_every, root)
    return Scene(name=root.resolve().name, root=root, train=train, test=test, points=points, colors=colors,
                 extent=camera_extent([v.camera for v in (train or views)], points),
                 background=tuple(background), mesh_path=mesh_path_of(root))


FORMAT = DatasetFormat(
    "colmap", is_colmap, load_colmap, priority=20,
    needs="images/ with the photos and sparse/0/ with cameras, images and points3D as .bin or .txt, "
          "as COLMAP or `splatzoo sfm` writes them")


# --- writing ------------------------------------------------------------------------------------------------

def write_model(out_dir, cameras: list[Camera], names: list[str], points: np.ndarray | None = None,
                colors: np.ndarray | None = None, tracks: list[list[tuple[int, np.ndarray]]] | None = None, *,
                text: bool = False) -> Path:
    """Write a COLMAP model of known PINHOLE cameras (one COLMAP camera per distinct intrinsics).

    points [M,3], colors [M,3] uint8 or [0,1] float; tracks[m] = [(view index, xy pixel position), ...]
    (observations, so the model is like one SfM would give). Writes binary, or text with text=True.
    """
    pycolmap = import_pycolmap()

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    cam_ids: dict[tuple, int] = {}
    view_cam = []
    for cam in cameras:
        K = cam.K.double()
        key = (cam.width, cam.height, *[round(float(x), 9) for x in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])])
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=key[0], height=key[1],
                                                            params=list(key[2:]), camera_id=cam_ids[key]))
        view_cam.append(cam_ids[key])
    keypoints: list[list[np.ndarray]] = [[] for _ in cameras]
    elements: list[list[tuple[int, int]]] = []
    if points is not None and tracks is not None:
        for m, track in enumerate(tracks):
            els = []
            for vi, xy in track:
                els.append((vi, len(keypoints[vi])))
                keypoints[vi].append(np.asarray(xy, dtype=np.float64))
            elements.append(els)
    for i, (cam, name) in enumerate(zip(cameras, names)):
        kp = np.array(keypoints[i], dtype=np.float64).reshape(-1, 2)
        image = pycolmap.Image(name=name, keypoints=kp, camera_id=view_cam[i], image_id=i + 1)
        w2c = cam.world_to_camera.double().numpy()
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
    if points is not None:
        cols = np.asarray(colors if colors is not None else np.full_like(points, 0.5))
        if cols.dtype != np.uint8:
            cols = (np.clip(cols, 0, 1) * 255 + 0.5).astype(np.uint8)
        for m, p in enumerate(np.asarray(points, dtype=np.float64)):
            els = elements[m] if elements else []
            track = pycolmap.Track([pycolmap.TrackElement(vi + 1, k) for vi, k in els])
            rec.add_point3D(p, track, cols[m])
    (rec.write_text if text else rec.write_binary)(str(out_dir))
    return out_dir
