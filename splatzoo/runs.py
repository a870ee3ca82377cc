"""Run folders: the one place that creates, resumes, locks, loads and evaluates a training run.

A run folder holds
  config.json       what made the run: dataset (absolute path and fingerprint), load options, model and its full
                    config, training config; resume and reuse happen only when these match. Also a fingerprint of
                    the code that trained it (code_fingerprint): a run made by other code is named as such
  checkpoint.pt     the latest training state (written atomically; by iteration, by time and on SIGINT/SIGTERM)
  model.pt          the trained model (present once training finished)
  model.szp         the same model packed at the run's storage precision (--store): its stored size
  train_log.jsonl   one JSON record per logged iteration
  metrics.json      evaluation on the test views; renders/ their images; mesh.ply from `extract-mesh`
  .splatzoo.lock    held (flock) by the one process writing the folder; names that process
Every file is read safely (torch files with weights_only=True, JSON parsed and checked) and written atomically.
Commands (train, eval, render, compare, sweep, extract-mesh, export, the viewer) go through `Run`.
"""
from __future__ import annotations

import dataclasses
import errno
import functools
import hashlib
import json
import os
import re
import shutil
import signal
import socket
import sys
import threading
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch

from .errors import SplatzooError
from .io import json_line, read_json, read_torch, torch_save, write_json, write_text
from .model_checks import check_fits_scene
from .model_files import ModelFormat, open_model, register_format
from .training import TrainConfig, Trainer
from .training.trainer import test_psnr

RUN_FORMAT = 1
LOCK_NAME = ".splatzoo.lock"
# where --overwrite keeps the run it replaces until the new run's first checkpoint: restored if the new run fails
# (or is killed) before then, deleted once the new run has a checkpoint of its own
REPLACED_NAME = ".splatzoo-replaced"
# everything a run writes; `overwrite` removes exactly these (never a file splatzoo did not write)
RUN_ENTRIES = ("config.json", "checkpoint.pt", "model.pt", "model.szp", "train_log.jsonl", "metrics.json", "renders",
               "mesh.ply")
SCENE_OPTION_DEFAULTS = {"resolution": None, "max_width": None, "test_every": 8, "background": "auto",
                         "skip_missing": False}
# the sources that decide a run's numbers (the dataset has its own fingerprint): the models, the trainer, the
# rasterizers and the metrics; a run records their hash, so compare can tell a run made by other code
TRAINING_CODE = ("models", "training", "rasterizers", "csrc", "types.py", "geometry.py", "metrics.py", "evaluate.py")


class RunLockedError(SplatzooError):
    """Another process is writing the run folder."""


class TrainingInterrupted(SplatzooError):
    """Training stopped on SIGINT/SIGTERM after writing a checkpoint; `exit_code` is the shell's convention."""

    def __init__(self, message: str, exit_code: int):
        super().__init__(message)
        self.exit_code = exit_code


@dataclass
class TrainResult:
    run_dir: Path
    model: torch.nn.Module
    metrics: dict


# --- what made a run --------------------------------------------------------------------------------------------

def normalize_scene_options(options: dict | None) -> dict:
    """The load_scene options with every default filled in, in JSON form: equal options compare equal."""
    unknown = set(options or {}) - set(SCENE_OPTION_DEFAULTS)
    if unknown:
        raise SplatzooError(f"unknown scene option(s) {', '.join(sorted(unknown))}; known: "
                            f"{', '.join(SCENE_OPTION_DEFAULTS)}")
    merged = {**SCENE_OPTION_DEFAULTS, **{k: v for k, v in (options or {}).items() if v is not None}}
    from .data.background import parse_background

    merged["background"] = parse_background(merged["background"])  # "white" and (1, 1, 1) are one setting
    return json.loads(json.dumps(merged, default=list))


def scene_fingerprint(scene) -> str:
    """A hash of what training sees of a scene: view names, cameras (at the loaded resolution), image file sizes
    (or in-memory pixels), initial points and background. Cheap (no image is decoded); a dataset copied or moved
    elsewhere keeps its fingerprint."""
    h = hashlib.sha256()
    for split, views in (("train", scene.train), ("test", scene.test)):
        h.update(f"{split}:{len(views)}".encode())
        for v in views:
            c = v.camera
            h.update(f"{v.name}|{c.width}x{c.height}|".encode())
            h.update(c.world_to_camera.double().numpy().tobytes() + c.K.double().numpy().tobytes())
            if v.pixels is not None:
                h.update(hashlib.sha256(v.pixels.tobytes()).digest())
            elif v.path is not None:
                h.update(str(Path(v.path).stat().st_size if Path(v.path).exists() else -1).encode())
    h.update(scene.points.float().numpy().tobytes() + scene.colors.float().numpy().tobytes())
    h.update(repr(tuple(float(b) for b in scene.background)).encode())
    return h.hexdigest()[:32]


@functools.lru_cache(maxsize=None)
def code_fingerprint(model: str) -> str:
    """A hash (16 hex digits) of the code that trains and scores `model`: splatzoo's TRAINING_CODE and, for a plugin,
    the source file of its class. A run made before an edit to any of them has another fingerprint."""
    import inspect

    from .registry import MODELS

    h = hashlib.sha256(_core_code_hash())
    try:
        source = Path(inspect.getsourcefile(MODELS.get(model).cls)).resolve()
    except (TypeError, OSError, SplatzooError):  # an unknown name or a class without a file: the core alone
        source = None
    if source is not None and Path(__file__).resolve().parent not in source.parents:
        h.update(f"{source.name}\0".encode() + source.read_bytes())
    return h.hexdigest()[:16]


