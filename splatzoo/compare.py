"""`splatzoo compare`: train several models under one budget and report the trade side by side."""
from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from .errors import SplatzooError
from .evaluate import checked_lpips_net, lpips_net_of
from .figures import metric, pyplot, save_figure
from .io import write_json, write_text
from .runs import Run, differences, evaluate_run, made_by_other_code, make_record, train
from .training import TrainConfig


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
    views, width, height = (preset.views, preset.width, preset.height) if preset else (48, 256, 256)
    # the folder name states every setting, so a scene made for other settings is never reused
    data = Path(out) / f"scene-{name}-{width}x{height}-{views}views-seed{seed}"
    if not (data / "sparse").exists():
        make_synthetic_scene(name, data, views=views, width=width, height=height, seed=seed, progress=progress,
                             overwrite=data.exists())
    return data


@dataclass(frozen=True)
class ModelChoice:
    """One model of a comparison: its label (report rows, run folder), registered name and config options
    (typed values or strings; make_config converts and checks them)."""

    label: str
    model: str
    options: dict = field(default_factory=dict, hash=False)


def parse_model_arg(arg: str) -> ModelChoice:
    """'gabor' or 'gabor:n_waves=8,prune_waves=0.01' (or n-waves=8) -> ModelChoice(label=arg, ...)."""
    from .options import model_spec

    name, options = model_spec(arg)
    return ModelChoice(arg, name, options)


def parse_model_list(text: str) -> list[ModelChoice]:
    """A comma-separated list of models, each as parse_model_arg takes it: 'gabor:n_waves=8,wave_l1=0,2dgs' is two
    models (an item with '=' and no ':' is one more option of the model before it; model names hold no '=')."""
    from .errors import SplatzooError

    words: list[str] = []
    for item in filter(None, (t.strip() for t in text.split(","))):
        if "=" in item and ":" not in item:
            if not words:
                raise SplatzooError(f"model list {text!r} starts with an option ({item!r}); name the model first, "
                                    "e.g. gabor:n_waves=8")
            words[-1] += "," + item
        else:
            words.append(item)
    return [parse_model_arg(w) for w in words]


