"""Model export to binary PLY, the point-cloud layout that 3DGS/2DGS tools read, and back.

One vertex per primitive, float32 properties, little endian:
  x, y, z                      position (`means`)
  nx, ny, nz                   surfel normal (third column of the rotation), for viewers; not read back
  f_dc_0..2                    SH DC colour; for models without SH a preview of the mean colour, not read back
  f_rest_*                     higher SH bands, channel-major as 3DGS writes them (all R, then G, then B)
  opacity                      logit
  scale_0, scale_1             log sigma (2DGS: two scales)
  rot_0..3                     quaternion (w, x, y, z), unnormalised as trained
  gabor_color_base_0..2, gabor_color_diff_0..2 (or, for --color-param paper, gabor_color_a_0..2, gabor_color_b_0..2),
  gabor_weight_*, gabor_freq_*, gabor_phase_*   Gabor-family colour and waves
  <param>_<i>                  any other per-primitive parameter of a plugin, flattened row-major
Header comments name the splatzoo model and its config (`comment splatzoo model gabor`,
`comment splatzoo config {"n_waves": 4}`), and `comment splatzoo antialias true` a model trained and rendered with
the pixel-footprint filter, so `load_ply` rebuilds the same model. Parameters are stored exactly
(float32 as trained), so a round trip renders identically. A PLY without those comments (written by 2DGS itself)
loads as a `2dgs` model whose SH degree follows from the number of f_rest properties.

numpy only: no plyfile dependency.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import torch

from .errors import SplatzooError
from .io import atomic_path, ply_type_name, read_ply_vertices

FORMAT_VERSION = 1

# parameter name -> property prefix (or explicit names) of the standard layouts
_FIXED = {"means": ["x", "y", "z"], "logit_opacity": ["opacity"]}
_PREFIX = {"log_scales": "scale_", "quats": "rot_", "sh_dc": "f_dc_", "sh_rest": "f_rest_",
           "color_a": "gabor_color_a_", "color_b": "gabor_color_b_", "color_base": "gabor_color_base_",
           "color_diff": "gabor_color_diff_", "wave_weights": "gabor_weight_",
           "wave_freqs": "gabor_freq_", "wave_phases": "gabor_phase_"}
_CHANNEL_MAJOR = {"sh_rest"}          # 3DGS stores SH bands transposed: [N, 3, bands]
_DERIVED = ("nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")  # written for viewers, recomputed on load

def _property_names(name: str, trailing: tuple[int, ...]) -> list[str]:
    """The PLY property names of a per-primitive parameter with shape [N, *trailing]."""
    if name in _FIXED:
        return list(_FIXED[name])
    count = int(np.prod(trailing)) if trailing else 1
    prefix = _PREFIX.get(name, re.sub(r"[^A-Za-z0-9_]", "_", name) + "_")
    if not trailing and name not in _PREFIX:
        return [prefix[:-1]]
    return [f"{prefix}{i}" for i in range(count)]


def _to_columns(name: str, value: torch.Tensor) -> np.ndarray:
    """[N, *trailing] -> [N, count] in property order."""
    a = value.detach().cpu().float().numpy()
    if name in _CHANNEL_MAJOR and a.ndim == 3:
        a = a.transpose(0, 2, 1)
    return np.ascontiguousarray(a).reshape(a.shape[0], -1)


def _from_columns(name: str, columns: np.ndarray, trailing: tuple[int, ...]) -> torch.Tensor:
    n = columns.shape[0]
    if name in _CHANNEL_MAJOR and len(trailing) == 2:
        a = columns.reshape(n, trailing[1], trailing[0]).transpose(0, 2, 1)
    else:
        a = columns.reshape((n,) + tuple(trailing))
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))


def _exportable_parameters(model) -> dict[str, torch.Tensor]:
    """Per-primitive parameters by name; a clear error for what a per-vertex PLY cannot hold."""
    model_name = getattr(model, "name", "") or type(model).__name__
    params = dict(model.named_parameters())
    per = model.per_primitive() if hasattr(model, "per_primitive") else params
    if "means" not in per or tuple(per["means"].shape[1:]) != (3,):
        raise SplatzooError(f"cannot export model {model_name!r} to PLY: it has no per-primitive `means` [N,3] "
                            "parameter to use as vertex positions. Save it with splatzoo.save_model (.pt) instead")
    n = per["means"].shape[0]
    shared = [k for k in params if k not in per] + [k for k, v in per.items() if v.dim() == 0 or v.shape[0] != n]
    buffers = [k for k in model.state_dict() if k not in params and k not in per]  # model-wide persistent state
    if shared or buffers:
        raise SplatzooError(f"cannot export model {model_name!r} to PLY: {', '.join(sorted(set(shared + buffers)))} "
                            f"{'is' if len(set(shared + buffers)) == 1 else 'are'} not per-primitive (a PLY stores one "
                            "vertex per primitive). Save it with splatzoo.save_model (.pt) instead")
    return per


def _surfel_normals(per: dict[str, torch.Tensor]) -> np.ndarray:
    q = per.get("quats")
    if q is None or tuple(q.shape[1:]) != (4,):
        return np.zeros((per["means"].shape[0], 3), np.float32)
    from .geometry import quat_to_rotmat

    with torch.no_grad():
        return quat_to_rotmat(q.detach().float().cpu())[:, :, 2].numpy()


def _preview_dc(model, per: dict[str, torch.Tensor]) -> np.ndarray:
    """SH DC of each primitive's mean colour, so 2DGS viewers show something sensible for wave models."""
    from .geometry import rgb_to_sh0
    from .types import Camera

    n = per["means"].shape[0]
    try:
        with torch.no_grad():
            cam = Camera.look_at([0.0, 0.0, -1.0], [0.0, 0.0, 0.0], dtype=torch.float32)
            base = model.surfels(cam.to(per["means"].device)).base_color.detach().float().cpu()
        if tuple(base.shape) != (n, 3):
            raise ValueError
        return rgb_to_sh0(base.clamp(0, 1)).numpy()
    except Exception:  # a plugin's colour needs more than a camera: grey is an honest preview
        return np.zeros((n, 3), np.float32)


