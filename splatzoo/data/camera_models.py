"""COLMAP camera models: which ones a dataset may use, the pinhole intrinsics of those that need no undistortion,
and the adjustments pycolmap's undistorter needs.

What pycolmap's undistorter does with each model (checked against the installed pycolmap in the tests):
- every perspective model (pinhole, radial, OpenCV, division, FOV, EUCM and the fisheye models) is warped to a
  PINHOLE camera;
- a camera whose distortion terms are all zero is copied unchanged. For the non-fisheye models that camera *is*
  a pinhole camera and loads directly; a fisheye model with zero terms (and SIMPLE_FISHEYE / FISHEYE, which have
  none) is still a fisheye projection, so it is handed to the undistorter as the equivalent OPENCV_FISHEYE camera
  with a first term too small to move any pixel (1e-7 rad per rad^3) but large enough to be warped;
- non-perspective models (EQUIRECTANGULAR panoramas) cannot become a pinhole image at all: loading names them.
"""
from __future__ import annotations

import numpy as np

from ..errors import DataError

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
# Smallest first fisheye term that pycolmap treats as distortion (it ignores |k| <= 1e-8) with room to spare.
_FISHEYE_NUDGE = 1e-7


def import_pycolmap():
    """pycolmap, with SIGTERM handled as before: importing it installs a handler (its logging library's) that
    prints a C++ stack trace and kills the process, skipping every clean-up and checkpoint on the way out."""
    import signal
    import threading

    before = signal.getsignal(signal.SIGTERM)
    import pycolmap

    if before is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, before)
    return pycolmap


def model_name(cam) -> str:
    return cam.model_name if hasattr(cam, "model_name") else str(cam.model).split(".")[-1]


def all_models() -> list[str]:
    """Every camera model the installed pycolmap knows."""
    pycolmap = import_pycolmap()
    return [n for n in pycolmap.CameraModelId.__members__ if n != "INVALID"]


def _example(name: str):
    return import_pycolmap().Camera.create_from_model_name(1, name, 100.0, 64, 48)


def undistortable_models() -> list[str]:
    """The models pycolmap can warp to a pinhole image: the perspective ones."""
    return [n for n in all_models() if _example(n).is_perspective()]


def is_pinhole(cam) -> bool:
    """A camera that needs no undistortion: PINHOLE, SIMPLE_PINHOLE, or a non-fisheye perspective model whose
    distortion terms are all zero."""
    return model_name(cam) in PINHOLE_MODELS or (cam.is_perspective_pinhole() and cam.is_undistorted())


def pinhole_K(cam) -> np.ndarray:
    """3x3 intrinsics of a camera for which is_pinhole() holds."""
    if not is_pinhole(cam):
        raise DataError(f"camera {cam.camera_id} ({model_name(cam)}: {cam.params_to_string()}) is not a pinhole "
                        "camera and was not undistorted; delete the dataset's undistorted/ folder and load it again")
    return np.array([[cam.focal_length_x, 0, cam.principal_point_x], [0, cam.focal_length_y, cam.principal_point_y],
                     [0, 0, 1]], dtype=np.float64)


def check_undistortable(cam, where) -> None:
    """A DataError naming the camera's model when pycolmap cannot turn its images into pinhole images."""
    if cam.is_perspective():
        return
    import pycolmap

    name = model_name(cam)
    kind = " (a spherical 360-degree panorama)" if cam.is_spherical() else ""
    raise DataError(f"camera {cam.camera_id} of {where} uses the {name} camera model{kind}, which splatzoo cannot "
                    f"use: training needs pinhole images, and pycolmap {pycolmap.__version__} undistorts only "
                    f"perspective models ({', '.join(undistortable_models())}). Re-run SfM with one of those "
                    "(`splatzoo sfm IMAGES --out DATA --camera-model OPENCV`), or cut the panoramas into perspective "
                    "views first")


def for_undistortion(cam):
    """The camera to hand to pycolmap's undistorter in place of `cam`, or None when `cam` itself is warped correctly.
    A fisheye camera with all distortion terms zero would be copied unwarped (see the module doc)."""
    if not (cam.is_perspective_fisheye() and cam.is_undistorted()):
        return None
    pycolmap = import_pycolmap()
    params = [cam.focal_length_x, cam.focal_length_y, cam.principal_point_x, cam.principal_point_y,
              _FISHEYE_NUDGE, 0.0, 0.0, 0.0]
    return pycolmap.Camera(model="OPENCV_FISHEYE", width=cam.width, height=cam.height, params=params,
                           camera_id=cam.camera_id)


