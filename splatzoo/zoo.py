"""The model zoo API: list, create, save and load models by name."""
from __future__ import annotations

import contextlib
import dataclasses
import math
import typing
import warnings
from pathlib import Path

import torch

from .errors import SplatzooError
from .io import atomic_path, read_torch, torch_save
from .model_checks import drawing_problem, repair_geometry
from .models.base import ModelOptionError, RenderSettings, SplatModel
from .options import option_value
from .packing import PRECISIONS
from .registry import MODELS, ModelSpec

_MODEL_FILE_FIX = "pass a .pt or .szp file written by splatzoo (run/model.pt, run/model.szp or run/checkpoint.pt)"


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
        values[k] = option_value(f"model {name!r}", k, hints.get(k), v, known[k].default, error=ModelOptionError)
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
    """Write the model (name, resolved config, parameters) atomically: a packed file at the model's precision when
    the name ends in .szp (splatzoo.packing), else a torch file of float32 values."""
    from .packing import SUFFIX, pack_checkpoint

    if Path(path).suffix == SUFFIX:
        data = pack_checkpoint(model.checkpoint(), model.precision)
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
    else:
        torch_save(model.checkpoint(), path)


def stored_bytes(model: SplatModel, precision: str | None = None) -> int:
    """The size of the model's packed file at `precision` (default: its own): what the model costs to store."""
    from .packing import pack_checkpoint

    return len(pack_checkpoint(model.checkpoint(), precision or model.precision))


def plain_stored_bytes(name: str, count: int, precision: str, render_settings=None, **options) -> int:
    """The smallest stored size of model `name` (with `options`) holding `count` primitives: as created, less what it
    can shed under a byte budget without losing primitives (SplatModel.shed_richness: adaptive waves), with
    `render_settings` (its file records them too)."""
    return stored_bytes(plain_model(name, count, render_settings, **options), precision)


def plain_model(name: str, count: int, render_settings=None, **options) -> SplatModel:
    """Model `name` (with `options`, `render_settings`) of `count` primitives, with all it can shed under a byte
    budget without losing primitives shed (SplatModel.shed_richness). Its values are drawn from -1, -0.5, 0, 0.5 and 1,
    so that its file stores column ranges as a trained model's does at every count (packing: half floats at 8 bits,
    which a model's starting values, far from zero against their spread, or two rows a hair apart, may not allow)."""
    g = torch.Generator().manual_seed(0)
    model = create_model(name, torch.rand(count, 3, generator=g), torch.full((count, 3), 0.5), **options)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randint(-2, 3, p.shape, generator=g).to(p.dtype) / 2)
    if render_settings is not None:
        model.set_render_settings(render_settings)
    return model.shed_richness()


# plain_fit_count settles on the exact count up to this many primitives; above it, the estimate from a row's exact
# cost is within one primitive of it (only the header's digits vary), and each check builds and packs a model that
# large (a million 2dgs surfels: 8 s and 460 MB; `compare --budgets 200MB` holds twelve million)
EXACT_FIT_UP_TO = 50_000


def plain_fit_count(name: str, budget: int, precision: str, render_settings=None, **options) -> int:
    """The most primitives of model `name` (with `options`, `render_settings`) whose plain packed file at `precision`
    (plain_stored_bytes) fits in `budget` bytes, the file's fixed bytes included; 0 if not one."""
    def cost(count: int) -> int:
        return plain_stored_bytes(name, count, precision, render_settings, **options)

    if cost(1) > budget:
        return 0
    like = plain_model(name, 1000, render_settings, **options)
    # a row's exact cost, a fraction of a byte where rows store bits (beta-gabor's 17.125 at 8 bits): from whole bytes
    # the estimate starts high by a row in 137 and settles down one model build at a time (500 kB: 23 s)
    per = float(like.stored_row_bytes(precision).mean())
    if per <= 0:  # a plugin whose primitives store nothing per row: no budget bounds its count
        raise SplatzooError(f"{name}: its primitives store no bytes of their own at {precision}, so a size budget "
                            "cannot choose how many to train; give the count (--num-primitives) instead")
    n = max(0, 1000 + math.floor((budget - stored_bytes(like, precision)) / per))
    if n > EXACT_FIT_UP_TO:
        return n
    # the compressed header changes by a few bytes with n: settle on the exact count
    while n > 0 and cost(n) > budget:
        n -= 1
    while cost(n + 1) <= budget:
        n += 1
    return n


