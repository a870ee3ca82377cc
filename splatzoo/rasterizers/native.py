"""Native tile rasterizers, built lazily from splatzoo/csrc/ (package data): one pipeline on three devices.

`render` makes one extension call for the whole render: projection (project_surfel), culling, the depth sort, tile
binning and the tile loop, with the hand-written backward of each (csrc/surfel_math.h holds the maths). It runs the
C++ loops on CPU tensors, the CUDA kernels on CUDA tensors, and, with emulated=True, the same CUDA kernels compiled
for the host (csrc/cuda_emulation.h) on CPU tensors: the test-only "cuda-emulated" backend.

The extension is compiled on first use with torch.utils.cpp_extension.load into a cache directory
($SPLATZOO_EXTENSIONS_DIR, else $TORCH_EXTENSIONS_DIR/splatzoo, else ~/.cache/splatzoo/torch_extensions), never at
import time: one build per sources, compiler, flags, CPU, torch, Python and location (see _build_name). A failed build
raises BackendUnavailableError saying what to install.
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib.util
import os
import platform
import re
import subprocess
import sys
import sysconfig
import threading
import time
from dataclasses import dataclass, fields
from pathlib import Path

import torch

from ..errors import BackendUnavailableError
from ..types import SURFEL_FIELDS as FIELD_TABLE
from ..types import Camera, RenderOutput, Surfels
from .common import RasterSettings, background_tensor

CSRC = Path(__file__).resolve().parents[1] / "csrc"  # shipped inside the package (package data)
# The CPU build also holds the CUDA kernels compiled for the host emulation (the cuda-emulated backend).
CPU_SOURCES = ("ext.cpp", "rasterize_cpu.cpp", "rasterize_cuda_emulated.cpp")
CUDA_SOURCES = CPU_SOURCES + ("rasterize_cuda.cu",)
HEADERS = ("surfel_math.h", "rasterize.h", "cuda_emulation.h", "surfel_fields.h")
OUTPUTS = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion")
SURFEL_FIELDS = tuple(f.name for f in FIELD_TABLE)  # the order the extension takes them in

_lock = threading.Lock()
_modules: dict[str, object] = {}
_failures: dict[str, BackendUnavailableError] = {}


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
    # -fno-trapping-math lets GCC if-convert (and so vectorise) the division and selects of the pixel loop, and
    # -fno-math-errno the square root of the anti-aliased one (no errno branch); neither changes a result. Never
    # -ffast-math: the header's rounding trick and the reference's NaN/Inf rules need IEEE.
    return ["-O3", "-fopenmp", "-fno-trapping-math", "-fno-math-errno"] + _march_flags()


@functools.lru_cache(maxsize=None)
def _ninja_id() -> str:
    """The ninja that torch's builder runs (the first on PATH) and its version: part of the cache key, because two
    ninjas record different command hashes and each would rebuild (and replace) the other's library."""
    import shutil

    path = shutil.which("ninja") or "ninja: not found"
    try:
        version = subprocess.run([path, "--version"], capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        version = "?"
    return f"{os.path.realpath(path)} {version}"


@functools.lru_cache(maxsize=None)
def _compiler_id(kind: str) -> str:
    """The compilers' version lines (C++, and nvcc for CUDA): part of the cache key, so that a compiler upgrade or
    another checkout's toolchain never reuses or overwrites a build made with a different one."""
    cmds = [[os.environ.get("CXX", "c++"), "--version"]] + ([["nvcc", "--version"]] if kind == "cuda" else [])
    out = []
    for cmd in cmds:
        try:
            text = subprocess.run(cmd, capture_output=True, text=True, timeout=30).stdout.strip().splitlines()
            out.append(text[0] if cmd[0] != "nvcc" else text[-1])
        except (OSError, subprocess.SubprocessError, IndexError):
            out.append(f"{cmd[0]}: not found")
    return "; ".join(out)


def _build_name(kind: str) -> str:
    h = hashlib.sha1()
    h.update(_compiler_id(kind).encode())
    h.update(_ninja_id().encode())
    for name in (CUDA_SOURCES if kind == "cuda" else CPU_SOURCES) + HEADERS:
        h.update((CSRC / name).read_bytes())
    h.update(" ".join(build_flags()).encode())
    h.update(torch.__version__.encode())
    # The build files name the sources, torch's headers and libraries and Python's headers by absolute path, and ninja
    # rebuilds when any of them changes: so each checkout and each environment (venv, conda, interpreter) gets a build
    # of its own instead of rebuilding, and replacing under a running process, the build of another.
    torch_dir = os.path.dirname(os.path.abspath(torch.__file__))
    for where in (CSRC, torch_dir, sysconfig.get_paths()["include"], sys.version):
        h.update(b"\0" + str(where).encode())
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
            module = _build(kind)
            _check_fields(module)
            _modules[kind] = module
            return module
        except BackendUnavailableError as e:
            _failures[kind] = e
            raise


def _check_fields(module) -> None:
    """The build's field table (csrc/surfel_fields.h) must be the Surfels declaration's."""
    built = tuple(getattr(module, "SURFEL_FIELDS", ()))
    if built != SURFEL_FIELDS:
        raise BackendUnavailableError(
            f"the native rasterizer was compiled for the surfel fields {', '.join(built) or '(none)'}, but "
            f"splatzoo.types.Surfels declares {', '.join(SURFEL_FIELDS)}: csrc/surfel_fields.h is out of date; "
            "regenerate it with python -m splatzoo.rasterizers.fields")


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
    # The name is a hash of everything the build depends on, so a library already built under it is up to date:
    # it is imported as it is. Handing it to ninja again could rebuild it from file times alone (a checkout that
    # touched the sources) and relink it in place while other processes have it loaded.
    built = build_dir / f"{name}.so"
    damaged = None
    if built.is_file():
        try:
            return _import_built(name, built)
        except (ImportError, OSError) as e:  # a build cut short: made again below
            damaged = f"{type(e).__name__}: {str(e)[:200]}"
    try:
        with _announce_build(kind, build_dir, damaged):
            return cpp_extension.load(name=name, sources=sources, extra_cflags=flags, extra_cuda_cflags=cuda_flags,
                                      extra_ldflags=["-fopenmp"], build_directory=str(build_dir),
                                      with_cuda=(kind == "cuda"),
                                      verbose=os.environ.get("SPLATZOO_VERBOSE_BUILD") == "1")
    except Exception as e:  # compiler missing, compile error, or an import failure of the built module
        detail = str(e).strip().splitlines()
        detail = " | ".join(detail[-3:])[-600:] if detail else type(e).__name__
        raise BackendUnavailableError(
            f"could not build the native {kind} rasterizer in {build_dir}: {detail}. To fix: {_install_hint()}"
            + ("; and the CUDA toolkit (nvcc) matching torch.version.cuda" if kind == "cuda" else "")
            + ". Set SPLATZOO_VERBOSE_BUILD=1 to see the full build log.") from None


def _import_built(name: str, path: Path):
    """The extension module `name` from its built library."""
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"{path} is not a loadable extension")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def _announce_build(kind: str, build_dir: Path, damaged: str | None = None, every_s: float = 15.0):
    """Say on stderr that a build is running (it takes a minute or two, silently otherwise), and why when a cached
    one could not be loaded (`damaged`), with a line every `every_s` seconds while it runs and the time it took."""
    say = lambda msg: print(f"splatzoo: {msg}", file=sys.stderr, flush=True)  # noqa: E731
    what = "C++ and CUDA" if kind == "cuda" else "C++"
    if damaged:
        say(f"the cached {what} rasterizer could not be loaded ({damaged}); building it again")
    say(f"building the {what} rasterizer, once for this version, compiler and torch (about a minute or two) in "
        f"{build_dir}")
    done = threading.Event()
    t0 = time.monotonic()

    def tick():
        while not done.wait(every_s):
            say(f"  still building ({time.monotonic() - t0:.0f} s)")

    ticker = threading.Thread(target=tick, daemon=True)
    ticker.start()
    try:
        yield
        say(f"built the {what} rasterizer in {time.monotonic() - t0:.0f} s")
    finally:
        done.set()
        ticker.join()