def _config_dict(model) -> dict:
    import dataclasses

    cfg = getattr(model, "config", None)
    return dataclasses.asdict(cfg) if cfg is not None and dataclasses.is_dataclass(cfg) else {}


def save_ply(model, path) -> Path:
    """Write `model` as a binary PLY (layout in the module docstring), atomically. Returns the path."""
    from . import __version__

    path = Path(path)
    if path.is_dir():
        raise SplatzooError(f"cannot write the PLY to {path}: it is a folder; give a file name such as {path / 'model.ply'}")
    per = _exportable_parameters(model)
    name = getattr(model, "name", "")
    if not name:
        raise SplatzooError(f"cannot export a {type(model).__name__} without a registry name; create it with "
                            "splatzoo.create_model so that load_ply can rebuild it")
    n = per["means"].shape[0]
    columns: dict[str, np.ndarray] = {"x": None, "y": None, "z": None}  # order: 3DGS layout first
    normals = _surfel_normals(per)
    columns.update({"nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2]})
    if "sh_dc" not in per:
        dc = _preview_dc(model, per)
        columns.update({f"f_dc_{i}": dc[:, i] for i in range(3)})
    order = ["means", "sh_dc", "sh_rest", "logit_opacity", "log_scales", "quats"]
    order += [k for k in per if k not in order]
    for pname in order:
        if pname not in per:
            continue
        value = per[pname]
        props = _property_names(pname, tuple(value.shape[1:]))
        cols = _to_columns(pname, value)
        if cols.shape[1] != len(props):
            raise SplatzooError(f"parameter {pname!r} of shape {list(value.shape)} does not fit the PLY layout")
        for i, prop in enumerate(props):
            if prop in columns and columns[prop] is not None and prop not in _DERIVED:
                raise SplatzooError(f"cannot export model {name!r}: parameters map to the PLY property {prop!r} twice; "
                                    "rename the plugin parameter")
            columns[prop] = cols[:, i]
    arr = np.empty(n, dtype=[(k, "<f4") for k in columns])
    for k, v in columns.items():
        arr[k] = v
    header = ["ply", "format binary_little_endian 1.0",
              f"comment splatzoo {__version__} ply export, format {FORMAT_VERSION}",
              f"comment splatzoo model {name}",
              f"comment splatzoo config {json.dumps(_config_dict(model), separators=(',', ':'), default=str)}"]
    if getattr(model, "antialias", False):  # rendered with the pixel-footprint filter (absent: without)
        header.append("comment splatzoo antialias true")
    header.append(f"element vertex {n}")
    header += [f"property float {k}" for k in columns]
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(arr.tobytes())
    return path


# --- reading ------------------------------------------------------------------------------------------------

def _infer_2dgs(names: list[str], path) -> tuple[str, dict]:
    if "scale_2" in names:
        raise SplatzooError(f"{path} looks like a 3DGS PLY (three scales); splatzoo models are 2D surfels with two "
                            "(scale_0, scale_1). Only 2DGS or splatzoo PLY files can be loaded")
    rest = sum(1 for k in names if k.startswith("f_rest_"))
    degree = {0: 0, 9: 1, 24: 2, 45: 3}.get(rest)
    if degree is None:
        raise SplatzooError(f"{path}: {rest} f_rest properties match no SH degree (0, 9, 24 or 45 expected)")
    return "2dgs", {"sh_degree": degree}


def _present_width(name: str, names: list[str]) -> int:
    """How many consecutive `<prefix>0, <prefix>1, ...` properties the file has for a [N, width] parameter."""
    prefix, present, width = _property_names(name, (1,))[0][:-1], set(names), 0
    while f"{prefix}{width}" in present:
        width += 1
    return width


def _header_model(path, comments: list[str], names: list[str]) -> tuple[str, dict]:
    """(model name, config) from the `splatzoo model` / `splatzoo config` comments, or the 2DGS layout without them."""
    model_name, config = None, {}
    for c in comments:
        if c.startswith("splatzoo model "):
            model_name = c[len("splatzoo model "):].strip()
        elif c.startswith("splatzoo config "):
            try:
                config = json.loads(c[len("splatzoo config "):])
            except json.JSONDecodeError as e:
                raise SplatzooError(f"{path}: the 'splatzoo config' header comment is not valid JSON ({e}); "
                                    "export the model again") from None
            if not isinstance(config, dict):
                raise SplatzooError(f"{path}: the 'splatzoo config' header comment must be a JSON object of model "
                                    f"options, got a {type(config).__name__}; export the model again")
    if model_name is None:
        return _infer_2dgs(names, path)
    return model_name, config


def load_ply(path):
    """Rebuild the model written by `save_ply` (or a 2DGS point_cloud.ply, as a `2dgs` model). The header's model
    and config decide what is read, so each is checked against what the file holds before it sizes anything."""
    from .zoo import create_model, stored_config

    arr, comments = read_ply_vertices(path)
    names = list(arr.dtype.names)
    present = set(names)
    model_name, config = _header_model(path, comments, names)
    config = stored_config(model_name, config)
    try:
        model = create_model(model_name, **config)   # no primitives yet: it tells each parameter's trailing shape
    except SplatzooError as e:  # unknown model, bad option: the registry's or the config's own words, located
        raise type(e)(f"{path}: cannot rebuild the model its header names: {e}") from None
    except (TypeError, ValueError, RuntimeError) as e:  # a plugin's config or constructor refusing the options
        raise SplatzooError(f"{path}: model {model_name!r} refuses the header's config {str(config)[:200]} "
                            f"({type(e).__name__}: {str(e)[:200]}); export the model again") from None
    n = arr.shape[0]
    per = _exportable_parameters(model)
    new = {}
    variable = set(getattr(model, "variable_width", ()))
    for pname, empty in per.items():
        trailing = tuple(empty.shape[1:])
        if pname in variable and len(trailing) == 1:  # e.g. waves trimmed by pruning: the file tells the width
            trailing = (_present_width(pname, names),)
        needed = math.prod(trailing) if trailing else 1
        if needed > len(names):  # a crafted config (say a billion waves) must not make a billion names
            raise SplatzooError(f"{path}: parameter {pname!r} of model {model_name!r} with config {str(config)[:200]} "
                                f"needs {needed} properties but the file has {len(names)}; the header's config does "
                                "not match its data. Export the model again")
        props = _property_names(pname, trailing)
        missing = [p for p in props if p not in present]
        if missing:
            more = " ..." if len(missing) > 4 else ""
            raise SplatzooError(f"{path} lacks the properties {', '.join(missing[:4])}{more} of parameter {pname!r} "
                                f"of model {model_name!r} {config}; it was not written by "
                                "`splatzoo export` for this model (or with another config)")
        if empty.is_floating_point():
            stored = next((p for p in props if arr.dtype[p].kind != "f"), None)
            if stored is not None:  # float32 parameters written as int or uchar lose their fractions
                raise SplatzooError(f"{path}: {stored} is stored as {ply_type_name(arr.dtype[stored])} but holds a "
                                    f"float parameter ({pname!r}); the file was not written by splatzoo export or is "
                                    "damaged. Export the model again")
        cols = np.stack([arr[p].astype(np.float32) for p in props], 1) if props else np.zeros((n, 0), np.float32)
        bad = int(np.count_nonzero(~np.isfinite(cols)))
        if bad:
            raise SplatzooError(f"{path}: parameter {pname!r} has {bad} non-finite (NaN or inf) value(s) in "
                                f"{', '.join(props[:4])}{' ...' if len(props) > 4 else ''}; the run diverged or the "
                                "file is damaged. Export the model again from a run without NaN")
        if not empty.is_floating_point() and empty.dtype != torch.bool and cols.size:
            whole, info = np.array_equal(cols, np.round(cols)), torch.iinfo(empty.dtype)
            if not whole or cols.min() < info.min or cols.max() > info.max:
                raise SplatzooError(f"{path}: {pname!r} holds whole numbers (counts or indices) of {empty.dtype} but "
                                    "the file has fractions or out-of-range values there; the file is damaged. "
                                    "Export the model again")
        new[pname] = _from_columns(pname, cols, trailing)
    model.replace_parameters(new)
    model.antialias = "splatzoo antialias true" in comments
    return model


def export_run(run, out) -> Path:
    """Export the trained model of a run directory (through splatzoo.runs.Run), or a model .pt file, to the PLY
    `out`."""
    from .runs import Run
    from .zoo import load_model

    run = Path(run)
    if run.is_file():
        _check_export_target(run, Path(out))
        return save_ply(load_model(run), out)
    if not run.exists():
        raise SplatzooError(f"{run} does not exist; pass a run directory written by `splatzoo train` or a model .pt")
    r = Run(run)
    _check_export_target(r.model_path, Path(out))
    return save_ply(r.model(), out)


def _check_export_target(model_path: Path, out: Path) -> None:
    """`--out RUN/model.pt` would replace the trained model by a PLY: export writes only files named .ply, and never
    over the model it reads."""
    if out.suffix.lower() != ".ply" and not out.is_dir():  # a folder gets save_ply's own "is a folder" message
        suggestion = out.with_suffix(".ply") if out.name and out.suffix else out.parent / f"{out.name or 'model'}.ply"
        raise SplatzooError(f"export writes a PLY file, so --out must end in .ply; got {out}. Name the file e.g. "
                            f"{suggestion}")
    same = out.resolve() == model_path.resolve()
    if not same and out.exists():
        try:
            same = out.samefile(model_path)
        except OSError:
            same = False
    if same:
        raise SplatzooError(f"refusing to export onto the model being read ({model_path}); choose another --out, "
                            f"e.g. {model_path.with_suffix('.ply')}")
