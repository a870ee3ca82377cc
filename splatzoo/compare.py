"""`splatzoo compare`: train several models under one budget and report the trade side by side."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from .errors import SplatzooError
from .io import atomic_path, write_json, write_text
from .training import TrainConfig, train


@dataclass
class QuickPreset:
    """A small built-in scene and a short schedule (`--quick`). The default finishes `compare` in a few minutes on
    2 CPU cores; `sweep` uses a smaller one (sweep.SWEEP_QUICK)."""

    scene: str = "sweater"
    views: int = 24
    width: int = 128
    height: int = 128
    iterations: int = 1500
    num_primitives: int | None = 2000


def builtin_scene(out: Path, name: str | None, preset: QuickPreset | None, *, seed: int = 0,
                  progress: bool = True) -> Path:
    """The built-in synthetic scene `name` (default: the preset's, else sweater), rendered once into
    out/scene-<name> at the preset's size (full size without one); later calls reuse it."""
    from .data.synthetic import make_synthetic_scene

    name = name or (preset.scene if preset else "sweater")
    data = Path(out) / f"scene-{name}"
    if not (data / "sparse").exists():
        kw = {"views": preset.views, "width": preset.width, "height": preset.height} if preset else {}
        make_synthetic_scene(name, data, seed=seed, progress=progress, **kw)
    return data


def parse_model_arg(arg: str) -> tuple[str, str, dict]:
    """'gabor' or 'gabor:n_waves=8,...' -> (label, model name, options)."""
    name, _, rest = arg.partition(":")
    options = {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq:
            raise SplatzooError(f"model option {item!r} in {arg!r} must look like key=value")
        options[key.strip().replace("-", "_")] = value.strip()
    return arg, name, options


def compare(models: list[str], data=None, out="runs/compare", *, iterations: int | None = None,
            num_primitives: int | None = None, densify: bool = False, quick: bool = False, seed: int = 0,
            backend: str = "auto", scene_options: dict | None = None, progress: bool = True,
            synthetic_scene: str | None = None) -> dict:
    """Train every model with identical data, initial points and budget; write compare.json, report.md,
    compare.png and convergence.png into `out`. Without `data`, a built-in synthetic scene is made."""
    from .data import load_scene
    from .zoo import get_model_spec, make_config

    if not models:
        raise SplatzooError("name at least one model to compare, e.g. `splatzoo compare gabor 2dgs`")
    parsed = [parse_model_arg(m) for m in models]
    labels = [p[0] for p in parsed]
    if len(set(labels)) != len(labels):
        raise SplatzooError(f"each model may appear once; got {', '.join(labels)}")
    for _, name, opts in parsed:  # fail on a typo before hours of training
        get_model_spec(name)
        make_config(name, **opts)
    out = Path(out)
    preset = QuickPreset() if quick else None
    if data is None:
        data = builtin_scene(out, synthetic_scene, preset, seed=seed, progress=progress)
    scene_options = dict(scene_options or {})
    scene = load_scene(data, **scene_options)
    iterations = iterations or (preset.iterations if preset else 30000)
    num_primitives = num_primitives or (preset.num_primitives if preset else None)
    base_cfg = TrainConfig(iterations=iterations, num_primitives=num_primitives, densify=densify, seed=seed,
                           backend=backend)
    runs, settings = {}, {"data": str(data), "scene": scene.name, "iterations": iterations,
                          "num_primitives": num_primitives, "densify": densify, "seed": seed, "backend": backend,
                          "scene_options": scene_options, "models": labels,
                          "train_views": len(scene.train), "test_views": len(scene.test)}
    for label, name, opts in parsed:
        run_dir = out / "runs" / _safe(label)
        if (run_dir / "metrics.json").exists() and (run_dir / "model.pt").exists():
            runs[label] = json.loads((run_dir / "metrics.json").read_text())  # finished earlier: reuse
            continue
        resume = (run_dir / "checkpoint.pt").exists()
        result = train(scene, name, opts, replace(base_cfg), run_dir, resume=resume, progress=progress,
                       scene_options=scene_options)
        runs[label] = result.metrics
        settings["backend"] = result.metrics.get("backend", backend)
    report = {"runs": runs, "settings": settings}
    write_json(out / "compare.json", report)
    write_text(out / "report.md", report_markdown(report))
    plot_convergence({label: out / "runs" / _safe(label) for label in labels}, out / "convergence.png")
    plot_comparison(scene, {label: out / "runs" / _safe(label) for label in labels}, out / "compare.png",
                    backend=settings["backend"])
    return report


def _safe(label: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in label)


def report_markdown(report: dict) -> str:
    runs, s = report["runs"], report["settings"]
    labels = list(runs)
    best = {
        "ssim": max(labels, key=lambda k: runs[k]["ssim"]),
        "psnr": max(labels, key=lambda k: runs[k]["psnr"]),
        "lpips": min(labels, key=lambda k: runs[k]["lpips"] if math.isfinite(runs[k]["lpips"]) else 1e9),
    }

    def cell(label, key, fmt):
        text = fmt.format(runs[label][key])
        return f"**{text}**" if best.get(key) == label else text

    first = runs[labels[0]]
    conv = first.get("conventions", {})
    lines = [
        f"# splatzoo compare: {', '.join(labels)}", "",
        f"Scene `{s['scene']}` ({s['train_views']} train / {s['test_views']} test views), {s['iterations']} iterations, "
        f"{'densification on' if s['densify'] else 'densification off'}, "
        f"{s['num_primitives'] or 'all'} initial primitives, seed {s['seed']}, backend `{s['backend']}`.", "",
        "| model | SSIM ↑ | PSNR ↑ | LPIPS ↓ | FPS | train s | size MB | primitives |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k in labels:
        r = runs[k]
        lines.append(f"| {k} | {cell(k, 'ssim', '{:.4f}')} | {cell(k, 'psnr', '{:.2f}')} | {cell(k, 'lpips', '{:.4f}')} "
                     f"| {r['fps']:.1f} | {(r.get('train_seconds') or 0):.0f} | {r['size_bytes'] / 1e6:.3f} | {r['num_primitives']} |")
    lines += ["", f"Against `{labels[0]}`:", "", "| model | ΔPSNR dB | ΔSSIM | ΔLPIPS | FPS ratio | train-time ratio | size ratio |",
              "|---|---|---|---|---|---|---|"]
    for k in labels:
        r = runs[k]
        ratio = lambda a, b: (a / b) if b else float("nan")  # noqa: E731
        lines.append(f"| {k} | {r['psnr'] - first['psnr']:+.2f} | {r['ssim'] - first['ssim']:+.4f} | "
                     f"{r['lpips'] - first['lpips']:+.4f} | {ratio(r['fps'], first['fps']):.2f} | "
                     f"{ratio(r.get('train_seconds') or 0, first.get('train_seconds') or 0):.2f} | "
                     f"{ratio(r['size_bytes'], first['size_bytes']):.2f} |")
    lines += ["", f"Metrics: PSNR {conv.get('psnr', '')}; SSIM {conv.get('ssim', '')}; LPIPS {conv.get('lpips', '')}.",
              "Pictures: `compare.png` (ground truth, renders, surfels in random colours), `convergence.png`.", ""]
    return "\n".join(lines)


def _read_log(run_dir: Path) -> tuple[list, list, list, list]:
    it, loss, tit, tpsnr = [], [], [], []
    path = run_dir / "train_log.jsonl"
    if path.exists():
        for line in path.read_text().splitlines():
            rec = json.loads(line)
            if "loss" in rec:
                it.append(rec["iteration"])
                loss.append(rec["loss"])
            if "test_psnr" in rec:
                tit.append(rec["iteration"])
                tpsnr.append(rec["test_psnr"])
    return it, loss, tit, tpsnr


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_figure(fig, path: Path) -> None:
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")


def plot_convergence(run_dirs: dict[str, Path], path) -> None:
    plt = _figure()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for label, d in run_dirs.items():
        it, loss, tit, tpsnr = _read_log(d)
        if loss:
            k = max(1, len(loss) // 50)  # light smoothing so that the curves can be told apart
            sm = np.convolve(loss, np.ones(k) / k, mode="valid")
            a.plot(it[k - 1:], sm, label=label)
        if tpsnr:
            b.plot(tit, tpsnr, marker="o", ms=3, label=label)
    a.set(xlabel="iteration", ylabel="training loss", title="Training loss", yscale="log")
    b.set(xlabel="iteration", ylabel="PSNR (dB)", title="Test PSNR")
    for ax in (a, b):
        ax.grid(alpha=0.3)
        ax.legend()
    _save_figure(fig, Path(path))
    plt.close(fig)


@torch.no_grad()
def random_color_surfels(model, camera, seed: int = 0):
    """The model's surfels with one random colour each and no waves: shows primitive shapes."""
    from .types import Surfels

    s = model.surfels(camera)
    g = torch.Generator().manual_seed(seed)
    colors = torch.rand(s.num, 3, generator=g).to(s.means)
    return Surfels.constant_color(s.means, s.quats, s.scales, s.opacities, colors)


@torch.no_grad()
def plot_comparison(scene, run_dirs: dict[str, Path], path, *, backend: str = "auto", max_views: int = 3) -> None:
    from .evaluate import render_view
    from .rasterizers import rasterize
    from .zoo import load_model

    views = (scene.test or scene.train)
    views = views[:: max(1, len(views) // max_views)][:max_views]
    models = {label: load_model(d / "model.pt") for label, d in run_dirs.items()}
    cols = 1 + 2 * len(models)
    plt = _figure()
    fig, axes = plt.subplots(len(views), cols, figsize=(2.4 * cols, 2.5 * len(views)), squeeze=False)
    for r, v in enumerate(views):
        cells = [("ground truth", v.image_float())]
        for label, m in models.items():
            cells.append((label, render_view(m, v.camera, scene.background, backend)))
        for label, m in models.items():
            cam = v.camera.to(dtype=torch.float32)
            img = rasterize(random_color_surfels(m, cam), cam, backend=backend,
                            background=torch.ones(3)).rgb.clamp(0, 1)
            cells.append((f"{label} surfels", img))
        for c, (title, img) in enumerate(cells):
            ax = axes[r, c]
            ax.imshow(img.numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=9)
    fig.tight_layout()
    _save_figure(fig, Path(path))
    plt.close(fig)
