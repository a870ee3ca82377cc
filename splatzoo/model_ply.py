"""The PLY layout of a model: one vertex per primitive under the 3DGS property names every splat tool reads, with
splatzoo's own parameters riding along, written by `save_ply` and read back exactly by `load_ply`, which also reads
other tools' 2DGS and 3DGS PLY files as a `2dgs` model. The 3DGS layout's names (x y z, opacity, scale_*, rot_*,
f_dc_*, f_rest_*) belong to the file format and are listed here; every other per-primitive parameter is written under
the prefix its model class gives it in `ply_prefixes` (gabor's waves: gabor_weight_*, ...), else under its own name.

The layout
----------
One vertex per primitive, float32 properties, little endian, in the order of the 3DGS layout:
  x, y, z                      position (`means`)
  nx, ny, nz                   surfel normal (third column of the rotation), for viewers; not read back
  f_dc_0..2                    SH DC colour; for models without SH a preview of the mean colour, not read back
  f_rest_*                     higher SH bands, channel-major as 3DGS writes them (all R, then G, then B)
  opacity                      logit
  scale_0, scale_1, scale_2    log sigma; scale_2 is the surfel's thickness, -inf (see below); not read back
  rot_0..3                     quaternion (w, x, y, z), unnormalised as trained
  gabor_color_base_0..2, gabor_color_diff_0..2 (or, for --color-param paper, gabor_color_a_0..2, gabor_color_b_0..2),
  gabor_weight_*, gabor_freq_*, gabor_phase_*   Gabor-family colour and waves (--color-param per-wave: no
                               gabor_color_diff_*, and three gabor_weight_* a wave, its RGB amplitude, wave by wave)
  <param>_<i>                  any other per-primitive parameter of a plugin, flattened row-major
Header comments name the splatzoo model and its config (`comment splatzoo model gabor`,
`comment splatzoo config {"n_waves": 4}`), and `comment splatzoo antialias true` a model trained and rendered with
the pixel-footprint filter, so `load_ply` rebuilds the same model. Parameters are stored exactly (float32 as trained),
so a round trip renders identically.

The third scale. 3DGS readers need scale_2 (Spark 2.2.0 refuses a file without it, "Missing scale_2 property"; the
PlayCanvas engine behind SuperSplat reads the column unconditionally; GaussianSplats3D computes exp(undefined) = NaN),
and the 2DGS-aware ones agree on what a surfel's third scale is: zero, the thickness along the normal, which is the
third rotation column (as in our surfels). PlayCanvas splat-transform (3.7.0) reads a PLY without scale_2 as a
2DGS scene and fills the missing column with -Infinity, "linear 0, a zero-thickness surfel"; its NaN filter keeps
-Infinity in scale_*, and its SOG quantiser gives -Infinity its own codebook slot. Spark (2.2.0) encodes a linear scale below exp(-30) as exactly zero, and with `enable2DGS` draws a
splat with a zero scale as a flat surfel over the other two axes. GaussianSplats3D (0.4.7) in its 2D render mode
overrides the third scale with 0. So we write scale_2 = -inf, log(0): every one of them reads it as exactly flat, and
a plain 3DGS renderer gets exp(-inf) = 0, a flat Gaussian. The header also carries `comment SplatRenderMode: 2dgs`,
the tag Brush writes and splat-transform reads (it then carries "2dgs" into SOG's meta.json).

Reading (`load_ply`)
--------------------
- With a `splatzoo model` header comment: that model with that config, exactly.
- Without one, the 3DGS/2DGS property set (x y z, f_dc_0..2, opacity, scale_0 scale_1, rot_0..3, f_rest_* for
  SH degree 1..3) is read as a `2dgs` model whose SH degree follows from the number of f_rest properties:
  - two scales (2DGS's own files, splat-transform's 2DGS output) or a third that is -inf everywhere: exactly.
  - a real third scale (a 3DGS file): each Gaussian becomes the surfel spanning its two largest axes; the quaternion
    is turned (a cyclic permutation of the axes, so no mirror) so that the dropped, thinnest axis becomes the normal.
    This is an approximation for thick Gaussians, so a warning says how many were far from flat.
- A file whose model cannot be told is an error that names what is missing, never a silent 2dgs: properties a
  splatzoo model writes (gabor_*, falloff_logit, ...) without the header, or a missing standard property. Other
  unknown properties (another tool's extras) are ignored with a warning.
- An opacity logit of -inf or +inf in a file without the header (opacity exactly 0 or 1, as splat-transform reads a
  compressed PLY's 8 bits) is read as -SATURATED_LOGIT or +SATURATED_LOGIT.
- A model that draws nothing (0 surfels, every opacity below 1/255, every surfel collapsed to a point) is refused;
  zero quaternions become the identity (how they would be drawn) and log-scales beyond the largest size drawn are
  kept, each with a warning that gives the count (splatzoo.model_checks).
All reading and writing of the file itself goes through splatzoo.ply (plyfile). Model files of every format, this one
among them, are opened through splatzoo.model_files.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
import warnings
from pathlib import Path

import numpy as np
import torch

from .errors import SplatzooError
from .io import strict_json
from .model_checks import check_draws, repair_geometry
from .ply import ply_type_name, read_ply_vertices, write_ply_vertices

FORMAT_VERSION = 2     # 2: scale_2 (-inf) and the SplatRenderMode comment; version 1 files (two scales) still load
FLAT_LOG_SCALE = float("-inf")  # scale_2 of a surfel: log(0), see the module docstring
RENDER_MODE_COMMENT = "SplatRenderMode: 2dgs"
SATURATED_LOGIT = 20.0  # the opacity logit another tool's -inf / +inf (opacity 0 / 1) is read as: 2e-9 from 0 / 1

# parameter name -> property prefix (or explicit names) of the standard layouts
_FIXED = {"means": ["x", "y", "z"], "logit_opacity": ["opacity"]}
# the 3DGS layout's prefixes; a model's other parameters take the prefix its class lists in `ply_prefixes`
_PREFIX = {"log_scales": "scale_", "quats": "rot_", "sh_dc": "f_dc_", "sh_rest": "f_rest_"}
_CHANNEL_MAJOR = {"sh_rest"}          # 3DGS stores SH bands transposed: [N, 3, bands]
_DERIVED = ("nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "scale_2")  # written for viewers, not read back
# the properties of the 3DGS/2DGS layout a file without a splatzoo header must have
_STANDARD = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "rot_0", "rot_1", "rot_2", "rot_3")
_SH_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}  # f_rest count -> SH degree


def _prefixes(model) -> dict[str, str]:
    """Parameter name -> property prefix for `model`: the 3DGS layout's, then those its class lists."""
    return {**_PREFIX, **getattr(model, "ply_prefixes", {})}


