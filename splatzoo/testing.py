"""Random but realistic surfel scenes for tests and benchmarks of the rasterizers."""
from __future__ import annotations

import math

import torch

from .geometry import normals_to_quats
from .types import Camera, Surfels


def sphere_and_wall(n: int, width: int = 128, height: int = 128, K: int = 0, seed: int = 0, dtype=torch.float32,
                    px_sigma: tuple[float, float] = (1.0, 4.0)) -> tuple[Surfels, Camera]:
    """n surfels (70% on a unit sphere, 30% on a wall behind it) seen from 4 units away, each px_sigma pixels
    across, oriented near the surface normal, with K random waves."""
    g = torch.Generator().manual_seed(seed)
    d64 = torch.float64
    r = lambda *s: torch.rand(*s, generator=g, dtype=d64)  # noqa: E731
    cam = Camera.look_at((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), fov_deg=60.0, width=width, height=height)
    ns = int(0.7 * n)
    nw = n - ns
    d = torch.randn(ns, 3, generator=g, dtype=d64)
    d = d / d.norm(dim=1, keepdim=True)
    aspect = width / height
    wall = torch.stack([(r(nw) - 0.5) * 5 * max(aspect, 1), (r(nw) - 0.5) * 5 / min(aspect, 1),
                        torch.full((nw,), 1.5, dtype=d64)], 1)
    means = torch.cat([d, wall])
    normals = torch.cat([d, torch.tensor([0.0, 0.0, -1.0], dtype=d64).expand(nw, 3)])
    normals = normals + 0.2 * torch.randn(n, 3, generator=g, dtype=d64)
    q = normals_to_quats(normals)
    a = r(n) * math.pi  # spin about the normal: (w, 0, 0, sin) composed on the right
    c, s_ = torch.cos(a), torch.sin(a)
    quats = torch.stack([q[:, 0] * c - q[:, 3] * s_, q[:, 1] * c + q[:, 2] * s_, q[:, 2] * c - q[:, 1] * s_,
                         q[:, 3] * c + q[:, 0] * s_], 1)
    f = float(cam.K[0, 0])
    depth = (means[:, 2] + 4.0).clamp_min(0.5)
    scales = (px_sigma[0] + (px_sigma[1] - px_sigma[0]) * r(n, 2)) * depth[:, None] / f
    opac = 0.2 + 0.8 * r(n)
    color = r(n, 3)
    freq = 0.2 + 1.5 * r(n, K)  # cycles per sigma
    th = r(n, K) * math.pi
    wv = torch.stack([2 * math.pi * freq * torch.cos(th), 2 * math.pi * freq * torch.sin(th)], -1)
    wp = r(n, K) * 2 * math.pi
    wa = (r(n, K, 3) - 0.5) * 0.6
    return Surfels(means, quats, scales, opac, color, wv, wp, wa).to(dtype=dtype), cam


def dense_overlap(n: int = 5000, width: int = 128, height: int = 128, K: int = 0, seed: int = 0, dtype=torch.float32,
                  px_sigma: tuple[float, float] = (1.5, 5.0), max_tilt_deg: float = 50.0) -> tuple[Surfels, Camera]:
    """n surfels spread uniformly over the image at camera depth 2-4, each px_sigma pixels across, opacity 0.1-0.95,
    tilted up to max_tilt_deg from facing the camera: many overlapping semi-transparent layers per pixel, the case
    where a tile loop's per-pair cost dominates."""
    g = torch.Generator().manual_seed(seed)
    d64 = torch.float64
    r = lambda *s: torch.rand(*s, generator=g, dtype=d64)  # noqa: E731
    cam = Camera.look_at((0.0, 0.0, -4.0), (0.0, 0.0, 0.0), fov_deg=60.0, width=width, height=height)
    K_cam = cam.K.double()
    f = float(K_cam[0, 0])
    depth = 2.0 + 2.0 * r(n)
    px = torch.stack([r(n) * width, r(n) * height], 1)
    x_cam = (px[:, 0] - float(K_cam[0, 2])) / f * depth
    y_cam = (px[:, 1] - float(K_cam[1, 2])) / float(K_cam[1, 1]) * depth
    p_cam = torch.stack([x_cam, y_cam, depth], 1)
    R, t = cam.R.double(), cam.t.double()
    means = (p_cam - t) @ R  # camera -> world
    tilt = torch.deg2rad(max_tilt_deg * r(n))
    az = 2 * math.pi * r(n)
    n_cam = torch.stack([torch.sin(tilt) * torch.cos(az), torch.sin(tilt) * torch.sin(az), -torch.cos(tilt)], 1)
    quats = normals_to_quats(n_cam @ R)
    a = r(n) * math.pi  # spin about the normal
    c, s_ = torch.cos(a), torch.sin(a)
    quats = torch.stack([quats[:, 0] * c - quats[:, 3] * s_, quats[:, 1] * c + quats[:, 2] * s_,
                         quats[:, 2] * c - quats[:, 1] * s_, quats[:, 3] * c + quats[:, 0] * s_], 1)
    scales = (px_sigma[0] + (px_sigma[1] - px_sigma[0]) * r(n, 2)) * depth[:, None] / f
    opac = 0.1 + 0.85 * r(n)
    color = r(n, 3)
    freq = 0.2 + 1.5 * r(n, K)
    th = r(n, K) * math.pi
    wv = torch.stack([2 * math.pi * freq * torch.cos(th), 2 * math.pi * freq * torch.sin(th)], -1)
    wp = r(n, K) * 2 * math.pi
    wa = (r(n, K, 3) - 0.5) * 0.6
    return Surfels(means, quats, scales, opac, color, wv, wp, wa).to(dtype=dtype), cam


