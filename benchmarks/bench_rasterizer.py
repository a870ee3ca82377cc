"""Rasterizer benchmark: forward and forward+backward time per backend, for 2DGS (K=0) and Gabor (K=4) surfels.

    python benchmarks/bench_rasterizer.py [--json out.json] [--repeats 3] [--quick | --gpu] [--backends cpu,cuda]
                                          [--antialias off,on]
    splatzoo bench [...]              (the same, from the CLI)

Scenes: "sphere" (surfels on a sphere and a back wall, 1-4 px sigma, opacity 0.2-1) and "dense" (surfels spread
uniformly over the image at depth 2-4, 1.5-5 px sigma, opacity 0.1-0.95, tilted up to 50 degrees: many
overlapping semi-transparent layers per pixel). K=4a is the adaptive case: K=4 with per-surfel wave counts drawn
uniformly from 0..4. K=0t8 is the texture kind: K=0 waves and an 8x8 RGBA texture per surfel (--waves 0,0t4,0t8).
A trailing "b" gives every surfel the Beta falloff instead of the Gaussian, s uniform in [0.3, 1] (what a trained
`beta` holds: median 0.99 at the full protocol): the zoo's members are --waves 0,0b,4,6,0t4 (2dgs, beta, gabor,
neural-gabor's 6 free-direction waves, textured). "pairs" counts the (surfel, pixel) pairs a tile loop evaluates:
for every (surfel, tile) pair, the pixel rows of the tile inside the surfel's exact screen box, 16 pixels each;
rates are per core for the CPU (divided by torch.get_num_threads()) and per GPU for CUDA. Times are end to end (`rasterize`, every field requiring
grad; the backward of a loss on rgb, depth, normal and distortion), median of --repeats after one warm-up.
--antialias off,on times each case without and with the pixel-footprint filter (RasterSettings.pixel_filter), one
right after the other, and prints the ratio.

--against LIBRARY times this checkout's cpu rasterizer against another build of it in one process, call by call on the
same surfels (compare_builds): LIBRARY is the extension an older commit built, e.g. from a git worktree of it,
`python -c "import sys; sys.path.insert(0, WORKTREE); from splatzoo.rasterizers import native;
print(native.load('cpu').__file__)"`.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import sys
import time
from pathlib import Path

import torch

# (name, scene kind, width, height, surfels, backends allowed)
CONFIGS = (
    ("128x128/5k", "sphere", 128, 128, 5_000, ("cuda", "cpu", "reference")),
    ("128x128/5k dense", "dense", 128, 128, 5_000, ("cuda", "cpu", "reference")),
    ("256x256/20k", "sphere", 256, 256, 20_000, ("cuda", "cpu", "reference")),
    ("1920x1080/200k", "sphere", 1920, 1080, 200_000, ("cuda", "cpu")),
)
GPU_CONFIGS = (
    ("1920x1080/100k", "sphere", 1920, 1080, 100_000, ("cuda",)),
    ("1920x1080/500k", "sphere", 1920, 1080, 500_000, ("cuda",)),
    ("1920x1080/1M", "sphere", 1920, 1080, 1_000_000, ("cuda",)),
    ("1920x1080/200k dense", "dense", 1920, 1080, 200_000, ("cuda",)),
)
WAVES = ("0", "4", "4a")


BACKEND_NAMES = ("cuda", "cpu", "reference")
MAX_WAVES = 64      # far beyond any member (gabor stores at most 30); the memory check below bounds the rest
MAX_TEXTURE = 64    # the native kernels' limit on a texture side
MAX_REPEATS = 1000
WAVES_SYNTAX = re.compile(r"^(\d+)(a?)(?:t(\d+))?(b?)$")
WAVES_HELP = ("K waves (0, 4), Ka (K with per-surfel counts drawn from 0..K), KtT (K waves and a TxT texture), each "
              "with an optional trailing b (Beta kernels), e.g. 0,4,4a,0t4,0b")


def parse_waves(spec: str) -> tuple[int, bool, int, bool]:
    """(K waves, adaptive counts, texture size T (0: none), Beta kernels) of a --waves entry such as 4a, 0t4 or 0b;
    anything else, or more than MAX_WAVES waves or MAX_TEXTURE texels a side, is a SplatzooError that says why."""
    from splatzoo.errors import SplatzooError

    match = WAVES_SYNTAX.match(spec.strip())
    if match is None:
        raise SplatzooError(f"--waves entry {spec!r} is not a wave count; write {WAVES_HELP}")
    K, adaptive, tex, beta = match.groups()
    if len(K) > 6 or int(K) > MAX_WAVES:  # (a long digit string is not parsed: past any bound anyway)
        raise SplatzooError(f"--waves entry {spec!r} asks for {K if len(K) <= 6 else 'millions of'} waves per surfel; "
                            f"the benchmark takes at most {MAX_WAVES} (the zoo's members hold at most 30)")
    if tex is not None and (len(tex) > 6 or not 1 <= int(tex) <= MAX_TEXTURE):
        raise SplatzooError(f"--waves entry {spec!r} asks for a texture of {tex if len(tex) <= 6 else 'millions of'} "
                            f"texels a side; use 1 to {MAX_TEXTURE} (the rasterizer's limit), e.g. 0t4")
    K, T = int(K), int(tex or 0)
    return K, bool(adaptive), T, bool(beta)


def scene_bytes(surfels: int, waves: str) -> int:
    """About how much memory one benchmark scene takes at its peak: every per-surfel field (position, rotation,
    scales, opacity, colour, falloff: 16 floats; 6 per wave; 4 per texel), four times over (the values, their
    gradients, the copy on the backend's device, make_scene's temporaries)."""
    K, _, T, _ = parse_waves(waves)
    return surfels * (16 + 6 * K + 4 * T * T) * 4 * 4


def _gpu_free_bytes() -> int | None:
    try:
        return int(torch.cuda.mem_get_info()[0]) if torch.cuda.is_available() else None
    except RuntimeError:
        return None


def check_request(backends, waves, configs=CONFIGS, repeats: int = 3) -> tuple[list[str] | None, tuple[str, ...]]:
    """Check a benchmark request before anything runs; returns (backends, waves) as run_benchmark takes them.
    backends, waves: comma-separated text or lists (backends None: every one available here). A bad entry, a
    backend that cannot run here or runs none of the scenes, a repeat count out of 1..MAX_REPEATS or a scene that
    would not fit in memory is a SplatzooError that names it."""
    from splatzoo.cli import available_memory
    from splatzoo.errors import SplatzooError
    from splatzoo.rasterizers import BACKENDS
    from splatzoo.registry import closest

    if isinstance(repeats, bool) or not isinstance(repeats, int) or not 1 <= repeats <= MAX_REPEATS:
        raise SplatzooError(f"--repeats {repeats!r}: give a whole number of timed repeats from 1 to {MAX_REPEATS} "
                            "(the median is reported)")

    def entries(value, option: str) -> list[str]:
        items = [t.strip() for t in value.split(",")] if isinstance(value, str) else [str(t).strip() for t in value]
        if not items or any(not t for t in items):
            raise SplatzooError(f"{option} {value!r} has an empty entry; give a comma-separated list without gaps")
        twice = sorted({t for t in items if items.count(t) > 1})
        if twice:
            raise SplatzooError(f"{option} {value!r} names {', '.join(twice)} twice; give each once")
        return items

    wave_list = entries(waves, "--waves")
    for w in wave_list:
        parse_waves(w)
    if backends is not None:
        backend_list = entries(backends, "--backends")
        for b in backend_list:
            if b not in BACKEND_NAMES:
                raise SplatzooError(f"unknown backend {b!r} in --backends; the rasterizer backends are "
                                    f"{', '.join(BACKEND_NAMES)}" + closest(b, BACKEND_NAMES))
            reason = BACKENDS.get(b).unavailable_reason()
            if reason is not None:
                raise SplatzooError(f"--backends {b}: the {b} backend cannot run here ({reason}); leave it out")
    else:
        backend_list = [b for b in BACKEND_NAMES if BACKENDS.get(b).available()]
    for b in backend_list:
        if not any(b in allowed for *_, allowed in configs):
            scenes = ", ".join(f"{c[0]} ({'/'.join(c[-1])})" for c in configs)
            raise SplatzooError(f"none of the chosen scenes runs on the {b} backend (scenes: {scenes}); choose "
                                "other scenes (--quick, --gpu or neither) or other --backends")
    if not backend_list:
        raise SplatzooError("no backend can run here; see `splatzoo bench --help` for --backends")
    budgets = [("memory", available_memory())]
    if "cuda" in backend_list:
        budgets.append(("GPU memory", _gpu_free_bytes()))
    for name, _, _, _, n, allowed in configs:
        if not set(allowed) & set(backend_list):
            continue
        for w in wave_list:
            need = scene_bytes(n, w)
            for what, have in budgets:
                if have is not None and need > have:
                    raise SplatzooError(f"--waves {w} on the scene {name} needs about {need / 2**30:.1f} GiB of "
                                        f"{what}, more than the {have / 2**30:.1f} GiB free; use fewer waves or a "
                                        "smaller texture, or --quick")
    return (backend_list if backends is not None else None), tuple(wave_list)


def make_scene(kind: str, n: int, width: int, height: int, waves: str, seed: int = 0, dtype=torch.float32):
    """A benchmark scene; waves "K", "Ka" (K waves with per-surfel counts drawn from 0..K) or "KtT" (K waves and a
    T x T texture per surfel: rgb in [-0.3, 0.3], alpha in [0.5, 1]), each with a trailing "b" for Beta kernels."""
    from splatzoo.testing import dense_overlap, sphere_and_wall

    K, adaptive, T, beta = parse_waves(waves)
    make = dense_overlap if kind == "dense" else sphere_and_wall
    s, cam = make(n, width, height, K, seed=seed, dtype=dtype)
    if adaptive:
        s.wave_counts = torch.randint(0, K + 1, (n,), generator=torch.Generator().manual_seed(seed), dtype=torch.int32)
    if T:
        t = torch.rand(n, T, T, 4, generator=torch.Generator().manual_seed(seed + 1)).to(dtype)
        s.texture = torch.cat([(t[..., :3] - 0.5) * 0.6, 0.5 + 0.5 * t[..., 3:]], -1)
    if beta:
        s.falloff = (0.3 + 0.7 * torch.rand(n, generator=torch.Generator().manual_seed(seed + 2))).to(dtype)
    return s, cam


def count_pairs(surfels, camera) -> int:
    """(surfel, pixel) pairs a tile loop evaluates (see the module docstring)."""
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
    fn()  # warm-up (and, for a native backend, the first-use build)
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def machine_info() -> dict:
    return {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "torch": torch.__version__, "python": platform.python_version(),
            "cuda_device": torch.cuda.get_device_name() if torch.cuda.is_available() else None}


def run_benchmark(backends=None, waves=WAVES, configs=CONFIGS, repeats: int = 3, reference_repeats: int = 1,
                  json_path: str | os.PathLike | None = None, echo=print, antialias=("off",)) -> dict:
    """Run every (config, backend, waves, antialias) and return {"machine": ..., "results": [...]}; optionally write
    JSON. antialias: "off" and/or "on" (the pixel-footprint filter)."""
    from splatzoo.cli import check_output_file
    from splatzoo.io import atomic_path
    from splatzoo.rasterizers import BACKENDS, rasterize
    from splatzoo.rasterizers.common import ANTIALIASED, SETTINGS

    backends, waves = check_request(backends, waves, configs, repeats)
    if json_path is not None:  # before the benchmark, not after it
        check_output_file(json_path, "--json")
    if backends is None:
        backends = [b for b in BACKEND_NAMES if BACKENDS.get(b).available()]
    threads = torch.get_num_threads()
    results = []
    header = f"{'scene':<22}{'backend':<11}{'K':>3}{'AA':>4}{'fwd ms':>11}{'fwd+bwd ms':>12}{'pairs':>14}{'Mpairs/s':>11}"
    echo(header)
    echo("-" * len(header))
    for name, kind, W, H, n, allowed in configs:
        for K in waves:
            scene, cam = make_scene(kind, n, W, H, K, seed=n + parse_waves(K)[0])
            pairs = count_pairs(scene, cam)
            for backend in backends:
                if backend not in allowed:
                    continue
                b = BACKENDS.get(backend)
                device = b.torch_device()
                s = scene.to(device).map(lambda t: t.detach().requires_grad_(True))
                sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
                reps = reference_repeats if backend == "reference" else repeats

                for aa in antialias:
                    settings = ANTIALIASED if aa == "on" else SETTINGS

                    def fwd():
                        with torch.no_grad():
                            rasterize(s, cam, backend=b, settings=settings)

                    def fwd_bwd():
                        out = rasterize(s, cam, backend=b, settings=settings)
                        loss = out.rgb.sum() + out.depth.sum() + out.normal.sum() + out.distortion.sum()
                        loss.backward()

                    t_f = _time(fwd, reps, sync)
                    t_fb = _time(fwd_bwd, reps, sync)
                    cores = threads if device.type == "cpu" else 1
                    row = {"scene": name, "kind": kind, "width": W, "height": H, "surfels": n, "K": K,
                           "backend": backend, "antialias": aa, "forward_ms": round(t_f, 3),
                           "forward_backward_ms": round(t_fb, 3), "pairs": pairs,
                           "pairs_per_s": pairs / (t_f / 1e3) / cores, "threads": cores}
                    results.append(row)
                    echo(f"{name:<22}{backend:<11}{K:>3}{aa:>4}{t_f:>11.2f}{t_fb:>12.2f}{pairs:>14,}"
                         f"{row['pairs_per_s'] / 1e6:>11.1f}")
                del s
    report = {"machine": machine_info(), "date": time.strftime("%Y-%m-%d %H:%M"), "results": results}
    _summary(results, echo)
    if json_path is not None:
        path = Path(json_path)
        with atomic_path(path) as tmp:  # never leave a half-written file
            tmp.write_text(json.dumps(report, indent=2))
        echo(f"wrote {path}")
    return report


def _summary(results, echo):
    def get(scene, backend, K, key, aa="off"):
        for r in results:
            if r["scene"] == scene and r["backend"] == backend and r["K"] == K and r.get("antialias", "off") == aa:
                return r[key]
        return None

    echo("")
    for scene in dict.fromkeys(r["scene"] for r in results):
        for native in ("cpu", "cuda"):
            for K in ("0", "4"):
                a, b = get(scene, "reference", K, "forward_backward_ms"), get(scene, native, K, "forward_backward_ms")
                if a and b:
                    echo(f"{scene} K={K}: {native} fwd+bwd is {a / b:.0f}x faster than the reference")
            for key, what in (("forward_ms", "fwd"), ("forward_backward_ms", "fwd+bwd")):
                k0, k4, k4a = (get(scene, native, K, key) for K in ("0", "4", "4a"))
                if k0 and k4:
                    extra = f", K=4a / K=0 = {k4a / k0:.2f}" if k4a else ""
                    echo(f"{scene}: {native} {what} K=4 / K=0 = {k4 / k0:.2f}{extra}")
                for K in ("0", "4", "4a"):
                    off, on = get(scene, native, K, key), get(scene, native, K, key, "on")
                    if off and on:
                        echo(f"{scene}: {native} {what} K={K} antialiased / plain = {on / off:.2f}")


def compare_builds(library, waves=WAVES, configs=CONFIGS[:2], repeats: int = 31, antialias=("off", "on"),
                   json_path=None, echo=print) -> list[dict]:
    """This checkout's cpu rasterizer against another build of it, `library` (an older commit's extension .so with
    the same bindings), in one process: each repeat runs both on the same surfels, one right after the other (the
    order alternating), forward and forward+backward. Times are the process's CPU time, which other processes on
    shared cores do not inflate as they do wall time. Rows: each build's fastest time (ms) and the median ratio
    new/old over the pairs run back to back."""
    from splatzoo.errors import SplatzooError
    from splatzoo.rasterizers import native, rasterize
    from splatzoo.rasterizers.common import ANTIALIASED, SETTINGS

    library = Path(library)
    if not library.is_file():
        raise SplatzooError(f"--against {library}: no such extension library; build the other commit's and give "
                            "the .so's path")
    new = native.load("cpu")
    old = native._import_built(library.stem, library)
    if tuple(getattr(old, "SURFEL_FIELDS", ())) != native.SURFEL_FIELDS:
        raise SplatzooError(f"--against {library}: it takes the surfel fields {getattr(old, 'SURFEL_FIELDS', ())}, "
                            f"this checkout {native.SURFEL_FIELDS}; only builds with the same bindings compare")
    _, waves = check_request(["cpu"], waves, configs, repeats)
    rows = []
    echo(f"{'scene':<18}{'K':>5}{'AA':>4}{'old fwd':>9}{'new fwd':>9}{'ratio':>7}{'old f+b':>9}{'new f+b':>9}"
         f"{'ratio':>7}   (CPU ms: the fastest; ratio: new/old, the median over pairs back to back)")
    try:
        for name, kind, W, H, n, _ in configs:
            for K in waves:
                scene, cam = make_scene(kind, n, W, H, K, seed=n + parse_waves(K)[0])
                s = scene.map(lambda t: t.detach().requires_grad_(True))
                for aa in antialias:
                    settings = ANTIALIASED if aa == "on" else SETTINGS

                    def fwd():
                        with torch.no_grad():
                            rasterize(s, cam, backend="cpu", settings=settings)

                    def fwd_bwd():
                        out = rasterize(s, cam, backend="cpu", settings=settings)
                        (out.rgb.sum() + out.depth.sum() + out.normal.sum() + out.distortion.sum()).backward()

                    row = {"scene": name, "K": K, "antialias": aa}
                    for key, fn in (("forward", fwd), ("forward_backward", fwd_bwd)):
                        times = {"old": [], "new": []}
                        for r in range(repeats + 1):  # the first pair warms up
                            for label, C in ((("old", old), ("new", new)) if r % 2 == 0 else
                                             (("new", new), ("old", old))):
                                native._modules["cpu"] = C
                                t0 = time.process_time()
                                fn()
                                if r > 0:
                                    times[label].append(time.process_time() - t0)
                        row[f"old_{key}_ms"] = min(times["old"]) * 1e3
                        row[f"new_{key}_ms"] = min(times["new"]) * 1e3
                        row[f"{key}_ratio"] = statistics.median(b / a for a, b in zip(times["old"], times["new"]))
                    rows.append(row)
                    echo(f"{name:<18}{K:>5}{aa:>4}{row['old_forward_ms']:>9.2f}{row['new_forward_ms']:>9.2f}"
                         f"{row['forward_ratio']:>7.3f}{row['old_forward_backward_ms']:>9.2f}"
                         f"{row['new_forward_backward_ms']:>9.2f}{row['forward_backward_ratio']:>7.3f}")
    finally:
        native._modules["cpu"] = new
    ratios = [r["forward_backward_ratio"] for r in rows]
    if ratios:
        echo(f"fwd+bwd new/old: {min(ratios):.3f} to {max(ratios):.3f}, geometric mean "
             f"{statistics.geometric_mean(ratios):.3f}")
    if json_path is not None:
        from splatzoo.io import atomic_path

        with atomic_path(Path(json_path)) as tmp:
            tmp.write_text(json.dumps({"machine": machine_info(), "date": time.strftime("%Y-%m-%d %H:%M"),
                                       "against": str(library), "rows": rows}, indent=2))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default="benchmarks/results/rasterizer.json", help="where to write the results")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--backends", default=None, help="comma-separated subset of cuda,cpu,reference")
    ap.add_argument("--waves", default=",".join(WAVES),
                    help="comma-separated wave counts: 0, 4, 4a (adaptive); 0t8: K=0 and 8x8 textures; "
                         "a trailing b: Beta kernels (0,0b,4,6,0t4: the zoo's members)")
    group = ap.add_mutually_exclusive_group()
    group.add_argument("--quick", action="store_true", help="only the 128x128 scenes")
    group.add_argument("--gpu", action="store_true", help="the 1920x1080 scenes of 100k, 500k and 1M surfels (cuda)")
    ap.add_argument("--antialias", default="off", help="off, on, or off,on (both, side by side)")
    ap.add_argument("--against", default=None, metavar="LIBRARY",
                    help="time the cpu rasterizer against another build of it (an older commit's extension .so), "
                         "call by call in one process")
    args = ap.parse_args(argv)
    modes = tuple(args.antialias.split(","))
    if not modes or set(modes) - {"off", "on"}:
        ap.error("--antialias takes off, on or off,on")
    configs = CONFIGS[:2] if args.quick else GPU_CONFIGS if args.gpu else CONFIGS
    from splatzoo.errors import SplatzooError

    try:
        if args.against:
            compare_builds(args.against, waves=args.waves, configs=configs, repeats=args.repeats, antialias=modes,
                           json_path=args.json)
            return 0
        run_benchmark(backends=args.backends, waves=args.waves, configs=configs, repeats=args.repeats,
                      json_path=args.json, antialias=modes)
    except SplatzooError as e:
        ap.error(str(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
