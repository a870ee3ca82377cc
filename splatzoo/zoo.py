"""The model zoo API: list, create, save and load models by name."""
from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import torch

from .errors import SplatzooError
from .io import torch_save
from .models.base import ModelOptionError, SplatModel
from .registry import MODELS, ModelSpec


def list_models() -> list[str]:
    """Names of every model: built-ins and installed plugins (plugins are not imported)."""
    return MODELS.names()


def get_model_spec(name: str) -> ModelSpec:
    return MODELS.get(name)


def make_config(name: str, **options):
    """The model's config dataclass with `options` applied; unset options keep their defaults."""
    spec = MODELS.get(name)
    known = {f.name: f for f in dataclasses.fields(spec.config_cls)}
    unknown = [k for k in options if k not in known]
    if unknown:
        raise ModelOptionError(f"model {name!r} has no option(s) {', '.join(unknown)}; its options are: "
                               f"{', '.join(known) or 'none'}")
    hints = typing.get_type_hints(spec.config_cls)
    values = {}
    for k, v in options.items():
        if v is None:
            continue
        typ = hints.get(k)
        try:
            values[k] = typ(v) if typ in (int, float, str) and not isinstance(v, bool) else v
        except (TypeError, ValueError) as e:
            raise ModelOptionError(f"model {name!r}: option {k} expects {typ.__name__}, got {v!r}") from e
    return spec.config_cls(**values)


def create_model(name: str, points=None, colors=None, *, seed: int = 0, **options) -> SplatModel:
    """Create model `name` with `options` (config fields). With `points` [N,3] and `colors` [N,3] in [0,1]
    (or 0..255) it is initialised from that point cloud; otherwise it has no primitives yet."""
    spec = MODELS.get(name)
    config = make_config(name, **options)
    if points is None:
        model = spec.cls(config, 0)
    else:
        if colors is None:
            colors = torch.full_like(torch.as_tensor(points, dtype=torch.float32), 0.5)
        model = spec.cls.from_points(config, points, colors, seed=seed)
    model.name = name
    return model


def save_model(model: SplatModel, path) -> None:
    """Write the model (name, resolved config, parameters) atomically."""
    torch_save(model.checkpoint(), path)


def model_from_checkpoint(ckpt: dict) -> SplatModel:
    spec = MODELS.get(ckpt["model"])
    config = spec.config_cls(**ckpt["config"])
    state = ckpt["state"]
    model = spec.cls(config, 0)
    model.load_checkpoint_state(state)
    model.name = ckpt["model"]
    return model


def load_model(path) -> SplatModel:
    """Load a model written by save_model (or the "model" entry of a training checkpoint)."""
    path = Path(path)
    if not path.is_file():
        raise SplatzooError(f"no model file at {path}; pass the path of a .pt file written by splatzoo")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise SplatzooError(f"cannot read model file {path}: {e}. Is it a splatzoo checkpoint?") from e
    if isinstance(ckpt, dict) and "state" not in ckpt and isinstance(ckpt.get("model"), dict):
        ckpt = ckpt["model"]  # a training checkpoint: the model is one entry of it
    if not isinstance(ckpt, dict) or "state" not in ckpt:
        raise SplatzooError(f"{path} is not a splatzoo model file (no 'state' entry)")
    return model_from_checkpoint(ckpt)