def compare(models: list[str], data=None, out="runs/compare", *, iterations: int | None = None,
            num_primitives: int | None = None, densify: bool = False, strategy: str = "auto", quick: bool = False,
            seed: int = 0, backend: str = "auto", scene_options: dict | None = None, progress: bool = True,
            synthetic_scene: str | None = None, overwrite: bool = False, equal_bytes: bool = False,
            antialias: bool = True, random_downscale: float = 0.0, budgets=None, store: str = "float32",
            budget_start: float | None = None, lpips_net: str | None = None) -> dict:
    """Train every model (names like 'gabor:n_waves=8', or ModelChoice) with identical data, initial points and
    budget; write compare.json, report.md, compare.png and convergence.png into `out`. Without `data`, a built-in
    synthetic scene is made. The budget is `num_primitives` each (equal count) or, with `equal_bytes`, the stored
    size of the first model trained with `num_primitives` (None: every initial point, as an equal-count compare
    trains it; after pruning, for adaptive waves): every other model
    gets as many primitives as fit in it (an adaptive one, as if it kept every wave). `antialias`
    trains and renders every model with the pixel-footprint filter (`random_downscale`: that fraction of the training
    views at 1/2 or 1/4 size). `strategy` (with `densify`): every model densifies so ("auto": each its own). Runs in
    out/runs/<label> made with the same settings are reused (finished) or resumed (interrupted); made with other
    settings, they are an error, or retrained with `overwrite`. Runs trained by other code (runs.code_fingerprint)
    are reused and named in the report, or retrained with `overwrite`.

    `budgets` (rate-distortion curves): a list of sizes, each a fraction of the first model's stored size at its
    count ('25%', 0.25) or a size in bytes ('200kB', '1.5MB', 200000). The first model is trained at its count,
    then every model at every budget, starting with `budget_start` (None: each model's own multiple,
    SplatModel.budget_start, which may depend on the count that fits) times as many primitives as its packed file
    can hold within it (budget_count) and shedding down to the budget from half-way (training/budget.py), in
    out/runs/<label>@<count>; rate.png and the report's rate table plot PSNR, LPIPS and FPS against stored bytes.
    `store`: the precision every model is stored (and fine-tuned) at (packing.PRECISIONS). `lpips_net`: the LPIPS
    network every run is scored with (vgg or alex; None: evaluate.LPIPS_NET); a finished run scored with another is
    scored again, not retrained."""
    from .data import load_scene

    choices, model_configs = _checked_choices(models)
    lpips_net = checked_lpips_net(lpips_net)
    if budget_start is not None and not (isinstance(budget_start, (int, float)) and math.isfinite(budget_start)
                                         and 1 <= budget_start <= 16):
        raise SplatzooError(f"--budget-start must be a number from 1 to 16 (how many times the primitives that fit "
                            f"a budget each budgeted run starts with), got {budget_start}")
    if strategy != "auto" and not densify:
        raise SplatzooError(f"--strategy {strategy} chooses how densification grows the count; add --densify, or "
                            "leave --strategy out for the fixed-count protocol")
    out = Path(out)
    preset = QuickPreset() if quick else None
    if data is None:
        data = builtin_scene(out, synthetic_scene, preset, seed=seed, progress=progress)
    scene_options = dict(scene_options or {})
    scene = load_scene(data, **scene_options)
    iterations = iterations or (preset.iterations if preset else 30000)
    num_primitives = num_primitives or (preset.num_primitives if preset else None)
    base_cfg = TrainConfig(iterations=iterations, num_primitives=num_primitives, densify=densify, strategy=strategy,
                           seed=seed, backend=backend, antialias=antialias,
                           random_downscale=random_downscale, store=store).validate()
    if (equal_bytes or budgets) and densify:
        raise SplatzooError("--equal-bytes and --budgets compare models at fixed primitive counts: leave "
                            "densification off")
    if equal_bytes and budgets:
        raise SplatzooError("--equal-bytes is the single budget of the first model's size, one point of what "
                            "--budgets draws: give one of them")
    sizes = parse_budgets(budgets) if budgets else []
    _refuse_small_budgets(choices, sizes, num_primitives or scene.points.shape[0], store)
    runner = _Runs(scene, scene_options, model_configs, base_cfg, overwrite=overwrite, backend=backend,
                   progress=progress, lpips_net=lpips_net,
                   folders={c.label: Run(out / "runs" / _safe(c.label)) for c in choices})
    for run in runner.folders.values():
        if run.status == "foreign":
            raise SplatzooError(f"{run.path} exists and is not a splatzoo run folder; move it or choose another --out")
    runs, counts = _train_all(runner, choices, num_primitives, equal_bytes=equal_bytes, budgets=bool(sizes))
    starts = {c.label: member_budget_start(c, budget_start) for c in choices}
    rate = rate_curves(choices, sizes, scene, out, store, runs, runner.folders, runner.plan,
                       runner.train_or_reuse, starts) if sizes else []
    settings = {"data": str(Path(data).resolve()), "scene": scene.name, "iterations": iterations,
                "num_primitives": num_primitives, "densify": densify, "strategy": strategy, "seed": seed,
                "backend": runs[choices[0].label].get("backend", backend), "scene_options": scene_options,
                "models": [c.label for c in choices], "equal_bytes": equal_bytes, "antialias": antialias,
                "random_downscale": random_downscale, "primitives": counts, "trained_by_other_code": runner.other_code,
                "train_views": len(scene.train), "test_views": len(scene.test), "store": store,
                "budgets": [text for text, _, _ in sizes], "budget_start": budget_start, "lpips_net": lpips_net}
    return _write_report(out, scene, {"runs": runs, "settings": settings}, rate, runner.folders)


