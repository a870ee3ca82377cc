"""Rasterizer backends: a registry of named backends, each with its device, availability check and render function.

Built in: "cuda" (CUDA kernels), "cpu" (C++ loops), "reference" (PyTorch, on any device) and the test-only
"cuda-emulated" (the CUDA kernels compiled for the host). `select_backend` makes the one decision of backend and
device a program needs; `rasterize` renders with a backend by name ("auto": the fastest that runs where the surfels
are).

Camera gradients: none. Every backend treats the camera as a constant (rasterize detaches it), so a camera whose
tensors require grad gets no gradient from any backend.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable

import torch

from ..errors import BackendUnavailableError, ShapeError
from ..registry import Registry
from ..types import Camera, RenderOutput, Surfels
from .common import SETTINGS, RasterSettings


@dataclass(frozen=True)
class Backend:
    """A rasterizer backend.

    device: "cpu" or "cuda", where its surfels must be; None: any device (the reference).
    check: raises BackendUnavailableError saying why the backend cannot run here (builds the extension if needed).
    render: (surfels, camera, background, settings, image_only) -> RenderOutput (image_only: rasterize's).
    auto_rank: preference under "auto", lower first; None: never chosen automatically.
    """

    name: str
    device: str | None
    description: str
    check: Callable[[], None]
    render: Callable[[Surfels, Camera, object, RasterSettings, bool], RenderOutput]
    auto_rank: int | None = None
    test_only: bool = False

    def unavailable_reason(self) -> str | None:
        """None if the backend runs here, else why not."""
        try:
            self.check()
            return None
        except BackendUnavailableError as e:
            return str(e)

    def available(self) -> bool:
        return self.unavailable_reason() is None

    def torch_device(self) -> torch.device:
        """The device a program using this backend keeps its model on."""
        return torch.device(self.device or "cpu")


BACKENDS: Registry[Backend] = Registry("rasterizer backend")


def register_backend(backend: Backend) -> Backend:
    return BACKENDS.register(backend.name, backend)


def _check_native(build: str):
    def check() -> None:  # native.load says why: no CUDA in torch, no GPU, no compiler, a build error
        from . import native

        native.load(build)

    return check


def _render_native(build: str, emulated: bool = False):
    def render(surfels, camera, background, settings, image_only=False):
        from . import native

        return native.render(surfels, camera, background, settings, build=build, emulated=emulated,
                             image_only=image_only)

    return render


def _render_reference(surfels, camera, background, settings, image_only=False):
    from .reference import rasterize_reference

    if not image_only:
        return rasterize_reference(surfels, camera, background, settings)
    with torch.no_grad():  # the same maths: the oracle of the native image-only renders
        out = rasterize_reference(surfels, camera, background, settings)
    return RenderOutput(rgb=out.rgb, alpha=out.alpha)


register_backend(Backend("cuda", "cuda", "CUDA tile rasterizer", _check_native("cuda"), _render_native("cuda"),
                         auto_rank=0))
register_backend(Backend("cpu", "cpu", "C++ (OpenMP) tile rasterizer", _check_native("cpu"), _render_native("cpu"),
                         auto_rank=1))
register_backend(Backend("reference", None, "pure PyTorch, differentiable by autograd (slow; the oracle)",
                         lambda: None, _render_reference, auto_rank=2))
register_backend(Backend("cuda-emulated", "cpu", "the CUDA kernels compiled for the host (tests only; slow)",
                         _check_native("cpu"), _render_native("cpu", emulated=True), test_only=True))

_warned: set = set()


def select_backend(backend: str | Backend = "auto", device=None) -> Backend:
    """The backend to use, by name or "auto" (cuda, then cpu, then reference: the first that runs here).

    device: where the surfels already are (rasterize passes theirs); None lets the backend decide (a program
    choosing where to put its model: it then uses backend.torch_device()). A backend that cannot run raises
    BackendUnavailableError, except under "auto", which falls back and warns once when a native backend that
    should run here failed (e.g. a CUDA build error on a machine with a GPU).
    """
    if isinstance(backend, Backend):
        return backend
    kind = None if device is None else torch.device(device).type
    if backend != "auto":
        b = BACKENDS.get(backend)
        if kind is None and b.device is not None:
            b.check()  # the program is about to put its model on b's device: say now if b cannot run here, and why
        if kind is not None and b.device not in (None, kind):
            raise BackendUnavailableError(f"the {b.name} backend renders surfels on the {b.device} device, but these "
                                          f"are on {kind}; move them with surfels.to('{b.device}') or use another "
                                          f"backend")
        return b
    skipped = []
    for b in sorted((e.spec for e in BACKENDS.entries() if e.spec.auto_rank is not None), key=lambda b: b.auto_rank):
        if kind is not None and b.device not in (None, kind):
            continue
        reason = b.unavailable_reason()
        if reason is None:
            # a native backend that fails where its device exists is worth a warning; a missing GPU is not
            loud = [(n, r) for n, d, r in skipped if d == "cpu" or torch.cuda.is_available()]
            if loud and b.name not in _warned:
                _warned.add(b.name)
                why = "; ".join(f"{n}: {r}" for n, r in loud)
                warnings.warn(f"splatzoo: using the {b.name} rasterizer backend because {why}", RuntimeWarning,
                              stacklevel=3)
            return b
        skipped.append((b.name, b.device, reason))
    raise BackendUnavailableError("no rasterizer backend can run here")  # unreachable: the reference always runs


def resolve_backend(backend: str, device) -> str:
    """The name of the backend `rasterize` would use for surfels on `device`."""
    return select_backend(backend, device).name


def available_backends(device=None) -> list[str]:
    """User-facing backends that can run here, fastest first (building the native extension if needed)."""
    ranked = sorted((e.spec for e in BACKENDS.entries() if not e.spec.test_only),
                    key=lambda b: (b.auto_rank is None, b.auto_rank or 0))
    kind = None if device is None else torch.device(device).type
    return [b.name for b in ranked if (kind is None or b.device in (None, kind)) and b.available()]


MAX_PIXELS = 2**31 - 1  # every backend indexes pixels (and tiles) with 32-bit integers


def check_image_size(camera: Camera) -> None:
    """Refuse an image no backend can index, before anything is allocated (a crafted camera must not crash)."""
    pixels = int(camera.width) * int(camera.height)
    if pixels > MAX_PIXELS:
        raise ShapeError(f"camera {camera.name!r} is {camera.width}x{camera.height} = {pixels:,} pixels; the "
                         f"rasterizer renders at most {MAX_PIXELS:,} pixels per image (about 46000 x 46000)")


def rasterize(surfels: Surfels, camera: Camera, *, backend: str | Backend = "auto", background=None,
              settings: RasterSettings = SETTINGS, image_only: bool = False) -> RenderOutput:
    """Render `surfels` seen from `camera`. Differentiable with respect to every Surfels field (not the camera).

    backend: "auto" (the fastest backend that runs on the surfels' device), a backend name (see BACKENDS.names())
    or a Backend. background: colour [3] (or a grey scalar) behind the surfels; black by default.
    settings: the rasterizer's numeric settings (near plane, alpha limits, ...).
    image_only: a render to look at (a viewer's frame, an evaluation, a frame rate): rgb and alpha only, the others
    None, not differentiable, and nothing kept for a backward; the same pixels as the full render.
    """
    if not isinstance(surfels, Surfels):
        raise TypeError(f"rasterize expects a splatzoo.Surfels, got {type(surfels).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"rasterize expects a splatzoo.Camera, got {type(camera).__name__}")
    if not isinstance(settings, RasterSettings):
        raise TypeError(f"settings must be a splatzoo RasterSettings, got {type(settings).__name__}")
    surfels.validate()
    check_image_size(camera)
    b = select_backend(backend, surfels.means.device)
    if image_only:
        return b.render(surfels, camera.detach(), background, settings, True)
    return b.render(surfels, camera.detach(), background, settings)