@functools.lru_cache(maxsize=None)
def _core_code_hash() -> bytes:
    """sha256 of splatzoo's TRAINING_CODE (read once a process; every model's fingerprint starts from it)."""
    package = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for entry in TRAINING_CODE:
        path = package / entry
        files = sorted(f for f in path.rglob("*") if f.suffix in (".py", ".h", ".cpp", ".cu")) if path.is_dir() \
            else [path]
        for f in files:
            h.update(f"{f.relative_to(package)}\0".encode() + (f.read_bytes() if f.is_file() else b"") + b"\0")
    return h.digest()


def made_by_other_code(record: dict) -> bool:
    """Whether the run of `record` was trained by other code than today's (see code_fingerprint). A run recorded
    before runs kept a fingerprint cannot tell: it counts as today's."""
    recorded = record.get("code")
    return isinstance(recorded, str) and recorded != code_fingerprint(record.get("model", ""))


def _scene_options_problem(options: dict) -> str | None:
    """What is wrong with the scene options of a run record (a hand edit, a damaged file), or None."""
    from .data.background import parse_background
    from .data.scene import scene_option_problem

    unknown = sorted(set(options) - set(SCENE_OPTION_DEFAULTS))
    if unknown:
        return (f"unknown scene option(s) {', '.join(map(repr, unknown))[:200]} (known: "
                f"{', '.join(SCENE_OPTION_DEFAULTS)})")
    for key, value in options.items():
        if key == "background":
            try:
                parse_background(value)
            except SplatzooError as e:
                return f"scene option background: {e}"
        elif value is not None:
            problem = scene_option_problem(key, value)
            if problem:
                return f"scene option {problem}"
    return None


def _train_config_problem(stored: dict) -> str | None:
    """A training config value of the wrong type (a hand edit): TrainConfig does not check types itself."""
    import math
    import types
    import typing

    hints = typing.get_type_hints(TrainConfig)
    for key, value in stored.items():
        want = hints.get(key)
        optional = typing.get_origin(want) in (typing.Union, types.UnionType)  # int | None
        if optional:
            if value is None:
                continue
            want = next(t for t in typing.get_args(want) if t is not type(None))
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        ok = {bool: isinstance(value, bool), str: isinstance(value, str),
              int: number and isinstance(value, int) and abs(value) < 2**63,
              float: number and (not isinstance(value, int) or abs(value) < 2**63)
              and math.isfinite(float(value))}.get(want, True)
        if not ok:
            return f"{key} must be {getattr(want, '__name__', want)}{' or null' if optional else ''}, got {value!r:.60}"
    return None


def make_record(scene, scene_options: dict | None, model: str, model_config, cfg: TrainConfig) -> dict:
    """config.json of a new run."""
    from . import __version__

    root = getattr(scene, "root", None)
    return {"format": RUN_FORMAT, "splatzoo": __version__, "code": code_fingerprint(model),
            "data": str(Path(root).expanduser().resolve()) if root else None,
            "data_fingerprint": scene_fingerprint(scene),
            "scene_options": normalize_scene_options(scene_options),
            "model": model, "model_config": _plain(dataclasses.asdict(model_config)),
            "train": _plain(dataclasses.asdict(cfg)),
            "scene": {"name": scene.name, "train_views": len(scene.train), "test_views": len(scene.test),
                      "extent": scene.extent, "background": list(scene.background),
                      "background_note": getattr(scene, "background_note", ""),
                      "random_background": bool(getattr(scene, "random_background", False))}}


def _plain(x):
    return json.loads(json.dumps(x, default=list))


def differences(recorded: dict, wanted: dict) -> list[str]:
    """What `wanted` (a full or partial record) asks for that the run in `recorded` was not made with. Keys absent
    from `wanted` are not compared; operational training fields (backend, checkpoint cadence) never conflict."""
    out = []
    if wanted.get("data_fingerprint") and recorded.get("data_fingerprint") and \
            wanted["data_fingerprint"] != recorded["data_fingerprint"]:
        out.append(f"dataset: {wanted.get('data') or 'the scene given'} is not the dataset the run was trained on "
                   f"({recorded.get('data')}): views, cameras, image files or points differ")
    if "model" in wanted and wanted["model"] != recorded.get("model"):
        out.append(f"model: run has {recorded.get('model')!r}, asked {wanted['model']!r}")
    operational = TrainConfig.operational_fields()
    train_defaults = {f.name: f.default for f in dataclasses.fields(TrainConfig)
                      if f.default is not dataclasses.MISSING}
    model = wanted.get("model", recorded.get("model"))
    for section in ("model_config", "train", "scene_options"):
        for key, value in _plain(wanted.get(section, {})).items():
            if section == "train" and key in operational:
                continue
            # a field the run's record lacks was added since: the run was made with what its default means
            default = {"scene_options": SCENE_OPTION_DEFAULTS, "train": train_defaults}.get(section, {}).get(key)
            have = recorded.get(section, {}).get(key, default)
            if section == "train" and key == "strategy":  # "auto" is the model's own: compare what ran
                have, value = _strategy_of(have, model), _strategy_of(value, model)
            if have != value:
                out.append(f"{key}: run has {have!r}, asked {value!r}")
    return out