# --- plausibility of a fitted camera ----------------------------------------------------------------------------

def projection_profile(cam, directions: int = 32, steps: int = 1500) -> dict:
    """How the camera maps rays to pixels, swept outward from the optical axis in several directions.

    fold_px: distance in pixels from the principal point at which the image stops moving outward while still inside
    the photo (the distortion polynomial turns back: undistorting folds the photo onto itself as ghost rings), or
    None when the mapping grows all the way to the photo's border. corner_px: distance to the farthest corner.
    corner_distortion: radial displacement at the corners relative to a pinhole camera of the same focal length
    (-0.1: barrel, 10 % inward), None for fisheye models (distorted by design) and for folding cameras.
    """
    w, h = cam.width, cam.height
    cx, cy = cam.principal_point_x, cam.principal_point_y
    corners = np.array([[0, 0], [w, 0], [0, h], [w, h]], dtype=np.float64) - [cx, cy]
    corner_px = float(np.linalg.norm(corners, axis=1).max())
    # ray directions (x, y) in the camera's normalised plane toward the corners and all around
    phi = np.concatenate([np.linspace(0, 2 * np.pi, directions, endpoint=False),
                          np.arctan2(corners[:, 1] / cam.focal_length_y, corners[:, 0] / cam.focal_length_x)])
    theta = np.linspace(0, np.radians(89.9), steps)
    T, P = np.meshgrid(theta, phi)                                    # [D, S]
    rays = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    with np.errstate(all="ignore"):
        xy = np.asarray(cam.img_from_cam(rays, check_cheirality=False), dtype=np.float64).reshape(len(phi), steps, 2)
        rho = np.linalg.norm(xy - [cx, cy], axis=2)
        inside = (xy[..., 0] >= 0) & (xy[..., 0] <= w) & (xy[..., 1] >= 0) & (xy[..., 1] <= h) & np.isfinite(rho)
    fold_px = None
    for d in range(len(phi)):
        leaves = np.flatnonzero(~inside[d])
        end = leaves[0] if len(leaves) else steps          # samples before the ray leaves the photo
        r = rho[d, :end]
        turn = np.flatnonzero(~(np.diff(r) > 0))           # not growing (or not finite)
        if len(turn):
            at = float(r[turn[0]])
            fold_px = at if fold_px is None else min(fold_px, at)
        elif end < steps and not np.isfinite(rho[d, end]):
            at = float(r[-1]) if len(r) else 0.0
            fold_px = at if fold_px is None else min(fold_px, at)
    corner_distortion = None
    if fold_px is None and not cam.is_perspective_fisheye():
        f = float(np.sqrt(cam.focal_length_x * cam.focal_length_y))
        worst = 0.0
        for d in range(directions, len(phi)):               # the corner directions
            leaves = np.flatnonzero(~inside[d])
            i = (leaves[0] if len(leaves) else steps) - 1
            if i > 0:
                pinhole = f * np.tan(theta[i])
                ratio = float(rho[d, i] / pinhole - 1)
                worst = ratio if abs(ratio) > abs(worst) else worst
        corner_distortion = worst
    return {"fold_px": fold_px, "corner_px": corner_px, "corner_distortion": corner_distortion}


def undistorted_size(cam) -> tuple[int, int] | None:
    """(width, height) of the pinhole image pycolmap's undistorter makes from this camera's photos (None: it cannot)."""
    pycolmap = import_pycolmap()
    if not cam.is_perspective():
        return None
    if is_pinhole(cam):
        return cam.width, cam.height
    try:
        und = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), for_undistortion(cam) or cam)
    except Exception:  # a camera pycolmap rejects: no canvas to compare with
        return None
    return int(und.width), int(und.height)


# --- how much of a photo its undistorted copy keeps -------------------------------------------------------------

