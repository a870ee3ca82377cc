"""Native tile rasterizers: C++ (OpenMP) on the CPU and CUDA on the GPU, built lazily from splatzoo/csrc/ (package data).

On the CPU one call does everything (`render`): the camera-dependent set-up of common.project and
common.screen_boxes, culling, the depth sort and the tile loop, each with a hand-written backward down to means,
quats and scales (see csrc/surfel_math.h for the maths). On the GPU the set-up stays in PyTorch (`common.project`,
autograd through it) and the native op takes the visible surfels, sorted front to back.

The extension is compiled on first use with torch.utils.cpp_extension.load into a cache directory
($SPLATZOO_EXTENSIONS_DIR, else $TORCH_EXTENSIONS_DIR/splatzoo, else ~/.cache/splatzoo/torch_extensions), never at
import time. A failed build raises BackendUnavailableError saying what to install.
"""
from __future__ import annotations

import hashlib
import os
import platform
import re
import threading
from pathlib import Path

import torch

from ..errors import BackendUnavailableError
from ..types import Camera, RenderOutput, Surfels
from .common import background_tensor, project

CSRC = Path(__file__).resolve().parents[1] / "csrc"  # shipped inside the package (package data)
CPU_SOURCES = ("ext.cpp", "rasterize_cpu.cpp")
CUDA_SOURCES = CPU_SOURCES + ("rasterize_cuda.cu",)
HEADERS = ("surfel_math.h", "rasterize.h")

_lock = threading.Lock()
_modules: dict[str, object] = {}
_failures: dict[str, BackendUnavailableError] = {}


def cpu_available() -> bool:
    """True if the C++ extension builds (or is already built) and loads here."""
    try:
        load("cpu")
        return True
    except BackendUnavailableError:
        return False


def cuda_available() -> bool:
    """True if the installed torch has CUDA, a GPU is visible, and the CUDA extension builds and loads.

    Decided by torch (torch.version.cuda, torch.cuda.is_available()), not by whether nvcc happens to be installed.
    """
    if torch.version.cuda is None or not torch.cuda.is_available():
        return False
    try:
        load("cuda")
        return True
    except BackendUnavailableError:
        return False


def _cpu_signature() -> str:
    """Identifies the instruction set we compile for (-march=native), so a shared cache never serves a binary
    built for another CPU."""
    text = platform.machine() + platform.processor()
    try:
        info = Path("/proc/cpuinfo").read_text(errors="ignore")
        model = re.search(r"^model name\s*:\s*(.*)$", info, re.M)
        flags = re.search(r"^(flags|Features)\s*:\s*(.*)$", info, re.M)
        text += (model.group(1) if model else "") + (flags.group(2) if flags else "")
    except OSError:
        pass
    return hashlib.sha1(text.encode()).hexdigest()[:8]


def _build_root() -> Path:
    if os.environ.get("SPLATZOO_EXTENSIONS_DIR"):
        return Path(os.environ["SPLATZOO_EXTENSIONS_DIR"])
    if os.environ.get("TORCH_EXTENSIONS_DIR"):
        return Path(os.environ["TORCH_EXTENSIONS_DIR"]) / "splatzoo"
    return Path.home() / ".cache" / "splatzoo" / "torch_extensions"


def _march_flags() -> list[str]:
    # -march=native lets GCC use AVX2/FMA in the pixel loop; the build name carries _cpu_signature().
    # SPLATZOO_PORTABLE=1 builds for the baseline ISA instead (e.g. a cache shared by different machines).
    if os.environ.get("SPLATZOO_PORTABLE") == "1" or platform.machine() not in ("x86_64", "AMD64", "aarch64", "arm64"):
        return []
    return ["-march=native"] if platform.machine() in ("x86_64", "AMD64") else ["-mcpu=native"]


def build_flags() -> list[str]:
    # -fno-trapping-math lets GCC if-convert (and so vectorise) the division and selects of the pixel loop; it
    # changes no result. Never -ffast-math: the header's rounding trick and the reference's NaN/Inf rules need IEEE.
    return ["-O3", "-fopenmp", "-fno-trapping-math"] + _march_flags()


def _build_name(kind: str) -> str:
    h = hashlib.sha1()
    for name in (CUDA_SOURCES if kind == "cuda" else CPU_SOURCES) + HEADERS:
        h.update((CSRC / name).read_bytes())
    h.update(" ".join(build_flags()).encode())
    h.update(torch.__version__.encode())
    return f"splatzoo_{kind}_{_cpu_signature()}_{h.hexdigest()[:10]}"


def _install_hint() -> str:
    return ("install a C++17 compiler (g++ >= 9 or clang; Debian/Ubuntu: apt-get install g++) and ninja "
            "(pip install ninja)")