@contextlib.contextmanager
def stored_values(model: SplatModel, precision: str):
    """Inside the block the model's parameters hold the values its packed file at `precision` loads back as; after
    it, the values they held before (edits made to them inside are lost). A gradient taken inside is the gradient at
    the stored values, applied afterwards to the full-precision ones: quantisation-aware training with the
    straight-through estimator."""
    stored = dict(stored_copy(model, precision).named_parameters())
    params = dict(model.named_parameters())
    if any(stored[k].shape != p.shape for k, p in params.items()):
        raise SplatzooError(f"{model.name}: its stored layout does not load back in the shape it trains in; it cannot "
                            f"be trained at precision {precision}")
    kept = {k: p.data for k, p in params.items()}
    for k, p in params.items():
        p.data = stored[k].data
    try:
        yield model
    finally:
        for k, p in params.items():
            p.data = kept[k]


def stored_copy(model: SplatModel, precision: str) -> SplatModel:
    """The model as its packed file at `precision` loads back (a new model; `precision` recorded in it)."""
    from .packing import check_precision, quantise_state

    ck = model.checkpoint()
    ck["state"] = quantise_state(ck["state"], check_precision(precision))
    ck["precision"] = precision
    return model_from_checkpoint(ck).to(next(model.parameters()).device)


# --- loading ----------------------------------------------------------------------------------------------------

_CONFIG_TYPES = {bool: (bool,), int: (int,), float: (int, float), str: (str,)}


def stored_config(name: str, config: dict) -> dict:
    """A config as a file recorded it (checkpoint, PLY header, run record), with the options added since filled in
    with what the file meant: a config class lists them in `stored_defaults` (where that differs from today's
    default). Anything that is not a model name and a dict is returned as it is, for the caller to refuse."""
    try:
        spec = MODELS.get(name) if isinstance(name, str) else None
    except SplatzooError:
        return config
    if spec is None or not isinstance(config, dict):
        return config
    return {**getattr(spec.config_cls, "stored_defaults", {}), **config}


def _check_config(name: str, config_cls, config: dict, fail) -> None:
    """Checkpoint configs were written by dataclasses.asdict: every value already has its field's type."""
    known = {f.name for f in dataclasses.fields(config_cls)}
    unknown = [k for k in config if k not in known]
    if unknown:
        raise fail(f"its config has option(s) {_brief(', '.join(map(repr, unknown)))} that model {name!r} does not "
                   f"have (its options: {', '.join(sorted(known)) or 'none'})")
    hints = typing.get_type_hints(config_cls)
    for k, v in config.items():
        allowed = _CONFIG_TYPES.get(hints.get(k))
        if allowed and (not isinstance(v, allowed) or (isinstance(v, bool) and bool not in allowed)):
            raise fail(f"config option {k} of model {name!r} must be {hints[k].__name__}, got {_brief(repr(v))}")
        if hints.get(k) is float and isinstance(v, int) and abs(v) > 1e308:  # no float holds it
            raise fail(f"config option {k} of model {name!r} is {_brief(repr(v), 60)}, too large for a float")


def _brief(x, limit: int = 200) -> str:
    """First line of str(x), shortened: crafted files can hold huge values, and messages stay one line."""
    text = (str(x).strip().splitlines() or [""])[0]
    return text if len(text) <= limit else text[:limit] + " ..."


def _shapes(model: SplatModel) -> dict[str, tuple[int, ...]]:
    """Shapes of what a checkpoint restores: the stored state and the per-primitive tensors."""
    tensors = {**model.state_dict(), **model.per_primitive()}
    return {k: tuple(v.shape) for k, v in tensors.items()}


def _check_shapes(name: str, expected: dict, tensors: dict, variable: set, fail) -> None:
    """`expected` is from the model built with 0 primitives: a first dimension of 0 marks a per-primitive tensor,
    whose rows must agree across tensors and whose trailing shape is fixed (but for pruned-width ones)."""
    rows = {}
    for k, ref in expected.items():
        if k not in tensors:
            continue
        shape = tuple(tensors[k].shape)
        if ref and ref[0] == 0:
            same = len(shape) == len(ref) and (shape[1:] == ref[1:] or k in variable)
            if not same:
                raise fail(f"{k} has shape {list(shape)} but model {name!r} expects "
                     f"[N{''.join(f', {d}' for d in ref[1:])}] (N primitives)")
            rows[k] = shape[0]
        elif shape != ref:
            raise fail(f"{k} has shape {list(shape)} but model {name!r} expects {list(ref)}")
    if len(set(rows.values())) > 1:
        counts = ", ".join(f"{k}: {n}" for k, n in rows.items())
        raise fail(f"its per-primitive parameters disagree on the number of primitives ({counts})")


