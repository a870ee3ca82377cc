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