def load(kind: str = "cpu"):
    """Build (once, cached on disk) and import the native extension for `kind` ("cpu" or "cuda").

    Raises BackendUnavailableError with the reason and what to install when it cannot be built or run here.
    """
    if kind not in ("cpu", "cuda"):
        raise BackendUnavailableError(f"unknown native rasterizer kind {kind!r}; use 'cpu' or 'cuda'")
    with _lock:
        if kind in _modules:
            return _modules[kind]
        if kind in _failures:
            raise _failures[kind]
        try:
            _modules[kind] = _build(kind)
            return _modules[kind]
        except BackendUnavailableError as e:
            _failures[kind] = e
            raise


def _build(kind: str):
    if kind == "cuda":
        if torch.version.cuda is None:
            raise BackendUnavailableError(
                f"the installed torch {torch.__version__} has no CUDA support; install a CUDA build of torch "
                "(see https://pytorch.org/get-started/locally/) to use the cuda rasterizer")
        if not torch.cuda.is_available():
            raise BackendUnavailableError("torch has CUDA support but no CUDA device is visible "
                                          "(check the driver and CUDA_VISIBLE_DEVICES)")
    missing = [n for n in (CUDA_SOURCES if kind == "cuda" else CPU_SOURCES) + HEADERS if not (CSRC / n).is_file()]
    if missing:
        raise BackendUnavailableError(
            f"the native rasterizer sources are missing ({', '.join(missing)} under {CSRC}); the installed splatzoo "
            "is incomplete: reinstall it (pip install --force-reinstall splatzoo, or pip install -e . from a checkout)")
    from torch.utils import cpp_extension

    try:
        cpp_extension.verify_ninja_availability()
    except RuntimeError:
        raise BackendUnavailableError("building the native rasterizer needs ninja: pip install ninja") from None
    name = _build_name(kind)
    build_dir = _build_root() / name
    build_dir.mkdir(parents=True, exist_ok=True)
    sources = [str(CSRC / n) for n in (CUDA_SOURCES if kind == "cuda" else CPU_SOURCES)]
    flags = build_flags()
    cuda_flags = ["-O3", "-lineinfo"]  # no --use_fast_math: results should match the CPU and the reference
    if kind == "cuda":
        flags = flags + ["-DSPLATZOO_WITH_CUDA"]
        cuda_flags = cuda_flags + ["-DSPLATZOO_WITH_CUDA"]
    try:
        return cpp_extension.load(name=name, sources=sources, extra_cflags=flags, extra_cuda_cflags=cuda_flags,
                                  extra_ldflags=["-fopenmp"], build_directory=str(build_dir),
                                  with_cuda=(kind == "cuda"), verbose=os.environ.get("SPLATZOO_VERBOSE_BUILD") == "1")
    except Exception as e:  # compiler missing, compile error, or an import failure of the built module
        detail = str(e).strip().splitlines()
        detail = " | ".join(detail[-3:])[-600:] if detail else type(e).__name__
        raise BackendUnavailableError(
            f"could not build the native {kind} rasterizer in {build_dir}: {detail}. To fix: {_install_hint()}"
            + ("; and the CUDA toolkit (nvcc) matching torch.version.cuda" if kind == "cuda" else "")
            + ". Set SPLATZOO_VERBOSE_BUILD=1 to see the full build log.") from None


# Saved-state tensors returned by the extension after the 6 outputs (see csrc/ext.cpp).
_N_PUBLIC = 6


class _RasterizeFn(torch.autograd.Function):
    """Per-surfel tensors (visible, front to back) -> the six image outputs, with the hand-written backward."""

    @staticmethod
    def forward(ctx, C, width, height, T, center, depth, normal, opac, base, wv, wp, wa, boxes, wave_counts=None):
        # wave_counts: int32 [M] or None (all K waves); it is not differentiable
        out = C.forward(T, center, depth, normal, opac, base, wv, wp, wa, boxes, width, height, wave_counts)
        ctx.C, ctx.size, ctx.wave_counts = C, (width, height), wave_counts
        ctx.save_for_backward(T, center, depth, normal, opac, base, wv, wp, wa, boxes, *out)
        saved = out[_N_PUBLIC:]
        ctx.mark_non_differentiable(*saved)
        return tuple(out[:_N_PUBLIC])

    @staticmethod
    def backward(ctx, *grads):
        t = ctx.saved_tensors
        inputs, outs = t[:10], list(t[10:])
        g = [torch.zeros_like(o) if gr is None else gr for gr, o in zip(grads, outs[:_N_PUBLIC])]
        v = ctx.C.backward(*inputs, ctx.size[0], ctx.size[1], outs, g, ctx.wave_counts)
        return (None, None, None, *v, None, None)


