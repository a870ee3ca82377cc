"""Rasterizer backends, chosen by name: "reference" (PyTorch), "cpu" (C++), "cuda", or "auto"."""
from __future__ import annotations

import warnings

from ..errors import BackendUnavailableError, UnknownNameError
from ..registry import closest
from ..types import Camera, RenderOutput, Surfels

BACKENDS = ("reference", "cpu", "cuda")
_warned_fallback = False


def available_backends(device=None) -> list[str]:
    """Backends that can run here (building the native extension if needed)."""
    from . import native

    names = []
    if native.cuda_available():
        names.append("cuda")
    if native.cpu_available():
        names.append("cpu")
    names.append("reference")
    return names


def resolve_backend(backend: str, device) -> str:
    """Map "auto" to the fastest backend that can run on `device`; check explicit names."""
    global _warned_fallback
    if backend not in BACKENDS + ("auto",):
        raise UnknownNameError(f"unknown rasterizer backend {backend!r}; known: auto, {', '.join(BACKENDS)}"
                               + closest(backend, BACKENDS + ("auto",)))
    if backend != "auto":
        return backend
    from . import native

    kind = getattr(device, "type", str(device))
    try:
        if kind == "cuda":
            native.load("cuda")
            return "cuda"
        native.load("cpu")
        return "cpu"
    except BackendUnavailableError as e:
        if not _warned_fallback:
            warnings.warn(f"splatzoo: native rasterizer unavailable, using the slow reference backend ({e})",
                          RuntimeWarning, stacklevel=3)
            _warned_fallback = True
        return "reference"


def rasterize(surfels: Surfels, camera: Camera, *, backend: str = "auto", background=None) -> RenderOutput:
    """Render `surfels` seen from `camera`. Differentiable with respect to every Surfels field.

    backend: "auto" (cuda, then cpu, then reference), "reference", "cpu" or "cuda".
    background: colour [3] (or a grey scalar) behind the surfels; black by default.
    """
    if not isinstance(surfels, Surfels):
        raise TypeError(f"rasterize expects a splatzoo.Surfels, got {type(surfels).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"rasterize expects a splatzoo.Camera, got {type(camera).__name__}")
    surfels.validate()
    name = resolve_backend(backend, surfels.means.device)
    if name == "reference":
        from .reference import rasterize_reference

        return rasterize_reference(surfels, camera, background)
    from . import native

    return native.rasterize_native(surfels, camera, background, device_kind=name)