def _model_from_checkpoint(ckpt, where: str, fix: str) -> SplatModel:
    """model_from_checkpoint with errors that say where the checkpoint came from (`where`) and what to do (`fix`)."""
    def fail(problem: str) -> SplatzooError:
        return SplatzooError(f"{where}: {problem}; {fix}")

    if not isinstance(ckpt, dict):
        raise fail(f"expected a splatzoo model (a dict with 'model', 'config' and 'state'), found "
                   f"a {type(ckpt).__name__}")
    missing = [k for k in ("model", "config", "state") if k not in ckpt]
    if missing:
        raise fail(f"not a splatzoo model: no {', '.join(map(repr, missing))} entry")
    name, config, state = ckpt["model"], ckpt["config"], ckpt["state"]
    if not isinstance(name, str) or not isinstance(config, dict) or not isinstance(state, dict):
        raise fail("not a splatzoo model: 'model' must be a name, 'config' and 'state' dicts")
    config = stored_config(name, config)
    settings, precision = _stored_settings(ckpt, fail)
    try:
        spec = MODELS.get(name)
    except SplatzooError as e:  # unknown or broken plugin model: the registry's message, located
        raise type(e)(f"{where}: {e}") from None
    _check_config(name, spec.config_cls, config, fail)
    try:
        model = spec.cls(spec.config_cls(**config), 0)
    except (SplatzooError, TypeError, ValueError, RuntimeError) as e:
        raise fail(f"its config {_brief(config)} is not valid for model {name!r} ({_brief(e)})") from None
    state = _checked_state(model, state, name, config, fail)
    expected = _shapes(model)
    variable = set(getattr(model, "variable_width", ()))
    if not _own_layout(model, state, name, config, fail):
        _check_shapes(name, expected, state, variable, fail)
    try:
        model.load_checkpoint_state(state)
    except (TypeError, KeyError, ValueError, RuntimeError, IndexError, OverflowError) as e:  # Overflow: a count of 3e38
        raise fail(f"its state does not fit model {name!r} with config {_brief(config)} "
                   f"({type(e).__name__}: {_brief(e)})") from None
    _check_shapes(name, expected, {**model.state_dict(), **model.per_primitive()}, variable, fail)
    empty = drawing_problem(model)
    if empty:
        raise fail(empty)
    _check_drawable(model, fail)
    model.name = name
    model.set_render_settings(settings)
    model.precision = precision
    return model


def _stored_settings(ckpt: dict, fail) -> tuple[RenderSettings, str]:
    """(render settings, precision) a checkpoint records; absent entries mean what they meant before they existed
    (no filter, black, float32)."""
    antialias = ckpt.get("antialias", False)
    if not isinstance(antialias, bool):
        raise fail(f"'antialias' must be true or false, found {_brief(antialias)}")
    precision = ckpt.get("precision", "float32")
    if precision not in PRECISIONS:
        raise fail(f"'precision' must be one of {', '.join(PRECISIONS)}, found {_brief(precision)}")
    background = ckpt.get("background")
    if background is not None:
        ok = isinstance(background, (list, tuple)) and len(background) == 3 and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in background)
        if not ok:
            raise fail(f"'background' must be a colour of 3 finite numbers, found {_brief(background)}")
        background = tuple(float(c) for c in background)
    return RenderSettings(antialias, background), precision