def _strategy_of(strategy, model: str | None):
    """The densification strategy `strategy` stands for with model `model` ("auto": the model's own)."""
    if strategy != "auto" or model is None:
        return strategy
    from .registry import MODELS

    spec = MODELS.get(model) if model in MODELS.names() else None
    return getattr(spec.cls, "densify_strategy", "adc") if spec is not None else strategy


# --- the run folder ---------------------------------------------------------------------------------------------

class Run:
    """A run folder and the operations on it. `status` is one of new, foreign (a folder that is not a run),
    started (config only), interrupted (checkpoint, no model), finished (model.pt)."""

    def __init__(self, path):
        self.path = Path(path).expanduser().absolute()
        self.config_path = self.path / "config.json"
        self.checkpoint_path = self.path / "checkpoint.pt"
        self.model_path = self.path / "model.pt"
        self.stored_model_path = self.path / "model.szp"  # the packed file at the run's storage precision
        self.log_path = self.path / "train_log.jsonl"
        self.metrics_path = self.path / "metrics.json"
        self.renders_dir = self.path / "renders"
        self.lock_path = self.path / LOCK_NAME

    def __repr__(self) -> str:
        return f"Run({str(self.path)!r}, {self.status})"

    @property
    def status(self) -> str:
        try:
            return self._status()
        except OSError as e:  # a name longer than the file system allows, a folder we may not read, ...
            raise SplatzooError(f"run folder {str(self.path)[:200]} cannot be looked up ({e.strerror or e}); "
                                "choose another folder") from None

    def _status(self) -> str:
        if not self.path.exists():
            return "new"
        if not self.path.is_dir():
            return "foreign"
        if self.model_path.exists():
            return "finished" if self.config_path.exists() else "foreign"
        if self.checkpoint_path.exists():
            return "interrupted" if self.config_path.exists() else "foreign"
        if self.config_path.exists():
            return "started"
        names = [p.name for p in self.path.iterdir()
                 if p.name not in (LOCK_NAME, REPLACED_NAME) and not _is_temp(p.name)]
        return "foreign" if names else "new"

    # reading -------------------------------------------------------------------------------------------------
    def record(self) -> dict:
        """config.json, checked: a clear error if it is missing or damaged."""
        fix = "the run folder is damaged: train again into a new --out (or restore config.json)"
        rec = read_json(self.config_path, "run configuration", fix)
        missing = [k for k in ("model", "model_config", "train", "data") if not isinstance(rec, dict) or k not in rec]
        if missing:
            raise SplatzooError(f"run configuration {self.config_path} lacks {', '.join(missing)}; {fix}")
        kinds = {"model": (str,), "model_config": (dict,), "train": (dict,), "data": (str, type(None)),
                 "scene_options": (dict, type(None))}
        for key, types in kinds.items():
            if key in rec and not isinstance(rec[key], types):
                want = " or ".join("null" if t is type(None) else {str: "a string", dict: "an object"}[t]
                                   for t in types)
                raise SplatzooError(f"run configuration {self.config_path} is malformed: {key!r} must be {want}, "
                                    f"not {type(rec[key]).__name__}; {fix}")
        problem = _scene_options_problem(rec.get("scene_options") or {})
        if problem:
            raise SplatzooError(f"run configuration {self.config_path} is malformed: {problem}; {fix}")
        return rec

    def train_config(self, record: dict | None = None) -> TrainConfig:
        rec = record or self.record()
        known = {f.name for f in dataclasses.fields(TrainConfig)}
        stored = {k: v for k, v in {**TrainConfig.stored_defaults, **rec["train"]}.items() if k in known}
        problem = _train_config_problem(stored)
        if problem:
            raise SplatzooError(f"run configuration {self.config_path} has an invalid training config ({problem}); "
                                "the run folder is damaged: train again into a new --out (or restore config.json)")
        try:
            return TrainConfig(**stored).validate()
        except TypeError as e:
            raise SplatzooError(f"run configuration {self.config_path} has an invalid training config ({e})") from None

    def checkpoint(self) -> dict:
        fix = (f"the checkpoint is damaged and the run cannot resume; delete {self.path} or pass --overwrite to "
               "train again")
        state = read_torch(self.checkpoint_path, "checkpoint", fix)
        need = ("model", "optimizer", "densify", "generator", "iteration", "train_seconds", "view_order")
        if not isinstance(state, dict) or any(k not in state for k in need):
            raise SplatzooError(f"checkpoint {self.checkpoint_path} is not a splatzoo training checkpoint; {fix}")
        return state

    def model(self, backend: str | None = None):
        """The trained model; with a backend name ("auto" too) on the device that backend renders on."""
        if self.status != "finished":
            self.require_run()
            hint = (" (training was interrupted: finish it with `splatzoo train --resume --out "
                    f"{self.path}`)" if self.checkpoint_path.exists() else "")
            raise SplatzooError(f"{self.path} has no trained model (model.pt){hint}")
        return open_model(self.model_path, backend=backend).model

    def scene(self, record: dict | None = None, *, skip_missing: bool = False):
        """The run's dataset with its recorded load options (skip_missing: also leave out frames whose image has
        gone missing since, whatever the run recorded)."""
        from .data import load_scene

        rec = record or self.record()
        data = rec.get("data")
        if not data:
            raise SplatzooError(f"{self.path} was trained on an in-memory scene; it has no dataset to reload")
        try:
            found = Path(data).exists()
        except OSError as e:  # a name longer than the file system allows (a damaged record), ...
            raise SplatzooError(f"the dataset of {self.path} ({data[:200]}) cannot be looked up ({e.strerror or e}); "
                                f"the run configuration {self.config_path} is damaged") from None
        if not found:
            raise SplatzooError(f"the dataset of {self.path} ({data}) no longer exists; restore it or move it back")
        scene = load_scene(data, **{**_load_options(rec), **({"skip_missing": True} if skip_missing else {})})
        for note in scene.notes:   # training prints every note; here only what changes the views scored
            if "whose images are missing" in note:
                print(f"splatzoo: {note}", file=sys.stderr, flush=True)
        return scene

    def load(self, backend: str | None = None, *, skip_missing: bool = False):
        """(model, scene, record) of a finished run."""
        self.require_run()
        model = self.model(backend)
        record = self.record()
        return model, self.scene(record, skip_missing=skip_missing), record

    def metrics(self) -> dict | None:
        if not self.metrics_path.exists():
            return None
        m = read_json(self.metrics_path, "metrics", f"run `splatzoo eval {self.path}` to write them again")
        if not isinstance(m, dict):
            raise SplatzooError(f"metrics {self.metrics_path} are malformed; run `splatzoo eval {self.path}`")
        return m

    def log(self) -> list[dict]:
        """The training log's records (a damaged line, e.g. cut short by a kill, is skipped)."""
        if not self.log_path.exists():
            return []
        out = []
        for line in self.log_path.read_text(errors="replace").splitlines():
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if isinstance(rec, dict) and isinstance(rec.get("iteration"), int):
                out.append(rec)
        return out

    def require_run(self) -> None:
        if self.path.is_file():
            what = "a model file" if self.path.suffix in (".pt", ".ply") else "a file"
            raise SplatzooError(f"{self.path} is {what}, not a run folder; pass the --out folder of `splatzoo train`"
                                " (a model file loads in Python with splatzoo.load_model or splatzoo.load_ply)")
        if not self.path.is_dir():
            raise SplatzooError(f"run directory {self.path} does not exist; pass the --out folder of `splatzoo train`")
        if not self.config_path.exists():
            raise SplatzooError(f"{self.path} is not a splatzoo run (no config.json); pass the --out folder of "
                                "`splatzoo train`")

    # writing (hold the lock) -----------------------------------------------------------------------------------
    @contextmanager
    def lock(self, command: str = "splatzoo", *, create: bool = False):
        """Exclusive lock on the folder while a process writes it; a second writer gets a RunLockedError that
        names the first. The lock is released when the process ends, however it ends (flock). Only training
        creates the folder; other commands need an existing run."""
        import fcntl

        if not create:
            self.require_run()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise SplatzooError(f"cannot create run folder {self.path}: {e.strerror or e}; choose a writable --out") from None
        held = False
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or "another process"
                raise RunLockedError(f"{self.path} is in use by {holder}; wait for it to finish or choose another "
                                     "--out") from None
            held = True
            try:  # who holds it, for the message above; a full disk leaves it unnamed (the writes then say so)
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"`{command}` (pid {os.getpid()} on {socket.gethostname()}, since "
                              f"{time.strftime('%Y-%m-%d %H:%M:%S')})\n".encode(), 0)
            except OSError:
                pass
            self._remove_stale_temp_files()
            self._settle_replaced()
            yield self
        finally:
            if held:  # the holder's name goes with it: a folder at rest is byte-identical before and after a command
                try:
                    os.ftruncate(fd, 0)
                except OSError:
                    pass
            os.close(fd)  # releases the flock

    @contextmanager
    def writing(self, command: str, target, option: str):
        """Hold the run's lock while `command` writes `target` inside the run folder; a target elsewhere only reads
        the run, which then needs no lock and may be on read-only media (an archive, a shared disk). `option` is
        the command's option that writes elsewhere, named when the run folder cannot be written."""
        target = Path(target).resolve()
        inside = self.path.resolve() in (target, *target.parents)
        if not inside:
            self.require_run()
            yield self
            return
        if self.path.is_dir() and not os.access(self.path, os.W_OK):  # a read-only file system or no permission
            raise SplatzooError(f"{self.path} is read-only; pass {option} to write the results elsewhere")
        with self.lock(command):
            yield self

    def _remove_stale_temp_files(self) -> None:
        """Temporary files of atomic writes that a kill left behind (only the lock holder writes here)."""
        for folder in (self.path, self.renders_dir, self.renders_dir / "test", self.renders_dir / "train"):
            if folder.is_dir():
                for p in folder.iterdir():
                    if _is_temp(p.name) and p.is_file():
                        p.unlink(missing_ok=True)

    def clear(self) -> None:
        """Remove what a run wrote; files splatzoo did not write stay."""
        for name in RUN_ENTRIES:
            p = self.path / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()

    # --overwrite: the old run is moved aside, not deleted, until the new one has a checkpoint ------------------
    @property
    def replaced_path(self) -> Path:
        return self.path / REPLACED_NAME

    def set_aside(self) -> None:
        """Move what a run wrote into REPLACED_NAME (one rename per entry, on the same file system), so a new run
        can start in the folder and the old one can come back if the new one fails before its first checkpoint."""
        entries = [name for name in RUN_ENTRIES if (self.path / name).exists()]
        if not entries:
            return
        try:
            self.replaced_path.mkdir()
            for name in entries:
                os.replace(self.path / name, self.replaced_path / name)
        except OSError as e:
            self.restore_replaced()
            raise SplatzooError(f"cannot set the run in {self.path} aside to replace it ({e.strerror or e}); it is "
                                "unchanged. Free disk space or fix the folder's permissions") from None

    def restore_replaced(self) -> bool:
        """Bring back the run that --overwrite set aside (removing what the new run wrote): True if there was one."""
        aside = self.replaced_path
        if not aside.is_dir():
            return False
        self.clear()
        for p in aside.iterdir():
            os.replace(p, self.path / p.name)
        aside.rmdir()
        return True

    def drop_replaced(self) -> None:
        """The new run has a checkpoint of its own: the run it replaced is deleted for good."""
        if self.replaced_path.is_dir():
            shutil.rmtree(self.replaced_path)

    def _settle_replaced(self) -> None:
        """A run set aside by a process that died: kept out if the new run got its first checkpoint, else restored."""
        if not self.replaced_path.is_dir():
            return
        if self.checkpoint_path.exists() or self.model_path.exists():
            self.drop_replaced()
        else:
            self.restore_replaced()
            print(f"note: {self.path}: a run started with --overwrite stopped before its first checkpoint; the run "
                  "it was to replace is restored", file=sys.stderr, flush=True)

    def write_metrics(self, metrics: dict) -> None:
        write_json(self.metrics_path, metrics)