@dataclass(frozen=True)
class _Call:
    """Everything about one render call that is not a differentiable surfel tensor."""

    C: object
    settings: object  # the extension's Settings struct
    KR: torch.Tensor
    Kt: torch.Tensor
    eye: torch.Tensor
    width: int
    height: int
    wave_counts: torch.Tensor | None
    emulated: bool


class _RenderFn(torch.autograd.Function):
    """Surfel fields -> the six image outputs (before the background), with the extension's hand-written backward.
    Camera tensors are constants: no backend propagates gradients to the camera (see rasterizers.rasterize)."""

    @staticmethod
    def forward(ctx, call: _Call, *surfel_tensors):
        fields = dict(zip(SURFEL_FIELDS, surfel_tensors))
        means, quats, scales = fields["means"], fields["quats"], fields["scales"]
        out, state = call.C.render(call.settings, list(surfel_tensors), call.wave_counts, call.KR, call.Kt, call.eye,
                                   call.width, call.height, call.emulated)
        ctx.call = call
        ctx.state_names = tuple(state)
        ctx.save_for_backward(means, quats, scales, *state.values())
        return tuple(out[k] for k in OUTPUTS)

    @staticmethod
    def backward(ctx, *cotangents):
        call = ctx.call
        means, quats, scales, *saved = ctx.saved_tensors
        state = dict(zip(ctx.state_names, saved))
        v_out = {k: g for k, g in zip(OUTPUTS, cotangents) if g is not None}
        v = call.C.render_backward(call.settings, means, quats, scales, call.KR, call.Kt, call.eye, call.width,
                                   call.height, state, v_out, call.emulated)
        return (None, *(v[k] for k in SURFEL_FIELDS))


