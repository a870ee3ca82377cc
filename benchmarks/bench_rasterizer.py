"""Rasterizer benchmark: forward and forward+backward time per backend, for 2DGS (K=0) and Gabor (K=4) surfels.

    python benchmarks/bench_rasterizer.py [--json out.json] [--repeats 3] [--quick]
    splatzoo bench [...]              (the same, from the CLI)

Scenes are random but realistic: surfels on a sphere and a back wall in front of the camera, 1-4 pixels sigma.
"pairs" counts the (surfel, pixel) pairs the native tile loop evaluates: for every (surfel, tile) pair, the pixel
rows of the tile inside the surfel's exact screen box, 16 pixels each. The same count is used for the reference so
the rates compare equal work. Rates are per core: divided by torch.get_num_threads(). "op" columns time the
extension's forward/backward alone, without the PyTorch set-up (projection, sorting, gathers) around it.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

CONFIGS = (  # (name, width, height, surfels, backends allowed)
    ("128x128/5k", 128, 128, 5_000, ("cuda", "cpu", "reference")),
    ("256x256/20k", 256, 256, 20_000, ("cuda", "cpu", "reference")),
    ("1920x1080/200k", 1920, 1080, 200_000, ("cuda", "cpu")),
)


def random_scene(n: int, width: int, height: int, K: int, seed: int = 0, dtype=torch.float32):
    """n surfels (70% on a unit sphere, 30% on a wall behind it) seen from 4 units away, 1-4 px sigma."""
    from splatzoo.testing import sphere_and_wall

    return sphere_and_wall(n, width, height, K, seed=seed, dtype=dtype)

def count_pairs(surfels, camera) -> int:
    """(surfel, pixel) pairs the native CPU tile loop evaluates (see the module docstring)."""
    from splatzoo.rasterizers.common import project

    with torch.no_grad():
        p = project(surfels, camera.to(surfels.means.device, surfels.means.dtype))
        b = p.boxes[p.visible].double()
        W, H = camera.width, camera.height
        x0 = torch.ceil(b[:, 0] - 0.5).clamp(min=0)
        x1 = torch.floor(b[:, 2] - 0.5).clamp(max=W - 1)
        y0 = torch.ceil(b[:, 1] - 0.5).clamp(min=0)
        y1 = torch.floor(b[:, 3] - 0.5).clamp(max=H - 1)
        ok = (x0 <= x1) & (y0 <= y1)
        tiles_x = torch.div(x1, 16, rounding_mode="floor") - torch.div(x0, 16, rounding_mode="floor") + 1
        return int(((y1 - y0 + 1) * 16 * tiles_x)[ok].sum().item())


def _time(fn, repeats: int, sync) -> float:
    fn()  # warm-up (and, for the native backend, the first-use build)
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def _time_kernel(C, s, cam, repeats, sync):
    """The extension's own forward and backward (no PyTorch set-up around it): what the tile loop costs."""
    from splatzoo.rasterizers.common import project

    with torch.no_grad():
        cam = cam.to(s.means.device, s.means.dtype)
        p = project(s, cam)
        vis = torch.nonzero(p.visible).squeeze(1)
        order = vis[torch.sort(p.depth[vis], stable=True).indices]
        args = [t[order].contiguous() for t in (p.T, p.center_px, p.depth, p.normal, s.opacities, s.base_color,
                                                 s.wave_vectors, s.wave_phases, s.wave_amplitudes, p.boxes)]
        out = C.forward(*args, cam.width, cam.height)
        g = torch.Generator(device=s.means.device).manual_seed(0)
        grads = [torch.randn(o.shape, generator=g, device=o.device, dtype=o.dtype) for o in out[:6]]
        k_f = _time(lambda: C.forward(*args, cam.width, cam.height), repeats, sync)
        k_b = _time(lambda: C.backward(*args, cam.width, cam.height, list(out), grads), repeats, sync)
    return k_f, k_b