def _open_run_folder(path, *, latest: bool = False):
    """model_files' reader of a run folder: (its trained model, model.pt, ""); with `latest`, an interrupted run's
    last checkpoint instead (and a note that says so), what a viewer shows of a run still training."""
    run = Run(path)
    if not latest:
        return run.model(), run.model_path, ""
    status = run.status
    if status == "foreign":
        raise SplatzooError(f"{path} is not a splatzoo run folder")
    if status in ("new", "started"):
        raise SplatzooError(f"{path} holds no model yet (no model.pt or checkpoint.pt); train it first")
    if status == "finished":
        return run.model(), run.model_path, ""
    return open_model(run.checkpoint_path).model, run.checkpoint_path, "interrupted: showing its last checkpoint"


register_format(ModelFormat("run", "a run folder written by `splatzoo train` (its model.pt)", _open_run_folder,
                            folder=True))

_TEMP = re.compile(r"^\..+\.[A-Za-z0-9_]{8}(\.[A-Za-z0-9]+)?$")


def _is_temp(name: str) -> bool:
    """A temporary file of io.atomic_path: `.<target name>.<8 random characters>[.<suffix>]`."""
    return name != LOCK_NAME and bool(_TEMP.match(name))


# --- training ---------------------------------------------------------------------------------------------------

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
          evaluate_at_end: bool = True, stop_after: int | None = None, scene_options: dict | None = None,
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
    (no model options: the file's).
    """
    out = Run(out or Path("runs") / (model or "gabor"))
    from .training.distributed import launched_world

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
                               stop_after=stop_after, command=command)
    made = not out.path.exists()
    with out.lock(command, create=True), _restoring_on_failure(out, made):
        scene, model, model_config, cfg, state = _prepare(out, data, model, model_options, config, scene_options,
                                                          resume=resume, overwrite=overwrite, init_from=init_from)
        if cfg.nproc > 1:
            if watch is not None:
                raise SplatzooError(f"{out.path} trains on {cfg.nproc} processes; the live viewer watches one. "
                                    "Resume without --viewer")
            return _spawn_ranks(out, scene, model, model_config, cfg, state is not None, progress=progress,
                                evaluate_at_end=evaluate_at_end, stop_after=stop_after)
        return _train_loop(out, scene, model, model_config, cfg, state, progress=progress,
                           evaluate_at_end=evaluate_at_end, stop_after=stop_after, watch=watch)


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
    from .data import load_scene
    from .zoo import make_config, stored_config

    if out.status == "foreign":
        raise SplatzooError(f"{out.path} exists and is not a splatzoo run folder; choose a new or empty --out")
    if resume and overwrite:
        raise SplatzooError("--resume continues a run and --overwrite replaces it: pass one of them")
    status = out.status
    if resume:
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
            scene = data if hasattr(data, "train") else load_scene(data, **_load_options(record))
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
    else:
        if data is None:
            raise SplatzooError("name the dataset to train on (DATA)")
        # everything that can fail on bad input fails before an old run is replaced
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
        state = None
    return scene, model, model_config, cfg, state


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


def _load_options(record: dict) -> dict:
    """The recorded scene options as load_scene arguments."""
    opts = dict(record.get("scene_options", {}))
    if isinstance(opts.get("background"), list):
        opts["background"] = tuple(opts["background"])
    return {k: v for k, v in opts.items() if v is not None}


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
                evaluate_at_end: bool, stop_after: int | None, distributed: bool = False, watch=None) -> TrainResult:
    """The loop around Trainer.step: logs, checkpoints (by iteration, by time, on SIGINT/SIGTERM), the final
    model and its evaluation. distributed: this process is one rank of torch.distributed's default process group;
    every rank runs the loop and rank 0 alone writes."""
    from .rasterizers import select_backend
    from .training.distributed import Comm, ProcessGroupComm

    chosen = select_backend(cfg.backend)  # the one decision of backend and device for this run
    backend, device = chosen.name, chosen.torch_device()
    comm = ProcessGroupComm(device) if distributed else Comm()
    writer = comm.rank == 0
    init_from = run.record().get("init_from") if state is None and writer else None
    if init_from:  # a fresh run from a model file's surfels (also when resumed before its first checkpoint)
        net = initial_model(init_from, model, dataclasses.asdict(model_config))
        check_fits_scene(net, scene, f"--init-from {init_from}")
        trainer = Trainer(scene, net, cfg, backend, device, comm=comm)
    elif state is None:  # a fresh run: its errors are its own, not a checkpoint's
        trainer = Trainer.start(scene, model, model_config, cfg, backend, device, comm=comm)
    else:
        try:
            _check_adam_groups(state["optimizer"])
            _check_tensors(state["densify"], "the densification statistics")
            trainer = Trainer.resume(scene, state, cfg, backend, device, comm=comm)
            _check_learning_rates(trainer, scene)
        except (KeyError, ValueError, TypeError, RuntimeError, IndexError, OverflowError) as e:  # Overflow: 10**400
            raise SplatzooError(f"checkpoint {run.checkpoint_path} does not hold a consistent training state ({e}); "
                                f"delete {run.path} or pass --overwrite to train again") from None
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
    metrics = {}
    net = trainer.net
    if stop == cfg.iterations and writer:
        from .zoo import save_model, stored_copy

        # the model is what its packed file (model.szp, at the run's --store precision) loads back as; model.pt holds
        # the same values as a torch file. The full-precision values' test PSNR says what the storage cost
        trained = net
        trained.precision = cfg.store
        save_model(trained, run.stored_model_path)
        net = stored_copy(trained, cfg.store) if cfg.store != "float32" else trained
        save_model(net, run.model_path)
        if evaluate_at_end:
            try:
                extra = ({"float32_psnr": test_psnr(trained, scene, backend, max_views=len(scene.test))}
                         if net is not trained and scene.test else {})
                metrics = {**_evaluate_into(run, net, scene, backend, train_seconds=trainer.train_seconds,
                                            iterations=cfg.iterations), **extra}
                if extra:
                    run.write_metrics(metrics)
            except KeyboardInterrupt:
                raise TrainingInterrupted(f"training finished ({run.model_path} written) but its evaluation was "
                                          f"interrupted; evaluate with: splatzoo eval {run.path}", 130) from None
    return TrainResult(run.path, net, metrics)


# --- several processes -------------------------------------------------------------------------------------------

def _train_launched(out: Run, world: int, data, model, model_options, config, scene_options, *, resume: bool,
                    overwrite: bool, progress: bool, evaluate_at_end: bool, stop_after: int | None,
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
                               evaluate_at_end=evaluate_at_end, stop_after=stop_after, distributed=True)
    finally:
        _leave_process_group(dist)


def _spawn_ranks(run: Run, scene, model: str, model_config, cfg: TrainConfig, resume: bool, *, progress: bool,
                 evaluate_at_end: bool, stop_after: int | None) -> TrainResult:
    """Train on cfg.nproc processes (torch.distributed: gloo on CPU, NCCL on CUDA) while this process holds the
    run's lock. Ctrl-C reaches every rank from the terminal; SIGTERM to this process is passed on. A rank that
    fails or dies ends the run with a clear error; the last checkpoint stays."""
    import tempfile

    import torch.multiprocessing as mp

    # The ranks meet through a file (no listening store socket) and talk over the loopback interface only:
    # torch.distributed has no authentication, so nothing of a one-machine run may listen on the network.
    rendezvous = Path(tempfile.mkdtemp(prefix="splatzoo-ranks-")) / "store"
    # each rank's heartbeat (a thread beating even while the rank computes or waits in a collective): a rank that
    # stops beating was stopped (SIGSTOP) or hangs, and the others would wait for it until gloo's 10-minute timeout
    beats = mp.get_context("spawn").Array("d", cfg.nproc, lock=False)
    ctx = mp.start_processes(_rank_main, nprocs=cfg.nproc, join=False, start_method="spawn",
                             args=(cfg.nproc, str(rendezvous), beats, str(run.path), scene, model,
                                   dataclasses.asdict(model_config), dataclasses.asdict(cfg), resume, progress,
                                   evaluate_at_end, stop_after))
    pids = [p.pid for p in ctx.processes]
    silent_after = float(os.environ.get("SPLATZOO_RANK_TIMEOUT", RANK_TIMEOUT_S))
    started = time.time()

    def forward(signum, frame):
        for pid in pids:
            try:
                os.kill(pid, signum)
            except ProcessLookupError:
                pass

    previous = {s: signal.signal(s, forward if s == signal.SIGTERM else signal.SIG_IGN)
                for s in (signal.SIGINT, signal.SIGTERM)} if threading.current_thread() is threading.main_thread() else {}
    try:
        while not ctx.join(timeout=1.0):
            now = time.time()
            for rank, beat in enumerate(beats[:]):
                if now - (beat or started) > silent_after:  # no beat yet: counted from the spawn
                    for pid in pids:
                        try:
                            os.kill(pid, signal.SIGKILL)
                        except ProcessLookupError:
                            pass
                    raise SplatzooError(f"rank {rank} of {cfg.nproc} stopped responding (no heartbeat for "
                                        f"{silent_after:.0f} s: stopped, or hung); the run was ended "
                                        f"({_what_is_kept(run)})")
    except mp.ProcessExitedException as e:
        code = e.exit_code
        if code in (130, 143):
            name = "SIGINT" if code == 130 else "SIGTERM"
            raise TrainingInterrupted(f"training stopped by {name}; checkpoint written. Resume with: splatzoo "
                                      f"train --resume --out {run.path}", code) from None
        how = f"was killed by {signal.Signals(-code).name}" if code < 0 else f"exited with code {code}"
        raise SplatzooError(f"rank {e.error_index} of {cfg.nproc} {how}; the run stopped "
                            f"({_what_is_kept(run)})") from None
    except mp.ProcessRaisedException as e:
        last = str(e).strip().splitlines()[-1]
        raise SplatzooError(f"rank {e.error_index} of {cfg.nproc} failed: {last} ({_what_is_kept(run)})") from None
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        shutil.rmtree(rendezvous.parent, ignore_errors=True)
    from .zoo import load_model

    return TrainResult(run.path, load_model(run.model_path) if run.model_path.exists() else None,
                       run.metrics() or {})


def _what_is_kept(run: Run) -> str:
    if run.checkpoint_path.exists():
        return f"its last checkpoint is kept; resume with: splatzoo train --resume --out {run.path}"
    return "it stopped before its first checkpoint"


def loopback_interface() -> str | None:
    """The name of the loopback network interface ("lo" on Linux, "lo0" on macOS), None if there is none."""
    import socket as socket_module

    try:
        return next((name for _, name in socket_module.if_nameindex() if name.startswith("lo")), None)
    except OSError:
        return None


RANK_TIMEOUT_S = 60.0  # a rank whose heartbeat is older than this ends an --nproc run ($SPLATZOO_RANK_TIMEOUT)
HEARTBEAT_S = 2.0


def _beat(beats, rank: int) -> None:
    """Write this rank's heartbeat every HEARTBEAT_S seconds, from a daemon thread: it keeps beating while the rank
    computes or waits for the others, and stops only when the whole process is stopped or gone."""
    def run():
        while True:
            beats[rank] = time.time()
            time.sleep(HEARTBEAT_S)

    threading.Thread(target=run, name="splatzoo-heartbeat", daemon=True).start()


def _rank_main(rank: int, world: int, rendezvous: str, beats, run_path: str, scene, model: str, model_config: dict,
               cfg: dict, resume: bool, progress: bool, evaluate_at_end: bool, stop_after: int | None) -> None:
    """One rank of `_spawn_ranks`: join the process group, train, and exit with the shell's code for how it ended."""
    from datetime import timedelta

    import torch.distributed as dist

    from .zoo import make_config

    _beat(beats, rank)

    cfg = TrainConfig(**cfg)
    cuda = cfg.backend == "cuda" or (cfg.backend == "auto" and torch.cuda.is_available())
    if cuda:
        torch.cuda.set_device(rank % torch.cuda.device_count())
    else:  # the ranks share the cores
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))
    lo = loopback_interface()
    if lo is not None:  # gloo and NCCL bind their connections to this interface (unless the user chose one)
        os.environ.setdefault("GLOO_SOCKET_IFNAME", lo)
        os.environ.setdefault("NCCL_SOCKET_IFNAME", lo)
    dist.init_process_group("nccl" if cuda else "gloo", init_method=f"file://{rendezvous}", rank=rank,
                            world_size=world, timeout=timedelta(minutes=10))
    code = 0
    try:
        run = Run(run_path)
        _train_loop(run, scene, model, make_config(model, **model_config), cfg,
                    run.checkpoint() if resume else None, progress=progress, evaluate_at_end=evaluate_at_end,
                    stop_after=stop_after, distributed=True)
    except TrainingInterrupted as e:
        if rank == 0:
            print(e, file=sys.stderr, flush=True)
        code = e.exit_code
    except SplatzooError as e:
        print(f"error (rank {rank}): {e}", file=sys.stderr, flush=True)
        code = 2
    finally:
        _leave_process_group(dist)
    if code:
        sys.exit(code)


