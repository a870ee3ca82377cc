"""Datasets: a registry of dataset formats (COLMAP, Blender), SfM from photos, and synthetic high-frequency
benchmark scenes.

Importing this package loads only numpy and torch; pycolmap, open3d and cv2 are imported when used.
"""
from .formats import detect_format, list_formats, load_scene, register_format
from .scene import DatasetFormat, Scene, View


def __getattr__(name):
    # Lazy so `import splatzoo.data` stays light: these pull in pycolmap / open3d when called.
    if name in ("run_sfm", "SfMResult", "similarity_align"):
        from . import sfm

        return getattr(sfm, name)
    if name in ("make_synthetic_scene", "list_scenes", "synthetic_cameras"):
        from . import synthetic

        return getattr(synthetic, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Scene", "View", "DatasetFormat", "load_scene", "detect_format", "list_formats", "register_format",
           "run_sfm", "SfMResult", "similarity_align", "make_synthetic_scene", "list_scenes", "synthetic_cameras"]