# pycolmap's undistorter keeps the focal length and crops the pinhole image to the region every pixel of which sees
# the photo. For a real lens that region is about the photo itself (the published fox calibration keeps 98.8% of each
# side; a fisheye's is larger): it shrinks only as far as the lens magnifies the photo's rim against its centre, and
# k1 = 0.3 on a 56-degree lens (corners pushed out 17%, beyond any photographic lens) still keeps 86%. Below
# WARN_REGION the coefficients are very likely wrong (a warning); below MIN_REGION (the rim magnified over 2x; k1 = 1e6
# or p1 = p2 = 1e3 keep one pixel) nothing real is left to train on and loading stops. Below 0.2 pycolmap would stop
# cropping and pad the image with black instead, which training would learn as scene.
WARN_REGION = 0.8
MIN_REGION = 0.5


def undistorted_region(cam) -> tuple[int, int]:
    """(width, height) of the pinhole image (same focal length) every pixel of which sees the photo: the size pycolmap's
    undistorter crops to, without its floor of 0.2x the photo's size."""
    pycolmap = import_pycolmap()
    options = pycolmap.UndistortCameraOptions()
    options.min_scale = 1e-9
    und = pycolmap.undistort_camera(options, for_undistortion(cam) or cam)
    return int(und.width), int(und.height)


def lens_terms(cam) -> str:
    """The camera's model and distortion terms by name, e.g. 'OPENCV: k1 1e+06, k2 0, p1 0, p2 0'."""
    names = [n.strip() for n in cam.params_info.split(",")]
    params = list(cam.params)
    terms = [f"{names[i]} {params[i]:.4g}" for i in cam.extra_params_idxs() if i < len(names)]
    return f"{model_name(cam)}: {', '.join(terms) or 'no distortion terms'}"


def check_finite(cam, who: str, fix: str) -> None:
    """A DataError naming `who` when one of the camera's parameters is NaN or infinite."""
    params = np.asarray(cam.params, dtype=np.float64)
    if not np.isfinite(params).all():
        names = [n.strip() for n in cam.params_info.split(",")]
        bad = [f"{names[i] if i < len(names) else i} {p:g}" for i, p in enumerate(params) if not np.isfinite(p)]
        raise DataError(f"{who}: its camera ({model_name(cam)}) has {', '.join(bad)}: parameters must be finite "
                        f"numbers; {fix}")


def fold_warning(cam, who: str, fix: str) -> str | None:
    """The warning for a lens whose distortion folds back inside the photo (projection_profile's fold_px), which
    undistorts into ghost rings, naming `who` (a camera, a frame) and ending with `fix`; None for a lens that does
    not fold. One text for the COLMAP and the transforms.json paths."""
    fold = projection_profile(cam)["fold_px"] if cam.is_perspective() else None
    if fold is None:
        return None
    return (f"{who} ({model_name(cam)}: {cam.params_to_string()}) has distortion that folds back {fold:.0f} px from "
            f"the image centre, inside the photos, so the undistorted images show ghost rings; this calibration is "
            f"probably wrong. {fix}")


def check_lens(cam, who: str, fix: str) -> str | None:
    """Whether `cam`'s photos can be undistorted into something to train on. Raises DataError (naming `who`, then
    `fix`) when a parameter is NaN or infinite, or when the region the undistorted image keeps (undistorted_region) is
    under MIN_REGION of the photo's width or height; returns a warning under WARN_REGION, else None."""
    check_finite(cam, who, fix)
    try:
        w, h = undistorted_region(cam)
    except Exception as e:  # pycolmap rejects a camera it cannot invert
        raise DataError(f"{who}: pycolmap cannot undistort its camera ({lens_terms(cam)}): {e}; {fix}") from None
    keep = min(w / cam.width, h / cam.height)
    if keep >= WARN_REGION:
        return None
    side = "width" if w / cam.width <= h / cam.height else "height"
    said = (f"{who}: its lens ({lens_terms(cam)}) leaves a valid undistorted region of {w}x{h} px of its "
            f"{cam.width}x{cam.height} photo ({100 * keep:.0f}% of its {side})")
    if keep < MIN_REGION:
        raise DataError(f"{said}, too little to train on: no photographic lens magnifies the photo's rim that much, "
                        f"so the distortion coefficients are wrong (a real lens keeps over {100 * WARN_REGION:.0f}%). "
                        f"{fix[0].upper()}{fix[1:]}")
    return (f"{said}; a real lens keeps over {100 * WARN_REGION:.0f}%, so the distortion coefficients are probably "
            f"wrong. {fix[0].upper()}{fix[1:]}")