def _leave_process_group(dist) -> None:
    """Every rank waits for the others before tearing the group down: a rank that destroyed it (rank 0 with it the
    rendezvous store) while another still used it aborted that rank now and then (gloo: std::terminate)."""
    from datetime import timedelta

    try:
        if dist.get_backend() == "gloo":
            dist.monitored_barrier(timeout=timedelta(seconds=60))
        else:
            dist.barrier()
    except Exception:  # a rank that is gone already: nothing to wait for
        pass
    dist.destroy_process_group()


def _truncate_log(run: Run, iteration: int) -> None:
    """Keep the log records up to the checkpoint we start from (later ones will be written again); a fresh run
    starts an empty log. Damaged lines (a kill mid-write) go."""
    keep = [r for r in run.log() if r["iteration"] <= iteration] if iteration else []
    write_text(run.log_path, "".join(json_line(r) for r in keep))


# --- evaluation and rendering of a run ---------------------------------------------------------------------------

def _evaluate_into(run: Run, model, scene, backend: str, **evaluate_options) -> dict:
    from .evaluate import evaluate, save_test_renders

    metrics = evaluate(model, scene, backend=backend, **evaluate_options)
    run.write_metrics(metrics)
    save_test_renders(model, scene, run.renders_dir, backend=backend)
    return metrics