def _checked_choices(models) -> tuple[list[ModelChoice], dict]:
    """(the models as ModelChoice, label -> its config): each label once, every option checked before training."""
    from .zoo import make_config

    if not models:
        raise SplatzooError("name at least one model to compare, e.g. `splatzoo compare gabor 2dgs`")
    choices = [m if isinstance(m, ModelChoice) else parse_model_arg(m) for m in models]
    labels = [c.label for c in choices]
    if len(set(labels)) != len(labels) or len({_safe(k) for k in labels}) != len(labels):
        raise SplatzooError(f"each model may appear once; got {', '.join(labels)}")
    return choices, {c.label: make_config(c.model, **c.options) for c in choices}  # a typo fails before training


def _refuse_small_budgets(choices: list[ModelChoice], sizes, count: int, store: str) -> None:
    """A budget too small for a model is refused before anything trains (or is retrained with --overwrite): a
    fraction against the first model's size at the start (`count` primitives), which a fixed-count run keeps (a
    shedding one only loses)."""
    start = stored_cost(choices[0], count, store) if sizes else 0
    for text, kind, value in sizes:
        target = int(value * start) if kind == "fraction" else int(value)
        for c in choices:
            if budget_count(c, target, store) < 1:
                raise too_small(c, text, target, store)


@dataclass
class _Runs:
    """The runs of one comparison: each model's folder (`folders`, by label), how a run is planned against what its
    folder holds and then trained or reused, and the labels whose reused runs other code trained (`other_code`)."""

    scene: object
    scene_options: dict
    model_configs: dict
    base_cfg: TrainConfig
    overwrite: bool
    backend: str
    progress: bool
    lpips_net: str
    folders: dict
    other_code: list = field(default_factory=list)

    def plan(self, c: ModelChoice, count: int, run: Run | None = None, max_bytes: int | None = None):
        """The run of `c` with `count` primitives (in `run`, default the model's own folder; within `max_bytes`
        stored): new, finished (reuse), started or interrupted (resume), or overwrite; a run made with other
        settings is an error without `overwrite`, never a row of old numbers."""
        run, cfg = run or self.folders[c.label], replace(self.base_cfg, num_primitives=count, max_bytes=max_bytes)
        status = run.status
        if status == "foreign":
            raise SplatzooError(f"{run.path} exists and is not a splatzoo run folder; move it or choose another --out")
        if status != "new":
            record = run.record()
            diffs = differences(record, make_record(self.scene, self.scene_options, c.model,
                                                    self.model_configs[c.label], cfg))
            if diffs and not self.overwrite:
                raise SplatzooError(f"{run.path} was trained with other settings ({'; '.join(diffs)}); pass "
                                    "--overwrite to retrain it, or choose another --out")
            if made_by_other_code(record) and status != "started":
                if self.overwrite:
                    diffs = diffs or ["code"]
                else:  # same settings, older code: kept (it may be hours of training), and said so
                    self.other_code.append(c.label)
                    if status == "finished":  # a resumed run's note comes from the launch (run_launch)
                        print(f"note: {run.path} was trained by other splatzoo code (its model, trainer, rasterizer "
                              "or metrics sources changed since); its numbers are reused and marked in the report. "
                              "--overwrite retrains it with today's code", file=sys.stderr, flush=True)
            status = "overwrite" if diffs else status
        return cfg, status

    def train_or_reuse(self, c: ModelChoice, cfg: TrainConfig, status: str, run: Run | None = None) -> dict:
        run = run or self.folders[c.label]
        if status == "finished":  # trained earlier with these settings: reuse (scored again for another LPIPS net)
            metrics = run.metrics()
            if metrics is not None and lpips_net_of(metrics) == self.lpips_net:
                return metrics
            return evaluate_run(run.path, backend=self.backend, lpips_net=self.lpips_net)
        return train(self.scene, c.model, c.options, cfg, run.path, resume=status in ("started", "interrupted"),
                     overwrite=status == "overwrite", progress=self.progress, scene_options=self.scene_options,
                     command="splatzoo compare", lpips_net=self.lpips_net).metrics


