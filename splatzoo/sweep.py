"""`splatzoo sweep`: the speed / accuracy trade of wave models, measured on a grid of (waves, primitives).

Every grid point is a fixed-count run (no densification, the same initial points for a given primitive count) trained
by `compare` (one compare per primitive count, so its runs, reuse of finished runs, report and pictures come for
free). n_waves 0 is the `2dgs` model. The sweep then collects PSNR, render time and model size of every point and
writes sweep.json, pareto.png (PSNR against render time and against size, Pareto fronts marked) and report.md.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from .compare import ModelChoice, QuickPreset, builtin_scene, compare
from .errors import SplatzooError
from .figures import metric, pyplot, save_figure
from .io import say_progress, write_json, write_text


# `--quick`: the whole default grid in well under an hour on 2 CPU cores (the grid sets the primitive counts)
SWEEP_QUICK = QuickPreset(views=16, width=96, height=96, iterations=400, num_primitives=None)


def parse_int_list(text, what: str) -> list[int]:
    """'0,1,2' (or a list) -> [0, 1, 2], with a clear error."""
    if isinstance(text, (list, tuple)):
        items = list(text)
    else:
        items = [t for t in str(text).replace(" ", "").split(",") if t]
    try:
        values = [int(v) for v in items]
    except ValueError:
        raise SplatzooError(f"{what} must be a comma-separated list of integers, got {text!r}") from None
    if not values:
        raise SplatzooError(f"{what} needs at least one value")
    if any(v < 0 for v in values) or len(set(values)) != len(values):
        raise SplatzooError(f"{what} must be distinct non-negative integers, got {text!r}")
    return values


def grid_choice(model: str, n_waves: int, options: dict | None = None) -> ModelChoice:
    """The compare entry of one grid column: the `2dgs` model for 0 waves, else `model` with n_waves and the
    other options (structured, so typed values arrive as they are); its label reads `gabor:n_waves=4[,opt=v]`."""
    if n_waves == 0:
        return ModelChoice("2dgs", "2dgs", {})
    extra = "".join(f",{k}={v}" for k, v in (options or {}).items())
    return ModelChoice(f"{model}:n_waves={n_waves}{extra}", model, {"n_waves": n_waves, **(options or {})})


def wave_models() -> list[str]:
    """The models a sweep can take: those whose config has n_waves (plugins that fail to load are left out)."""
    import dataclasses

    from .registry import MODELS

    return [e.name for e in MODELS.entries()
            if not e.broken and "n_waves" in {f.name for f in dataclasses.fields(e.spec.config_cls)}]


def check_sweep_model(model: str, waves: list[int], model_options: dict | None = None) -> None:
    """Refuse, before anything trains, a sweep that would not be what it says: a model without n_waves (every column
    would be something else), n_waves among its options (the grid sets it), options that no column would use (a
    grid of n_waves 0 only: the 2dgs model, which takes none of them) and options the model refuses."""
    import dataclasses

    from .zoo import get_model_spec, make_config

    options = dict(model_options or {})
    spec = get_model_spec(model)
    if "n_waves" not in {f.name for f in dataclasses.fields(spec.config_cls)}:
        raise SplatzooError(f"model {model!r} has no n_waves option, so a sweep over --n-waves cannot train it (n_waves "
                            f"0 is the 2dgs model); sweep one of the wave models: {', '.join(wave_models())}, or "
                            f"train {model} with `splatzoo train` or `splatzoo compare`")
    if "n_waves" in options:
        raise SplatzooError(f"n_waves={options['n_waves']} among the model options: the sweep sets n_waves from "
                            f"--n-waves; give the counts there, e.g. --n-waves 0,{options['n_waves']}")
    if options and not any(k > 0 for k in waves):
        raise SplatzooError(f"--n-waves {','.join(map(str, waves))} trains only the 2dgs model, which takes none of "
                            f"{model}'s options ({', '.join(options)}); add wave counts (e.g. --n-waves 0,4) or drop "
                            "the options")
    for k in (k for k in waves if k > 0):
        make_config(model, n_waves=k, **options)  # an option or a count the model refuses, named before training


def sweep(data=None, out="runs/sweep", *, model: str = "gabor", n_waves=(0, 1, 2, 4, 8),
          num_primitives=(1000, 2000, 4000), iterations: int | None = None, quick: bool = False, seed: int = 0,
          backend: str = "auto", scene_options: dict | None = None, progress: bool = True,
          synthetic_scene: str | None = None, model_options: dict | None = None, overwrite: bool = False,
          antialias: bool = True) -> dict:
    """Train the grid and write sweep.json, pareto.png and report.md into `out`; returns the sweep.json content.
    `antialias` trains and renders every run with the pixel-footprint filter.

    Without `data` a built-in synthetic scene is rendered (sweater; --quick: 96x96, 16 views). Runs live in
    out/n<primitives>/runs/<label>; finished runs are reused, so an interrupted sweep picks up where it stopped.
    """
    waves = parse_int_list(n_waves, "--n-waves")
    counts = parse_int_list(num_primitives, "--num-primitives")
    if 0 in counts:
        raise SplatzooError("--num-primitives values must be at least 1")
    check_sweep_model(model, waves, model_options)
    if model_options and 0 in waves:
        say_progress(progress)(f"note: n_waves 0 is the 2dgs model, trained without {model}'s options "
                               f"({', '.join(f'{k}={v}' for k, v in model_options.items())}); the other columns "
                               "take them")
    out = Path(out)
    preset = SWEEP_QUICK if quick else None
    if data is None:
        data = builtin_scene(out, synthetic_scene, preset, seed=seed, progress=progress)
    iterations = iterations or (preset.iterations if preset else 30000)
    choices = {k: grid_choice(model, k, model_options) for k in waves}
    points, per_count = [], {}
    for n in counts:
        report = compare(list(choices.values()), data, out / f"n{n}", iterations=iterations, num_primitives=n,
                         densify=False, seed=seed, backend=backend, scene_options=scene_options, progress=progress,
                         overwrite=overwrite, antialias=antialias)
        per_count[n] = report["settings"]
        for k, choice in choices.items():
            label = choice.label
            r = report["runs"][label]
            fps = metric(r.get("fps"))
            points.append({"n_waves": k, "num_primitives": n, "model": "2dgs" if k == 0 else model, "label": label,
                           "psnr": metric(r.get("psnr")), "ssim": metric(r.get("ssim")), "lpips": metric(r.get("lpips")),
                           "fps": fps,
                           "render_ms": 1000.0 / fps if fps and math.isfinite(fps) else float("nan"),
                           "size_bytes": r["size_bytes"], "train_seconds": r.get("train_seconds"),
                           "waves_active": r.get("waves_active"), "run": str(out / f"n{n}" / "runs")})
    mark_pareto(points, "render_ms", "pareto_time")
    mark_pareto(points, "size_bytes", "pareto_size")
    first = per_count[counts[0]]
    result = {"settings": {"data": str(data), "scene": first["scene"], "model": model,
                           "model_options": model_options or {}, "n_waves": waves, "num_primitives": counts,
                           "iterations": iterations, "densify": False, "seed": seed, "backend": first["backend"],
                           "scene_options": scene_options or {}, "antialias": antialias,
                           "train_views": first["train_views"],
                           "test_views": first["test_views"]},
              "points": points}
    write_json(out / "sweep.json", result)
    plot_pareto(points, out / "pareto.png", title=f"{first['scene']}: {model} waves x primitives, "
                                                   f"{iterations} iterations")
    write_text(out / "report.md", sweep_markdown(result))
    return result


def mark_pareto(points: list[dict], cost: str, key: str) -> None:
    """points[i][key] = True where no other point has both lower-or-equal `cost` and higher-or-equal PSNR (one
    of them strictly): the best PSNR money (time or bytes) can buy."""
    for p in points:
        p[key] = not any(q is not p and q[cost] <= p[cost] and q["psnr"] >= p["psnr"]
                         and (q[cost] < p[cost] or q["psnr"] > p["psnr"]) for q in points
                         if math.isfinite(q[cost]) and math.isfinite(q["psnr"]))
        if not (math.isfinite(p[cost]) and math.isfinite(p["psnr"])):
            p[key] = False


def sweep_markdown(result: dict) -> str:
    s, pts = result["settings"], result["points"]
    waves, counts = s["n_waves"], s["num_primitives"]
    at = {(p["n_waves"], p["num_primitives"]): p for p in pts}
    lines = [f"# splatzoo sweep: {s['model']} waves x primitives", "",
             f"Scene `{s['scene']}` ({s['train_views']} train / {s['test_views']} test views), {s['iterations']} "
             f"iterations per run, densification off (fixed primitive count, the same initial points per count), "
             f"seed {s['seed']}, backend `{s['backend']}`"
             f"{', anti-aliased (pixel-footprint filter)' if s.get('antialias') else ''}. n_waves 0 is the `2dgs` model. Render time is "
             "1000 / FPS over the test views (wall clock on this machine); size is the stored float32 parameters.",
             "", "| n_waves | primitives | PSNR ↑ | SSIM ↑ | LPIPS ↓ | render ms | size MB | Pareto (time / size) |",
             "|---|---|---|---|---|---|---|---|"]
    for k in waves:
        for n in counts:
            p = at[(k, n)]
            front = " / ".join("yes" if p[f] else "-" for f in ("pareto_time", "pareto_size"))
            lines.append(f"| {k} | {n} | {p['psnr']:.2f} | {p['ssim']:.4f} | {p['lpips']:.4f} | {p['render_ms']:.1f} "
                         f"| {p['size_bytes'] / 1e6:.3f} | {front} |")
    lines += ["", "PSNR (dB) by waves (rows) and primitives (columns):", "",
              "| n_waves | " + " | ".join(str(n) for n in counts) + " |", "|---|" + "---|" * len(counts)]
    for k in waves:
        lines.append(f"| {k} | " + " | ".join(f"{at[(k, n)]['psnr']:.2f}" for n in counts) + " |")
    for key, what in (("pareto_time", "render time"), ("pareto_size", "model size")):
        front = sorted((p for p in pts if p[key]), key=lambda p: p["render_ms" if key == "pareto_time" else "size_bytes"])
        lines += ["", f"Pareto front, PSNR against {what}: " +
                  ", ".join(f"{p['n_waves']} waves x {p['num_primitives']}" for p in front) + "."]
    lines += ["", "Picture: `pareto.png`. Per-count comparisons (renders, convergence): `n<primitives>/report.md`.", ""]
    return "\n".join(lines)


def plot_pareto(points: list[dict], path, title: str = "") -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    waves = sorted({p["n_waves"] for p in points})
    counts = sorted({p["num_primitives"] for p in points})
    markers = "osD^v<>ph*"
    cmap = plt.get_cmap("viridis")
    for ax, cost, key, label, scale in ((axes[0], "render_ms", "pareto_time", "render time per frame (ms)", 1.0),
                                        (axes[1], "size_bytes", "pareto_size", "model size (MB)", 1e-6)):
        for i, k in enumerate(waves):
            for j, n in enumerate(counts):
                p = next(q for q in points if q["n_waves"] == k and q["num_primitives"] == n)
                ax.scatter(p[cost] * scale, p["psnr"], color=cmap(i / max(1, len(waves) - 1)),
                           marker=markers[j % len(markers)], s=55, edgecolors="k" if p[key] else "none", zorder=3,
                           label=f"{k} waves" if j == 0 else None)
        front = sorted((p for p in points if p[key]), key=lambda p: p[cost])
        ax.step([p[cost] * scale for p in front], [p["psnr"] for p in front], where="post", color="crimson",
                lw=1.5, alpha=0.8, label="Pareto front", zorder=2)
        ax.set(xlabel=label, ylabel="test PSNR (dB)", xscale="log")
        ax.grid(alpha=0.3, which="both")
    for j, n in enumerate(counts):  # marker legend for primitive counts
        axes[1].scatter([], [], marker=markers[j % len(markers)], color="grey", label=f"{n} primitives")
    axes[0].legend(fontsize=8, loc="best")
    axes[1].legend(fontsize=8, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, Path(path))
    plt.close(fig)


def load_sweep(path) -> dict:
    return json.loads(Path(path).read_text())
