"""Scene and View: what every dataset reader returns; DatasetFormat: what a reader declares (formats.py keeps the
registry and `load_scene`); image decoding and helpers shared by the readers.

Images stay on disk until asked for: a View decodes its file on first use and keeps the pixels only while a
process-wide byte budget allows (env SPLATZOO_IMAGE_CACHE_MB, default 1024), so a 200-image full-HD capture
does not need tens of GB while a 48-view 256x256 synthetic scene is decoded once.
"""
from __future__ import annotations

import contextlib
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..errors import DataError
from ..types import Camera


class MissingMaskError(DataError):
    """A mask that the dataset's own files name but that does not exist: loading stops (masks="auto" does not fall
    back to loading without masks, as it does for an incomplete masks/ folder)."""


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr")


# --- image decoding ---------------------------------------------------------------------------------------

_JPEG_START, _JPEG_END = b"\xff\xd8", b"\xff\xd9"
_PNG_START, _PNG_END = b"\x89PNG\r\n\x1a\n", b"IEND\xaeB`\x82"
_PADDING = b"\x00\xff\r\n\t "   # what some writers leave after the end marker
_TAIL = 4096


def _missing_end(head: bytes, tail: bytes) -> str | None:
    """Why a JPEG or PNG file is cut short, judged by its end marker, or None if it ends properly (or is another
    format). A decoder fills a cut-off JPEG with grey without complaint, so the marker is the cheap signal."""
    if head.startswith(_JPEG_START) and not tail.rstrip(_PADDING).endswith(_JPEG_END):
        return "the JPEG data stops before its end-of-image marker (FFD9)"
    if head.startswith(_PNG_START) and not tail.rstrip(_PADDING).endswith(_PNG_END):
        return "the PNG data stops before its IEND chunk"
    return None


@contextlib.contextmanager
def _no_pixel_limit():
    """PIL refuses images over about 179 MP as possible decompression bombs, even to read their header. A real
    photo can be that large and is decoded once (then downscaled, see target_scale), so the limit is lifted for our
    own reads; a crafted header over a small body still fails to decode and is named as damaged."""
    from PIL import Image

    saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
    try:
        yield
    finally:
        Image.MAX_IMAGE_PIXELS = saved


def _decodes_fully(source) -> str | None:
    """The decoder's verdict for a file whose end marker is missing: None when PIL decodes every pixel (extra data
    after the image, as some cameras append, is fine), else its complaint."""
    from PIL import Image

    try:
        with _no_pixel_limit(), Image.open(source) as im:
            im.load()
        return None
    except Exception as e:  # PIL raises OSError, SyntaxError, ValueError... for damaged data
        return str(e) or type(e).__name__


def _truncated_error(path: Path, reason: str) -> DataError:
    return DataError(f"image {path} is truncated or damaged ({reason}); the file was probably cut off while being "
                     "copied or downloaded. Copy it again from the original, or delete it (and re-run "
                     "`splatzoo sfm` if it is part of a COLMAP model)")