def load_run(run_dir, backend: str | None = None):
    """(model, scene, config record) of a finished run; with a backend name ("auto" too), the model is on the
    device that backend renders on."""
    return Run(run_dir).load(backend)


def evaluate_run(run_dir, *, backend: str = "auto", lpips_net: str | None = None,
                 lpips_convention: str | None = None, scales=(), out=None, skip_missing: bool = False) -> dict:
    """Evaluate a finished run on its test views and write RUN/metrics.json (or the file `out`: the run is then only
    read, so it may be on read-only media); `scales` (each below 1) adds the metrics of smaller renders against
    area-averaged images (evaluate_scales) as its "scales" entry. skip_missing: leave out views whose image has gone
    missing (see load_scene)."""
    from .evaluate import LPIPS_CONVENTION, LPIPS_NET, evaluate, evaluate_scales

    run = Run(run_dir)
    target = Path(out) if out is not None else run.metrics_path
    with run.writing("splatzoo eval", target, "--out FILE.json"):
        model, scene, record = run.load(backend, skip_missing=skip_missing)
        old = run.metrics() if run.metrics_path.exists() else None
        metrics = evaluate(model, scene, backend=backend, train_seconds=(old or {}).get("train_seconds"),
                           iterations=record["train"].get("iterations"), lpips_net=lpips_net or LPIPS_NET,
                           lpips_convention=lpips_convention or LPIPS_CONVENTION)
        if scales:
            metrics["scales"] = evaluate_scales(model, scene, scales, backend=backend, lpips_net=lpips_net or LPIPS_NET,
                                                lpips_convention=lpips_convention or LPIPS_CONVENTION)
        write_json(target, metrics)
    return metrics