def _train_all(runner: _Runs, choices: list[ModelChoice], num_primitives, *, equal_bytes: bool,
               budgets: bool) -> tuple[dict, dict]:
    """(label -> metrics, label -> primitive count) of every model at its count: with equal counts every run is
    decided before any trains; with equal bytes the first model sets the budget, then the others are decided; with
    budgets only the first model trains here (rate_curves does the rest)."""
    phases = [choices[:1], choices[1:]] if equal_bytes else [choices[:1]] if budgets else [choices]
    counts, runs, budget = {}, {}, None
    for phase in phases:
        for c in phase:
            counts[c.label] = num_primitives if budget is None else max(1, budget // bytes_per_primitive(c))
        planned = {c.label: runner.plan(c, counts[c.label]) for c in phase}
        for c in phase:
            runs[c.label] = runner.train_or_reuse(c, *planned[c.label])
        if equal_bytes:
            budget = int(runs[choices[0].label]["size_bytes"])
    return runs, counts


def _write_report(out: Path, scene, report: dict, rate: list, folders: dict) -> dict:
    """compare.json, report.md and the pictures (rate.png with budgets, convergence.png, compare.png) of `report`
    (its runs and settings; `rate` added when there is one)."""
    settings, shown = report["settings"], folders
    if rate:
        report["rate"] = rate
        largest = max(r["budget_bytes"] for r in rate)  # the pictures show every model at the largest budget
        shown = {r["model"]: Run(out / "runs" / r["run"]) for r in rate if r["budget_bytes"] == largest}
    write_json(out / "compare.json", report)
    write_text(out / "report.md", report_markdown(report))
    if rate:
        plot_rate(rate, out / "rate.png", title=f"{scene.name}, stored as {settings['store']}")
    plot_convergence(shown, out / "convergence.png")
    plot_comparison(scene, shown, out / "compare.png", backend=settings["backend"])
    return report


def member_budget_start(choice: ModelChoice, given: float | None = None):
    """fit -> how many times the `fit` primitives that a budget holds a budgeted run of `choice` starts with: `given`
    (--budget-start) for every budget, or by default its model's own (SplatModel.budget_start)."""
    from .registry import MODELS

    return (lambda fit: float(given)) if given else MODELS.get(choice.model).cls.budget_start


def rate_curves(choices, sizes, scene, out: Path, store: str, runs: dict, run_dirs: dict, plan, train_or_reuse,
                starts: dict) -> list:
    """compare --budgets: every model at every budget (the first model's run at its count, in `runs`, sets the
    fractions), each run planned (and refused, if it must be) before any trains; one record per (budget, model).
    Each starts with starts[label](fit) times the `fit` primitives that its budget holds."""
    first = choices[0]
    reference = stored_size_of(runs[first.label], run_dirs[first.label], store)
    reference_count = run_dirs[first.label].record()["train"]["num_primitives"] or scene.points.shape[0]
    like = run_dirs[first.label].model()  # every run's file records the same render settings
    planned_runs = []
    for text, kind, value in sizes:
        target = int(value * reference) if kind == "fraction" else int(value)
        for c in choices:
            fit = budget_count(c, target, store, like)  # a model that sheds richness: as many as fit plain
            if fit < 1:
                raise too_small(c, text, target, store, like)
            count = math.ceil(starts[c.label](fit) * fit)
            same = c is first and count == reference_count <= fit  # the reference run fits as it is
            run = run_dirs[c.label] if same else Run(out / "runs" / f"{_safe(c.label)}@{count}")
            planned_runs.append((text, target, c, fit, count, run,
                                 None if same else plan(c, count, run, target)))
    rate = []
    for text, target, c, fit, count, run, planned in planned_runs:
        metrics = runs[c.label] if planned is None else train_or_reuse(c, *planned, run=run)
        rate.append({"model": c.label, "budget": text, "budget_bytes": target, "fit_primitives": fit,
                     "start_primitives": count,
                     "num_primitives": metrics.get("num_primitives", count),
                     "run": run.path.name, "stored_bytes": stored_size_of(metrics, run, store),
                     **{k: metrics.get(k) for k in ("size_bytes", "psnr", "ssim", "lpips", "fps", "float32_psnr")}})
    return rate


_UNITS = {"b": 1, "kb": 1e3, "mb": 1e6, "gb": 1e9, "kib": 1024, "mib": 1024**2, "gib": 1024**3}
_SIZE = re.compile(r"([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*(%|[kKmMgG]i?[bB]|[bB])?")  # a number and its unit


def parse_size(text: str, option: str) -> int:
    """'200kB', '1.5MB' or '120000' -> bytes, for an option that takes one size (train's --max-bytes)."""
    m = _SIZE.fullmatch(str(text).strip())
    if not m or m.group(2) == "%":
        raise SplatzooError(f"{option}: {str(text)[:60]!r} is not a size; give one such as 200kB, 1.5MB or 120000 "
                            "(bytes)")
    value = float(m.group(1)) * _UNITS[(m.group(2) or "b").lower()]
    if not (math.isfinite(value) and value >= 1):
        raise SplatzooError(f"{option}: {text!r} must be at least 1 byte")
    return int(value)


def parse_budgets(budgets) -> list[tuple[str, str, float]]:
    """'5%,25%,100%' or ['200kB', 0.25, 120000] -> [(text, 'fraction' | 'bytes', value)] in the order given. A
    fraction (a percentage, or a float) is of the first model's stored size at its count; a number with a unit (B,
    kB, MB, GB, KiB, MiB, GiB) or a whole number is bytes."""
    items = [t for t in budgets.split(",") if t.strip()] if isinstance(budgets, str) else list(budgets)
    out = []
    for item in items:
        if isinstance(item, (int, float)) and not isinstance(item, bool):
            text, kind, value = (f"{100 * item:g}%", "fraction", float(item)) if isinstance(item, float) else \
                (f"{item}B", "bytes", float(item))
        else:
            text = str(item).strip()
            m = _SIZE.fullmatch(text)
            if not m:
                raise SplatzooError(f"--budgets: {text!r} is not a budget; give fractions of the first model's size "
                                    "(5%,25%,100%) or sizes (200kB, 1.5MB, 120000), separated by commas")
            number, unit = float(m.group(1)), (m.group(2) or "b").lower()
            kind, value = ("fraction", number / 100) if unit == "%" else ("bytes", number * _UNITS[unit])
        if not (math.isfinite(value) and value > 0) or (kind == "fraction" and value > 100):
            raise SplatzooError(f"--budgets: {text!r} must be a positive size (a fraction up to 10000%)")
        out.append((text, kind, value))
    if not out:
        raise SplatzooError("--budgets: name at least one budget, such as 5%,25%,100%")
    if len({t for t, _, _ in out}) != len(out):
        raise SplatzooError(f"--budgets: each budget once, got {budgets}")
    return out


def stored_cost(choice: ModelChoice, count: int, store: str, like=None) -> int:
    """The smallest stored size of `choice` with `count` primitives: as trained from the start, less what it can
    shed under a byte budget without losing primitives (SplatModel.shed_richness: a gabor-adaptive model's waves),
    with the render settings of the model `like` (a trained run's: its file records them too)."""
    from .zoo import plain_stored_bytes

    return plain_stored_bytes(choice.model, count, store, like.render_settings if like is not None else None,
                              **choice.options)


def too_small(choice: ModelChoice, text: str, budget: int, store: str, like=None) -> SplatzooError:
    return SplatzooError(f"budget {text} ({budget:,} bytes) holds no primitive of {choice.label} (one costs "
                         f"{stored_cost(choice, 1, store, like):,} bytes stored as {store}); give a larger budget")


def budget_count(choice: ModelChoice, budget: int, store: str, like=None) -> int:
    """The most primitives of `choice` whose packed file at `store` fits in `budget` bytes (0 if not one), with the
    render settings of the model `like`."""
    from .zoo import plain_fit_count

    return plain_fit_count(choice.model, budget, store, like.render_settings if like is not None else None,
                           **choice.options)


def stored_size_of(metrics: dict, run: Run, store: str) -> int:
    """A finished run's stored size: from its metrics, or (evaluated before packed files) its model packed now."""
    from .zoo import stored_bytes

    if metrics.get("stored_bytes") is not None:
        return int(metrics["stored_bytes"])
    return stored_bytes(run.model(), store)


def bytes_per_primitive(choice: ModelChoice) -> int:
    """What one more primitive adds to the model's stored size (as trained from the start: every wave present)."""
    from .zoo import create_model

    sizes = []
    for n in (1, 2):
        model = create_model(choice.model, torch.zeros(n, 3), torch.full((n, 3), 0.5), **choice.options)
        sizes.append(model.size_bytes())
    return sizes[1] - sizes[0]


def _safe(label: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in label)


def _densification(settings: dict) -> str:
    if not settings["densify"]:
        return "densification off"
    strategy = settings.get("strategy", "auto")
    return f"densification on ({'each model its own strategy' if strategy == 'auto' else f'strategy {strategy}'})"


def report_markdown(report: dict) -> str:
    runs, s = report["runs"], report["settings"]
    labels = list(runs)
    get = lambda k, key: metric(runs[k].get(key))  # noqa: E731

    def best_of(key, better):
        finite = [k for k in labels if math.isfinite(get(k, key))]
        return better(finite, key=lambda k: get(k, key)) if finite else None

    best = {"ssim": best_of("ssim", max), "psnr": best_of("psnr", max), "lpips": best_of("lpips", min)}

    def cell(label, key, spec):
        v = get(label, key)
        text = format(v, spec) if math.isfinite(v) else "-"
        return f"**{text}**" if best.get(key) == label else text

    def ratio(a, b):
        return format(a / b, ".2f") if b and math.isfinite(a / b) else "-"

    first = labels[0]
    conv = runs[first].get("conventions", {})
    budget = (f"equal bytes: each model as many primitives as fit in the trained size of "
              f"{s['num_primitives'] or 'all initial points'} of `{first}`" if s.get("equal_bytes")
              else f"{s['num_primitives'] or 'all'} initial primitives")
    downscaled = (f", {s['random_downscale']:g} of the training views at 1/2 or 1/4 size"
                  if s.get("random_downscale") else "")
    lines = [
        f"# splatzoo compare: {', '.join(labels)}", "",
        f"Scene `{s['scene']}` ({s['train_views']} train / {s['test_views']} test views), {s['iterations']} iterations, "
        f"{_densification(s)}, "
        f"{budget}, seed {s['seed']}, backend `{s['backend']}`"
        f"{', anti-aliased (pixel-footprint filter)' if s.get('antialias') else ''}"
        f"{downscaled}.", "",
        "| model | SSIM ↑ | PSNR ↑ | LPIPS ↓ | FPS | train s | size MB | primitives |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k in labels:
        lines.append(f"| {k} | {cell(k, 'ssim', '.4f')} | {cell(k, 'psnr', '.2f')} | {cell(k, 'lpips', '.4f')} "
                     f"| {cell(k, 'fps', '.1f')} | {cell(k, 'train_seconds', '.0f')} | "
                     f"{get(k, 'size_bytes') / 1e6:.3f} | {runs[k].get('num_primitives')} |")
    if s.get("trained_by_other_code"):
        lines += ["", f"Reused runs trained by other splatzoo code than this report's: "
                  f"{', '.join(s['trained_by_other_code'])}. `--overwrite` retrains them with today's code."]
    lines += ["", f"Against `{first}`:", "", "| model | ΔPSNR dB | ΔSSIM | ΔLPIPS | FPS ratio | train-time ratio | size ratio |",
              "|---|---|---|---|---|---|---|"]
    for k in labels:
        delta = {key: get(k, key) - get(first, key) for key in ("psnr", "ssim", "lpips")}
        d = {key: format(v, spec) if math.isfinite(v) else "-"
             for (key, v), spec in zip(delta.items(), ("+.2f", "+.4f", "+.4f"))}
        lines.append(f"| {k} | {d['psnr']} | {d['ssim']} | {d['lpips']} | {ratio(get(k, 'fps'), get(first, 'fps'))} | "
                     f"{ratio(get(k, 'train_seconds'), get(first, 'train_seconds'))} | "
                     f"{ratio(get(k, 'size_bytes'), get(first, 'size_bytes'))} |")
    if report.get("rate"):
        lines += rate_markdown(report["rate"], s.get("store", "float32"), s.get("budget_start"))
    lines += ["", f"Metrics: PSNR {conv.get('psnr', '')}; SSIM {conv.get('ssim', '')}; LPIPS {conv.get('lpips', '')}.",
              "Pictures: `compare.png` (ground truth, renders, surfels in random colours), `convergence.png`"
              + (", `rate.png` (PSNR, LPIPS and FPS against stored bytes)." if report.get("rate") else "."), ""]
    return "\n".join(lines)


def rate_markdown(rate: list[dict], store: str, budget_start: dict | float | None = None) -> list[str]:
    """The rate table: each budget a row, each model its PSNR / LPIPS with its stored size and count; the best PSNR
    of each budget in bold. budget_start: each model's start (a dict by label; one number in reports before
    members had their own)."""
    models = list(dict.fromkeys(r["model"] for r in rate))
    budgets = list(dict.fromkeys(r["budget"] for r in rate))
    at = {(r["budget"], r["model"]): r for r in rate}
    told = {m: t for m, t in _starts_told(rate, models, budget_start).items() if t}
    if len(set(told.values())) == 1 and len(told) == len(models):
        start = (f"; each run started with {next(iter(told.values()))} the primitives that fit and shed down to its "
                 "budget")
    elif told:
        start = ("; each run started with " + ", ".join(f"{v} ({m})" for m, v in told.items())
                 + " the primitives that fit and shed down to its budget")
    else:
        start = ""
    lines = ["", f"Rate: every model at every budget, stored as {store} (PSNR / LPIPS, stored kB, primitives at the "
             f"end{start}):", "",
             "| budget | " + " | ".join(models) + " |", "|---" * (len(models) + 1) + "|"]
    for b in budgets:
        row = [at[(b, m)] for m in models]
        best = max(range(len(row)), key=lambda i: metric(row[i].get("psnr")) if math.isfinite(metric(row[i].get("psnr")))
                   else -math.inf)
        cells = []
        for i, r in enumerate(row):
            psnr = f"{metric(r.get('psnr')):.2f}"
            cells.append(f"{f'**{psnr}**' if i == best else psnr} / {metric(r.get('lpips')):.4f}, "
                         f"{r['stored_bytes'] / 1e3:.1f} kB, {r['num_primitives']}")
        lines.append(f"| {b} ({row[0]['budget_bytes'] / 1e3:.1f} kB) | " + " | ".join(cells) + " |")
    if store != "float32":
        losses = [metric(r.get("float32_psnr")) - metric(r.get("psnr")) for r in rate]
        losses = [x for x in losses if math.isfinite(x)]
        if losses:
            lines += ["", f"Storage at {store} cost {max(losses):+.2f} dB at most (mean {np.mean(losses):+.2f}) "
                      "against the same runs' full-precision values."]
    return lines


def _starts_told(rate: list[dict], models: list[str], budget_start) -> dict[str, str]:
    """Each model's start as the rate table says it ('3x', or '3x / 1.8x / 1.4x by budget'; '' for what fits): from
    its records' start and fit counts, or in reports from before records had them, from `budget_start` (a dict by
    label, or one number for all)."""
    given = budget_start if isinstance(budget_start, dict) else {m: budget_start for m in models}
    told = {}
    for m in models:
        rows = [r for r in rate if r["model"] == m]
        if rows and all(r.get("start_primitives") and r.get("fit_primitives") for r in rows):
            multiples = [f"{r['start_primitives'] / r['fit_primitives']:.2g}x" for r in rows]
        else:
            multiples = [f"{given[m]:g}x"] if given.get(m) else []
        distinct = list(dict.fromkeys(multiples))
        told[m] = "" if distinct in ([], ["1x"]) else distinct[0] if len(distinct) == 1 else \
            " / ".join(multiples) + " by budget"
    return told


def plot_rate(rate: list[dict], path, *, title: str = "") -> None:
    """rate.png: PSNR, LPIPS and FPS against stored bytes, one curve per model."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for model in dict.fromkeys(r["model"] for r in rate):
        pts = sorted((r for r in rate if r["model"] == model), key=lambda r: r["stored_bytes"])
        kb = [r["stored_bytes"] / 1e3 for r in pts]
        for ax, key in zip(axes, ("psnr", "lpips", "fps")):
            ax.plot(kb, [metric(r.get(key)) for r in pts], marker="o", ms=4, label=model)
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    for ax, (label, better) in zip(axes, (("PSNR (dB)", "higher"), ("LPIPS", "lower"), ("FPS", "higher"))):
        ax.set(xscale="log", xlabel="stored size (kB)", ylabel=label, title=f"{label}, {better} is better")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))  # 1, 2, 5, 10, 20, ... kB
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, y=1.03)
    save_figure(fig, Path(path))
    plt.close(fig)


def _read_log(run: Run) -> tuple[list, list, list, list]:
    it, loss, tit, tpsnr = [], [], [], []
    for rec in run.log():
        if "loss" in rec:
            it.append(rec["iteration"])
            loss.append(rec["loss"])
        if rec.get("test_psnr") is not None:
            tit.append(rec["iteration"])
            tpsnr.append(rec["test_psnr"])
    return it, loss, tit, tpsnr


def plot_convergence(run_dirs: dict[str, Run], path) -> None:
    plt = pyplot()
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
    save_figure(fig, Path(path))
    plt.close(fig)


@torch.no_grad()
def random_color_surfels(model, camera, seed: int = 0):
    """The model's surfels with one random colour each and no waves, as opaque as the model draws them: shows
    primitive shapes."""
    from .display import random_colors, recolored

    s = model.surfels(camera.to(next(model.parameters()).device, torch.float32))
    return recolored(s, random_colors(s.num, seed))


@torch.no_grad()
def plot_comparison(scene, run_dirs: dict[str, Run], path, *, backend: str = "auto", max_views: int = 3) -> None:
    views = (scene.test or scene.train)
    views = views[:: max(1, len(views) // max_views)][:max_views]
    models = {label: run.model() for label, run in run_dirs.items()}
    cols = 1 + 2 * len(models)
    plt = pyplot()
    fig, axes = plt.subplots(len(views), cols, figsize=(2.4 * cols, 2.5 * len(views)), squeeze=False)
    for r, v in enumerate(views):
        cells = [("ground truth", v.image_float())]
        for label, m in models.items():
            cells.append((label, m.render(v.camera, background=scene.background, backend=backend).image()))
        for label, m in models.items():
            shapes = random_color_surfels(m, v.camera)
            cells.append((f"{label} surfels", m.render(v.camera, background=1.0, backend=backend,
                                                         surfels=shapes).image()))
        for c, (title, img) in enumerate(cells):
            ax = axes[r, c]
            ax.imshow(img.numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, Path(path))
    plt.close(fig)
