"""Native (C++ / CUDA) tile rasterizers. Placeholder until the extension lands."""
from __future__ import annotations

from ..errors import BackendUnavailableError


def cpu_available() -> bool:
    return False


def cuda_available() -> bool:
    return False


def load(kind: str):
    raise BackendUnavailableError(f"the native {kind} rasterizer is not built in this version")


def rasterize_native(surfels, camera, background, *, device_kind: str):
    load(device_kind)
