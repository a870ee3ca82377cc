"""One training iteration for any registered model on any Scene, with the 2DGS recipe (losses, learning rates and
densification schedule of the official 2DGS code; see TrainConfig). The loop around it, with its files, lives in
splatzoo.runs (`splatzoo.runs.train`).
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import ClassVar, NamedTuple

import torch

from ..errors import SplatzooError
from ..model_checks import densify_budget
from ..evaluate import area_resize
from ..packing import PRECISIONS
from ..types import Camera, RenderOutput
from ..models.base import RenderSettings
from ..zoo import create_model, model_from_checkpoint, plain_stored_bytes, stored_values
from . import budget, frequency, mcmc, wave_fit
from .densify import DensifyStats, densify_and_prune, reset_opacity
from .distributed import Comm
from .losses import distortion_loss, normal_consistency_loss, photometric_loss

REFERENCE_ITERATIONS = 30000  # the schedule below is stated for this many iterations and scaled to the run
MAX_GROWTH = 0.5              # one densification step adds at most this fraction of the current count
STRATEGIES = ("adc", "mcmc", "frequency")  # densification strategies (TrainConfig.strategy; "auto": the model's)
ERROR_AVERAGE = 0.01          # the model's recent_error: an exponential average over about 1/this many steps
DOWNSCALES = (0.5, 0.25)      # the smaller scales --random-downscale trains at ...
MIN_DOWNSCALED_SIDE = 64      # ... where the view's shorter side stays at least this many pixels
PROBE_VIEWS = 4               # the model's probe_error renders this many training views, evenly spaced


MAX_SEED = 2**63 - 1  # torch generators take 64-bit seeds


def memory_estimate(model: str, model_config, primitives: int) -> int:
    """Bytes a model of `primitives` primitives holds in training: each parameter row with its gradient and Adam's
    two moments (4 copies), the densification statistics, and its initial points (a lower bound: renders and
    autograd's saved tensors come on top)."""
    from ..zoo import MODELS

    spec = MODELS.get(model)
    empty = spec.cls(model_config, 0)  # parameter shapes without primitives: the per-primitive row sizes
    per_row = sum(math.prod(p.shape[1:]) for p in empty.parameters())
    return primitives * (4 * 4 * per_row + 4 * 2 + 4 * 6)


def available_memory() -> int | None:
    """Bytes the system can give without swapping (MemAvailable), None where it cannot be read."""
    try:
        with open("/proc/meminfo") as info:
            for line in info:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_memory(model: str, model_config, initial: int, budget: int, device: torch.device) -> None:
    """Refuse, with the estimate, a primitive count the machine cannot hold, before anything is allocated."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        where, have = f"free on {torch.cuda.get_device_name(device)}", free
    else:
        where, have = "available", available_memory()
    if have is None:
        return
    for what, n, option in (("start with", initial, "--num-primitives"), ("grow to", budget, "--max-primitives")):
        need = memory_estimate(model, model_config, n)
        if need > 0.8 * have:
            raise SplatzooError(f"{model} would {what} {n:,} primitives, which needs at least {need / 2**30:.1f} GiB "
                                f"for its parameters and optimizer state, but {have / 2**30:.1f} GiB are {where}; "
                                f"pass a smaller {option}")


def check_start(scene, model: str, model_config, cfg, device: torch.device, initial: int | None = None) -> None:
    """Refuse a fresh run the machine cannot hold, before anything is allocated. initial: the primitive count it
    starts from (None: the scene's points, or --num-primitives of them)."""
    initial = initial if initial is not None else cfg.num_primitives or scene.points.shape[0]
    budget = (cfg.max_primitives or densify_budget(scene, initial)) if cfg.densify else initial
    check_memory(model, model_config, initial, budget, device)
    if cfg.max_bytes:
        check_byte_budget(scene, model, model_config, cfg)


def check_byte_budget(scene, model: str, model_config, cfg) -> None:
    """Refuse a --max-bytes that cannot hold the file of one plain primitive: no shedding could meet it."""
    # the file records the render settings: its size with either background the run may store
    one = max(plain_stored_bytes(model, 1, cfg.store, RenderSettings(cfg.antialias, background),
                                 **dataclasses.asdict(model_config))
              for background in (None, tuple(float(c) for c in scene.background)))
    if cfg.max_bytes < one:
        raise SplatzooError(f"--max-bytes {cfg.max_bytes:,} holds no {model} surfel: the file of one costs {one:,} "
                            f"bytes stored as {cfg.store}; give a larger budget (or a smaller --store)")


@dataclass
class TrainConfig:
    iterations: int = 30000
    batch_size: int = field(default=1, metadata={"help": "views per step on each process"})
    nproc: int = field(default=1, metadata={"help": "data-parallel processes (torch.distributed)"})
    backend: str = field(default="auto", metadata={"operational": True})
    seed: int = 0
    densify: bool = True
    strategy: str = field(default="auto", metadata={
        "help": "how densification grows the count: auto (the model's own choice: frequency for neural-gabor, adc "
                "for the others), adc (2DGS's adaptive density control: clone, split, prune, opacity resets), mcmc "
                "(grow by 5% a step to the budget, then move dead surfels onto live ones) or frequency (Neural "
                "Gabor splatting's: grow where the render's frequency bands differ from the photos')"})
    densify_views: int = field(default=frequency.VIEWS, metadata={
        "help": "training views rendered per densification step of --strategy frequency (all of them when there "
                "are fewer)"})
    num_primitives: int | None = field(default=None, metadata={"help": "start from exactly this many primitives"})
    max_primitives: int | None = field(default=None, metadata={
        "help": "cap on the count densification reaches (default: one surfel per 128 training pixels, at least "
                "twice the initial count)"})
    lambda_dssim: float = 0.2
    lambda_normal: float = 0.05
    lambda_dist: float = 0.0
    normal_from: int = 7000
    dist_from: int = 3000
    position_lr_init: float = 1.6e-4
    position_lr_final: float = 1.6e-6
    densify_from: int = 500
    densify_until: int = 15000
    densify_interval: int = 100
    densify_grad_threshold: float = 2e-4
    min_opacity: float = 0.05
    opacity_reset_interval: int = 3000
    checkpoint_every: int = field(default=2000, metadata={"operational": True})     # iterations (not scaled)
    checkpoint_minutes: float = field(default=5.0, metadata={"operational": True})  # also by time; 0: off
    eval_every: int = 0            # test PSNR every this many iterations; 0: ten times per run
    antialias: bool = field(default=True, metadata={
        "help": "train (and render the model) with the pixel-footprint filter: sharp and alias-free when rendered "
                "smaller than trained, and as good or better at full size (off: the screen-space filter of 2DGS, "
                "1.1-1.3x faster on the CPU)"})
    random_downscale: float = field(default=0.0, metadata={
        "help": "fraction of training views rendered at a random smaller scale (1/2 or 1/4, keeping at least 64 "
                "px) and compared with the area-averaged image (multi-scale training; meant for --antialias)"})
    store: str = field(default="float32", metadata={
        "help": "the precision the model is stored at: float32, float16 or 8bit (positions at 16 bits, other values "
                "8 bits over each column's range); the last --store-finetune of the run trains through the stored "
                "values, and the run's model and numbers are the stored model's"})
    store_finetune: float = field(default=0.1, metadata={
        "help": "fraction of the run, at its end, that trains through the stored values (quantisation-aware; with "
                "--store below float32)"})
    max_bytes: int | None = field(default=None, metadata={
        "help": "a byte budget: the model ends the run no larger than this, stored at --store (the size of its "
                "packed file). From half-way on it sheds what costs the training views least: its weakest surfels "
                "or, for beta-gabor and gabor-adaptive, its faintest waves (training/budget.py). It starts from at "
                "most twice the surfels that fit plain (the scene's points subsampled; --num-primitives overrides) "
                "and densification grows it to no more, to choose from"})
    log_every: int = 10

    # what a stored record written before an option's default changed meant where it lacks the key: runs from
    # before the anti-aliased default were trained without it
    stored_defaults: ClassVar[dict] = {"antialias": False}

    def validate(self) -> "TrainConfig":
        """A clear error for values no run can use (NaN weights, zero iterations, negative counts)."""
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise SplatzooError(f"training option {f.name} must be a finite number, got {v}")
            if isinstance(v, (int, float)) and not isinstance(v, bool) and v < 0:
                raise SplatzooError(f"training option {f.name} must not be negative, got {v}")
        if self.iterations < 1:
            raise SplatzooError(f"--iterations must be at least 1, got {self.iterations}")
        if self.random_downscale > 1:
            raise SplatzooError(f"--random-downscale is a fraction of the training views, 0 to 1; got "
                                f"{self.random_downscale}")
        if self.store not in PRECISIONS:
            raise SplatzooError(f"--store must be one of {', '.join(PRECISIONS)}, got {self.store!r}")
        if self.store_finetune > 1:
            raise SplatzooError(f"--store-finetune is a fraction of the run, 0 to 1; got {self.store_finetune}")
        if self.strategy not in ("auto",) + STRATEGIES:
            raise SplatzooError(f"--strategy must be one of auto, {', '.join(STRATEGIES)}, got {self.strategy!r}")
        for name in ("num_primitives", "max_primitives", "log_every", "checkpoint_every", "batch_size", "nproc",
                     "densify_views", "max_bytes"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise SplatzooError(f"training option {name} must be at least 1, got {getattr(self, name)}")
        if not 0 <= self.seed <= MAX_SEED:
            raise SplatzooError(f"--seed must be between 0 and {MAX_SEED} (2^63 - 1), got {self.seed}")
        return self

    @classmethod
    def operational_fields(cls) -> set[str]:
        """Fields that change how a run is executed, not what it computes: they may differ on resume."""
        return {f.name for f in dataclasses.fields(cls) if f.metadata.get("operational")}

    def at(self, reference_iteration: int) -> int:
        """A schedule point stated for 30k iterations, scaled to this run's length."""
        return max(1, round(reference_iteration * self.iterations / REFERENCE_ITERATIONS))

    def trains_stored(self, step: int) -> bool:
        """Whether `step` renders the model through its stored values (the end of a run with --store)."""
        return self.store != "float32" and step > self.iterations * (1 - self.store_finetune)

    @property
    def views_per_step(self) -> int:
        return self.batch_size * self.nproc

    @property
    def eval_interval(self) -> int:
        return self.eval_every or max(1, self.iterations // 10)


def resolve_strategy(strategy: str, model) -> str:
    """The densification strategy a run uses: `strategy`, or for "auto" the model's own (its densify_strategy)."""
    if strategy != "auto":
        return strategy
    chosen = getattr(model, "densify_strategy", "adc")
    if chosen not in STRATEGIES:
        raise SplatzooError(f"model {getattr(model, 'name', '') or type(model).__name__} asks for the densification "
                            f"strategy {chosen!r}, which is none of {', '.join(STRATEGIES)}; pass --strategy")
    return chosen


def select_initial_points(points: torch.Tensor, colors: torch.Tensor, n: int | None, seed: int):
    """Exactly `n` initial points (all of them if n is None): a seeded subsample, or jittered repeats when the
    cloud is smaller. Depends only on the scene and the seed, so every model starts from the same points."""
    if n is None or n == points.shape[0]:
        return points, colors
    if n < 1:
        raise SplatzooError(f"--num-primitives must be at least 1, got {n}")
    if points.shape[0] == 0:
        raise SplatzooError("the scene has no initial points to start from; run SfM or supply a point cloud")
    g = torch.Generator().manual_seed(seed + 7919)
    if n < points.shape[0]:
        idx = torch.randperm(points.shape[0], generator=g)[:n]
        return points[idx], colors[idx]
    extra = torch.randint(points.shape[0], (n - points.shape[0],), generator=g)
    spread = (points.max(0).values - points.min(0).values).norm() * 1e-3
    jitter = torch.randn(extra.numel(), 3, generator=g) * spread
    return torch.cat([points, points[extra] + jitter]), torch.cat([colors, colors[extra]])


def _position_lr(cfg: TrainConfig, step: int, extent: float) -> float:
    t = min(max(step / max(cfg.iterations, 1), 0.0), 1.0)
    return extent * math.exp(math.log(cfg.position_lr_init) * (1 - t) + math.log(cfg.position_lr_final) * t)


class ViewLoss(NamedTuple):
    """One view's loss and what it was computed from."""
    loss: torch.Tensor      # everything the view adds: photometric and regularisers
    photo: torch.Tensor     # the photometric part
    render: RenderOutput
    target: torch.Tensor    # the image it was compared with (area-averaged when the view was rendered smaller)
    camera: Camera          # the camera rendered
    scale: float            # 1, or the smaller scale --random-downscale drew


# ---- a checkpoint's training state, checked before anything trains (a ValueError names what is wrong) --------------
def _number(value, what: str, *, integer: bool = False) -> float:
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    # a Python int is finite however large (math.isfinite(10**400) would raise OverflowError)
    if not ok or isinstance(value, bool) or (isinstance(value, float) and not math.isfinite(value)):
        raise ValueError(f"{what} is {value!r}, not a finite {'integer' if integer else 'number'}")
    return value


def check_progress(state: dict, cfg: "TrainConfig", num_views: int) -> None:
    """The loop's position: iteration in [0, iterations], elapsed time, the remaining view order (distinct training
    view indices) and the recent error average."""
    it = _number(state["iteration"], "iteration", integer=True)
    if not 0 <= it <= cfg.iterations:
        shown = str(it) if abs(it) < 10 ** 15 else f"{str(it)[:12]}... ({len(str(it))} digits)"
        raise ValueError(f"iteration {shown} is outside the run's 0..{cfg.iterations}")
    if _number(state["train_seconds"], "train_seconds") < 0:
        raise ValueError(f"train_seconds is negative ({state['train_seconds']})")
    order = state["view_order"]
    if not isinstance(order, (list, tuple)) or len(order) > num_views:
        raise ValueError(f"view_order must list at most the {num_views} training views, got "
                         f"{type(order).__name__} of {len(order) if isinstance(order, (list, tuple)) else '?'}")
    for i in order:
        if _number(i, "a view_order entry", integer=True) < 0 or i >= num_views:
            shown = str(i) if abs(i) < 10 ** 15 else f"{str(i)[:12]}... ({len(str(i))} digits)"
            raise ValueError(f"view_order names view {shown}, but the dataset has {num_views} training views")
    if len(set(order)) != len(order):
        raise ValueError("view_order names a training view twice")
    if state.get("recent_error") is not None and _number(state["recent_error"], "recent_error") < 0:
        raise ValueError(f"recent_error is negative ({state['recent_error']})")


def check_optimizer_state(optimizer: torch.optim.Optimizer, iteration: int) -> None:
    """Adam's moments, once loaded: the shape of their parameter, finite; present for every parameter once training
    has started (missing ones would silently restart from zero)."""
    for group in optimizer.param_groups:
        for j, p in enumerate(group["params"]):
            name = f"{group.get('name', 'group')}[{j}]" if len(group["params"]) > 1 else group.get("name", "?")
            st = optimizer.state.get(p)
            if not st:
                if iteration > 0 and p.numel() > 0:
                    raise ValueError(f"the optimizer has no Adam state for parameter {name} after {iteration} "
                                     "iterations")
                continue
            for key in ("exp_avg", "exp_avg_sq"):
                m = st.get(key)
                if not isinstance(m, torch.Tensor) or m.shape != p.shape:
                    raise ValueError(f"Adam's {key} of {name} has shape {list(getattr(m, 'shape', []))}, its "
                                     f"parameter {list(p.shape)}")
                if not bool(torch.isfinite(m).all()):
                    raise ValueError(f"Adam's {key} of {name} holds non-finite values")
            step = st.get("step")
            if step is not None and not (torch.isfinite(torch.as_tensor(step, dtype=torch.float64)).all()
                                         and float(step) >= 0):
                raise ValueError(f"Adam's step of {name} is {step!r}")


def check_densify_state(stats: "DensifyStats", num_primitives: int | None) -> None:
    """The densification statistics: one finite non-negative value per primitive (num_primitives; None: any one
    length, for a strategy that does not read them)."""
    items = stats.state_dict().items()
    want = num_primitives
    for key, t in items:
        if not isinstance(t, torch.Tensor) or t.dim() != 1 or (want is not None and t.shape[0] != want):
            raise ValueError(f"densification statistic {key} has shape {list(getattr(t, 'shape', []))}, "
                             f"not [{want if want is not None else 'N'}] (one value per primitive)")
        want = t.shape[0]  # the statistics agree with each other
        if not t.is_floating_point() or not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
            raise ValueError(f"densification statistic {key} must hold finite non-negative values")


class Trainer:
    """The state of one training run (model, optimizer, densification statistics, random generator, position in
    the view order) and one `step()` of the loop. Files, signals and progress belong to the runs layer
    (splatzoo.runs); `state_dict()` is everything a checkpoint needs for a bit-identical resume."""

    def __init__(self, scene, net, cfg: TrainConfig, backend: str, device: torch.device, state: dict | None = None,
                 comm: Comm | None = None):
        self.scene, self.cfg, self.backend, self.device = scene, cfg, backend, device
        self.comm = comm or Comm()
        self.net = net.to(device)
        self.strategy = resolve_strategy(cfg.strategy, self.net)
        # larger batches: learning rates x sqrt(views per step), Adam's betas to the power of it (the rule
        # Grendel-GS reports for Gaussian splatting; one view per step leaves the 2DGS recipe unchanged)
        g = cfg.views_per_step
        self.lr_scale = math.sqrt(g)
        groups = self.net.optim_groups(scene.extent)
        for group in groups:
            group["lr"] = group.get("lr", 0.0) * self.lr_scale
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15, betas=(0.9 ** g, 0.999 ** g))
        self.stats = DensifyStats(self.net.num_primitives)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.iteration, self.train_seconds, self.view_order = 0, 0.0, []
        if state is not None:
            check_progress(state, cfg, len(scene.train))
            # checkpoints from before the error average start it again (it settles within ~100 steps)
            self.net.recent_error = None if state.get("recent_error") is None else float(state["recent_error"])
            self.optimizer.load_state_dict(state["optimizer"])
            check_optimizer_state(self.optimizer, int(state["iteration"]))
            self.stats.load_state_dict(state["densify"])
            # only adc reads them (the other strategies do not resize them when they edit the model)
            check_densify_state(self.stats, None if self.strategy != "adc" else self.net.num_primitives)
            if self.comm.rank != 0:  # the checkpoint holds the sums over all ranks; rank 0 carries them on
                self.stats.grad_sum.zero_()
                self.stats.count.zero_()
            self.gen.set_state(state["generator"])
            self.iteration, self.train_seconds = int(state["iteration"]), float(state["train_seconds"])
            self.view_order = [int(i) for i in state["view_order"]]
        self.background = torch.tensor(scene.background, dtype=torch.float32, device=device)
        self.random_background = bool(getattr(scene, "random_background", False))
        # the model's render settings are the run's: its filter, and the photos' backdrop it renders over by default
        # once trained (random colours teach no backdrop; random colours through masks replace the photos' backdrop,
        # which the model then renders over)
        masked = bool(getattr(scene, "masked_backdrop", False))
        self.net.set_render_settings(antialias=cfg.antialias, background=None if self.random_background and not masked
                                     else tuple(float(c) for c in scene.background))
        self.view_index = {id(v): i for i, v in enumerate(scene.train)}
        self.densify_on = cfg.densify and hasattr(self.net, "logit_opacity")
        self.mcmc = self.densify_on and self.strategy == "mcmc"
        self.frequency = self.densify_on and self.strategy == "frequency"
        self.d_from, self.d_until = cfg.at(cfg.densify_from), cfg.at(cfg.densify_until)
        # a short run keeps the 30k schedule's windows: densification decides on at least densify_interval
        # iterations of gradient statistics, and opacity resets come no closer than opacity_reset_interval / 3
        self.d_every = max(cfg.at(cfg.densify_interval), cfg.densify_interval)
        self.reset_every = max(cfg.at(cfg.opacity_reset_interval), cfg.opacity_reset_interval // 3)
        # from the scene and the config alone, so that a resumed run has the same budget
        self.budget = cfg.max_primitives or densify_budget(scene, cfg.num_primitives or scene.points.shape[0])
        if cfg.max_bytes:  # densification grows to budget_start times the surfels the byte budget holds plain
            self.budget = min(self.budget, budget.start_count(self.net, cfg.max_bytes, cfg.store))
        self._probe_views = None  # (camera, image) pairs of _probe_error, made on its first call
        self.shedding_steps = set(budget.shedding_steps(cfg.iterations)) if cfg.max_bytes else set()
        self.wave_fit_step = self.net.wave_fit_step(cfg.iterations)
        self.net.probe_error = self._probe_error

    @classmethod
    def start(cls, scene, model: str, model_config, cfg: TrainConfig, backend: str, device,
              comm: Comm | None = None) -> "Trainer":
        """A fresh run: the model initialised from the scene's points (chosen by the seed); under a byte budget without
        --num-primitives, from no more of them than budget.start_count."""
        count, points, capped = cfg.num_primitives, scene.points.shape[0], False
        if cfg.max_bytes and count is None and points:
            # shedding from many times the budget strips a rich model's waves while surfels are plenty (beta-gabor on
            # the fox at 25% of 2dgs's bytes: from all 11,849 points it kept no wave, 21.51 dB; from 1,782, 23.27;
            # BENCHMARKS.md, "train --max-bytes starts from twice what fits")
            one = create_model(model, scene.points[:1], scene.colors[:1], **dataclasses.asdict(model_config))
            start = budget.start_count(one, cfg.max_bytes, cfg.store)  # a row costs the same at any count
            capped = start < points
            count = start if capped else None
        check_start(scene, model, model_config, cfg, device, initial=count)
        if capped and (comm is None or comm.rank == 0):
            print(f"--max-bytes {cfg.max_bytes:,}: starting from {count:,} of the scene's {points:,} points "
                  f"({start / budget.plain_count(one, cfg.max_bytes, cfg.store):.3g}x the {model} surfels the budget "
                  "holds plain)", flush=True)
        pts, cols = select_initial_points(scene.points, scene.colors, count, cfg.seed)
        net = create_model(model, pts, cols, seed=cfg.seed, **dataclasses.asdict(model_config))
        return cls(scene, net, cfg, backend, device, comm=comm)

    @classmethod
    def resume(cls, scene, state: dict, cfg: TrainConfig, backend: str, device, comm: Comm | None = None) -> "Trainer":
        return cls(scene, model_from_checkpoint(state["model"]), cfg, backend, device, state, comm=comm)

    def state_dict(self) -> dict:
        """The checkpoint. With several ranks every rank must call it (it sums the densification statistics)."""
        stats = self.stats.state_dict()
        if self.comm.world > 1:
            stats = {k: v.clone() for k, v in stats.items()}
            self.comm.sum_(list(stats.values()))
        return {"model": self.net.checkpoint(), "optimizer": self.optimizer.state_dict(),
                "densify": stats, "generator": self.gen.get_state(), "iteration": self.iteration,
                "train_seconds": self.train_seconds, "view_order": list(self.view_order),
                "recent_error": self.net.recent_error}

    def _view_generator(self, view, step: int, salt: int) -> torch.Generator:
        """A generator of its own for each (step, view, purpose): the same draws on every rank and after a resume,
        and none taken from the generator that orders the views."""
        seed = (self.cfg.seed * 1_000_003 + step) * 65_537 + self.view_index.get(id(view), 0)
        return torch.Generator().manual_seed((seed + (salt << 48)) % 2**63)  # any seed up to MAX_SEED

    def _downscale(self, view, step: int) -> float:
        """1, or the smaller scale this (step, view) trains at under --random-downscale."""
        p = self.cfg.random_downscale
        if p <= 0:
            return 1.0
        side = min(view.camera.width, view.camera.height)
        # smaller, the surfels shrink below a pixel and the view says little (measured: it costs full-size quality)
        scales = [s for s in DOWNSCALES if side * s >= MIN_DOWNSCALED_SIDE]
        draw = torch.rand(2, generator=self._view_generator(view, step, salt=1))
        return scales[int(draw[1] * len(scales))] if scales and float(draw[0]) < p else 1.0

    def _loss(self, view, step: int) -> ViewLoss:
        """The loss of one view (at a smaller scale for some draws of --random-downscale)."""
        cfg = self.cfg
        if self.random_background:
            # a colour of its own for each (step, view)
            bg = torch.rand(3, generator=self._view_generator(view, step, salt=0))
            target = view.image_float(background=bg)  # RGBA: composited over bg; masked photo: backdrop replaced
            bg = bg.to(self.device)
        else:
            target, bg = view.image_float(), self.background
        cam = view.camera
        scale = self._downscale(view, step)
        if scale < 1:
            cam = cam.scaled(scale)
            target = area_resize(target, cam.width, cam.height)
        cam, target = cam.to(self.device, torch.float32), target.to(self.device)
        render = self.net.render(cam, background=bg, backend=self.backend)
        l_photo = photometric_loss(render.rgb, target, cfg.lambda_dssim)
        loss = l_photo
        if self.mcmc:
            loss = loss + mcmc.regulariser(self.net)
        penalty = self.net.regulariser()  # the model's own (e.g. sparse waves)
        if penalty is not None:
            loss = loss + penalty
        if cfg.lambda_normal > 0 and step > cfg.at(cfg.normal_from):
            loss = loss + cfg.lambda_normal * normal_consistency_loss(render, cam)
        if cfg.lambda_dist > 0 and step > cfg.at(cfg.dist_from):
            loss = loss + cfg.lambda_dist * distortion_loss(render)
        return ViewLoss(loss, l_photo, render, target, cam, scale)

    def _backward(self, views: list, step: int, track: bool):
        """Sum of the views' gradients, divided by the step's view count (over all ranks) once summed over ranks.
        Each view's own gradient feeds the densification statistics, as with one view per step. Also returns the
        step's mean absolute colour error over the covered pixels, averaged over all views of all ranks (summed with
        the gradients: every rank sees the same value)."""
        params = [p for g in self.optimizer.param_groups for p in g["params"]]
        total = {}
        losses, photos = [], []
        error = torch.zeros((), device=self.device)
        for view in views:
            loss, l_photo, render, target, cam, scale = self._loss(view, step)
            for p in params:
                p.grad = None
            loss.backward()
            if track and scale == 1:  # densification decides on full-size views
                self.stats.accumulate(self.net, cam)
            for p in params:
                if p.grad is not None:
                    total[p] = p.grad if p not in total else total[p] + p.grad
            losses.append(loss.detach())
            photos.append(l_photo.detach())
            # where the surfels are (alpha over 1/2): an empty backdrop would dilute the error by the image's share of
            # it, so an object filling a quarter of the frame would seem fitted 4x better than it is
            covered = (render.alpha.detach() > 0.5)[..., None]
            error += ((render.rgb.detach() - target).abs() * covered).sum() / (3 * covered.sum()).clamp_min(1)
        grads = [total.setdefault(p, torch.zeros_like(p)) for p in params]
        self.comm.sum_(grads + [error])
        n = self.cfg.views_per_step
        for p, grad in zip(params, grads):
            p.grad = grad / n if n > 1 else grad
        return torch.stack(losses).mean(), torch.stack(photos).mean(), render, target, error / n

    @torch.no_grad()
    def _probe_error(self, surfels_of) -> float:
        """The mean squared colour error over PROBE_VIEWS fixed training views (full size, the run's background),
        each rendered from surfels_of(camera): the same views every call, so two calls compare two models. Their
        cameras and images are prepared on the first call (a pruning makes several)."""
        if self._probe_views is None:
            train = self.scene.train
            self._probe_views = [self._full_size(v) for v in train[:: max(1, len(train) // PROBE_VIEWS)][:PROBE_VIEWS]]
        total = 0.0
        for cam, target in self._probe_views:
            rgb = self.net.render(cam, background=self.background, backend=self.backend,
                                  surfels=surfels_of(cam)).rgb
            total += float(((rgb - target) ** 2).mean())
        return total / len(self._probe_views)

    def _mcmc_step(self, step: int) -> None:
        """--strategy mcmc: every densification interval, dead surfels move onto live ones and the count grows by
        up to GROWTH toward the budget; every step, nearly dead surfels wander along their planes."""
        cfg, net = self.cfg, self.net
        if self.d_from < step <= cfg.at(mcmc.REFINE_UNTIL) and step % self.d_every == 0:
            mcmc.relocate_dead(net, self.optimizer, self.gen)
            n = net.num_primitives
            mcmc.add_surfels(net, self.optimizer, min(self.budget, n + max(1, int(mcmc.GROWTH * n))) - n, self.gen)
        lr = next(g["lr"] for g in self.optimizer.param_groups if g.get("name") == "means")
        mcmc.inject_noise(net, lr, self.gen)

    def _frequency_step(self) -> dict:
        """--strategy frequency: one frequency-aware densification step (training/frequency.py) on densify_views
        training views drawn at random, each rendered at full size over the run's background."""
        cfg, net, train = self.cfg, self.net, self.scene.train
        if net.num_primitives >= self.budget:
            return {}
        picks = torch.randperm(len(train), generator=self.gen)[:min(cfg.densify_views, len(train))].tolist()
        views = (self._full_size(train[i]) for i in picks)
        return frequency.densify_step(net, self.optimizer, views, scene_extent=self.scene.extent, budget=self.budget,
                                      generator=self.gen, min_opacity=cfg.min_opacity, background=self.background,
                                      backend=self.backend, comm=self.comm)

    def _fit_views(self) -> list:
        """The training views (wave_fit.VIEWS at most, evenly spaced) at full size over the run's background."""
        train = self.scene.train
        picks = sorted({round(i * (len(train) - 1) / max(wave_fit.VIEWS - 1, 1))
                        for i in range(min(wave_fit.VIEWS, len(train)))})
        return [self._full_size(train[i]) for i in picks]

    def _full_size(self, view) -> tuple:
        """(camera, photo) of a scene view at full size on the run's device, the photo over the run's background."""
        return (view.camera.to(self.device, torch.float32),
                view.image_float(background=self.background.cpu()).to(self.device))

    def _fit_waves(self) -> dict:
        """The model's waves fitted to the training photos (training/wave_fit.py): what was fitted, in how long."""
        start = time.perf_counter()
        fitted = wave_fit.fit_waves(self.net, self.optimizer, self._fit_views(), self.background, self.backend)
        return {**fitted, "seconds": round(time.perf_counter() - start, 3)}

    def _next_views(self) -> list:
        """The next views_per_step training views of the run's own order (a new permutation whenever it runs out)."""
        views = []
        for _ in range(self.cfg.views_per_step):  # every rank draws the same views and renders its share
            if not self.view_order:
                self.view_order = torch.randperm(len(self.scene.train), generator=self.gen).tolist()
            views.append(self.scene.train[self.view_order.pop()])
        return views

    def step(self, views: list | None = None) -> dict:
        """One iteration; returns {"loss", "photo"} and, on logging iterations, the log records to write (rank 0).
        views: the iteration's views (views_per_step of them: scene views, or `View.from_tensor(camera, image)`)
        when the caller draws them, as a nerfstudio data manager does; None: the next ones of the run's own order."""
        cfg, net, optimizer, scene, comm = self.cfg, self.net, self.optimizer, self.scene, self.comm
        step = self.iteration + 1
        t0 = time.perf_counter()
        views = self._next_views() if views is None else list(views)
        if len(views) != cfg.views_per_step:
            raise SplatzooError(f"Trainer.step was given {len(views)} views; the run trains on {cfg.views_per_step} "
                                "a step (batch_size x nproc)")
        mine = views[comm.rank * cfg.batch_size:(comm.rank + 1) * cfg.batch_size]
        for g in optimizer.param_groups:
            if g.get("name") == "means":
                g["lr"] = _position_lr(cfg, step, scene.extent) * self.lr_scale
        track = self.densify_on and self.strategy == "adc" and step <= self.d_until
        with stored_values(net, cfg.store) if cfg.trains_stored(step) else contextlib.nullcontext():
            loss, l_photo, render, target, error = self._backward(mine, step, track)
        # one read of the step's numbers (each read makes a GPU wait), and the divergence check on it
        loss_value, photo_value, error = torch.stack([loss.detach(), l_photo.detach(), error.detach()]).tolist()
        if not math.isfinite(loss_value):
            raise SplatzooError(f"loss became {loss_value} at iteration {step}; lower the learning rates or "
                                "report the scene (the run keeps its last checkpoint)")
        previous = net.recent_error
        net.recent_error = error if previous is None else previous + ERROR_AVERAGE * (error - previous)
        optimizer.step()
        if self.mcmc:
            self._mcmc_step(step)
        elif self.frequency:  # its own opacity decay stands in for the resets
            if self.d_from < step <= self.d_until and step % self.d_every == 0:
                self._frequency_step()
        elif self.densify_on and self.d_from < step <= self.d_until:
            if step % self.d_every == 0:
                if comm.world > 1:  # every rank decides from the statistics of all views
                    comm.sum_([self.stats.grad_sum, self.stats.count])
                # surfels get 100 iterations to recover from an opacity reset before transparent ones go
                recovering = step > self.reset_every and step - (step // self.reset_every) * self.reset_every < 100
                densify_and_prune(net, optimizer, self.stats, grad_threshold=cfg.densify_grad_threshold,
                                  scene_extent=scene.extent, min_opacity=0.0 if recovering else cfg.min_opacity,
                                  generator=self.gen,
                                  max_world_scale=0.1 * scene.extent if step > self.reset_every else None,
                                  max_primitives=self.budget, max_growth=MAX_GROWTH)
            if step % self.reset_every == 0:
                reset_opacity(net, optimizer)
        net.on_step(step, cfg, optimizer)  # model-specific edits (e.g. adaptive waves); no-op by default
        fitted = self._fit_waves() if step == self.wave_fit_step else None
        if cfg.max_bytes and step in self.shedding_steps:
            budget.enforce(net, optimizer, self._probe_error, cfg.max_bytes, cfg.store,
                           budget.share_due(step, cfg.iterations))
            if self.stats.grad_sum.shape[0] != net.num_primitives:  # surfels went: past densification, statistics
                self.stats = DensifyStats(net.num_primitives)      # restart (a checkpoint holds one row each)
        self.train_seconds += time.perf_counter() - t0
        self.iteration = step
        out = {"loss": loss_value, "photo": photo_value, "records": []}
        if step % cfg.log_every == 0 or step == cfg.iterations:
            mean = torch.stack([loss, l_photo]).to(torch.float32)
            comm.sum_([mean])  # the loss of all the step's views
            mean = mean / comm.world
            mse = ((render.rgb.detach() - target) ** 2).mean().item()
            out["records"].append({"iteration": step, "loss": mean[0].item(), "photo": mean[1].item(),
                                   "train_psnr": -10 * math.log10(max(mse, 1e-10)),
                                   "num_primitives": net.num_primitives, "seconds": round(self.train_seconds, 3),
                                   **net.summary()})
        if fitted is not None:
            out["records"].append({"iteration": step, "wave_fit": fitted})
        if comm.rank == 0 and scene.test and (step % cfg.eval_interval == 0 or step == cfg.iterations):
            out["records"].append({"iteration": step, "test_psnr": test_psnr(net, scene, self.backend)})
        return out


@torch.no_grad()
def test_psnr(model, scene, backend: str, max_views: int = 8) -> float:
    """Mean PSNR over (up to max_views evenly spaced) test views."""
    from ..metrics import psnr

    views = scene.test[:: max(1, len(scene.test) // max_views)][:max_views]
    vals = []
    for v in views:
        rgb = model.render(v.camera, background=scene.background, backend=backend).rgb.clamp(0, 1)
        vals.append(min(psnr(rgb.cpu(), v.image_float()), 100.0))
    return float(sum(vals) / len(vals))