class _RenderCpuFn(torch.autograd.Function):
    """Surfels -> the six image outputs on the CPU: projection, culling, sorting and the tile loop all in C++, with
    the hand-written backward of each (csrc/ext.cpp render / render_backward)."""

    @staticmethod
    def forward(ctx, C, camera_tensors, width, height, wave_counts, means, quats, scales, opac, base, wv, wp, wa):
        KR, Kt, eye = camera_tensors
        out = C.render(means, quats, scales, opac, base, wv, wp, wa, KR, Kt, eye, width, height, wave_counts)
        ctx.C, ctx.size, ctx.has_counts = C, (width, height), wave_counts is not None
        ctx.save_for_backward(means, quats, scales, KR, Kt, eye, *out)
        return tuple(out[:_N_PUBLIC])

    @staticmethod
    def backward(ctx, *grads):
        t = ctx.saved_tensors
        saved = list(t[6:])
        g = [torch.zeros_like(o) if gr is None else gr for gr, o in zip(grads, saved[:_N_PUBLIC])]
        v = ctx.C.render_backward(*t[:6], ctx.size[0], ctx.size[1], saved, g, ctx.has_counts)
        return (None, None, None, None, None, *v)


def rasterize_native(surfels: Surfels, camera: Camera, background=None, *, device_kind: str = "cpu") -> RenderOutput:
    """Render with the native tile rasterizer; same contract and maths as rasterize_reference."""
    C = load(device_kind)
    s = surfels
    want = "cuda" if device_kind == "cuda" else "cpu"
    if s.means.device.type != want:
        raise BackendUnavailableError(f"the {device_kind} rasterizer needs surfels on the {want} device, got "
                                      f"{s.means.device}; move them with surfels.to('{want}') or pick another backend")
    if s.means.dtype not in (torch.float32, torch.float64):
        raise BackendUnavailableError(f"the native rasterizer supports float32 and float64, got {s.means.dtype}")
    cam = camera.to(s.means.device, s.means.dtype)
    bg = background_tensor(background, s.means)
    render = _render_cpu if device_kind == "cpu" else _render_cuda
    rgb, alpha, depth, median, normal, dist = render(C, s, cam)
    rgb = rgb + (1 - alpha)[..., None] * bg
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal, distortion=dist)


def _render_cpu(C, s: Surfels, cam: Camera) -> tuple:
    """The six outputs (before the background): projection, culling, sorting and the tile loop in one C++ call."""
    camera_tensors = (cam.K @ cam.R, cam.K @ cam.t, cam.center)
    return _RenderCpuFn.apply(C, camera_tensors, cam.width, cam.height, s.wave_counts, s.means, s.quats, s.scales,
                              s.opacities, s.base_color, s.wave_vectors, s.wave_phases, s.wave_amplitudes)


def _render_cuda(C, s: Surfels, cam: Camera) -> tuple:
    """The six outputs (before the background): the per-surfel set-up in PyTorch (common.project), the tile loop
    native."""
    H, W = cam.height, cam.width
    if s.num:
        proj = project(s, cam)
        vis = torch.nonzero(proj.visible).squeeze(1)
        # front to back by centre depth, ties by index: the same order as the reference
        order = vis[torch.sort(proj.depth.detach()[vis], stable=True).indices]
    else:
        order = torch.zeros(0, dtype=torch.long, device=s.means.device)
    if order.numel() == 0:
        z = s.means.new_zeros
        # keep the graph connected so .backward() works on an empty render
        tie = (s.means.sum() + s.opacities.sum() + s.base_color.sum()) * 0
        return z(H, W, 3) + tie, z(H, W), z(H, W), z(H, W), z(H, W, 3), z(H, W)
    counts = None if s.wave_counts is None else s.wave_counts[order].to(torch.int32).contiguous()
    return _RasterizeFn.apply(
        C, W, H, proj.T[order], proj.center_px[order], proj.depth[order], proj.normal[order],
        s.opacities[order], s.base_color[order], s.wave_vectors[order], s.wave_phases[order],
        s.wave_amplitudes[order], proj.boxes[order].detach(), counts)
    # CUDA: the per-surfel set-up in PyTorch (common.project), the tile loop native
    if s.num:
        proj = project(s, cam)
        vis = torch.nonzero(proj.visible).squeeze(1)
        # front to back by centre depth, ties by index: the same order as the reference
        order = vis[torch.sort(proj.depth.detach()[vis], stable=True).indices]
    else:
        order = torch.zeros(0, dtype=torch.long, device=s.means.device)
    if order.numel() == 0:
        z = s.means.new_zeros
        # keep the graph connected so .backward() works on an empty render
        tie = (s.means.sum() + s.opacities.sum() + s.base_color.sum()) * 0
        rgb = z(H, W, 3) + tie + bg
        return RenderOutput(rgb=rgb, alpha=z(H, W), depth=z(H, W), median_depth=z(H, W), normal=z(H, W, 3),
                            distortion=z(H, W))
    counts = None if s.wave_counts is None else s.wave_counts[order].to(torch.int32).contiguous()
    rgb, alpha, depth, median, normal, dist = _RasterizeFn.apply(
        C, W, H, proj.T[order], proj.center_px[order], proj.depth[order], proj.normal[order],
        s.opacities[order], s.base_color[order], s.wave_vectors[order], s.wave_phases[order],
        s.wave_amplitudes[order], proj.boxes[order].detach(), counts)
    rgb = rgb + (1 - alpha)[..., None] * bg
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal, distortion=dist)
