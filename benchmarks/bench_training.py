"""End-to-end training at paper scale: wall time, throughput and peak memory of a whole run of 2dgs and gabor on one
scene, a per-iteration breakdown of where a step's time goes, and (given gsplat's examples folder) gsplat's own 2DGS
trainer on the same data, iterations and device.

    python benchmarks/bench_training.py [--data DATA | --scene sweater --width 1920 --height 1080 --views 120]
        [--iterations 30000] [--models 2dgs,gabor] [--backend auto] [--breakdown-steps 200]
        [--gsplat-examples PATH/TO/gsplat/examples] [--work DIR] [--json FILE]
    splatzoo bench --training [same options]

Without --data a built-in synthetic scene is rendered at --width x --height with --views views (once, into --work).
Each model trains with splatzoo's defaults (densification on) for --iterations, exactly as `splatzoo train` does,
and is scored on the test views (PSNR, SSIM, LPIPS, FPS image-only): "train min" is the training loop, "all min" the
whole command (loading, training, checkpoints, evaluation), after a warm-up run that pays the one-time costs. The breakdown is a second, short run of
--breakdown-steps steps with a timer around each part of a step: the data (View.image_float), the model's surfels,
the rasterizer's forward and backward, the losses' forward, the optimiser, the densification (statistics, splits,
prunes, resets), and the rest (autograd of the parameter maps, bookkeeping). On a GPU each timer synchronises the
device, so the parts add up to a slower step than the throughput run: compare shares, not sums. Host syncs per step are
counted (splatzoo.testing.HostSyncs) on one step after the warm-up.

gsplat's trainer (`simple_trainer_2dgs.py default`, needs gsplat and its examples' requirements, CUDA only) runs as a
subprocess with --max_steps = --iterations, evaluated only at the end; its stats/*.json give its wall time, memory,
count and PSNR/SSIM/LPIPS (its own metric code: torchmetrics, LPIPS alex by default).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import subprocess
import sys
import time
import types
from pathlib import Path

import torch

from splatzoo.data import load_scene
from splatzoo.data.scene import View
from splatzoo.data.synthetic import make_synthetic_scene
from splatzoo.rasterizers import native, resolve_backend
from splatzoo.testing import HostSyncs
from splatzoo.training import trainer as trainer_module
from splatzoo.training.trainer import TrainConfig, Trainer
from splatzoo.zoo import make_config

PARTS = ("data", "surfels", "raster fwd", "raster bwd", "losses", "optimiser", "densify", "other")


class PartTimers:
    """Wall time per part of a training step, by wrapping the functions that do each part (restored on exit). With
    `sync`, the device is synchronised around every timed call, so that GPU work is charged to the part that
    launched it."""

    def __init__(self, trainer: Trainer, sync) -> None:
        self.trainer, self.sync = trainer, sync
        self.seconds = dict.fromkeys(PARTS, 0.0)
        self._undo: list = []
        self._depth = 0

    def _timed(self, part: str, fn):
        timers = self

        def run(*args, **kwargs):
            if timers._depth:  # a timed call inside another (a loss rendering nothing, say): charged to the outer
                return fn(*args, **kwargs)
            timers._depth += 1
            timers.sync()
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                timers.sync()
                timers.seconds[part] += time.perf_counter() - t0
                timers._depth -= 1
        return run

    def _wrap(self, owner, name: str, part: str, static: bool = False) -> None:
        shared = isinstance(owner, (type, types.ModuleType))  # else an instance: its bound method is shadowed
        original = owner.__dict__[name] if isinstance(owner, type) else getattr(owner, name)
        fn = original.__func__ if isinstance(original, staticmethod) else original
        wrapped = self._timed(part, fn)
        setattr(owner, name, staticmethod(wrapped) if static else wrapped)
        self._undo.append((owner, name, original if shared else None))

    def __enter__(self) -> "PartTimers":
        t = self.trainer
        self._wrap(View, "image_float", "data")
        self._wrap(t.net, "surfels", "surfels")
        self._wrap(native._RenderFn, "forward", "raster fwd", static=True)
        self._wrap(native._RenderFn, "backward", "raster bwd", static=True)
        for name in ("photometric_loss", "normal_consistency_loss", "distortion_loss"):
            self._wrap(trainer_module, name, "losses")
        self._wrap(t.optimizer, "step", "optimiser")
        for name in ("densify_and_prune", "reset_opacity"):
            self._wrap(trainer_module, name, "densify")
        self._wrap(t.stats, "accumulate", "densify")
        return self

    def __exit__(self, *exc) -> None:
        for owner, name, original in reversed(self._undo):
            if original is not None:
                setattr(owner, name, original)
            else:  # an instance's shadowing attribute: dropped, the class's method shows again
                with contextlib.suppress(AttributeError):
                    delattr(owner, name)
        self._undo.clear()


def _device_sync(device: torch.device):
    return torch.cuda.synchronize if device.type == "cuda" else (lambda: None)


def breakdown(scene, model: str, backend: str, device: torch.device, steps: int, warmup: int = 5) -> dict:
    """ms per step for each part over `steps` steps of a run with densification on (after `warmup` steps), and the
    host syncs of one step."""
    cfg = TrainConfig(iterations=max(30000, steps + warmup + 1), backend=backend)
    trainer = Trainer.start(scene, model, make_config(model), cfg, backend, device)
    sync = _device_sync(device)
    for _ in range(warmup):
        trainer.step()
    with HostSyncs() as syncs:
        trainer.step()
    sync()
    with PartTimers(trainer, sync) as timers:
        t0 = time.perf_counter()
        for _ in range(steps):
            trainer.step()
        sync()
        total = time.perf_counter() - t0
    parts = {k: 1000 * v / steps for k, v in timers.seconds.items()}
    parts["other"] = 1000 * total / steps - sum(v for k, v in parts.items() if k != "other")
    return {"step_ms": 1000 * total / steps, "parts_ms": parts, "host_syncs_per_step": syncs.total,
            "host_syncs_by_kind": dict(syncs.by_kind), "primitives": trainer.net.num_primitives}


def train_end_to_end(data: Path, model: str, iterations: int, backend: str, out: Path) -> dict:
    """A whole `splatzoo train` run (defaults, densification on), scored on the test views: wall time, metrics and
    peak device memory."""
    from splatzoo.runs import train

    cuda = backend == "cuda"
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    result = train(data, model, {}, TrainConfig(iterations=iterations, backend=backend), out, progress=False,
                   overwrite=True)
    wall = time.perf_counter() - t0
    metrics = json.loads((out / "metrics.json").read_text())
    train_s = metrics.get("train_seconds") or wall
    return {"wall_s": wall, "train_s": train_s, "it_per_s": iterations / train_s,
            "psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics["lpips"], "fps": metrics["fps"],
            "primitives": result.model.num_primitives, "size_mb": metrics["size_bytes"] / 1e6,
            "peak_gpu_gib": torch.cuda.max_memory_allocated() / 2**30 if cuda else None}


def gsplat_trainer(examples: Path, data: Path, iterations: int, out: Path) -> dict:
    """gsplat's own 2DGS trainer on `data` for `iterations` steps, evaluated once at the end."""
    script = examples / "simple_trainer_2dgs.py"
    if not script.is_file():
        return {"error": f"{script} not found"}
    cmd = [sys.executable, str(script), "default", "--data_dir", str(data), "--data_factor", "1", "--result_dir",
           str(out), "--max_steps", str(iterations), "--eval_steps", str(iterations), "--save_steps",
           str(iterations), "--disable_viewer"]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=examples, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        return {"error": f"exit {r.returncode}: {(r.stderr or r.stdout)[-800:]}"}
    stats = out / "stats"
    train_stats = json.loads((stats / f"train_step{iterations - 1:04d}.json").read_text())
    val = json.loads((stats / f"val_step{iterations - 1:04d}.json").read_text())
    train_s = train_stats.get("ellipse_time") or wall
    return {"wall_s": wall, "train_s": train_s, "it_per_s": iterations / train_s,
            "psnr": val["psnr"], "ssim": val["ssim"], "lpips": val["lpips"],
            "fps": 1 / val["ellipse_time"] if val.get("ellipse_time") else None, "primitives": val.get("num_GS"),
            "peak_gpu_gib": train_stats.get("mem")}


