"""The training loop: any registered model on any Scene, with the 2DGS recipe (losses, learning rates and
densification schedule of the official 2DGS code; see TrainConfig).

A run directory holds config.json (fully resolved), checkpoint.pt (latest, written atomically), model.pt
(final), train_log.jsonl and, after evaluation, metrics.json and renders/.
"""
from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..errors import SplatzooError
from ..io import torch_save, write_json, write_text
from ..rasterizers import rasterize, select_backend
from ..zoo import create_model, make_config, model_from_checkpoint, save_model
from .densify import DensifyStats, densify_and_prune, reset_opacity
from .losses import distortion_loss, normal_consistency_loss, photometric_loss

REFERENCE_ITERATIONS = 30000  # the schedule below is stated for this many iterations and scaled to the run


@dataclass
class TrainConfig:
    iterations: int = 30000
    backend: str = "auto"
    seed: int = 0
    densify: bool = True
    num_primitives: int | None = field(default=None, metadata={"help": "start from exactly this many primitives"})
    max_primitives: int | None = None
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
    checkpoint_every: int = 2000   # iterations (not scaled)
    eval_every: int = 0            # test PSNR every this many iterations; 0: ten times per run
    log_every: int = 10

    def at(self, reference_iteration: int) -> int:
        """A schedule point stated for 30k iterations, scaled to this run's length."""
        return max(1, round(reference_iteration * self.iterations / REFERENCE_ITERATIONS))

    @property
    def eval_interval(self) -> int:
        return self.eval_every or max(1, self.iterations // 10)


@dataclass
class TrainResult:
    run_dir: Path
    model: torch.nn.Module
    metrics: dict


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


class _Progress:
    """A rich progress bar on a terminal; a line every tenth of the run otherwise (logs, CI)."""

    def __init__(self, total: int, start: int, label: str, enabled: bool):
        self.total, self.label, self.enabled = total, label, enabled
        self.bar = None
        self.last_line = start
        if enabled and sys.stderr.isatty():
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                                TimeRemainingColumn(), TextColumn("{task.fields[info]}"), transient=False)
            self.task = self.bar.add_task(label, total=total, completed=start, info="")
            self.bar.start()

    def update(self, step: int, info: str) -> None:
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(self.task, completed=step, info=info)
        elif step - self.last_line >= max(1, self.total // 10) or step == self.total:
            self.last_line = step
            print(f"[{self.label}] {step}/{self.total} {info}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def _config_record(data, scene_options: dict, model_name: str, model_config, cfg: TrainConfig, scene) -> dict:
    return {"data": str(data), "scene_options": scene_options, "model": model_name,
            "model_config": dataclasses.asdict(model_config), "train": dataclasses.asdict(cfg),
            "scene": {"name": scene.name, "train_views": len(scene.train), "test_views": len(scene.test),
                      "extent": scene.extent, "background": list(scene.background)}}


def train(scene, model: str = "gabor", model_options: dict | None = None, config: TrainConfig | None = None,
          out=None, *, resume: bool = False, progress: bool = True, evaluate_at_end: bool = True,
          stop_after: int | None = None, scene_options: dict | None = None) -> TrainResult:
    """Train `model` on `scene` (a splatzoo.data.Scene, or a path for load_scene) into run directory `out`.

    resume: continue from out/checkpoint.pt with the run's saved configuration; the result is the same as an
    uninterrupted run. stop_after: stop (with a checkpoint) after this iteration, as an interruption would.
    scene_options: the load_scene options (resolution, max_width, test_every, background), recorded so that
    `splatzoo eval` reloads the same views.
    """
    from ..data import load_scene

    scene_options = dict(scene_options or {})
    if not hasattr(scene, "train"):
        scene = load_scene(scene, **scene_options)
    data_path = getattr(scene, "root", "")
    cfg = config or TrainConfig()
    out = Path(out or Path("runs") / f"{model}")
    ckpt_path = out / "checkpoint.pt"
    state = None
    if resume:
        if not ckpt_path.is_file():
            raise SplatzooError(f"cannot resume: no checkpoint at {ckpt_path}; start the run without --resume")
        state = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        saved = json.loads((out / "config.json").read_text())
        cfg = TrainConfig(**saved["train"])
        model = saved["model"]
        model_options = saved["model_config"]
    elif ckpt_path.exists():
        raise SplatzooError(f"{out} already holds a run; pass --resume to continue it or choose another --out")
    if cfg.iterations < 1:
        raise SplatzooError(f"--iterations must be at least 1, got {cfg.iterations}")
    if not scene.train:
        raise SplatzooError(f"scene {scene.name!r} has no training views")

    chosen = select_backend(cfg.backend)  # the one decision of backend and device for this run
    backend, device = chosen.name, chosen.torch_device()
    model_config = make_config(model, **(model_options or {}))
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "config.json", _config_record(data_path, scene_options, model, model_config, cfg, scene))

    gen = torch.Generator().manual_seed(cfg.seed)
    if state is None:
        pts, cols = select_initial_points(scene.points, scene.colors, cfg.num_primitives, cfg.seed)
        net = create_model(model, pts, cols, seed=cfg.seed, **dataclasses.asdict(model_config))
        start, train_seconds, view_order = 0, 0.0, []
    else:
        net = model_from_checkpoint(state["model"])
        gen.set_state(state["generator"])
        start, train_seconds, view_order = state["iteration"], state["train_seconds"], list(state["view_order"])
    net = net.to(device)
    groups = net.optim_groups(scene.extent)
    optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
    stats = DensifyStats(net.num_primitives)
    if state is not None:
        optimizer.load_state_dict(state["optimizer"])
        stats.load_state_dict(state["densify"])
        _truncate_log(out / "train_log.jsonl", start)
    elif (out / "train_log.jsonl").exists():
        (out / "train_log.jsonl").unlink()

    bg = torch.tensor(scene.background, dtype=torch.float32, device=device)
    densify_on = cfg.densify and hasattr(net, "logit_opacity")
    d_from, d_until, d_every = cfg.at(cfg.densify_from), cfg.at(cfg.densify_until), max(cfg.at(cfg.densify_interval), 10)
    reset_every = cfg.at(cfg.opacity_reset_interval)
    bar = _Progress(cfg.iterations, start, f"{model}", progress)
    log = open(out / "train_log.jsonl", "a")
    ema = None
    stop = cfg.iterations if stop_after is None else min(stop_after, cfg.iterations)
    try:
        for step in range(start + 1, stop + 1):
            t0 = time.perf_counter()
            if not view_order:
                view_order = torch.randperm(len(scene.train), generator=gen).tolist()
            view = scene.train[view_order.pop()]
            cam = view.camera.to(device, torch.float32)
            target = view.image_float().to(device)
            for g in optimizer.param_groups:
                if g.get("name") == "means":
                    g["lr"] = _position_lr(cfg, step, scene.extent)
            render = rasterize(net.surfels(cam), cam, backend=backend, background=bg)
            l_photo = photometric_loss(render.rgb, target, cfg.lambda_dssim)
            loss = l_photo
            if cfg.lambda_normal > 0 and step > cfg.at(cfg.normal_from):
                loss = loss + cfg.lambda_normal * normal_consistency_loss(render, cam)
            if cfg.lambda_dist > 0 and step > cfg.at(cfg.dist_from):
                loss = loss + cfg.lambda_dist * distortion_loss(render)
            if not torch.isfinite(loss):
                raise SplatzooError(f"loss became {loss.item()} at iteration {step}; lower the learning rates or "
                                    f"report the scene (the last checkpoint is {ckpt_path})")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if densify_on and step <= d_until:
                stats.accumulate(net, cam)
            optimizer.step()
            if densify_on and d_from < step <= d_until:
                if step % d_every == 0:
                    # surfels get 100 iterations to recover from an opacity reset before transparent ones go
                    recovering = step > reset_every and step - (step // reset_every) * reset_every < 100
                    densify_and_prune(net, optimizer, stats, grad_threshold=cfg.densify_grad_threshold,
                                      scene_extent=scene.extent, min_opacity=0.0 if recovering else cfg.min_opacity,
                                      generator=gen,
                                      max_world_scale=0.1 * scene.extent if step > reset_every else None,
                                      max_primitives=cfg.max_primitives)
                if step % reset_every == 0:
                    reset_opacity(net, optimizer)
            net.on_step(step, cfg, optimizer)  # model-specific edits (e.g. adaptive waves); no-op by default
            train_seconds += time.perf_counter() - t0
            lv = loss.item()
            ema = lv if ema is None else 0.9 * ema + 0.1 * lv
            if step % cfg.log_every == 0 or step == cfg.iterations:
                mse = ((render.rgb.detach() - target) ** 2).mean().item()
                log.write(json.dumps({"iteration": step, "loss": lv, "photo": l_photo.item(),
                                      "train_psnr": -10 * math.log10(max(mse, 1e-10)),
                                      "num_primitives": net.num_primitives, "seconds": round(train_seconds, 3),
                                      **net.summary()}) + "\n")
            if scene.test and (step % cfg.eval_interval == 0 or step == cfg.iterations):
                log.write(json.dumps({"iteration": step, "test_psnr": test_psnr(net, scene, backend)}) + "\n")
            log.flush()
            bar.update(step, f"loss {ema:.4f}  {net.num_primitives} prims  {step / max(train_seconds, 1e-9):.1f} it/s")
            if step % cfg.checkpoint_every == 0 or step == stop:
                _save_checkpoint(ckpt_path, net, optimizer, stats, gen, step, train_seconds, view_order)
    finally:
        log.close()
        bar.close()
    metrics = {}
    if stop == cfg.iterations:
        save_model(net, out / "model.pt")
        if evaluate_at_end:
            from ..evaluate import evaluate, save_test_renders

            metrics = evaluate(net, scene, backend=backend, train_seconds=train_seconds, iterations=cfg.iterations)
            write_json(out / "metrics.json", metrics)
            save_test_renders(net, scene, out / "renders", backend=backend)
    return TrainResult(out, net, metrics)


def _save_checkpoint(path, net, optimizer, stats, gen, step, train_seconds, view_order) -> None:
    torch_save({"model": net.checkpoint(), "optimizer": optimizer.state_dict(), "densify": stats.state_dict(),
                "generator": gen.get_state(), "iteration": step, "train_seconds": train_seconds,
                "view_order": list(view_order)}, path)


def _truncate_log(path: Path, iteration: int) -> None:
    """Drop log lines written after the checkpoint we resume from (they will be written again)."""
    if not path.exists():
        return
    keep = [line for line in path.read_text().splitlines() if line.strip()
            and json.loads(line).get("iteration", 0) <= iteration]
    write_text(path, "".join(line + "\n" for line in keep))


@torch.no_grad()
def test_psnr(model, scene, backend: str, max_views: int = 8) -> float:
    """Mean PSNR over (up to max_views evenly spaced) test views."""
    from ..metrics import psnr

    views = scene.test[:: max(1, len(scene.test) // max_views)][:max_views]
    device = next(model.parameters()).device
    bg = torch.tensor(scene.background, dtype=torch.float32, device=device)
    vals = []
    for v in views:
        cam = v.camera.to(device, torch.float32)
        rgb = rasterize(model.surfels(cam), cam, backend=backend, background=bg).rgb.clamp(0, 1)
        vals.append(min(psnr(rgb.cpu(), v.image_float()), 100.0))
    return float(sum(vals) / len(vals))
