"""The models in ns-train's output folders: `read_nerfstudio_output(folder)`, with no nerfstudio needed.

`ns-train splatzoo-<member>` writes OUTPUT/<experiment>/splatzoo-<member>/<timestamp>/ holding config.yml and
nerfstudio_models/step-<step>.ckpt. Each checkpoint keeps splatzoo's whole training state (the model as
`SplatModel.checkpoint()` writes it, Adam, densification statistics, generator, schedule: training_state) as the
model's extra state, `pipeline["_model._extra_state"]`; the model is read from it, with splatzoo's own checks.
"""
from __future__ import annotations

import re
from pathlib import Path

from ...errors import SplatzooError

STATE_FORMAT = "splatzoo-nerfstudio"   # the extra state's "format" (training_state); its "version":
STATE_VERSION = 1
METHOD_PREFIX = "splatzoo-"            # every method of this package is named splatzoo-<member>
_CHECKPOINT = re.compile(r"^step-(\d+)\.ckpt$")
_METHOD = re.compile(r"^method_name: *['\"]?([^'\"\n]*)['\"]? *$", re.MULTILINE)


def _is_output(folder: Path) -> bool:
    return (folder / "config.yml").is_file() and (folder / "nerfstudio_models").is_dir()


def is_nerfstudio_output(path) -> bool:
    """Whether `path` is a folder ns-train wrote (config.yml and nerfstudio_models/), or one whose runs are in
    its subfolders (the method folder holding <timestamp>/ folders): cheap, by file names only."""
    path = Path(path)
    try:
        if not path.is_dir():
            return False
        return _is_output(path) or any(_is_output(p) for p in path.iterdir() if p.is_dir())
    except OSError:
        return False


def checkpoints(folder) -> list[Path]:
    """The step-<step>.ckpt files of an output folder, by step."""
    models = Path(folder) / "nerfstudio_models"
    found = [(int(m.group(1)), p) for p in models.iterdir() if (m := _CHECKPOINT.match(p.name)) and p.is_file()]
    return [p for _, p in sorted(found)]


def _output_folder(path: Path) -> tuple[Path, str]:
    """(the output folder to read, a note): `path` itself, or the newest of the runs in its subfolders."""
    if _is_output(path):
        return path, ""
    runs = sorted((p for p in path.iterdir() if p.is_dir() and _is_output(p)), key=lambda p: p.name)
    if not runs:
        raise SplatzooError(f"{path} is not an ns-train output folder: it holds no config.yml and "
                            "nerfstudio_models/ (pass the folder ns-train printed, outputs/<name>/<method>/<timestamp>)")
    note = f"the newest of {len(runs)} runs in {path}: {runs[-1].name}" if len(runs) > 1 else ""
    return runs[-1], note


def method_name(folder) -> str | None:
    """The method_name that config.yml records (read as text: the file names nerfstudio's classes)."""
    try:
        text = (Path(folder) / "config.yml").read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise SplatzooError(f"{folder}/config.yml cannot be read ({e.strerror or e})") from None
    m = _METHOD.search(text)
    return m.group(1).strip() if m else None


def training_state(checkpoint: dict, train: dict, state: dict | None) -> dict:
    """What a splatzoo method keeps in nerfstudio's checkpoint (the model's extra state): the model as
    `SplatModel.checkpoint()` writes it, the run's TrainConfig as a dict (its "iterations": the schedule's length) and
    `Trainer.state_dict()` less its "model" entry (Adam, densification statistics, generator, "iteration"), or None
    before the first step."""
    return {"format": STATE_FORMAT, "version": STATE_VERSION, "model": checkpoint, "train": train, "state": state}


def extra_state(pipeline: dict, where) -> dict:
    """splatzoo's state in a checkpoint's pipeline state dict (under DDP's "module." prefix too), checked for its
    format."""
    state = pipeline.get("_model._extra_state", pipeline.get("_model.module._extra_state"))
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        raise SplatzooError(f"{where} holds no splatzoo model (it was not written by an ns-train splatzoo-<member> "
                            "method)")
    if state.get("version") != STATE_VERSION:
        raise SplatzooError(f"{where} holds splatzoo state of version {state.get('version')!r}, and this splatzoo "
                            f"reads version {STATE_VERSION}; read it with the splatzoo that wrote it")
    if not isinstance(state.get("model"), dict):
        raise SplatzooError(f"{where}: its splatzoo state has no model")
    return state


def load_checkpoint(path) -> dict:
    """A nerfstudio checkpoint read safely (weights_only: a crafted file cannot run code) onto the CPU."""
    import pickle

    import torch

    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError, OSError) as e:
        raise SplatzooError(f"{path} cannot be read as a nerfstudio checkpoint ({type(e).__name__}: "
                            f"{str(e).splitlines()[0][:200] if str(e) else ''}); it is damaged or not a "
                            "checkpoint") from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("pipeline"), dict):
        raise SplatzooError(f"{path} is not a nerfstudio checkpoint (no pipeline state)")
    return ckpt


def model_of_state(state: dict, where):
    """The splatzoo model of a checkpoint's splatzoo state: at its storage precision once the schedule is done
    (as `splatzoo train` leaves model.pt), else as trained so far."""
    from ...zoo import model_from_checkpoint, stored_copy

    try:
        model = model_from_checkpoint(state["model"])
    except SplatzooError as e:
        raise type(e)(f"{where}: {e}") from None
    train = state.get("train") or {}
    store = train.get("store", "float32")
    progress = state.get("state") or {}
    finished = progress.get("iteration") is not None and progress.get("iteration") == train.get("iterations")
    if store != "float32" and finished:
        model.precision = store
        model = stored_copy(model, store)
    return model


def open_nerfstudio_output(path, *, latest: bool = False):
    """(model, the checkpoint read, a note) of an ns-train output folder: model_files' folder-format reader. Its
    newest checkpoint is read; a run stopped before the end of its schedule is read too, and the note says so
    (`latest` changes nothing: ns-train keeps no other model than its checkpoints)."""
    path = Path(path)
    folder, note = _output_folder(path)
    method = method_name(folder)
    if method is None or not method.startswith(METHOD_PREFIX):
        raise SplatzooError(f"{folder} was written by nerfstudio's method {method or '(unknown)'}, not by a splatzoo "
                            f"method; splatzoo reads the outputs of `ns-train {METHOD_PREFIX}<member>`")
    found = checkpoints(folder)
    if not found:
        raise SplatzooError(f"{folder} holds no checkpoint yet (nerfstudio_models/ has no step-*.ckpt): let ns-train "
                            "save one (it saves every --steps-per-save steps and at the end)")
    ckpt_path = found[-1]
    state = extra_state(load_checkpoint(ckpt_path)["pipeline"], ckpt_path)
    model = model_of_state(state, ckpt_path)
    done, total = (state.get("state") or {}).get("iteration"), (state.get("train") or {}).get("iterations")
    if isinstance(done, int) and isinstance(total, int) and done < total:
        note = "; ".join(filter(None, [note, f"unfinished: iteration {done} of {total}"]))
    return model, ckpt_path, note


def read_nerfstudio_output(folder):
    """The splatzoo model that `ns-train splatzoo-<member>` wrote into `folder` (the folder with config.yml and
    nerfstudio_models/, or its method folder: then its newest run), from its newest checkpoint."""
    return open_nerfstudio_output(folder)[0]