def machine() -> str:
    """The device, driver and versions, written beside every number."""
    parts = [f"torch {torch.__version__}"]
    if torch.cuda.is_available():
        parts.append(f"{torch.cuda.get_device_name()} (CUDA {torch.version.cuda})")
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            driver = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                                    capture_output=True, text=True, timeout=20).stdout.strip()
            parts.append(f"driver {driver}")
    else:
        parts.append(f"CPU, {os.cpu_count()} cores, {torch.get_num_threads()} torch threads")
    return ", ".join(parts)


def _row(label: str, r: dict) -> str:
    if "error" in r:
        return f"{label:<15} {r['error']}"

    def f(key, fmt, scale=1.0):
        v = r.get(key)
        if v is None or (isinstance(v, float) and math.isnan(v)):
            return "-"
        return format(v if scale == 1.0 else v * scale, fmt)

    return (f"{label:<15}{f('train_s', '.2f', 1 / 60):>10}{f('wall_s', '.2f', 1 / 60):>9}{f('it_per_s', '.1f'):>8}{f('psnr', '.2f'):>8}"
            f"{f('ssim', '.4f'):>8}{f('lpips', '.4f'):>8}{f('fps', '.1f'):>9}{f('primitives', 'd'):>10}"
            f"{f('peak_gpu_gib', '.2f'):>9}")