def render_run(run_dir, *, split: str = "test", video: bool = False, backend: str = "auto",
               frames: int = 60, out=None, skip_missing: bool = False) -> list[Path]:
    """Write the split's renders as PNG (and an orbit video, WebM) into RUN/renders (or the folder `out`: the run
    is then only read); returns the written paths."""
    _check_split(split)
    run = Run(run_dir)
    folder = Path(out) if out is not None else run.renders_dir
    with run.writing("splatzoo render", folder, "--out FOLDER"):
        model, scene, _ = run.load(backend, skip_missing=skip_missing)
        return _render_views(model, scene, folder, split=split, video=video, backend=backend, frames=frames)


def _check_split(split: str) -> None:
    if split not in ("test", "train"):
        raise SplatzooError(f"unknown split {split!r}; use test or train")


def _render_views(model, scene, folder: Path, *, split: str, video: bool, backend: str, frames: int) -> list[Path]:
    """The split's renders as PNG in `folder` and, with `video`, an orbit of the training cameras as WebM."""
    from .evaluate import orbit_cameras, resolve_backend, save_test_renders, write_video

    paths = save_test_renders(model, scene, folder, backend=backend, split=split)
    if video:
        cams = orbit_cameras([v.camera for v in scene.train], frames)
        paths.append(write_video(model, cams, scene.background, folder / "orbit.webm",
                                 backend=resolve_backend(backend, next(model.parameters()).device)))
    return paths