def run_benchmark(backends=None, waves=(0, 4), configs=CONFIGS, repeats: int = 3, reference_repeats: int = 1,
                  json_path: str | os.PathLike | None = None, echo=print) -> dict:
    """Run every (config, backend, K) and return {"machine": ..., "results": [...]}; optionally write JSON."""
    from splatzoo.rasterizers import native, rasterize

    if backends is None:
        backends = [b for b, ok in (("cuda", native.cuda_available()), ("cpu", native.cpu_available()),
                                    ("reference", True)) if ok]
    threads = torch.get_num_threads()
    results = []
    header = (f"{'scene':<16}{'backend':<11}{'K':>2}{'fwd ms':>11}{'fwd+bwd ms':>12}{'pairs':>12}{'Mpairs/s/core':>15}"
              f"{'op fwd':>10}{'op bwd':>10}{'op Mp/s/c':>12}")
    echo(header)
    echo("-" * len(header))
    for name, W, H, n, allowed in configs:
        for K in waves:
            scene, cam = random_scene(n, W, H, K, seed=n + K)
            pairs = count_pairs(scene, cam)
            for backend in backends:
                if backend not in allowed:
                    continue
                device = "cuda" if backend == "cuda" else "cpu"
                s = scene.to(device).map(lambda t: t.detach().requires_grad_(True))
                sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
                reps = reference_repeats if backend == "reference" else repeats
                fwd = lambda: rasterize(s, cam, backend=backend)  # noqa: E731

                def fwd_bwd():
                    out = rasterize(s, cam, backend=backend)
                    loss = out.rgb.sum() + out.depth.sum() + out.normal.sum() + out.distortion.sum()
                    loss.backward()

                t_f = _time(fwd, reps, sync)
                t_fb = _time(fwd_bwd, reps, sync)
                cores = threads if device == "cpu" else 1
                row = {"scene": name, "width": W, "height": H, "surfels": n, "K": K, "backend": backend,
                       "forward_ms": round(t_f, 2), "forward_backward_ms": round(t_fb, 2), "pairs": pairs,
                       "pairs_per_s_per_core": pairs / (t_f / 1e3) / cores, "threads": cores}
                kernel = ""
                if backend in ("cpu", "cuda"):
                    k_f, k_b = _time_kernel(native.load(backend), s, cam, reps, sync)
                    row.update(kernel_forward_ms=round(k_f, 2), kernel_backward_ms=round(k_b, 2),
                               kernel_pairs_per_s_per_core=pairs / (k_f / 1e3) / cores)
                    kernel = f"{k_f:>10.1f}{k_b:>10.1f}{row['kernel_pairs_per_s_per_core'] / 1e6:>12.1f}"
                results.append(row)
                echo(f"{name:<16}{backend:<11}{K:>2}{t_f:>11.1f}{t_fb:>12.1f}{pairs:>12,}"
                     f"{row['pairs_per_s_per_core'] / 1e6:>15.1f}{kernel}")
    report = {"machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                          "torch_threads": threads, "torch": torch.__version__, "python": platform.python_version(),
                          "cuda_device": torch.cuda.get_device_name() if torch.cuda.is_available() else None},
              "date": time.strftime("%Y-%m-%d"), "results": results}
    _summary(results, echo)
    if json_path is not None:
        path = Path(json_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(report, indent=2))
        tmp.replace(path)  # never leave a half-written file
        echo(f"wrote {path}")
    return report


def _summary(results, echo):
    def get(scene, backend, K, key):
        for r in results:
            if r["scene"] == scene and r["backend"] == backend and r["K"] == K:
                return r[key]
        return None

    echo("")
    for scene in dict.fromkeys(r["scene"] for r in results):
        for K in (0, 4):
            a, b = get(scene, "reference", K, "forward_backward_ms"), get(scene, "cpu", K, "forward_backward_ms")
            if a and b:
                echo(f"{scene} K={K}: cpu fwd+bwd is {a / b:.0f}x faster than the reference")
        k0, k4 = get(scene, "cpu", 0, "forward_backward_ms"), get(scene, "cpu", 4, "forward_backward_ms")
        if k0 and k4:
            echo(f"{scene}: cpu K=4 fwd+bwd / K=0 fwd+bwd = {k4 / k0:.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default="benchmarks/results/rasterizer.json", help="where to write the results")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--backends", default=None, help="comma-separated subset of cuda,cpu,reference")
    ap.add_argument("--quick", action="store_true", help="only the 128x128/5k scene")
    args = ap.parse_args(argv)
    backends = args.backends.split(",") if args.backends else None
    configs = CONFIGS[:1] if args.quick else CONFIGS
    run_benchmark(backends=backends, configs=configs, repeats=args.repeats, json_path=args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