MAX_SIDE = 16384  # a synthetic scene's image side: 16K, far past the paper's 1080p


def check_request(*, data=None, size: str = "1920x1080", views: int = 120, iterations: int = 30000,
                  models: str = "2dgs,gabor", backend: str = "auto", gsplat_examples=None,
                  synthetic: bool = False) -> list[str]:
    """Check what `splatzoo bench --training` asks for before anything is rendered or trained, and return the
    arguments of run(). A size beyond MAX_SIDE or beyond this machine's memory, a model that does not exist, a
    missing dataset or gsplat folder is a SplatzooError that names it. synthetic: --size or --views were typed
    (they shape the synthetic scene, so they cannot go with --data)."""
    from splatzoo.cli import available_memory, describe_path
    from splatzoo.errors import SplatzooError
    from splatzoo.registry import MODELS

    width, _, height = size.lower().partition("x")
    if not (width.strip().isdigit() and height.strip().isdigit()):
        raise SplatzooError(f"--size must be WIDTHxHEIGHT in pixels, e.g. 1920x1080; got {size!r}")
    width, height = int(width), int(height)
    if not (8 <= width <= MAX_SIDE and 8 <= height <= MAX_SIDE):
        raise SplatzooError(f"--size {size}: give 8 to {MAX_SIDE} pixels a side, e.g. 1920x1080")
    if isinstance(views, bool) or not 2 <= views <= 100000:
        raise SplatzooError(f"--views {views}: a synthetic scene needs 2 to 100000 views (every 8th is a test view)")
    # the rendered views (8-bit, with alpha) held at once, and one float32 render's buffers
    need = views * width * height * 4 + width * height * 128
    have = available_memory()
    if data is None and have is not None and need > have:
        raise SplatzooError(f"--size {size} with {views} views needs about {need / 2**30:.1f} GiB of memory, more than "
                            f"the {have / 2**30:.1f} GiB free; use a smaller --size or fewer --views")
    if isinstance(iterations, bool) or iterations < 1:
        raise SplatzooError(f"--iterations {iterations}: train each model for at least 1 iteration")
    names = [m.strip() for m in models.split(",")]
    if not names or any(not m for m in names):
        raise SplatzooError(f"--models {models!r} has an empty entry; give comma-separated model names, e.g. "
                            "2dgs,gabor")
    twice = sorted({m for m in names if names.count(m) > 1})
    if twice:
        raise SplatzooError(f"--models {models!r} names {', '.join(twice)} twice; give each once")
    for m in names:
        if ":" in m or "=" in m:
            raise SplatzooError(f"--models {m!r}: the training benchmark trains each model with its defaults; give "
                                "model names only (see `splatzoo models`)")
        MODELS.get(m)  # an unknown name lists the known ones
    if backend not in ("auto", "cpu", "cuda", "reference"):
        from splatzoo.registry import closest

        raise SplatzooError(f"--backend {backend!r}: use auto, cpu, cuda or reference"
                            + closest(backend, ("auto", "cpu", "cuda", "reference")))
    if backend != "auto":
        from splatzoo.rasterizers import BACKENDS

        BACKENDS.get(backend).check()  # says why it cannot run here
    argv = ["--width", str(width), "--height", str(height), "--views", str(views), "--iterations", str(iterations),
            "--models", ",".join(names), "--backend", backend]
    if data is not None:
        if synthetic:
            raise SplatzooError("--size and --views shape the synthetic scene; with --data the dataset's own images "
                                "are used: drop them or --data")
        what = describe_path(data)
        if what is not None or not Path(data).is_dir():
            raise SplatzooError(f"--data {data} {what or 'is a file'}; give a dataset folder (COLMAP or "
                                "transforms.json)")
        argv += ["--data", str(data)]
    if gsplat_examples is not None:
        script = Path(gsplat_examples) / "simple_trainer_2dgs.py"
        if not script.is_file():
            raise SplatzooError(f"--gsplat-examples {gsplat_examples}: {script} not found; give gsplat's examples "
                                "folder (the one holding simple_trainer_2dgs.py)")
        argv += ["--gsplat-examples", str(gsplat_examples)]
    return argv