_settings_cache: dict = {}


def settings_struct(C, settings: RasterSettings):
    """The extension's Settings struct for `settings`, every field set by name (and checked to be every field)."""
    key = (id(C), settings)
    if key not in _settings_cache:
        if settings.tile != C.TILE:
            raise BackendUnavailableError(f"RasterSettings.tile={settings.tile}, but the native rasterizer is compiled "
                                          f"for tiles of {C.TILE} pixels")
        names = {f.name for f in fields(settings)} - {"tile"}
        if names != set(C.SETTINGS_FIELDS):
            raise BackendUnavailableError(f"the native rasterizer's settings {sorted(C.SETTINGS_FIELDS)} differ from "
                                          f"RasterSettings {sorted(names)}: rebuild it (stale build cache?)")
        struct = C.Settings()
        for name in names:
            setattr(struct, name, float(getattr(settings, name)))
        _settings_cache[key] = struct
    return _settings_cache[key]


def refuse_python_kind(kind: str, backend: str) -> None:
    """A Python appearance kind (Surfels.appearance_kind) has no C++ section: the native backends refuse it by name."""
    from ..errors import SplatzooError
    from ..registry import APPEARANCE_KINDS

    origin = next((e.origin for e in APPEARANCE_KINDS.entries() if e.name == kind), "built-in")
    origin = "registered from code" if origin == "built-in" else origin  # register_appearance_kind's
    raise SplatzooError(
        f"the {backend} backend cannot render the appearance kind {kind!r}: it is written in Python ({origin}), and "
        "only the reference backend renders and differentiates Python kinds. Use --backend reference (backend="
        "'reference'), or give the kind its own section in splatzoo/csrc/surfel_math.h with its rows in the Surfels "
        "field table and its twin in rasterizers/reference.py (README, 'Plugins'), after which every backend renders "
        "it")


def render(surfels: Surfels, camera: Camera, background=None, settings: RasterSettings | None = None, *,
           build: str = "cpu", emulated: bool = False, image_only: bool = False) -> RenderOutput:
    """Render with the native tile rasterizer of `build` ("cpu" or "cuda"); same contract and maths as
    rasterize_reference. emulated=True runs the CUDA kernels under the host emulation (CPU tensors).
    image_only=True: rgb and alpha only, outside autograd, with no state kept for a backward (to look at)."""
    s = surfels
    if s.appearance_kind is not None:
        refuse_python_kind(s.appearance_kind, "cuda-emulated" if emulated else build)
    C = load(build)
    want = "cuda" if build == "cuda" else "cpu"
    if s.means.device.type != want:
        raise BackendUnavailableError(f"this rasterizer needs surfels on the {want} device, got {s.means.device}; "
                                      f"move them with surfels.to('{want}') or pick another backend")
    if s.means.dtype not in (torch.float32, torch.float64):
        raise BackendUnavailableError(f"the native rasterizer supports float32 and float64, got {s.means.dtype}")
    # camera products on the host in float64, rounded once to the surfels' dtype: the extension reads them on the
    # host, so a camera on the GPU would cost a device-to-host copy (a sync) per tensor and pass
    cam = camera.detach().to("cpu", torch.float64)
    KR, Kt, eye = ((cam.K @ cam.R).to(s.means.dtype), (cam.K @ cam.t).to(s.means.dtype), cam.center.to(s.means.dtype))
    call = _Call(C, settings_struct(C, settings or RasterSettings()), KR, Kt, eye, cam.width, cam.height,
                 s.wave_counts, emulated)
    if image_only:
        with torch.no_grad():
            out, _ = C.render(call.settings, [getattr(s, k).detach() for k in SURFEL_FIELDS], s.wave_counts, KR, Kt,
                              eye, cam.width, cam.height, emulated, True)
            rgb, alpha = out["rgb"], out["alpha"]
            rgb = rgb + (1 - alpha)[..., None] * background_tensor(background, rgb)
        return RenderOutput(rgb=rgb, alpha=alpha)
    rgb, alpha, depth, median, normal, dist = _RenderFn.apply(call, *(getattr(s, k) for k in SURFEL_FIELDS))
    rgb = rgb + (1 - alpha)[..., None] * background_tensor(background, s.means)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal, distortion=dist)