def _checked_state(model: SplatModel, state: dict, name: str, config: dict, fail) -> dict:
    """The checkpoint's state with floating tensors as float32, each entry a dense finite tensor with data and every
    parameter of `model` (built with 0 primitives) present."""
    params = dict(model.named_parameters())
    # the zoo's models compute in float32: another floating type (a file saved in half or double precision, or
    # edited) is read as float32 values, and a double beyond float32's range becomes infinite, refused below
    state = {k: v.float() if isinstance(v, torch.Tensor) and v.is_floating_point() and v.dtype != torch.float32
             and v.layout == torch.strided and v.device.type == "cpu" else v for k, v in state.items()}
    for k, v in state.items():
        if not isinstance(k, str) or not isinstance(v, torch.Tensor) or v.layout != torch.strided:
            raise fail(f"state entry {k!r} is a {type(v).__name__}, not a dense tensor")
        if v.device.type != "cpu":  # read with map_location="cpu": only a meta tensor (no data) is left elsewhere
            raise fail(f"state entry {k!r} holds no data (a {v.device.type} tensor)")
        if k in params and not v.is_floating_point():
            raise fail(f"parameter {k} holds {v.dtype} values; parameters are floating point")
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            bad = int((~torch.isfinite(v)).sum())
            raise fail(f"{k} has {bad} non-finite (NaN or inf) value(s): the run diverged or the file is damaged")
    lacking = [k for k in params if k not in state]
    if lacking:
        raise fail(f"its state lacks parameter(s) {', '.join(lacking)} of model {name!r} with config {_brief(config)}")
    return state


def _own_layout(model: SplatModel, state: dict, name: str, config: dict, fail) -> bool:
    """Whether `state` is in a layout the model's own checkpoint() writes (e.g. packed waves: then its loader checks
    the rest); its entries must be the model's either way."""
    stored = model.state_dict()
    try:  # entries the model's own checkpoint() adds (e.g. packed waves): then its loader checks the layout
        own_format = set(model.checkpoint()["state"]) - set(stored)
    except Exception:
        own_format = set()
    own_format |= set(getattr(model, "legacy_state_keys", ()))  # what older files of the layout hold
    packed = bool(own_format & set(state))
    extra = [k for k in state if k not in stored and not (packed and k in own_format)]
    absent = [] if packed else [k for k in stored if k not in state]  # a packed layout's loader checks the rest
    if extra or absent:
        problems = ([f"unexpected {', '.join(extra)}"] if extra else []) + (
            [f"missing {', '.join(absent)}"] if absent else [])
        raise fail(f"its state does not match model {name!r} with config {_brief(config)}: {'; '.join(problems)}")
    return packed


def _check_drawable(model: SplatModel, fail) -> None:
    """The surfels the model hands the rasterizer, for one camera looking at it, lie in the field table's ranges
    (values no loader check names, e.g. a quaternion of 3e38, would otherwise be refused at the first render)."""
    from .errors import ShapeError
    from .types import Camera

    means = model.per_primitive().get("means")
    if means is None or means.shape[0] == 0:
        return
    centre = means.detach().double().mean(0)
    camera = Camera.look_at(centre + torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), centre, width=8, height=8,
                            dtype=torch.float32)
    try:
        with torch.no_grad():
            model.surfels(camera).validate()
    except ShapeError as e:
        raise fail(f"its surfels cannot be drawn: {e}") from None


def model_from_checkpoint(ckpt: dict) -> SplatModel:
    """The model stored by SplatModel.checkpoint() (as save_model and training write it), checked entry by entry:
    a damaged or crafted checkpoint is a SplatzooError, not a model that fails later."""
    return _model_from_checkpoint(ckpt, "model checkpoint",
                                  "use a checkpoint written by splatzoo (save_model or training)")


def load_model(path) -> SplatModel:
    """Load a model written by save_model (or the "model" entry of a training checkpoint). The file is read with
    weights_only: a crafted file cannot run code, it is refused. So is a model that draws nothing (0 surfels, every
    opacity or scale at nothing: splatzoo.model_checks); what the rasterizer would change silently (a zero quaternion,
    a log-scale beyond the largest size drawn) is a warning with its count."""
    from .packing import SUFFIX, is_packed, read_packed

    path = Path(path)
    if path.suffix == SUFFIX or is_packed(path):
        where = f"packed model {path}"
        model = _model_from_checkpoint(read_packed(path), where, _MODEL_FILE_FIX)
    else:
        ckpt = read_torch(path, "model file", _MODEL_FILE_FIX)
        if isinstance(ckpt, dict) and "state" not in ckpt and isinstance(ckpt.get("model"), dict):
            ckpt = ckpt["model"]  # a training checkpoint: the model is one entry of it
        where = f"model file {path}"
        model = _model_from_checkpoint(ckpt, where, _MODEL_FILE_FIX)
    for note in repair_geometry(model):
        warnings.warn(f"{where}: {note}", UserWarning, stacklevel=2)
    return model
