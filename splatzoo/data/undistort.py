"""Undistortion: photos taken through a distorted lens warped into pinhole images, the one way both dataset readers
(COLMAP, transforms.json) do it.

Each photo is warped by pycolmap's undistorter to the PINHOLE camera it makes from the photo's lens (the same focal
length, cropped to the region every pixel of which sees the photo); its alpha channel and its mask are warped by the
same map. The copies live in one folder per dataset, DATA/<folder name> (or ~/.cache/splatzoo/<folder name>/<hash of
DATA> when DATA is read-only): the photo DATA/<path>.<ext> becomes <folder>/<path>.<stamp>.png and its mask
<folder>/masks/<path>.<stamp>.png. The stamp is a fingerprint of the lens and the source file (path, size, time), so
a copy is made once, reused while its photo and lens are unchanged, and replaced (the old one deleted) when either
changes. Copies of the layout older splatzoo versions made for COLMAP datasets (one whole undistorted dataset:
images/, sparse/ and a source.json naming what it was made from) are removed when the per-photo copies are first made
(remove_older_layout).

Before any pixel is warped each distinct lens is checked: a lens that keeps too little of its photo is refused and one
that keeps little is warned about (camera_models.check_lens), as is a lens whose distortion folds back inside the
photo (camera_models.fold_warning); a lens pycolmap cannot invert, or whose pinhole image would be absurdly large, is
refused.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import DataError
from .camera_models import check_lens, fold_warning, for_undistortion, import_pycolmap
from .scene import read_image, read_mask

MAX_GROWTH = 4  # a pinhole image over this many times the photo's width or height: the lens is wrong


@dataclass
class DistortedPhoto:
    """A photo to undistort: its file (inside the dataset folder), the pycolmap camera it was taken with (at the
    photo's size), that camera in words for warnings and errors, and its mask file (None: no mask to warp)."""

    path: Path
    lens: object
    who: str
    mask: Path | None = None


@dataclass
class UndistortedPhoto:
    """A photo's undistorted copy, its mask's (None: no mask), and the PINHOLE camera it was warped to: 3x3 K and
    size."""

    path: Path
    mask: Path | None
    K: np.ndarray
    width: int
    height: int


def undistort_photos(root: Path, folder_name: str, photos: list[DistortedPhoto], fix: str) -> list[UndistortedPhoto]:
    """The undistorted copies of `photos` (photos of the dataset folder `root`), in their order, made in the folder
    `folder_name` of the module docstring where they are not there already. `fix` ends every warning and refusal
    about a lens: what the user should do about it."""
    pycolmap = import_pycolmap()
    options = pycolmap.UndistortCameraOptions()
    target = undistorted_dir(root, folder_name)
    if target.exists() and not target.is_dir():
        raise DataError(f"{target} is a file, but splatzoo keeps the undistorted copies of {root}'s photos in a folder "
                        "of that name; move or delete that file and load again")
    _check_lenses(photos, fix)
    remove_older_layout(root, target)
    pinholes: dict[tuple, object] = {}
    done, jobs = [], []
    for photo in photos:
        warped_lens = for_undistortion(photo.lens) or photo.lens  # a fisheye with zero terms is still warped
        key = _lens_key(warped_lens)
        if key not in pinholes:
            pinholes[key] = _pinhole_camera(options, warped_lens, photo, fix)
        pinhole = pinholes[key]
        stem = photo.path.relative_to(root).with_suffix("")
        out = target / f"{stem}.{_stamp(warped_lens, photo.path)}.png"
        mask_out = target / "masks" / f"{stem}.{_stamp(warped_lens, photo.mask)}.png" if photo.mask else None
        if not out.is_file() or (mask_out is not None and not mask_out.is_file()):
            jobs.append((photo, warped_lens, out, mask_out))
        K = np.array([[pinhole.focal_length_x, 0, pinhole.principal_point_x],
                      [0, pinhole.focal_length_y, pinhole.principal_point_y], [0, 0, 1]], dtype=np.float64)
        done.append(UndistortedPhoto(out, mask_out, K, int(pinhole.width), int(pinhole.height)))
    if jobs:
        print(f"splatzoo: undistorting {len(jobs)} image(s) of {root} into {target} (done once, reused later) ...",
              file=sys.stderr, flush=True)
    for photo, warped_lens, out, mask_out in jobs:
        if not out.is_file():
            px = read_image(photo.path)
            warped = _warp(options, warped_lens, px[:, :, :3])
            if px.shape[2] == 4:   # alpha is warped by the same map
                warped = np.concatenate([warped, _warp(options, warped_lens, px[:, :, 3])[:, :, None]], axis=2)
            _write_png(out, warped)
        if mask_out is not None and not mask_out.is_file():
            _write_png(mask_out, _warp(options, warped_lens, read_mask(photo.mask)))
    return done


def undistorted_dir(root: Path, folder_name: str) -> Path:
    """DATA/<folder_name>, or a per-dataset folder under ~/.cache/splatzoo/<folder_name> when DATA is read-only."""
    if os.access(root, os.W_OK):
        return root / folder_name
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "splatzoo" / folder_name
    return cache / hashlib.sha1(str(root.resolve()).encode()).hexdigest()[:16]


STAMPED = re.compile(r".+\.[0-9a-f]{12}\.png")  # a per-photo copy: <name>.<stamp>.png


def remove_older_layout(root: Path, target: Path) -> int:
    """Remove the undistorted dataset an older splatzoo made of `root`: in `target` (its images/, masks/ and sparse/
    beside today's stamped copies, marked by a source.json with a "stamp"), and, for a read-only dataset, the cache
    folder beside `target` whose source.json names `root`. Only what that layout wrote goes; returns the number of
    files removed."""
    def made_by_older_layout(folder: Path) -> bool:
        try:
            marker = json.loads((folder / "source.json").read_text())
        except (OSError, ValueError):
            return False
        if not (isinstance(marker, dict) and "stamp" in marker):
            return False
        return folder == target or str(marker.get("from")) in (str(root), str(root.resolve()))

    def files(folder: Path) -> list[Path]:
        return [p for p in folder.rglob("*") if p.is_file()] if folder.is_dir() else []

    siblings = ([p for p in target.parent.iterdir() if p != target and p.is_dir()]
                if target.parent != root and target.parent.is_dir() else [])  # the cache's other datasets
    removed = 0
    for folder in filter(made_by_older_layout, [target] + siblings):
        if folder != target:   # a whole cache folder of the older layout
            removed += len(files(folder))
            shutil.rmtree(folder, ignore_errors=True)
            continue
        old = [p for sub in ("images", "masks") for p in files(folder / sub) if not STAMPED.fullmatch(p.name)]
        for p in old + [folder / "source.json"]:
            p.unlink(missing_ok=True)
        removed += len(old) + 1 + len(files(folder / "sparse"))
        shutil.rmtree(folder / "sparse", ignore_errors=True)
    if removed:
        print(f"splatzoo: removed {removed} file(s) of an older undistorted copy of {root} (now kept photo by photo "
              f"in {target})", file=sys.stderr, flush=True)
    return removed


def _lens_key(lens) -> tuple:
    return lens.model_name, tuple(lens.params), lens.width, lens.height


def _check_lenses(photos: list[DistortedPhoto], fix: str) -> None:
    """check_lens and fold_warning once per distinct lens, naming the first photo's camera; warnings are printed."""
    seen = set()
    for photo in photos:
        key = _lens_key(photo.lens)
        if key in seen:
            continue
        seen.add(key)
        for warning in (check_lens(photo.lens, photo.who, fix),
                        fold_warning(photo.lens, photo.who, fix[0].upper() + fix[1:])):
            if warning:
                print(f"splatzoo: warning: {warning}", file=sys.stderr, flush=True)


def _pinhole_camera(options, lens, photo: DistortedPhoto, fix: str):
    """The PINHOLE camera pycolmap's undistorter makes from `lens`; a DataError when it makes none or an absurd one."""
    pycolmap = import_pycolmap()
    try:
        pinhole = pycolmap.undistort_camera(options, lens)
    except Exception as e:  # pycolmap rejects a camera it cannot invert
        raise DataError(f"cannot undistort {photo.path}: pycolmap rejects its camera ({lens.model_name}: "
                        f"{lens.params_to_string()}): {e}; {fix}") from None
    w, h = int(pinhole.width), int(pinhole.height)
    if not (1 <= w <= MAX_GROWTH * lens.width and 1 <= h <= MAX_GROWTH * lens.height):
        raise DataError(f"cannot undistort {photo.path}: its camera ({lens.model_name}: "
                        f"{lens.params_to_string()}) would become a {w}x{h} image from a {lens.width}x{lens.height} "
                        f"photo; {fix}")
    return pinhole


def _stamp(lens, *files: Path | None) -> str:
    """What an undistorted file was made from: the camera and each source file's path, size and time."""
    h = hashlib.sha1(f"{lens.model_name}|{lens.width}x{lens.height}|{list(lens.params)!r}".encode())
    for f in files:
        if f is not None:
            st = f.stat()
            h.update(f"|{f.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    return h.hexdigest()[:12]


def _warp(options, lens, px: np.ndarray) -> np.ndarray:
    """pycolmap's undistortion of uint8 [H,W,3] or [H,W] pixels."""
    pycolmap = import_pycolmap()
    out, _ = pycolmap.undistort_image(options, pycolmap.Bitmap.from_array(np.ascontiguousarray(px)), lens)
    return np.asarray(out.to_array())


def _write_png(path: Path, px: np.ndarray) -> None:
    """Write atomically (splatzoo.atomic): a cache file is whole or absent. Older copies of the same
    photo (another stamp), left by a changed photo or lens, are deleted."""
    import cv2

    if px.ndim == 3:
        px = px[:, :, [2, 1, 0, 3]] if px.shape[2] == 4 else px[:, :, ::-1]
    ok, data = cv2.imencode(".png", np.ascontiguousarray(px))
    if not ok:
        raise DataError(f"cannot encode the undistorted image {path}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocking = next((p for p in reversed(path.parents) if p.exists() and not p.is_dir()), path.parent)
        raise DataError(f"cannot write the undistorted image {path}: {blocking} is a file where splatzoo needs a "
                        "folder; move or delete that file and load again") from None
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.tobytes())
    pattern = re.compile(re.escape(path.name.rsplit(".", 2)[0]) + r"\.[0-9a-f]{12}\.png")
    for stale in path.parent.iterdir():
        if stale != path and pattern.fullmatch(stale.name):
            stale.unlink(missing_ok=True)
