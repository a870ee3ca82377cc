"""The run folder: what made a run (its config record and fingerprints), the folder's status, lock and --overwrite,
its checkpoints, log and metrics, and its trained model, which model_files opens through the run folder format
registered here.

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
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import re
import shutil
import socket
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch

from .errors import SplatzooError
from .io import read_json, read_torch, write_json
from .model_files import ModelFormat, open_model, register_format
from .training import TrainConfig

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
_PACKAGE = Path(__file__).resolve().parent  # splatzoo/, where TRAINING_CODE lies


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
    if source is not None and _PACKAGE not in source.parents:
        h.update(f"{source.name}\0".encode() + source.read_bytes())
    return h.hexdigest()[:16]


@functools.lru_cache(maxsize=None)
def _core_code_hash() -> bytes:
    """sha256 of splatzoo's TRAINING_CODE (read once a process; every model's fingerprint starts from it)."""
    package = _PACKAGE
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
            if self.checkpoint_path.exists():
                hint = f" (training was interrupted: finish it with `splatzoo train --resume --out {self.path}`)"
            elif self.replaced_path.is_dir():  # settled by the next command that takes the lock (_settle_replaced)
                hint = (f" (a run started with --overwrite stopped before its first checkpoint; the run it was to "
                        f"replace is kept in {self.replaced_path} and comes back with the next command that writes "
                        f"the folder, e.g. `splatzoo eval {self.path}`)")
            else:
                hint = ""
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
        scene = load_scene(data, **{**load_options(rec), **({"skip_missing": True} if skip_missing else {})})
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


def load_options(record: dict) -> dict:
    """The recorded scene options as load_scene arguments."""
    opts = dict(record.get("scene_options", {}))
    if isinstance(opts.get("background"), list):
        opts["background"] = tuple(opts["background"])
    return {k: v for k, v in opts.items() if v is not None}

