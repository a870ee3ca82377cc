"""A training launch: the request checked against the run folder (its lock held), a new run made ready or an
interrupted one resumed with its state checked, the loop around Trainer.step with its log, checkpoints (by
iteration, by time, on SIGINT/SIGTERM) and final model, and torchrun's ranks. --nproc ranks on this machine are
spawned by splatzoo.run_spawn.
"""
from __future__ import annotations

import dataclasses
import errno
import os
import shutil
import signal
import sys
import threading
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path

import torch

from .errors import SplatzooError
from .io import json_line, torch_save, write_json, write_text
from .model_checks import check_fits_scene
from .model_files import open_model
from .run_folder import (Run, TrainingInterrupted, TrainResult, differences, load_options, made_by_other_code,
                         make_record, normalize_scene_options, scene_fingerprint)
from .run_spawn import leave_process_group, spawn_ranks
from .training import TrainConfig, Trainer
from .training.trainer import test_psnr

class _StopSignals:
    """SIGINT/SIGTERM during training ask the loop to stop after the current iteration (a second SIGINT stops at
    once). Only the main thread can own signal handlers; elsewhere (a training thread) this does nothing."""

    def __init__(self, say):
        self.say, self.signum, self.previous = say, None, {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self.previous[s] = signal.signal(s, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.signum is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signum = signum
        if self.say is not None:
            self.say(f"{signal.Signals(signum).name}: stopping after this iteration to write a checkpoint "
                     "(Ctrl-C again to stop at once)")

    def __exit__(self, *exc):
        for s, h in self.previous.items():
            signal.signal(s, h)


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

    def say(self, message: str) -> None:
        if self.bar is not None:
            self.bar.console.print(message)
        else:
            print(message, file=sys.stderr, flush=True)

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


def _asked_record(model, model_options, config, scene_options, recorded_model: str) -> dict:
    """The partial record a resume request states explicitly (None = not stated)."""
    asked = {}
    if model is not None:
        asked["model"] = model
    if model_options:
        from .zoo import make_config

        full = dataclasses.asdict(make_config(model or recorded_model, **model_options))
        asked["model_config"] = {k: full[k] for k in model_options}
    if config is not None:
        asked["train"] = dict(config) if isinstance(config, dict) else dataclasses.asdict(config)
    if scene_options:
        asked["scene_options"] = {k: v for k, v in normalize_scene_options(scene_options).items() if k in scene_options}
    return asked


def train(data, model: str | None = None, model_options: dict | None = None, config: TrainConfig | dict | None = None,
          out=None, *, resume: bool = False, overwrite: bool = False, progress: bool = True,
          evaluate_at_end: bool = True, lpips_net: str | None = None, stop_after: int | None = None,
          scene_options: dict | None = None,
          command: str = "splatzoo train", watch=None, init_from=None) -> TrainResult:
    """Train `model` (default gabor) on `data` (a dataset path or a loaded Scene) into the run folder `out`.

    resume: continue the run in `out` with its recorded settings; the result is bit-identical to an uninterrupted
    run. Options passed with resume must agree with the run (else a clear error): a TrainConfig states every
    field, a dict only its keys; `data` may be None (the recorded dataset) and must otherwise be the same
    dataset. overwrite: replace a run in `out`.
    SIGINT/SIGTERM stop after the current iteration with a checkpoint (TrainingInterrupted); stop_after stops
    the same way, silently, after that iteration (tests). watch(net, iteration, scene, final): called after every
    step and at the end (a live viewer); one process only. init_from: start from the surfels of this model file
    (.ply or .pt) instead of the scene's points; its model must be `model` (None: the file's) with the same config
    (no model options: the file's). lpips_net: the LPIPS network of the evaluation at the end (vgg or alex; None:
    evaluate.LPIPS_NET).
    """
    out = Run(out or Path("runs") / (model or "gabor"))
    from .evaluate import checked_lpips_net
    from .training.distributed import launched_world

    lpips_net = checked_lpips_net(lpips_net)  # refused before the run folder is made

    if isinstance(config, TrainConfig):  # a value no run can use is refused before the run folder is made
        config.validate()

    if resume and not out.path.is_dir():  # before the lock, which would make the folder
        raise SplatzooError(f"cannot resume: {out.path} holds no run (no checkpoint); start it without --resume")
    world = launched_world()
    if init_from is not None:
        if resume:
            raise SplatzooError("--init-from starts a new run from a model file; --resume continues a run from its "
                                "checkpoint: pass one of them")
        nproc = config.nproc if isinstance(config, TrainConfig) else (config or {}).get("nproc", 1)
        if world or nproc > 1:
            raise SplatzooError("--init-from trains on one process; drop --nproc (or torchrun)")
    if watch is not None and (world or (config.nproc if isinstance(config, TrainConfig) else
                                        (config or {}).get("nproc", 1)) > 1):
        raise SplatzooError("the live viewer watches training on one process; drop --viewer or --nproc")
    if world:
        return _train_launched(out, world, data, model, model_options, config, scene_options, resume=resume,
                               overwrite=overwrite, progress=progress, evaluate_at_end=evaluate_at_end,
                               lpips_net=lpips_net,
                               stop_after=stop_after, command=command)
    made = not out.path.exists()
    with out.lock(command, create=True), _restoring_on_failure(out, made):
        scene, model, model_config, cfg, state = _prepare(out, data, model, model_options, config, scene_options,
                                                          resume=resume, overwrite=overwrite, init_from=init_from)
        if cfg.nproc > 1:
            if watch is not None:
                raise SplatzooError(f"{out.path} trains on {cfg.nproc} processes; the live viewer watches one. "
                                    "Resume without --viewer")
            return spawn_ranks(out, scene, model, model_config, cfg, state is not None, loop=_train_loop,
                               progress=progress, evaluate_at_end=evaluate_at_end, lpips_net=lpips_net,
                               stop_after=stop_after)
        return _train_loop(out, scene, model, model_config, cfg, state, progress=progress,
                           evaluate_at_end=evaluate_at_end, lpips_net=lpips_net, stop_after=stop_after, watch=watch)


@contextmanager
def _restoring_on_failure(run: Run, made: bool):
    """A new run that fails (or is interrupted) before its first checkpoint gives the folder back to the run that
    --overwrite set aside (the error then says so), or removes the folder it made (`made`: the folder did not exist
    before this command), which holds nothing to resume from."""
    try:
        yield
    except BaseException as e:
        if made and run.path.is_dir() and not (run.checkpoint_path.exists() or run.model_path.exists()):
            shutil.rmtree(run.path, ignore_errors=True)  # the lock file goes too: the flock dies with its fd
        elif run.restore_replaced():
            note = f" The run that --overwrite was to replace is restored in {run.path}, unchanged."
            if isinstance(e, SplatzooError):
                e.args = (f"{e.args[0] if e.args else e}{note}", *e.args[1:])
            else:
                print(note.strip(), file=sys.stderr, flush=True)
        raise


def _prepare(out: Run, data, model, model_options, config, scene_options, *, resume: bool, overwrite: bool,
             world: int = 1, init_from=None):
    """Check a request against the run folder (its lock held) and make the run ready to train:
    (scene, model, model_config, cfg, state). `world`: the processes a launcher started (1: none)."""
    if out.status == "foreign":
        raise SplatzooError(f"{out.path} exists and is not a splatzoo run folder; choose a new or empty --out")
    if resume and overwrite:
        raise SplatzooError("--resume continues a run and --overwrite replaces it: pass one of them")
    if resume:
        return _prepare_resume(out, data, model, model_options, config, scene_options, world=world)
    return _prepare_new(out, data, model, model_options, config, scene_options, overwrite=overwrite, world=world,
                        init_from=init_from)


def _prepare_resume(out: Run, data, model, model_options, config, scene_options, *, world: int):
    """_prepare of --resume: the run's own settings, those the request states checked against them."""
    from .data import load_scene
    from .zoo import make_config, stored_config

    status = out.status
    if status == "new":
        raise SplatzooError(f"cannot resume: {out.path} holds no run (no checkpoint); start it without --resume")
    if status == "finished":
        raise SplatzooError(f"{out.path} holds a finished run (model.pt); nothing to resume. Evaluate it "
                            f"with `splatzoo eval {out.path}` or train into another --out")
    record = out.record()
    asked = _asked_record(model, model_options, config, scene_options, record["model"])
    if data is None:
        scene = out.scene(record)
    else:
        scene = data if hasattr(data, "train") else load_scene(data, **load_options(record))
    root = str(Path(scene.root).expanduser().resolve()) if getattr(scene, "root", None) else None
    asked.update(data=root, data_fingerprint=scene_fingerprint(scene))
    conflicts = differences(record, asked)
    if conflicts:
        raise SplatzooError(f"--resume continues {out.path} with its own settings, but these differ: "
                            + "; ".join(conflicts) + ". Resume without them, or train into another --out")
    model = record["model"]
    if made_by_other_code(record):
        print(f"note: {out.path} was started by other splatzoo code (its model, trainer, rasterizer or metrics "
              "sources changed since); it continues with today's", file=sys.stderr, flush=True)
    model_config = make_config(model, **stored_config(model, record["model_config"]))
    cfg = out.train_config(record)
    if config is not None:  # operational fields (backend, checkpoint cadence) may change on resume
        stated = config if isinstance(config, dict) else dataclasses.asdict(config)
        cfg = dataclasses.replace(cfg, **{k: v for k, v in stated.items()
                                          if k in TrainConfig.operational_fields()}).validate()
    if root and record.get("data") != root:  # the same dataset, moved: remember where it is now
        record["data"] = root
        write_json(out.config_path, record)
    if world > 1 and cfg.nproc != world:
        raise SplatzooError(f"{out.path} trains on {cfg.nproc} processes; resume it with {cfg.nproc} "
                            f"(torchrun --nproc-per-node {cfg.nproc}), not {world}")
    if not scene.train:
        raise SplatzooError(f"scene {scene.name!r} has no training views")
    _check_backend(cfg, spawn=world <= 1)
    state = out.checkpoint() if out.checkpoint_path.exists() else None
    return scene, model, model_config, cfg, state


def _prepare_new(out: Run, data, model, model_options, config, scene_options, *, overwrite: bool, world: int,
                 init_from=None):
    """_prepare of a new run (or one replacing the run in the folder, with `overwrite`): everything that can fail
    on bad input fails before an old run is set aside; then config.json is written."""
    from .data import load_scene
    from .zoo import make_config

    if data is None:
        raise SplatzooError("name the dataset to train on (DATA)")
    initial = None
    if init_from is not None:
        initial = initial_model(init_from, model, model_options)
        model, model_config = initial.name, initial.config
    model = model or "gabor"
    if initial is None:
        model_config = make_config(model, **(model_options or {}))
    cfg = (TrainConfig(**config) if isinstance(config, dict) else config or TrainConfig()).validate()
    if initial is not None and cfg.num_primitives:
        raise SplatzooError(f"--num-primitives chooses initial points, but --init-from {init_from} starts from "
                            f"its {initial.num_primitives} surfels: pass one of them")
    if world > 1:  # the processes a launcher started are the run's ranks
        if cfg.nproc not in (1, world):
            raise SplatzooError(f"--nproc {cfg.nproc} disagrees with the {world} processes the launcher "
                                "started; leave --nproc out under torchrun")
        cfg = dataclasses.replace(cfg, nproc=world)
    scene_options = dict(scene_options or {})
    normalize_scene_options(scene_options)
    status = out.status
    if status != "new" and not overwrite:
        what = {"finished": "a finished run (model.pt)", "interrupted": "an interrupted run",
                "started": "a run that never wrote a checkpoint"}[status]
        raise SplatzooError(f"{out.path} already holds {what}; pass --resume to continue it, --overwrite "
                            "to replace it, or choose another --out")
    scene = data if hasattr(data, "train") else load_scene(data, **scene_options)
    if not scene.train:
        raise SplatzooError(f"scene {scene.name!r} has no training views")
    for note in getattr(scene, "notes", ()):
        print(note, file=sys.stderr, flush=True)
    if initial is not None:
        check_fits_scene(initial, scene, f"--init-from {init_from}")
    _check_can_start(scene, model, model_config, cfg, initial, spawn=world <= 1)
    out.set_aside()  # deleted at the new run's first checkpoint, restored if it fails before
    record = make_record(scene, scene_options, model, model_config, cfg)
    if initial is not None:
        record["init_from"] = str(Path(init_from).expanduser().resolve())
    write_json(out.config_path, record)
    return scene, model, model_config, cfg, None


def _check_can_start(scene, model: str, model_config, cfg: TrainConfig, initial=None, *, spawn: bool) -> None:
    """What can still refuse a new run after its request is checked, asked before an old run is replaced: the
    backend (and its devices for --nproc) and the memory its primitives need."""
    from .training.trainer import check_start

    check_start(scene, model, model_config, cfg, _check_backend(cfg, spawn=spawn),
                initial=None if initial is None else initial.num_primitives)


def _check_backend(cfg: TrainConfig, *, spawn: bool) -> torch.device:
    """The device of the run's backend, refused by name if the backend cannot run here or has too few GPUs for
    --nproc (one process per GPU). spawn: this process starts the --nproc ranks (not a launcher such as torchrun,
    whose ranks may span machines), which on the CPU share this machine's cores."""
    from .rasterizers import select_backend

    device = select_backend(cfg.backend).torch_device()
    cores = os.cpu_count() or 1
    if spawn and device.type == "cpu" and cfg.nproc > cores:
        raise SplatzooError(f"--nproc {cfg.nproc} starts {cfg.nproc} processes that share this machine's {cores} "
                            f"CPU cores; pass --nproc {cores} or fewer")
    if cfg.nproc > 1 and device.type == "cuda" and cfg.nproc > torch.cuda.device_count():
        raise SplatzooError(f"--nproc {cfg.nproc} trains one process per GPU, but this machine has "
                            f"{torch.cuda.device_count()}; pass --nproc {max(1, torch.cuda.device_count())} or "
                            "--backend cpu")
    return device


def initial_model(path, model: str | None = None, model_options: dict | None = None):
    """The model of the file `path` (.ply or .pt) to start training from: it must be `model` (None: any), and with
    `model_options` its config must agree with them."""
    from .zoo import make_config

    path = Path(path)
    if not path.is_file():
        raise SplatzooError(f"--init-from {path}: no such file; pass a model file (.ply from `splatzoo export` or "
                            "another 2DGS/3DGS tool, or a .pt)")
    net = open_model(path).model
    if model is not None and net.name != model:
        raise SplatzooError(f"--init-from {path} holds a {net.name!r} model but this run trains {model!r}; train "
                            f"--model {net.name} (or leave --model out to take the file's model)")
    if model_options:
        asked = dataclasses.asdict(make_config(net.name, **model_options))
        have = dataclasses.asdict(net.config)
        differ = [f"{k}: file {have[k]!r}, asked {asked[k]!r}" for k in asked if asked[k] != have.get(k)]
        if differ:
            raise SplatzooError(f"--init-from {path}: the file's {net.name} model has other options ("
                                f"{'; '.join(differ)}); leave the model options out to take the file's")
    return net



def _check_adam_groups(optimizer) -> None:
    """The hyperparameters of a checkpoint's Adam groups, which torch loads unchecked and uses only at the next step:
    lr, betas and eps finite numbers in their ranges, weight_decay and the flags as the trainer leaves them (Adam's
    defaults). A ValueError says what is wrong (the caller names the checkpoint)."""
    import math

    groups = optimizer.get("param_groups") if isinstance(optimizer, dict) else None
    if not isinstance(groups, list) or not all(isinstance(g, dict) for g in groups):
        raise ValueError("the optimizer state has no list of parameter groups")
    defaults = torch.optim.Adam([torch.zeros(1)]).defaults

    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and abs(v) <= 1e308 and math.isfinite(v)

    for i, group in enumerate(groups):
        name = group.get("name", i)
        for key in ("lr", "betas", "eps", "weight_decay"):
            if key not in group:
                raise ValueError(f"Adam's {key} is missing from optimizer group {name!r}")
        betas = group["betas"]
        problems = {"lr": number(group["lr"]) and group["lr"] >= 0,
                    "eps": number(group["eps"]) and 0 < group["eps"] <= 1,
                    "weight_decay": group["weight_decay"] == defaults["weight_decay"],  # the trainer uses none
                    "betas": isinstance(betas, (tuple, list)) and len(betas) == 2
                    and all(number(b) and 0 <= b < 1 for b in betas)}
        for key, default in defaults.items():
            # flags: the trainer leaves them at Adam's defaults (maximize would climb the loss, capturable needs a
            # GPU); older files may lack newer ones, which torch then fills in
            if key not in problems and key in group:
                problems[key] = group[key] is default or (default is None and group[key] is False)
        bad = next((k for k, ok in problems.items() if not ok), None)
        if bad is not None:
            raise ValueError(f"Adam's {bad} of optimizer group {name!r} is {group[bad]!r:.60}")
    moments = optimizer.get("state")
    if not isinstance(moments, dict) or not all(isinstance(m, dict) for m in moments.values()):
        raise ValueError("the optimizer state has no dict of per-parameter Adam states")
    for key, m in moments.items():
        # torch casts the moments to their parameter's dtype when it loads them, but not the step count
        step = m.get("step", 0)
        ok = (number(step) if not isinstance(step, torch.Tensor) else
              step.numel() == 1 and step.layout == torch.strided and step.device.type == "cpu"
              and (step.is_floating_point() or step.dtype in (torch.int32, torch.int64)))
        if not ok:
            raise ValueError(f"Adam's step of parameter {key!r:.20} is {step!r:.60}, not a count")


def _check_learning_rates(trainer, scene) -> None:
    """The resumed optimizer's groups are the model's own (by name), with the learning rates the trainer gives them:
    only the position group's follows a schedule (set every step), the others keep theirs for the whole run, so a
    checkpoint that says otherwise was edited or damaged (a ValueError says how)."""
    import math

    own = {g["name"]: g.get("lr", 0.0) * trainer.lr_scale for g in trainer.net.optim_groups(scene.extent)}
    for group in trainer.optimizer.param_groups:
        name = group.get("name")
        if name not in own:
            raise ValueError(f"optimizer group {name!r:.60} is not one of the model's ({', '.join(own)})")
        if name != "means" and not math.isclose(group["lr"], own[name], rel_tol=1e-6):
            raise ValueError(f"Adam's lr of optimizer group {name!r} is {group['lr']!r:.60}, but the run gives it "
                             f"{own[name]:.6g}")


def _check_tensors(entries, what: str) -> None:
    """`entries` is a dict of dense tensors with data (a ValueError says what is not)."""
    if not isinstance(entries, dict):
        raise ValueError(f"{what} are a {type(entries).__name__}, not a dict of tensors")
    for key, value in entries.items():
        if not isinstance(value, torch.Tensor) or value.layout != torch.strided or value.device.type != "cpu":
            raise ValueError(f"{what}: {key!r:.60} is a {type(value).__name__}"
                             f"{f' on {value.device.type}' if isinstance(value, torch.Tensor) else ''}, not a tensor "
                             "with data")


def _train_loop(run: Run, scene, model: str, model_config, cfg: TrainConfig, state, *, progress: bool,
                evaluate_at_end: bool, stop_after: int | None, lpips_net: str, distributed: bool = False,
                watch=None) -> TrainResult:
    """The loop around Trainer.step: logs, checkpoints (by iteration, by time, on SIGINT/SIGTERM), the final
    model and its evaluation. distributed: this process is one rank of torch.distributed's default process group;
    every rank runs the loop and rank 0 alone writes."""
    from .rasterizers import select_backend
    from .training.distributed import Comm, ProcessGroupComm

    chosen = select_backend(cfg.backend)  # the one decision of backend and device for this run
    backend, device = chosen.name, chosen.torch_device()
    comm = ProcessGroupComm(device) if distributed else Comm()
    writer = comm.rank == 0
    trainer = _trainer(run, scene, model, model_config, cfg, state, backend, device, comm)
    if writer:
        _truncate_log(run, trainer.iteration)
    stop = cfg.iterations if stop_after is None else min(stop_after, cfg.iterations)
    bar = _Progress(cfg.iterations, trainer.iteration, model, progress and writer)
    say = bar.say if progress else (lambda m: print(m, file=sys.stderr, flush=True))
    ema, last_save = None, time.monotonic()

    def save():
        nonlocal last_save
        diverged = [name for name, p in trainer.net.named_parameters() if not bool(torch.isfinite(p).all())]
        if diverged:  # every rank holds the same parameters, so every rank stops here
            raise SplatzooError(f"the run diverged: {', '.join(diverged)} became NaN or infinite by iteration "
                                f"{trainer.iteration}; nothing was written, {run.checkpoint_path} keeps the last good "
                                "state. Lower the learning rates or report the scene")
        state = trainer.state_dict()  # every rank: it sums the densification statistics
        if writer:
            torch_save(state, run.checkpoint_path)
            run.drop_replaced()  # the new run can resume now: the run it replaced is gone for good
        last_save = time.monotonic()

    try:
        with open(run.log_path if writer else os.devnull, "a") as log, _StopSignals(say if writer else None) as signals:
            while trainer.iteration < stop:
                result = trainer.step()
                step = trainer.iteration
                for rec in result["records"]:
                    log.write(json_line(rec))
                log.flush()
                if watch is not None:
                    watch(trainer.net, step, scene, final=step == stop)
                ema = result["loss"] if ema is None else 0.9 * ema + 0.1 * result["loss"]
                bar.update(step, f"loss {ema:.4f}  {trainer.net.num_primitives} prims  "
                                 f"{step / max(trainer.train_seconds, 1e-9):.1f} it/s")
                # ranks agree on every decision: a signal or a clock seen by one rank stops or saves them all
                stopping = comm.any(signals.signum is not None)
                due = step % cfg.checkpoint_every == 0 or comm.any(
                    cfg.checkpoint_minutes > 0 and time.monotonic() - last_save >= 60 * cfg.checkpoint_minutes)
                if due or step == stop or stopping:
                    save()
                if stopping and step < cfg.iterations:
                    comm.barrier()  # the checkpoint is on disk before any rank exits
                    signum = signals.signum or signal.SIGTERM
                    raise TrainingInterrupted(
                        f"training stopped by {signal.Signals(signum).name} at iteration {step}/{cfg.iterations}; "
                        f"checkpoint written. Resume with: splatzoo train --resume --out {run.path}", 128 + signum)
    except OSError as e:  # the training log on a full disk (checkpoints say so themselves, through io)
        if e.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG):
            raise
        raise SplatzooError(f"cannot write to {run.path}: {e.strerror}. Free disk space, then resume with: "
                            f"splatzoo train --resume --out {run.path} (the last checkpoint is kept)") from None
    finally:
        bar.close()
    if stop == cfg.iterations and writer:
        return _finish(run, trainer, scene, cfg, backend, evaluate_at_end=evaluate_at_end, lpips_net=lpips_net)
    return TrainResult(run.path, trainer.net, {})


def _trainer(run: Run, scene, model: str, model_config, cfg: TrainConfig, state, backend: str, device, comm) -> Trainer:
    """The run's Trainer: from a model file's surfels (--init-from), from the scene's points, or from the checkpoint
    `state`, which is checked first (a damaged or edited one is named, never trained on)."""
    init_from = run.record().get("init_from") if state is None and comm.rank == 0 else None
    if init_from:  # a fresh run from a model file's surfels (also when resumed before its first checkpoint)
        net = initial_model(init_from, model, dataclasses.asdict(model_config))
        check_fits_scene(net, scene, f"--init-from {init_from}")
        return Trainer(scene, net, cfg, backend, device, comm=comm)
    if state is None:  # a fresh run: its errors are its own, not a checkpoint's
        return Trainer.start(scene, model, model_config, cfg, backend, device, comm=comm)
    try:
        _check_adam_groups(state["optimizer"])
        _check_tensors(state["densify"], "the densification statistics")
        trainer = Trainer.resume(scene, state, cfg, backend, device, comm=comm)
        _check_learning_rates(trainer, scene)
    except (KeyError, ValueError, TypeError, RuntimeError, IndexError, OverflowError) as e:  # Overflow: 10**400
        raise SplatzooError(f"checkpoint {run.checkpoint_path} does not hold a consistent training state ({e}); "
                            f"delete {run.path} or pass --overwrite to train again") from None
    return trainer


def _finish(run: Run, trainer: Trainer, scene, cfg: TrainConfig, backend: str, *, evaluate_at_end: bool,
            lpips_net: str) -> TrainResult:
    """The trained model written (model.szp at the run's --store precision, model.pt with the values it loads back
    as) and, with `evaluate_at_end`, evaluated on the test views (metrics.json, renders/; LPIPS with `lpips_net`,
    which train() has checked)."""
    from .zoo import save_model, stored_copy

    metrics = {}
    # the model is what its packed file (model.szp, at the run's --store precision) loads back as; model.pt holds
    # the same values as a torch file. The full-precision values' test PSNR says what the storage cost
    trained = trainer.net
    trained.precision = cfg.store
    save_model(trained, run.stored_model_path)
    net = stored_copy(trained, cfg.store) if cfg.store != "float32" else trained
    save_model(net, run.model_path)
    if evaluate_at_end:
        try:
            extra = ({"float32_psnr": test_psnr(trained, scene, backend, max_views=len(scene.test))}
                     if net is not trained and scene.test else {})
            metrics = {**_evaluate_into(run, net, scene, backend, train_seconds=trainer.train_seconds,
                                        iterations=cfg.iterations, lpips_net=lpips_net), **extra}
            if extra:
                run.write_metrics(metrics)
        except KeyboardInterrupt:
            raise TrainingInterrupted(f"training finished ({run.model_path} written) but its evaluation was "
                                      f"interrupted; evaluate with: splatzoo eval {run.path}", 130) from None
    return TrainResult(run.path, net, metrics)


def _train_launched(out: Run, world: int, data, model, model_options, config, scene_options, *, resume: bool,
                    overwrite: bool, progress: bool, evaluate_at_end: bool, lpips_net: str,
                    stop_after: int | None,
                    command: str) -> TrainResult:
    """`train` in each of the processes a launcher (torchrun) started: rank 0 takes the run's lock, checks the
    request and prepares the run as one process would, then hands its decisions (scene, model, config, the
    checkpoint to resume) to the other ranks, so every rank starts from the same state without reading the run
    folder. The rendezvous comes from the launcher's environment (MASTER_ADDR, MASTER_PORT)."""
    from datetime import timedelta

    import torch.distributed as dist

    rank = int(os.environ["RANK"])
    if torch.cuda.is_available():  # NCCL for CUDA tensors, gloo for CPU ones: the backend is decided later
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", rank)) % torch.cuda.device_count())
        group_backend = "cpu:gloo,cuda:nccl"
    else:
        group_backend = "gloo"
        local_world = int(os.environ.get("LOCAL_WORLD_SIZE", world))
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // local_world))  # the ranks on a machine share its cores
    dist.init_process_group(group_backend, timeout=timedelta(minutes=10))
    try:
        with ExitStack() as held:
            decided = [None, None]  # [failure message, (scene, model, model_config, cfg, state)]
            if rank == 0:
                try:
                    made = not out.path.exists()
                    held.enter_context(out.lock(command, create=True))
                    held.enter_context(_restoring_on_failure(out, made))
                    decided[1] = _prepare(out, data, model, model_options, config, scene_options, resume=resume,
                                          overwrite=overwrite, world=world)
                except Exception as e:
                    decided[0] = str(e) or type(e).__name__
                    dist.broadcast_object_list(decided, src=0)
                    raise
            dist.broadcast_object_list(decided, src=0)
            if decided[0] is not None:
                raise SplatzooError(decided[0])
            scene, model, model_config, cfg, state = decided[1]
            return _train_loop(out, scene, model, model_config, cfg, state, progress=progress,
                               evaluate_at_end=evaluate_at_end, lpips_net=lpips_net, stop_after=stop_after,
                               distributed=True)
    finally:
        leave_process_group(dist)



def _truncate_log(run: Run, iteration: int) -> None:
    """Keep the log records up to the checkpoint we start from (later ones will be written again); a fresh run
    starts an empty log. Damaged lines (a kill mid-write) go."""
    keep = [r for r in run.log() if r["iteration"] <= iteration] if iteration else []
    write_text(run.log_path, "".join(json_line(r) for r in keep))



def _evaluate_into(run: Run, model, scene, backend: str, **evaluate_options) -> dict:
    from .evaluate import evaluate, save_test_renders

    metrics = evaluate(model, scene, backend=backend, **evaluate_options)
    run.write_metrics(metrics)
    save_test_renders(model, scene, run.renders_dir, backend=backend)
    return metrics