# Operators that make the host wait for the device: a scalar read (item(), float(t), bool(t), an `if` on a
# tensor) and the ones whose output size depends on the data (the host must learn the size before it allocates).
HOST_SYNC_OPS = ("aten._local_scalar_dense", "aten.nonzero", "aten.masked_select", "aten._unique2", "aten.unique_dim",
                 "aten.unique_consecutive", "aten.equal")


class HostSyncs:
    """Counts the points at which a program on a GPU would wait for the device, while the program runs on any
    device (so a CPU-only test can hold the count of a training step): the operators of HOST_SYNC_OPS, seen by a
    dispatch mode (C++ extension calls included), and Tensor.tolist / Tensor.numpy, which read memory directly.
    A copy to the host (`.cpu()`) is not counted: on a CPU run it is no operation at all.

        with HostSyncs() as syncs:
            trainer.step()
        syncs.total, syncs.by_kind  # {"aten._local_scalar_dense": 3, "tolist": 1, ...}
        syncs.sites                 # {(file, line, kind): count} of the splatzoo code that asked
    """

    def __init__(self) -> None:
        from collections import Counter

        self.by_kind: Counter = Counter()
        self.sites: Counter = Counter()
        self._mode = None
        self._saved: dict = {}

    @property
    def total(self) -> int:
        return sum(self.by_kind.values())

    def _record(self, kind: str) -> None:
        import traceback

        stack = traceback.extract_stack()[:-2]
        # host-side by design, so no wait on a GPU: Adam's step counters, and a camera's checks (Camera.to checks a
        # camera before it moves it to the device)
        if any("/torch/optim/" in f.filename or (f.filename.endswith("/splatzoo/types.py") and f.name == "__post_init__")
               for f in stack[-6:]):
            return
        self.by_kind[kind] += 1
        here = next((f for f in reversed(stack)
                     if "/splatzoo/" in f.filename and not f.filename.endswith("testing.py")), None)
        self.sites[(here.filename.split("/splatzoo/")[-1], here.lineno, kind) if here else ("?", 0, kind)] += 1

    def __enter__(self) -> "HostSyncs":
        from torch.utils._python_dispatch import TorchDispatchMode

        counter = self

        class _Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                name = str(func.overloadpacket) if hasattr(func, "overloadpacket") else str(func)
                if name in HOST_SYNC_OPS:
                    counter._record(name)
                return func(*args, **(kwargs or {}))

        for method in ("tolist", "numpy"):
            original = getattr(torch.Tensor, method)
            self._saved[method] = original

            def wrapped(t, *a, _original=original, _method=method, **kw):
                counter._record(_method)
                return _original(t, *a, **kw)

            setattr(torch.Tensor, method, wrapped)
        self._mode = _Mode()
        self._mode.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._mode.__exit__(*exc)
        for method, original in self._saved.items():
            setattr(torch.Tensor, method, original)
        self._saved.clear()