def check_image_complete(path: Path, data: bytes | None = None) -> None:
    """A DataError naming `path` when the file is a JPEG or PNG cut short. Reads only the first and last few
    kilobytes unless the end marker is missing (then the decoder decides); `data`: the file's bytes if in memory."""
    if data is not None:
        head, tail = data[:16], data[-_TAIL:]
    else:
        with open(path, "rb") as f:
            head = f.read(16)
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - _TAIL))
            tail = f.read()
    reason = _missing_end(head, tail)
    if reason is None:
        return
    import io

    complaint = _decodes_fully(io.BytesIO(data) if data is not None else path)
    if complaint is not None:
        raise _truncated_error(Path(path), f"{reason}; the decoder says: {complaint}")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file from its header, without decoding the pixels; a missing, unreadable or
    truncated (JPEG/PNG) file is a DataError that names it."""
    from PIL import Image, UnidentifiedImageError

    try:
        with _no_pixel_limit(), Image.open(path) as im:
            size = int(im.size[0]), int(im.size[1])
        check_image_complete(path)
        return size
    except FileNotFoundError:
        raise DataError(f"image {path} does not exist; restore the file or remove it from the dataset") from None
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise DataError(f"image {path} is unreadable or corrupt ({e}); re-export the image or delete it "
                        "and re-run SfM") from None


def image_has_alpha(path: Path) -> bool:
    from PIL import Image

    try:
        with _no_pixel_limit(), Image.open(path) as im:
            return im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info)
    except OSError:
        return False


def read_image(path: Path) -> np.ndarray:
    """Decode to uint8 [H,W,3] RGB or [H,W,4] RGBA (straight alpha). EXIF rotation is ignored, as COLMAP does.
    A truncated JPEG or PNG is a DataError (decoders would fill the missing part with grey)."""
    import cv2

    try:
        raw = Path(path).read_bytes()
    except FileNotFoundError:
        raise DataError(f"image {path} does not exist; restore the file or remove it from the dataset") from None
    except OSError as e:
        raise DataError(f"image {path} cannot be read ({e.strerror or e}); check the file and its "
                        "permissions") from None
    check_image_complete(path, raw)
    data = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED) if raw else None
    if data is None or data.size == 0:
        raise DataError(f"image {path} is unreadable or corrupt (cannot decode it); re-export the image "
                        "or delete it and re-run SfM")
    if data.dtype == np.uint16:
        data = (data.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    elif data.dtype != np.uint8:  # float EXR and friends: assume [0,1]
        data = (np.clip(data.astype(np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)
    if data.ndim == 2:
        data = data[:, :, None]
    c = data.shape[2]
    if c == 1:
        return np.repeat(data, 3, axis=2)
    if c == 2:  # grey + alpha
        return np.concatenate([np.repeat(data[:, :, :1], 3, axis=2), data[:, :, 1:]], axis=2)
    if c == 3:
        return np.ascontiguousarray(data[:, :, ::-1])
    return np.ascontiguousarray(data[:, :, [2, 1, 0, 3]])


def read_mask(path: Path) -> np.ndarray:
    """Decode a mask file to uint8 [H,W]: its alpha channel if it has one, else its grey level."""
    px = read_image(path)
    return px[:, :, 3] if px.shape[2] == 4 else px[:, :, :3].max(axis=2)


def _resize(px: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    if px.shape[1] == width and px.shape[0] == height:
        return px
    shrink = width < px.shape[1] and height < px.shape[0]
    out = cv2.resize(px, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return out[:, :, None] if out.ndim == 2 and px.ndim == 3 else out


class _PixelCache:
    """Decoded pixels kept while they fit a byte budget; beyond it views decode on every call."""

    def __init__(self) -> None:
        self._items: dict[tuple, np.ndarray] = {}
        self._used = 0
        self._lock = threading.Lock()

    @staticmethod
    def budget() -> int:
        try:
            return int(float(os.environ.get("SPLATZOO_IMAGE_CACHE_MB", "1024")) * 2**20)
        except ValueError:
            return 2**30

    def get(self, key: tuple, load) -> np.ndarray:
        with self._lock:
            hit = self._items.get(key)
        if hit is not None:
            return hit
        px = load()
        px.setflags(write=False)  # shared between callers: nobody may edit it in place
        with self._lock:
            if self._used + px.nbytes <= self.budget():
                self._items[key] = px
                self._used += px.nbytes
        return px

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._used = 0


PIXEL_CACHE = _PixelCache()


# --- View and Scene ---------------------------------------------------------------------------------------

@dataclass(eq=False)   # identity: views can key dicts, and tensors have no truth value
class View:
    """One posed image. `camera` is float32 and already scaled to the requested resolution.

    image() -> uint8 [H,W,3]; image_float() -> float32 [H,W,3] in [0,1], RGBA sources composited over
    `background`; mask() -> float32 [H,W] in [0,1] (None unless masks were requested when loading).
    """

    camera: Camera
    name: str
    path: Path | None = field(default=None, repr=False)
    mask_path: Path | None = field(default=None, repr=False)   # a separate mask file, if any
    use_mask: bool = field(default=False, repr=False)          # mask() answers (from mask_path or alpha)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    pixels: np.ndarray | None = field(default=None, repr=False, compare=False)  # in-memory source

    @staticmethod
    def from_tensor(camera: Camera, image: torch.Tensor, name: str = "", *,
                    background=(0.0, 0.0, 0.0)) -> "View":
        """A view over an in-memory image: uint8 or float [0,1], [H,W,3] or [H,W,4] (straight alpha)."""
        a = torch.as_tensor(image).detach().cpu()
        if a.is_floating_point():
            a = (a.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
        if a.dim() != 3 or a.shape[2] not in (3, 4):
            raise DataError(f"View.from_tensor: image must be [H,W,3] or [H,W,4], got {list(a.shape)}")
        return View(camera=camera, name=name or camera.name, background=tuple(background),
                    use_mask=a.shape[2] == 4, pixels=a.numpy())

    # Premultiplied RGB (+ alpha) at camera size: resizing premultiplied colour keeps edges free of fringes.
    def _premultiplied(self) -> np.ndarray:
        w, h = self.camera.width, self.camera.height
        if self.pixels is not None:
            return self._premultiplied_at(w, h)
        return PIXEL_CACHE.get(("img", str(self.path), w, h), lambda: self._premultiplied_at(w, h))

    def _premultiplied_at(self, w: int, h: int) -> np.ndarray:
        px = self.pixels if self.pixels is not None else read_image(self.path)
        if px.shape[2] == 4:
            f = px.astype(np.float32)
            a = f[:, :, 3:4] / 255.0
            f = np.concatenate([f[:, :, :3] * a, f[:, :, 3:4]], axis=2)
            f = _resize(f, w, h)
            return (np.clip(f, 0, 255) + 0.5).astype(np.uint8)
        return _resize(np.ascontiguousarray(px[:, :, :3]), w, h)

    def source_size(self) -> tuple[int, int]:
        """(width, height) of the image as stored (the file, or the in-memory pixels), whatever the camera's size."""
        if self.pixels is not None:
            return int(self.pixels.shape[1]), int(self.pixels.shape[0])
        if self.path is not None:
            return image_size(self.path)
        return self.camera.width, self.camera.height

    def image(self) -> torch.Tensor:
        """uint8 [H,W,3] at camera size."""
        px = self._premultiplied()
        if px.shape[2] == 3:
            return torch.from_numpy(px.copy())
        return (self._composite(px) * 255 + 0.5).to(torch.uint8)

    def image_at(self, width: int, height: int) -> torch.Tensor:
        """uint8 [height,width,3]: the image resized to another size than the camera's (transparency over the view's
        background), decoded afresh and not kept in the pixel cache, which holds what training reads."""
        px = self._premultiplied_at(width, height)
        if px.shape[2] == 3:
            return torch.from_numpy(np.array(px))   # a copy: px may be the view's own pixels
        return (self._composite(px) * 255 + 0.5).to(torch.uint8)

    def image_float(self, background=None) -> torch.Tensor:
        """float32 [H,W,3] in [0,1] at camera size; transparent pixels show `background` (default: the view's).
        A photo without alpha but with a mask shows `background` in place of its backdrop: the uniform colour
        `self.background` around the object, replaced in proportion to 1 - mask (exact for an anti-aliased mask of an
        object shot in front of that colour)."""
        px = self._premultiplied()
        if px.shape[2] == 3:
            photo = torch.from_numpy(px.astype(np.float32) / np.float32(255.0))
            if background is None or not self.use_mask:
                return photo
            change = torch.as_tensor(background, dtype=torch.float32) - torch.as_tensor(self.background,
                                                                                     dtype=torch.float32)
            return (photo + (1 - self.mask()[..., None]) * change).clamp_(0, 1)
        return self._composite(px, background)

    def _composite(self, px: np.ndarray, background=None) -> torch.Tensor:
        t = torch.from_numpy(px.astype(np.float32) / np.float32(255.0))
        bg = torch.as_tensor(self.background if background is None else background, dtype=torch.float32)
        return (t[:, :, :3] + (1 - t[:, :, 3:4]) * bg).clamp_(0, 1)

    def mask(self) -> torch.Tensor | None:
        """float32 [H,W] in [0,1], or None when masks were not requested."""
        if not self.use_mask:
            return None
        w, h = self.camera.width, self.camera.height
        if self.mask_path is None:
            px = self._premultiplied()
            if px.shape[2] != 4:
                raise DataError(f"image {self.path} has no alpha channel and no mask file; load without masks")
            return torch.from_numpy(px[:, :, 3].astype(np.float32) / np.float32(255.0))

        def load() -> np.ndarray:
            return _resize(read_mask(self.mask_path), w, h)

        m = PIXEL_CACHE.get(("mask", str(self.mask_path), w, h), load)
        return torch.from_numpy(m.astype(np.float32) / np.float32(255.0))