def _property_names(name: str, trailing: tuple[int, ...], prefixes: dict[str, str]) -> list[str]:
    """The PLY property names of a per-primitive parameter with shape [N, *trailing] (`prefixes`: `_prefixes`)."""
    if name in _FIXED:
        return list(_FIXED[name])
    count = int(np.prod(trailing)) if trailing else 1
    prefix = prefixes.get(name, re.sub(r"[^A-Za-z0-9_]", "_", name) + "_")
    if not trailing and name not in prefixes:
        return [prefix[:-1]]
    return [f"{prefix}{i}" for i in range(count)]


def _to_columns(name: str, value: torch.Tensor) -> np.ndarray:
    """[N, *trailing] -> [N, count] in property order."""
    a = value.detach().cpu().float().numpy()
    if name in _CHANNEL_MAJOR and a.ndim == 3:
        a = a.transpose(0, 2, 1)
    return np.ascontiguousarray(a).reshape(a.shape[0], math.prod(a.shape[1:]))  # not -1: a model may have 0 rows


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
    cfg = getattr(model, "config", None)
    return dataclasses.asdict(cfg) if cfg is not None and dataclasses.is_dataclass(cfg) else {}


def model_columns(model) -> dict[str, np.ndarray]:
    """The model's PLY properties in file order (name -> float32 [N]), as `save_ply` writes them."""
    per = _exportable_parameters(model)
    name = getattr(model, "name", "") or type(model).__name__
    columns: dict[str, np.ndarray] = {"x": None, "y": None, "z": None}  # order: 3DGS layout first
    normals = _surfel_normals(per)
    columns.update({"nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2]})
    if "sh_dc" not in per:
        dc = _preview_dc(model, per)
        columns.update({f"f_dc_{i}": dc[:, i] for i in range(3)})
    order = ["means", "sh_dc", "sh_rest", "logit_opacity", "log_scales", "quats"]
    order += [k for k in per if k not in order]
    n, prefixes = per["means"].shape[0], _prefixes(model)
    for pname in order:
        if pname not in per:
            continue
        value = per[pname]
        props = _property_names(pname, tuple(value.shape[1:]), prefixes)
        cols = _to_columns(pname, value)
        if cols.shape[1] != len(props):
            raise SplatzooError(f"parameter {pname!r} of shape {list(value.shape)} does not fit the PLY layout")
        for i, prop in enumerate(props):
            if prop in columns and columns[prop] is not None and prop not in _DERIVED:
                raise SplatzooError(f"cannot export model {name!r}: parameters map to the PLY property {prop!r} twice; "
                                    "rename the plugin parameter")
            columns[prop] = cols[:, i]
        if pname == "log_scales" and props == ["scale_0", "scale_1"]:
            columns["scale_2"] = np.full(n, FLAT_LOG_SCALE, np.float32)  # a surfel: zero thickness
    return columns


def save_ply(model, path, *, text: bool = False, comments: tuple[str, ...] = ()) -> Path:
    """Write `model` as a binary (or, with text=True, ASCII) PLY in the layout of the module docstring, atomically,
    with `comments` added to the header. Returns the path."""
    from . import __version__

    path = Path(path)
    if path.is_dir():
        raise SplatzooError(f"cannot write the PLY to {path}: it is a folder; give a file name such as {path / 'model.ply'}")
    name = getattr(model, "name", "")
    if not name:
        _exportable_parameters(model)  # its own, more specific, refusal first
        raise SplatzooError(f"cannot export a {type(model).__name__} without a registry name; create it with "
                            "splatzoo.create_model so that load_ply can rebuild it")
    columns = model_columns(model)
    n = len(next(v for v in columns.values() if v is not None))
    arr = np.empty(n, dtype=[(k, "<f4") for k in columns])
    for k, v in columns.items():
        arr[k] = v
    extra = list(comments)
    comments = [f"splatzoo {__version__} ply export, format {FORMAT_VERSION}", f"splatzoo model {name}",
                f"splatzoo config {json.dumps(_config_dict(model), separators=(',', ':'), default=str)}"]
    if getattr(model, "antialias", False):  # rendered with the pixel-footprint filter (absent: without)
        comments.append("splatzoo antialias true")
    if "scale_2" in columns and np.all(columns["scale_2"] == FLAT_LOG_SCALE):
        comments.append(RENDER_MODE_COMMENT)
    return write_ply_vertices(path, arr, comments + extra, text=text)


# --- reading ------------------------------------------------------------------------------------------------

def _present_width(name: str, names: list[str], prefixes: dict[str, str]) -> int:
    """How many consecutive `<prefix>0, <prefix>1, ...` properties the file has for a [N, width] parameter."""
    prefix, present, width = _property_names(name, (1,), prefixes)[0][:-1], set(names), 0
    while f"{prefix}{width}" in present:
        width += 1
    return width


def _builtin_properties() -> dict[str, list[str]]:
    """Property name -> the built-in models that write it, for the properties beyond the 3DGS layout (at each model's
    default config). A file holding them without a header was written by splatzoo and lost its header."""
    from .registry import MODELS
    from .zoo import create_model

    out: dict[str, list[str]] = {}
    for entry in MODELS.entries():
        if entry.origin != "built-in" or entry.broken:
            continue
        try:
            model = create_model(entry.name)
            per = _exportable_parameters(model)
        except Exception:  # a model that cannot be built empty or exported says nothing here
            continue
        for pname, value in per.items():
            for prop in _property_names(pname, tuple(value.shape[1:]), _prefixes(model)):
                if prop not in _STANDARD and not prop.startswith("f_rest_"):
                    out.setdefault(prop, []).append(entry.name)
    return out


def _standard_model(path, names: list[str]) -> tuple[str, dict, list[str]]:
    """(model, config, ignored properties) of a PLY without a splatzoo header: the 2DGS/3DGS layout as `2dgs`, or an
    error naming why its model cannot be told."""
    fix = ("Export it again with `splatzoo export` (which writes the header), or add the header comments "
           "`comment splatzoo model NAME` and `comment splatzoo config {...}`")
    ours = _builtin_properties()
    found = [k for k in names if k.startswith("gabor_") or k in ours]
    if found:
        models = ", ".join(repr(m) for m in ours.get(found[0], ["gabor"]))
        raise SplatzooError(f"{path} holds the properties {', '.join(found[:4])}{' ...' if len(found) > 4 else ''} of "
                            f"the splatzoo model {models} but no 'comment splatzoo model' header, so its model (and "
                            f"its options) cannot be told; loading it as 2dgs would drop them silently. {fix}")
    missing = [k for k in _STANDARD if k not in names]
    if missing:
        what = ("a point cloud (colours as red, green, blue), not a splat model" if "red" in names else
                "not a 2DGS/3DGS splat file")
        raise SplatzooError(f"{path} has no 'comment splatzoo model' header and lacks the properties "
                            f"{', '.join(missing)} of the 2DGS/3DGS layout, so its model cannot be told: it is {what}. "
                            f"{fix}")
    rest = sum(1 for k in names if k.startswith("f_rest_"))
    if rest not in _SH_DEGREE or any(f"f_rest_{i}" not in names for i in range(rest)):
        raise SplatzooError(f"{path}: its {rest} f_rest properties match no SH degree (0, 9, 24 or 45 expected, "
                            "numbered from f_rest_0); the file is damaged or not a 2DGS/3DGS splat file")
    known = set(_STANDARD) | set(_DERIVED) | {f"f_rest_{i}" for i in range(rest)}
    ignored = [k for k in names if k not in known]
    return "2dgs", {"sh_degree": _SH_DEGREE[rest]}, ignored


# quaternions (w, x, y, z) of the cyclic axis permutations: R @ P puts axis k last (k = 0: (e1, e2, e0); k = 1:
# (e2, e0, e1)), a proper rotation, so no axis is mirrored
_CYCLE = {0: np.array([0.5, 0.5, 0.5, 0.5]), 1: np.array([0.5, -0.5, -0.5, -0.5])}


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of quaternions (w, x, y, z) [N,4] and [4]: the rotation a after b."""
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], 1)


def flatten_gaussians(log_scales: np.ndarray, quats: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """3D Gaussians (log scales [N,3], quaternions [N,4]) -> surfels (log scales [N,2], quaternions [N,4]) spanning
    each Gaussian's two largest axes, the thinnest becoming the normal (third rotation column); and how many were far
    from flat (thinnest sigma above a tenth of the next). A Gaussian whose third axis is already the thinnest keeps
    its quaternion bit for bit."""
    s = log_scales.astype(np.float64)
    q = quats.astype(np.float64)
    thin = np.where(s[:, 2] <= s[:, :2].min(1), 2, np.where(s[:, 0] <= s[:, 1], 0, 1))
    out_s, out_q = s[:, :2].copy(), q.copy()
    for k, keep in ((0, [1, 2]), (1, [2, 0])):
        rows = thin == k
        if rows.any():
            out_s[rows] = s[rows][:, keep]
            out_q[rows] = _quat_mul(q[rows], _CYCLE[k])
    kept = np.sort(s, 1)
    with np.errstate(invalid="ignore"):
        thick = int(np.count_nonzero(kept[:, 0] > kept[:, 1] + math.log(0.1)))
    return out_s.astype(np.float32), np.where((thin == 2)[:, None], quats, out_q.astype(np.float32)), thick


def _header_model(path, comments: list[str], names: list[str]) -> tuple[str, dict, bool, list[str]]:
    """(model name, config, whether the header named it, properties to ignore) from the `splatzoo model` /
    `splatzoo config` comments, or the standard layout's model without them."""
    model_name, config = None, {}
    for c in comments:
        if c.startswith("splatzoo model "):
            model_name = c[len("splatzoo model "):].strip()
        elif c.startswith("splatzoo config "):
            try:
                config = strict_json(c[len("splatzoo config "):])
            except (ValueError, RecursionError) as e:
                raise SplatzooError(f"{path}: the 'splatzoo config' header comment is not valid JSON "
                                    f"({str(e)[:100]}); export the model again") from None
            if not isinstance(config, dict):
                raise SplatzooError(f"{path}: the 'splatzoo config' header comment must be a JSON object of model "
                                    f"options, got a {type(config).__name__}; export the model again")
    if model_name is None:
        model_name, config, ignored = _standard_model(path, names)
        return model_name, config, False, ignored
    return model_name, config, True, []


def load_ply(path):
    """Rebuild the model written by `save_ply`, or read another tool's 2DGS/3DGS PLY as a `2dgs` model (see the
    module docstring). The header's model and config decide what is read, so each is checked against what the file
    holds before it sizes anything."""
    from .zoo import stored_config

    arr, comments = read_ply_vertices(path)
    names = list(arr.dtype.names)
    model_name, config, ours, ignored = _header_model(path, comments, names)
    config = stored_config(model_name, config)
    model = _empty_model(path, model_name, config)
    columns, notes = _columns_as_drawn(path, arr, ours, ignored)
    model.replace_parameters(_parameters(path, arr, columns, model, model_name, config))
    model.set_render_settings(antialias="splatzoo antialias true" in comments)
    check_draws(model, str(path), "export the model again from a run that trained (or pass another file)")
    notes += [f"{path}: {note}" for note in repair_geometry(model)]
    model.notes = notes
    for note in notes:
        warnings.warn(note, UserWarning, stacklevel=2)
    return model


def _empty_model(path, model_name: str, config: dict):
    """The header's model with its config and no primitives yet: it tells each parameter's trailing shape."""
    from .zoo import create_model

    try:
        return create_model(model_name, **config)
    except SplatzooError as e:  # unknown model, bad option: the registry's or the config's own words, located
        raise type(e)(f"{path}: cannot rebuild the model its header names: {e}") from None
    except (TypeError, ValueError, RuntimeError) as e:  # a plugin's config or constructor refusing the options
        raise SplatzooError(f"{path}: model {model_name!r} refuses the header's config {str(config)[:200]} "
                            f"({type(e).__name__}: {str(e)[:200]}); export the model again") from None


def _columns_as_drawn(path, arr, ours: bool, ignored: list[str]) -> tuple[dict, list[str]]:
    """(property -> values, notes): the file's columns with zero quaternions given the identity and, in another
    tool's file (`ours` False), saturated opacities made finite and 3D Gaussians flattened to surfels; each change
    said in a note."""
    names, n = list(arr.dtype.names), arr.shape[0]
    present = set(names)
    columns = {k: arr[k] for k in names}
    notes = []
    rot = [f"rot_{i}" for i in range(4)]
    if all(k in present for k in rot) and all(arr.dtype[k].kind == "f" for k in rot):
        zero = _zero_quaternions(np.stack([arr[k] for k in rot], 1))
        if zero.any():  # drawn as the identity anyway (the rasterizer normalises by at least ZERO_QUATERNION): say so
            for i, k in enumerate(rot):
                columns[k] = np.where(zero, np.float32(i == 0), arr[k]).astype(arr.dtype[k])
            notes.append(f"{path}: {int(zero.sum())} of its {n} surfels have a zero rotation quaternion (no "
                         "orientation); they were given the identity rotation, which is how they would be drawn. Check "
                         "the tool that wrote the file")
    if not ours:
        if "opacity" in present and arr.dtype["opacity"].kind == "f":
            # an opacity of exactly 0 or 1 is a logit of -inf or +inf: what splat-transform reads from the 8 bits of
            # a compressed PLY; kept as the finite logit of (nearly) the same opacity, so it is not taken for damage
            with np.errstate(invalid="ignore"):
                infinite = np.isinf(arr["opacity"])
            if infinite.any():
                columns["opacity"] = np.where(infinite, np.sign(arr["opacity"]) * SATURATED_LOGIT,
                                              arr["opacity"]).astype(arr.dtype["opacity"])
        if ignored:
            more = " ..." if len(ignored) > 8 else ""
            notes.append(f"{path}: ignored the properties {', '.join(ignored[:8])}{more}, which the 2DGS/3DGS layout "
                         "does not have")
        if "scale_2" in present and not np.all(arr["scale_2"] == FLAT_LOG_SCALE):
            notes.append(_flatten_columns(path, arr, columns))
    return columns, notes


def _flatten_columns(path, arr, columns: dict) -> str:
    """A 3DGS file's Gaussians (three scales) as surfels, in `columns`; the note that says so."""
    _float_columns(path, arr, ["scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"], "log_scales")
    scales = np.stack([arr[f"scale_{i}"] for i in range(3)], 1)
    quats = np.stack([columns[f"rot_{i}"] for i in range(4)], 1)
    bad = ~np.isfinite(quats).all(1) | np.isnan(scales).any(1) | (scales == np.inf).any(1)
    if bad.any():
        raise SplatzooError(f"{path}: {int(bad.sum())} Gaussian(s) have NaN or infinite scales or rotations; "
                            "the file is damaged")
    flat_scales, flat_quats, thick = flatten_gaussians(scales, quats)
    columns.update({"scale_0": flat_scales[:, 0], "scale_1": flat_scales[:, 1]})
    columns.update({f"rot_{i}": flat_quats[:, i] for i in range(4)})
    return (f"{path} is a 3DGS file (three scales): each Gaussian was read as the 2D surfel spanning its "
            f"two largest axes, its thinnest axis becoming the normal; {thick} of {arr.shape[0]} were far from flat "
            "(thinnest axis over a tenth of the next), so renders differ from a 3DGS renderer's there")


def _parameters(path, arr, columns: dict, model, model_name: str, config: dict) -> dict[str, torch.Tensor]:
    """The model's per-primitive parameters from the file's `columns`, each checked against what the model needs."""
    names, n = list(arr.dtype.names), arr.shape[0]
    present, prefixes = set(names), _prefixes(model)
    new = {}
    variable = set(getattr(model, "variable_width", ()))
    for pname, empty in _exportable_parameters(model).items():
        trailing = tuple(empty.shape[1:])
        if pname in variable and trailing:  # e.g. waves trimmed by pruning: the file tells the width
            per_slot = math.prod(trailing[1:])  # values a slot holds (per-wave colours: 3)
            trailing = (_present_width(pname, names, prefixes) // per_slot,) + trailing[1:]
        needed = math.prod(trailing) if trailing else 1
        if needed > len(names):  # a crafted config (say a billion waves) must not make a billion names
            raise SplatzooError(f"{path}: parameter {pname!r} of model {model_name!r} with config {str(config)[:200]} "
                                f"needs {needed} properties but the file has {len(names)}; the header's config does "
                                "not match its data. Export the model again")
        props = _property_names(pname, trailing, prefixes)
        missing = [p for p in props if p not in present]
        if missing:
            more = " ..." if len(missing) > 4 else ""
            raise SplatzooError(f"{path} lacks the properties {', '.join(missing[:4])}{more} of parameter {pname!r} "
                                f"of model {model_name!r} {config}; it was not written by "
                                "`splatzoo export` for this model (or with another config)")
        if empty.is_floating_point():
            _float_columns(path, arr, props, pname)
        cols = np.stack([columns[p].astype(np.float32) for p in props], 1) if props else np.zeros((n, 0), np.float32)
        _check_values(path, pname, props, cols, empty)
        new[pname] = _from_columns(pname, cols, trailing)
    return new


def _check_values(path, pname: str, props: list[str], cols: np.ndarray, empty: torch.Tensor) -> None:
    """A parameter's values [N, len(props)] are finite and, for a whole-number tensor like `empty`, whole numbers in
    its type's range."""
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


def _zero_quaternions(quats: np.ndarray) -> np.ndarray:
    """[N] bool: which quaternions [N,4] are no rotation (shorter than model_checks.ZERO_QUATERNION)."""
    from .model_checks import ZERO_QUATERNION

    with np.errstate(over="ignore", invalid="ignore"):
        return np.linalg.norm(quats.astype(np.float64), axis=1) < ZERO_QUATERNION


def _float_columns(path, arr, props, pname: str) -> None:
    """float32 parameters written as int or uchar lose their fractions: refuse them."""
    stored = next((p for p in props if p in arr.dtype.names and arr.dtype[p].kind != "f"), None)
    if stored is not None:
        raise SplatzooError(f"{path}: {stored} is stored as {ply_type_name(arr.dtype[stored])} but holds a "
                            f"float parameter ({pname!r}); the file was not written by splatzoo export or is "
                            "damaged. Export the model again")