def run(argv: list[str] | None = None, echo=print) -> dict:
    ap = argparse.ArgumentParser(prog="bench_training", description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, help="a dataset folder (COLMAP or transforms); default: a synthetic scene")
    ap.add_argument("--scene", default="sweater", help="the built-in synthetic scene without --data")
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--views", type=int, default=120)
    ap.add_argument("--iterations", type=int, default=30000)
    ap.add_argument("--models", default="2dgs,gabor")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--breakdown-steps", type=int, default=200, help="0: no breakdown")
    ap.add_argument("--gsplat-examples", type=Path, help="gsplat's examples folder, to run its 2DGS trainer too")
    ap.add_argument("--work", type=Path, default=Path("benchmarks/results/training"))
    ap.add_argument("--json", type=Path, help="write the results here (default: WORK/training.json)")
    args = ap.parse_args(argv)
    from splatzoo.cli import check_output_file
    from splatzoo.errors import SplatzooError
    from splatzoo.io import atomic_path

    try:  # everything that can be refused is refused before the scene is rendered
        check_request(data=args.data, size=f"{args.width}x{args.height}", views=args.views, iterations=args.iterations,
                      models=args.models, backend=args.backend)  # a missing gsplat trainer is a row of the report
        out = check_output_file(args.json or args.work / "training.json", "--json")
    except SplatzooError as e:
        ap.error(str(e))
    gpu = torch.cuda.is_available() and args.backend in ("auto", "cuda")
    backend = resolve_backend(args.backend, torch.device("cuda" if gpu else "cpu"))
    device = torch.device("cuda" if backend == "cuda" else "cpu")
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    data = args.data
    if data is None:
        data = work / f"scene-{args.scene}-{args.width}x{args.height}-{args.views}views"
        if not (data / "sparse").exists():
            make_synthetic_scene(args.scene, data, views=args.views, width=args.width, height=args.height,
                                 overwrite=data.exists())
    scene = load_scene(data)
    view = scene.train[0].camera
    echo(f"# {machine()}; backend {backend}")
    echo(f"# {data.name}: {len(scene.train)} train / {len(scene.test)} test views at {view.width}x{view.height}, "
         f"{args.iterations} iterations")
    results: dict = {"machine": machine(), "backend": backend, "data": str(data), "iterations": args.iterations,
                     "size": [view.width, view.height], "train": {}, "breakdown": {}}
    echo(f"{'trainer':<15}{'train min':>10}{'all min':>9}{'it/s':>8}{'PSNR':>8}{'SSIM':>8}{'LPIPS':>8}{'FPS':>9}{'surfels':>10}"
         f"{'GPU GiB':>9}")
    models = [m.strip() for m in args.models.split(",")]
    # one-time costs (the native extension, LPIPS weights) before anything is timed
    train_end_to_end(data, models[0], 2, backend, work / "warm-up")
    for model in models:
        r = train_end_to_end(data, model, args.iterations, backend, work / f"run-{model}")
        results["train"][model] = r
        echo(_row(f"splatzoo {model}", r))
    if args.gsplat_examples is not None:
        r = gsplat_trainer(args.gsplat_examples.resolve(), data.resolve(), args.iterations,
                           (work / "gsplat-2dgs").resolve())
        results["train"]["gsplat 2dgs"] = r
        echo(_row("gsplat 2dgs", r))
    if len(models) == 2 and all("wall_s" in results["train"].get(m, {}) for m in models):
        a, b = (results["train"][m] for m in models)
        echo(f"# {models[1]} / {models[0]}: train time {b['train_s'] / a['train_s']:.2f}x, FPS {b['fps'] / a['fps']:.2f}x")
    if args.breakdown_steps > 0:
        echo(f"\n# per step, ms ({args.breakdown_steps} steps after 5, densification on; parts timed with a device sync "
             "each)")
        echo(f"{'model':<8}{'step':>8}" + "".join(f"{p:>12}" for p in PARTS) + f"{'syncs':>7}")
        for model in models:
            b = breakdown(scene, model, backend, device, args.breakdown_steps)
            results["breakdown"][model] = b
            echo(f"{model:<8}{b['step_ms']:>8.1f}" + "".join(f"{b['parts_ms'][p]:>12.2f}" for p in PARTS)
                 + f"{b['host_syncs_per_step']:>7}")
    with atomic_path(out) as tmp:  # never a half-written file
        tmp.write_text(json.dumps(results, indent=1, default=str))
    echo(f"# wrote {out}")
    return results


if __name__ == "__main__":
    run()