@dataclass(eq=False)
class Scene:
    """A dataset ready for training: views split into train/test, an initial point cloud and its scale."""

    name: str
    root: Path
    train: list[View]
    test: list[View]
    points: torch.Tensor      # [M,3] float32
    colors: torch.Tensor      # [M,3] float32 in [0,1]
    extent: float             # 1.1 x radius of the (train) camera centres around their mean
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mesh_path: Path | None = None
    random_background: bool = False   # training draws a new background colour per view and step
    masked_backdrop: bool = False     # ... put behind the object through the masks, in place of the photos' backdrop
    background_note: str = ""         # how the background was chosen (when it was not given)
    notes: list[str] = field(default_factory=list)  # what loading decided for the user (shown when training starts)

    @property
    def views(self) -> list[View]:
        """Every view, sorted by name."""
        return sorted(self.train + self.test, key=lambda v: v.name)

    def __repr__(self) -> str:
        return (f"Scene({self.name!r}, root={str(self.root)!r}, train={len(self.train)}, test={len(self.test)}, "
                f"points={self.points.shape[0]}, extent={self.extent:.4g})")


@dataclass(frozen=True)
class DatasetFormat:
    """A dataset folder layout that `load_scene` reads (registered in splatzoo.data.formats).

    detect(path) -> bool: cheap (file names only), True when the folder looks like this format.
    load(path, *, resolution, max_width, test_every, background, masks) -> Scene.
    needs: what a folder of this format holds, shown when no format recognises a folder.
    priority: lower is tried first, so a specific layout wins over a generic one that also matches.
    has_masks(path) -> bool: whether masks="auto" reads masks (default: the folder has masks/).
    """

    name: str
    detect: Callable[[Path], bool]
    load: Callable[..., Scene]
    needs: str
    priority: int = 100
    has_masks: Callable[[Path], bool] | None = None