# --- model files (.ply, .pt) with a dataset named on the command line --------------------------------------------

def _file_and_scene(path, data, backend: str, scene_options: dict | None):
    """(model on the backend's device, scene) of a model file and the dataset it is scored or rendered on."""
    from .data import load_scene
    from .rasterizers import select_backend

    if data is None:
        how = "splatzoo.load_ply" if Path(path).suffix.lower() == ".ply" else "splatzoo.load_model"
        raise SplatzooError(f"{path} is a model file, not a run folder: it records no dataset, so pass the one to use "
                            f"with --data DATA (in Python, {how} reads it)")
    model = open_model(path).model
    scene = load_scene(data, **(scene_options or {}))
    check_fits_scene(model, scene, str(path))
    return model.to(select_backend(backend).torch_device()), scene


def evaluate_file(path, data, *, backend: str = "auto", lpips_net: str | None = None,
                  lpips_convention: str | None = None, scales=(), out=None, scene_options: dict | None = None) -> dict:
    """Evaluate the model file `path` (.ply or .pt) on the test views of the dataset `data`; the metrics are
    returned, and written to the JSON file `out` when given."""
    from .evaluate import LPIPS_CONVENTION, LPIPS_NET, evaluate, evaluate_scales

    model, scene = _file_and_scene(path, data, backend, scene_options)
    metrics = evaluate(model, scene, backend=backend, lpips_net=lpips_net or LPIPS_NET,
                       lpips_convention=lpips_convention or LPIPS_CONVENTION)
    if scales:
        metrics["scales"] = evaluate_scales(model, scene, scales, backend=backend, lpips_net=lpips_net or LPIPS_NET,
                                            lpips_convention=lpips_convention or LPIPS_CONVENTION)
    if out is not None:
        write_json(out, metrics)
    return metrics


def render_file(path, data, *, split: str = "test", video: bool = False, backend: str = "auto", frames: int = 60,
                out=None, scene_options: dict | None = None) -> list[Path]:
    """Render the model file `path` (.ply or .pt) from the split's views of the dataset `data` into the folder `out`
    (default: <file name>_renders beside the file); returns the written paths."""
    _check_split(split)
    path = Path(path)
    model, scene = _file_and_scene(path, data, backend, scene_options)
    folder = Path(out) if out is not None else path.parent / f"{path.stem}_renders"
    return _render_views(model, scene, folder, split=split, video=video, backend=backend, frames=frames)