# --- helpers shared by the readers --------------------------------------------------------------------------

# The widest field of view a perspective camera may have (a focal below this is a broken calibration, e.g. 0 or a
# subnormal number that float32 rounds to 0), the narrowest (degrees), and how far outside the image the principal
# point may lie, in image sizes.
MAX_FOV_DEG = 179.0
MIN_FOV_DEG = 1e-3
PRINCIPAL_POINT_RANGE = 1.0


def check_cameras(views: list, where) -> None:
    """Every view's camera is one a photo can have: a focal that gives a field of view between MIN_FOV_DEG and
    MAX_FOV_DEG, a principal point within PRINCIPAL_POINT_RANGE image sizes of the image, a rotation (orthonormal,
    determinant +1; a zero quaternion is not one), and a name no other view has. Raises DataError naming the view."""
    import math

    seen: dict[str, int] = {}
    for v in views:
        cam = v.camera
        name = v.name or cam.name
        if name in seen:
            raise DataError(f"{where}: two views are named {name!r}; image names must be unique (a duplicated "
                            "frame in the camera file?)")
        seen[name] = 1
        K = cam.K.double()
        for axis, f, size in (("x", float(K[0, 0]), cam.width), ("y", float(K[1, 1]), cam.height)):
            lo = 0.5 * size / math.tan(math.radians(MAX_FOV_DEG) / 2)
            hi = 0.5 * size / math.tan(math.radians(MIN_FOV_DEG) / 2)
            if not lo <= f <= hi:
                raise DataError(f"{where}: view {name!r} has focal f{axis} = {f:g} px for a {cam.width}x{cam.height} "
                                f"image; a perspective camera needs {lo:.3g}..{hi:.3g} px (field of view "
                                f"{MIN_FOV_DEG:g}..{MAX_FOV_DEG:g} degrees). Check the intrinsics (units: pixels)")
        cx, cy = float(K[0, 2]), float(K[1, 2])
        r = PRINCIPAL_POINT_RANGE
        if not (-r * cam.width <= cx <= (1 + r) * cam.width and -r * cam.height <= cy <= (1 + r) * cam.height):
            raise DataError(f"{where}: view {name!r} has its principal point at ({cx:g}, {cy:g}), far outside its "
                            f"{cam.width}x{cam.height} image; check cx, cy (pixels)")
        R = cam.R.double()
        err = float((R @ R.T - torch.eye(3, dtype=torch.float64)).abs().max())
        if not (err < 1e-3 and float(torch.linalg.det(R)) > 0):
            raise DataError(f"{where}: view {name!r} has a camera orientation that is not a rotation (|R Rt - I| = "
                            f"{err:.3g}); a zero or broken quaternion or matrix in the pose file")


def camera_extent(cameras: list[Camera], points: torch.Tensor | None = None) -> float:
    """1.1 x the radius of the camera centres around their mean (the 2DGS/3DGS convention).

    With a single camera (or all at one spot) the radius is 0; then the point cloud's radius stands in, so
    learning rates scaled by the extent stay sensible.
    """
    centers = torch.stack([c.center.double() for c in cameras])
    radius = float((centers - centers.mean(0)).norm(dim=1).max())
    if radius < 1e-9 and points is not None and len(points) > 1:
        p = points.double()
        radius = float((p - p.mean(0)).norm(dim=1).max())
    return 1.1 * (radius if radius > 1e-9 else 1.0)


def scene_option_problem(key: str, value) -> str | None:
    """Why `value` cannot be load_scene's option `key` (resolution, max_width, test_every or skip_missing), or None."""
    import math

    whole = isinstance(value, int) and not isinstance(value, bool)
    if key == "resolution":
        if value is None or (whole and value in (1, 2, 4, 8)):
            return None
        return (f"resolution={value!r:.60} is not supported: use 1, 2, 4 or 8 (a downscale factor), or max_width for "
                "any other size")
    if key == "max_width":
        try:
            ok = value is None or (isinstance(value, (int, float)) and not isinstance(value, bool)
                                   and math.isfinite(float(value)) and value >= 1)
        except OverflowError:  # an integer too large for a float
            ok = False
        return None if ok else f"max_width={value!r:.60} must be a positive number of pixels"
    if key == "skip_missing":
        return None if isinstance(value, bool) else f"skip_missing={value!r:.60} must be true or false"
    if key == "test_every":
        if whole and (value == 0 or value >= 2):
            return None
        return (f"test_every={value!r:.60} is not allowed: use 0 (no test split) or a whole number >= 2 (every n-th "
                "image, by sorted name, is a test view)")
    return None


def split_views(views: list[View], test_every: int, where: Path) -> tuple[list[View], list[View]]:
    """Sort by name; index % test_every == 0 is a test view (0 disables the split)."""
    problem = scene_option_problem("test_every", test_every)
    if problem:
        raise DataError(problem)
    views = sorted(views, key=lambda v: v.name)
    if test_every == 0:
        return views, []
    test = [v for i, v in enumerate(views) if i % test_every == 0]
    train = [v for i, v in enumerate(views) if i % test_every != 0]
    if not train:
        raise DataError(f"{where}: only {len(views)} image(s), all of which would be test views; "
                        "load with test_every=0 or add images")
    return train, test


def target_scale(width: int, height: int, resolution: int | None, max_width: int | None) -> float:
    """The factor applied to a camera of this size: 1/resolution, then capped so width <= max_width."""
    factor = 1.0
    for key, value in (("resolution", resolution), ("max_width", max_width)):
        problem = scene_option_problem(key, value)
        if problem:
            raise DataError(problem)
    if resolution is not None:
        factor = 1.0 / resolution
    if max_width is not None:
        factor = min(factor, float(max_width) / width)
    return factor


def scale_camera(cam: Camera, factor: float) -> Camera:
    cam = cam.scaled(factor) if factor != 1.0 else cam
    return cam.to(dtype=torch.float32)


def list_images(folder: Path) -> list[Path]:
    """Image files under `folder` (recursively), sorted, as paths relative to it."""
    return sorted(p.relative_to(folder) for p in folder.rglob("*")
                  if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))


def find_mask(masks_dir: Path, name: str) -> Path | None:
    """masks/<name>, masks/<name>.png or masks/<stem>.png: the common conventions."""
    for cand in (masks_dir / name, masks_dir / (name + ".png"), (masks_dir / name).with_suffix(".png")):
        if cand.is_file():
            return cand
    return None


def mesh_path_of(root: Path) -> Path | None:
    """A ground-truth mesh named by scene.json (synthetic scenes), else mesh.ply if present."""
    import json

    info = root / "scene.json"
    if info.is_file():
        try:
            mesh = json.loads(info.read_text()).get("mesh")
        except (OSError, ValueError, AttributeError):
            mesh = None
        if mesh and (root / mesh).is_file():
            return root / mesh
    return root / "mesh.ply" if (root / "mesh.ply").is_file() else None
