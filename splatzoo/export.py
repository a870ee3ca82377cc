"""Model export: a registry of formats (`splatzoo export RUN --format FMT --out FILE`), the PLY layout every splat
tool reads, and `load_ply`, which reads it back (and the 2DGS and 3DGS PLY files of other tools).

Formats
-------
`EXPORTERS` holds one `ExporterSpec` per format: name, description, file suffix(es), an options dataclass and a
function `fn(source, out, *, progress=None, **options) -> Path`, where `source` is a run folder or a model file (.pt
or .ply). Built-ins: `ply` (below), `spz`, `sog` and `compressed-ply` (our `ply` converted by PlayCanvas
splat-transform, see splatzoo.splat_tools), and `baked` (splatzoo.bake) and `mesh-glb` (splatzoo.mesh_texture),
imported only when used. Plugins add formats through the entry-point group `splatzoo.exporters`, whose value is an
`ExporterSpec`. Options use the model-option syntax: `--format baked:max_splats=16000`.

The PLY layout (`ply`)
----------------------
One vertex per primitive, float32 properties, little endian, in the order of the 3DGS layout:
  x, y, z                      position (`means`)
  nx, ny, nz                   surfel normal (third column of the rotation), for viewers; not read back
  f_dc_0..2                    SH DC colour; for models without SH a preview of the mean colour, not read back
  f_rest_*                     higher SH bands, channel-major as 3DGS writes them (all R, then G, then B)
  opacity                      logit
  scale_0, scale_1, scale_2    log sigma; scale_2 is the surfel's thickness, -inf (see below); not read back
  rot_0..3                     quaternion (w, x, y, z), unnormalised as trained
  gabor_color_base_0..2, gabor_color_diff_0..2 (or, for --color-param paper, gabor_color_a_0..2, gabor_color_b_0..2),
  gabor_weight_*, gabor_freq_*, gabor_phase_*   Gabor-family colour and waves
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
All reading and writing of the file itself goes through splatzoo.ply (plyfile). `load_source` (what the commands
use) also reads run folders, .pt files and, through splat-transform, SPZ, SOG, compressed PLY, .splat and .ksplat
(splatzoo.splat_tools.read_splat_file): a file splat-transform cannot read is refused with its own message and the
file's name and format, and every message names the file, never the temporary PLY in between.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
import typing
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from .errors import PluginError, SplatzooError
from .io import read_ply_vertices, write_ply_vertices
from .model_checks import check_draws, check_in_view, repair_geometry
from .ply import compressed_ply, ply_type_name
from .registry import Registry

FORMAT_VERSION = 2     # 2: scale_2 (-inf) and the SplatRenderMode comment; version 1 files (two scales) still load
FLAT_LOG_SCALE = float("-inf")  # scale_2 of a surfel: log(0), see the module docstring
RENDER_MODE_COMMENT = "SplatRenderMode: 2dgs"
SATURATED_LOGIT = 20.0  # the opacity logit another tool's -inf / +inf (opacity 0 / 1) is read as: 2e-9 from 0 / 1

# parameter name -> property prefix (or explicit names) of the standard layouts
_FIXED = {"means": ["x", "y", "z"], "logit_opacity": ["opacity"]}
_PREFIX = {"log_scales": "scale_", "quats": "rot_", "sh_dc": "f_dc_", "sh_rest": "f_rest_",
           "color_a": "gabor_color_a_", "color_b": "gabor_color_b_", "color_base": "gabor_color_base_",
           "color_diff": "gabor_color_diff_", "wave_weights": "gabor_weight_",
           "wave_freqs": "gabor_freq_", "wave_phases": "gabor_phase_"}
_CHANNEL_MAJOR = {"sh_rest"}          # 3DGS stores SH bands transposed: [N, 3, bands]
_DERIVED = ("nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "scale_2")  # written for viewers, not read back
# the properties of the 3DGS/2DGS layout a file without a splatzoo header must have
_STANDARD = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "rot_0", "rot_1", "rot_2", "rot_3")
_SH_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}  # f_rest count -> SH degree


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
    n = per["means"].shape[0]
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

def _present_width(name: str, names: list[str]) -> int:
    """How many consecutive `<prefix>0, <prefix>1, ...` properties the file has for a [N, width] parameter."""
    prefix, present, width = _property_names(name, (1,))[0][:-1], set(names), 0
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
            per = _exportable_parameters(create_model(entry.name))
        except Exception:  # a model that cannot be built empty or exported says nothing here
            continue
        for pname, value in per.items():
            for prop in _property_names(pname, tuple(value.shape[1:])):
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
                config = json.loads(c[len("splatzoo config "):])
            except (json.JSONDecodeError, RecursionError) as e:
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
    from .zoo import create_model, stored_config

    arr, comments = read_ply_vertices(path)
    names = list(arr.dtype.names)
    present = set(names)
    model_name, config, ours, ignored = _header_model(path, comments, names)
    config = stored_config(model_name, config)
    try:
        model = create_model(model_name, **config)   # no primitives yet: it tells each parameter's trailing shape
    except SplatzooError as e:  # unknown model, bad option: the registry's or the config's own words, located
        raise type(e)(f"{path}: cannot rebuild the model its header names: {e}") from None
    except (TypeError, ValueError, RuntimeError) as e:  # a plugin's config or constructor refusing the options
        raise SplatzooError(f"{path}: model {model_name!r} refuses the header's config {str(config)[:200]} "
                            f"({type(e).__name__}: {str(e)[:200]}); export the model again") from None
    n = arr.shape[0]
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
            _float_columns(path, arr, ["scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"],
                           "log_scales")
            scales = np.stack([arr[f"scale_{i}"] for i in range(3)], 1)
            quats = np.stack([columns[f"rot_{i}"] for i in range(4)], 1)
            bad = ~np.isfinite(quats).all(1) | np.isnan(scales).any(1) | (scales == np.inf).any(1)
            if bad.any():
                raise SplatzooError(f"{path}: {int(bad.sum())} Gaussian(s) have NaN or infinite scales or rotations; "
                                    "the file is damaged")
            flat_scales, flat_quats, thick = flatten_gaussians(scales, quats)
            columns.update({"scale_0": flat_scales[:, 0], "scale_1": flat_scales[:, 1]})
            columns.update({f"rot_{i}": flat_quats[:, i] for i in range(4)})
            notes.append(f"{path} is a 3DGS file (three scales): each Gaussian was read as the 2D surfel spanning its "
                         f"two largest axes, its thinnest axis becoming the normal; {thick} of {n} were far from flat "
                         "(thinnest axis over a tenth of the next), so renders differ from a 3DGS renderer's there")
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
            _float_columns(path, arr, props, pname)
        cols = np.stack([columns[p].astype(np.float32) for p in props], 1) if props else np.zeros((n, 0), np.float32)
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
    check_draws(model, str(path), "export the model again from a run that trained (or pass another file)")
    notes += [f"{path}: {note}" for note in repair_geometry(model)]
    model.notes = notes
    for note in notes:
        warnings.warn(note, UserWarning, stacklevel=2)
    return model


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


# --- sources: a run folder, a model .pt, a model .ply ---------------------------------------------------------

# splat files of other formats that splat-transform turns into a PLY for load_ply
CONVERTIBLE_SUFFIXES = (".compressed.ply", ".spz", ".sog", ".splat", ".ksplat")


def load_source(source):
    """(model, the file it was read from) of a run folder (its trained model.pt), a model .pt or a model .ply; SPZ,
    SOG, compressed PLY, .splat and .ksplat files are converted to a PLY by splat-transform first (then read as
    splat files without a splatzoo header: `2dgs`). A model that draws nothing is refused here, whatever its file
    (splatzoo.model_checks)."""
    from .runs import Run
    from .zoo import load_model

    source = Path(source)
    try:
        is_file, exists = source.is_file(), source.exists()
    except OSError as e:
        raise SplatzooError(f"{str(source)[:200]} cannot be looked up ({e.strerror or e})") from None
    name = source.name.lower()
    if is_file and (name.endswith(CONVERTIBLE_SUFFIXES[1:]) or (name.endswith(".ply") and compressed_ply(source))):
        return _load_converted(source), source
    if is_file:
        with open(source, "rb") as f:
            magic = f.read(3)
        if magic == b"ply":
            return load_ply(source), source
        return load_model(source), source
    if not exists:
        raise SplatzooError(f"{source} does not exist; pass a run directory written by `splatzoo train`, a model .pt "
                            "or a model .ply")
    run = Run(source)
    return run.model(), run.model_path


def _load_converted(source: Path):
    """The model of a splat file that splat-transform converts to a PLY for load_ply. Every message and note names
    `source`, never the temporary PLY (which is gone by the time anyone reads them)."""
    import tempfile

    from .splat_tools import read_splat_file

    label = f"{source} (read through splat-transform)"
    with tempfile.TemporaryDirectory(prefix="splatzoo-load-") as folder:
        ply = read_splat_file(source, Path(folder) / "model.ply")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                model = load_ply(ply)
            except SplatzooError as e:
                raise type(e)(str(e).replace(str(ply), label)) from None
    model.notes = [note.replace(str(ply), label) for note in model.notes]
    for w in caught:
        warnings.warn(str(w.message).replace(str(ply), label), w.category, stacklevel=3)
    means = model.per_primitive().get("means")
    n = model.num_primitives
    if means is not None and n > 1 and bool((means.detach() == means.detach()[:1]).all()):
        point = ", ".join(f"{float(x):.4g}" for x in means.detach()[0])
        raise SplatzooError(f"{label}: every one of its {n} splats lies at the one point ({point}): the file's "
                            "positions were lost (it is damaged or was written wrongly); export or download it again")
    return model


# --- the exporter registry -------------------------------------------------------------------------------------

@dataclass
class ExporterSpec:
    """An export format. `fn(source, out, *, progress=None, **options) -> Path` writes `out` (atomically) from
    `source`, a run folder or a model file (.pt or .ply). `options` is a dataclass of the format's options (or None:
    none). Built-ins whose code lives in an optional module give `fn` and `options` as "module:name" strings, imported
    when the format is first used."""

    name: str
    fn: Callable[..., Path] | str
    options: type | str | None = None
    description: str = ""
    suffixes: tuple[str, ...] = (".ply",)
    extra: dict = field(default_factory=dict)

    def _resolve(self, target):
        if not isinstance(target, str):
            return target
        import importlib

        module, _, attr = target.partition(":")
        try:
            loaded = importlib.import_module(module)
        except ModuleNotFoundError as e:
            if not e.name or module.startswith(e.name):
                raise SplatzooError(f"export format {self.name!r} needs {module}, which this splatzoo installation "
                                    "does not have; update splatzoo (or pick another --format, see "
                                    "`splatzoo export --list`)") from None
            raise SplatzooError(f"export format {self.name!r} needs the Python package {e.name}, which is not "
                                f"installed: pip install {e.name} (or pick another --format)") from None
        try:
            return getattr(loaded, attr)
        except AttributeError:
            raise SplatzooError(f"export format {self.name!r}: {module} has no {attr}; this splatzoo installation "
                                "is incomplete, update it") from None

    def function(self) -> Callable[..., Path]:
        return self._resolve(self.fn)

    def options_class(self) -> type | None:
        return self._resolve(self.options)


def _validate_exporter_spec(obj: Any, name: str) -> ExporterSpec:
    if callable(obj) and not isinstance(obj, (ExporterSpec, type)):
        obj = obj()
    if not isinstance(obj, ExporterSpec):
        raise PluginError(f"entry point must name a splatzoo.export.ExporterSpec, got {type(obj).__name__}")
    if obj.name != name:
        raise PluginError(f"entry point name {name!r} differs from the spec's name {obj.name!r}")
    return obj


EXPORTERS: Registry[ExporterSpec] = Registry("export format", entry_point_group="splatzoo.exporters",
                                             validate=_validate_exporter_spec)


def register_exporter(spec: ExporterSpec) -> ExporterSpec:
    return EXPORTERS.register(spec.name, spec)


def list_formats() -> list[str]:
    return EXPORTERS.names()


_BOOLS = {"true": True, "1": True, "yes": True, "on": True, "false": False, "0": False, "no": False, "off": False}


def export_options(spec: ExporterSpec, options: dict):
    """The format's options dataclass with `options` (strings from the command line, or values) applied."""
    cls = spec.options_class()
    if cls is None:
        if options:
            raise SplatzooError(f"export format {spec.name!r} has no options; got {', '.join(options)}")
        return None
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = [k for k in options if k not in fields]
    if unknown:
        from .registry import closest

        raise SplatzooError(f"export format {spec.name!r} has no option(s) {', '.join(unknown)}; its options are: "
                            f"{', '.join(fields) or 'none'}" + closest(unknown[0], fields))
    hints = typing.get_type_hints(cls)
    values = {}
    for key, value in options.items():
        typ = hints.get(key)
        args = [a for a in typing.get_args(typ) if a is not type(None)]
        if args and len(args) == 1 and type(None) in typing.get_args(typ):  # Optional[X]
            if isinstance(value, str) and value.strip().lower() in ("none", "null", ""):
                values[key] = None
                continue
            typ = args[0]
        try:
            if typ is bool:
                if isinstance(value, bool):
                    values[key] = value
                elif isinstance(value, str) and value.strip().lower() in _BOOLS:
                    values[key] = _BOOLS[value.strip().lower()]
                else:
                    raise ValueError
            elif typ in (int, float):
                if isinstance(value, bool):
                    raise ValueError
                converted = typ(value) if typ is float else int(str(value).strip())
                if typ is float and not math.isfinite(converted):
                    raise ValueError
                values[key] = converted
            elif typ is str:
                values[key] = str(value)
            else:
                values[key] = value
        except (TypeError, ValueError, OverflowError):
            raise SplatzooError(f"export format {spec.name!r}: option {key} expects "
                                f"{getattr(typ, '__name__', typ)}, got {value!r}") from None
    try:
        return cls(**values)
    except (TypeError, ValueError) as e:
        raise SplatzooError(f"export format {spec.name!r}: {e}") from None


def describe_format(spec: ExporterSpec) -> str:
    """One line per option: name, type, default, help (or a note that the format's module is missing)."""
    try:
        cls = spec.options_class()
    except SplatzooError as e:
        return f"    (unavailable: {e})"
    if cls is None:
        return "    (no options)"
    hints = typing.get_type_hints(cls)
    rows = []
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        typ = hints.get(f.name, str)
        text = f.metadata.get("help", "")
        said = "(default" in text  # a help that states its own default
        rows.append(f"    {f.name}={getattr(typ, '__name__', str(typ)).upper()}  {text}"
                    + ("" if said else f" (default {default})"))
    return "\n".join(rows) if rows else "    (no options)"


def parse_format(text: str) -> tuple[ExporterSpec, object]:
    """'baked:max_splats=16000' -> (the spec, its options dataclass); the model-option syntax."""
    from .options import model_spec

    name, options = model_spec(text)
    spec = EXPORTERS.get(name)
    return spec, export_options(spec, options)


def _suffix_ok(out: Path, suffixes: tuple[str, ...]) -> bool:
    return any(out.name.lower().endswith(s.lower()) and len(out.name) > len(s) for s in suffixes)


def check_export_target(spec: ExporterSpec, out: Path, model_path: Path | None = None) -> None:
    """`--out RUN/model.pt` would replace the trained model: export writes only files with the format's suffix, and
    never over the file it reads."""
    if out.is_dir():
        raise SplatzooError(f"cannot write the export to {out}: it is a folder; give a file name such as "
                            f"{out / ('model' + (spec.suffixes or ('.ply',))[0])}")
    if spec.suffixes and not _suffix_ok(out, spec.suffixes):
        stem = out.name[:-len(out.suffix)] if out.suffix else (out.name or "model")
        suggestion = out.parent / f"{stem}{spec.suffixes[0]}"
        raise SplatzooError(f"export writes a {spec.suffixes[0][1:].upper()} file for --format {spec.name}, so --out "
                            f"must end in {' or '.join(spec.suffixes)}; got {out}. Name the file e.g. {suggestion}")
    if model_path is None:
        return
    same = out.resolve() == Path(model_path).resolve()
    if not same and out.exists():
        try:
            same = out.samefile(model_path)
        except OSError:
            same = False
    if same:
        raise SplatzooError(f"refusing to export onto the model being read ({model_path}); choose another --out, "
                            f"e.g. {Path(model_path).with_name(Path(model_path).stem + '-export' + spec.suffixes[0])}")


def _source_file(source: Path) -> Path | None:
    """The file a source will be read from (for the never-over-the-input check), without loading it."""
    source = Path(source)
    try:
        if source.is_dir():
            return source / "model.pt"
        return source if source.exists() else None
    except OSError:
        return None


def export(source, out, format: str = "ply", *, progress=None, **options) -> Path:
    """Export the model of `source` (a run folder, a model .pt or .ply) to `out` in `format` (a name, or a name with
    options: 'baked:max_splats=16000'); keyword `options` add to those. Returns the written path."""
    from .options import model_spec

    name, inline = model_spec(format)
    spec = EXPORTERS.get(name)
    opts = export_options(spec, {**inline, **options})
    out = Path(out)
    check_export_target(spec, out, _source_file(Path(source)))
    kwargs = dataclasses.asdict(opts) if opts is not None else {}
    return Path(spec.function()(Path(source), out, progress=progress, **kwargs))


# --- built-in formats ------------------------------------------------------------------------------------------

@dataclass
class PlyOptions:
    ascii: bool = field(default=False, metadata={"help": "write an ASCII PLY (larger, slower; to read by eye)"})
    viewer: str = field(default="exact", metadata={
        "help": "exact: the trained surfels (load_ply restores the model; for viewers set as splatzoo renders, e.g. "
                "Spark blurAmount 0.1, GaussianSplats3D antialiased with kernel2DSize 0.1); 3dgs: scales and "
                "opacities made for viewers that add 0.3 px^2 to every splat and keep its opacity (GaussianSplats3D's "
                "and SuperSplat's defaults), from the run's training cameras; a file for viewing, not for load_ply"})


VIEWER_DILATION = 0.3  # px^2 a 3DGS-style viewer adds to every splat's screen covariance
_VIEWER_FIX = ("Export it with ply:viewer=exact (the surfels as trained) instead, or from a run whose training cameras "
               "see the model")
VIEWER_RULES = ("exact", "3dgs", "mip")


def training_view_scale(means: torch.Tensor, axes: torch.Tensor, cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each surfel was seen in training, as medians over `cameras`: px2 [N], its world area per pixel^2
    ((depth / focal)^2), and fore [N,2], how much of each axis' length (axes [N,3,2], unit) survives on screen,
    squared (1 - (axis . view direction)^2, at least 0.05)."""
    px2, fore = [], []
    for cam in cameras:
        w2c = cam.world_to_camera.double()
        z = means @ w2c[2, :3] + w2c[2, 3]
        focal = math.sqrt(float(cam.K[0, 0]) * float(cam.K[1, 1]))
        px2.append(torch.where(z > 0.05, (z / focal) ** 2, torch.nan))
        d = torch.nn.functional.normalize(means - torch.linalg.inv(w2c)[:3, 3], dim=1)
        fore.append(1 - torch.einsum("nk,nki->ni", d, axes) ** 2)
    return torch.stack(px2).nanmedian(0).values, torch.stack(fore).median(0).values.clamp(0.05, 1.0)


@torch.no_grad()
def compensate_viewer_dilation(model, cameras, rule: str = "3dgs") -> None:
    """Rewrite the scales and opacities of `model` (in place) so that a viewer that adds VIEWER_DILATION px^2 to each
    splat draws it about as splatzoo does, at the scale the surfel was trained at (`training_view_scale`).

    s_i, axis i's variance on screen (px^2), becomes s_i' = max(s_i - (0.3 - f), s_i / 4), f the model's own footprint
    (0.1 px^2 when anti-aliased, else 0); the opacity keeps the splat's mass on screen (o sqrt(s0 s1)): rule "3dgs"
    (the viewer keeps the opacity) o' = o sqrt(s0 s1 / ((s0' + 0.3)(s1' + 0.3))), rule "mip" (the viewer rescales it
    by sqrt(s0' s1' / ((s0' + 0.3)(s1' + 0.3))), as Spark does) o' = o sqrt(s0 s1 / (s0' s1')); at most 0.99.

    A model none of whose surfels the cameras see (model_checks.check_in_view), or that would come out with every
    opacity below 1/255, is refused before anything changes: its file would show nothing."""
    from .geometry import quat_to_rotmat

    if rule not in VIEWER_RULES[1:]:
        raise SplatzooError(f"unknown viewer rule {rule!r}; known: {', '.join(VIEWER_RULES[1:])}")
    per = model.per_primitive()
    if "log_scales" not in per or "logit_opacity" not in per or "quats" not in per:
        raise SplatzooError(f"model {model.name!r} has no log_scales, logit_opacity and quats to compensate")
    means, quats = per["means"].double().cpu(), per["quats"].double().cpu()
    cameras = list(cameras)
    # a model no camera sees would be sized by guesswork and come out invisible: refused, saying where it is
    check_in_view(model, cameras, f"ply:viewer={rule} of the {model.name} model", fix=_VIEWER_FIX)
    axes = quat_to_rotmat(torch.nn.functional.normalize(quats, dim=1))[:, :, :2]
    px2, fore = training_view_scale(means, axes, cameras)
    px2 = torch.nan_to_num(px2, nan=float(px2.nanmedian()) if px2.isfinite().any() else 1.0)
    footprint = model.raster_settings.pixel_filter if getattr(model, "antialias", False) else 0.0
    log_scales = per["log_scales"].double().cpu()
    s = torch.exp(2 * log_scales) / px2[:, None] * fore
    shrunk = torch.maximum(s - (VIEWER_DILATION - footprint), s / 4)
    kept = s.prod(1) / ((shrunk + VIEWER_DILATION).prod(1) if rule == "3dgs" else shrunk.prod(1))
    opacity = (torch.sigmoid(per["logit_opacity"].double().cpu()) * kept.sqrt()).clamp(1e-6, 0.99)
    if float(opacity.max()) < model.raster_settings.alpha_min:
        raise SplatzooError(f"ply:viewer={rule}: made for the viewer's dilation, every one of the {model.name} "
                            f"model's {model.num_primitives} surfels would have an opacity below 1/255 (each is far "
                            f"under a pixel in the training views), so the file would show nothing. {_VIEWER_FIX}")
    new_scales = 0.5 * torch.log(shrunk * px2[:, None] / fore)
    like = per["log_scales"]
    model.replace_parameters({"log_scales": new_scales.to(like), "logit_opacity":
                              torch.logit(opacity).to(per["logit_opacity"])})


def export_ply(source, out, *, progress=None, ascii: bool = False, viewer: str = "exact") -> Path:
    """The `ply` format: the layout of the module docstring, which `load_ply` reads back exactly (viewer="exact"), or
    made for a viewer's dilation rule (`compensate_viewer_dilation`, from the run's training cameras)."""
    out = Path(out)
    if viewer not in VIEWER_RULES:
        raise SplatzooError(f"ply: viewer={viewer!r} is not known; use one of {', '.join(VIEWER_RULES)}")
    model, model_path = load_source(source)
    check_export_target(EXPORTERS.get("ply"), out, model_path)
    if viewer != "exact":
        from .runs import Run

        if not Path(source).is_dir():
            raise SplatzooError(f"ply:viewer={viewer} sizes each surfel at its training cameras: export from the run "
                                f"folder, not the file {source}")
        compensate_viewer_dilation(model, [v.camera for v in Run(source).scene().train], viewer)
    path = save_ply(model, out, text=ascii, comments=[f"splatzoo viewer {viewer}"] if viewer != "exact" else ())
    if progress:
        progress(f"{model.num_primitives} {model.name} primitives" + (f", made for {viewer} viewers" if
                                                                       viewer != "exact" else ""))
    return path


def export_run(run, out) -> Path:
    """Export the trained model of a run directory, or a model .pt (or .ply) file, to the PLY `out`."""
    out = Path(out)
    check_export_target(EXPORTERS.get("ply"), out, _source_file(Path(run)))
    return export_ply(run, out)


@dataclass
class SpzOptions:
    version: int = field(default=3, metadata={
        "help": "SPZ version to write: 3 (gzip; what Spark 2.2 and most viewers read) or 4 (splat-transform and "
                "newer readers only)"})

    def __post_init__(self):
        if self.version not in (3, 4):
            raise ValueError(f"version must be 3 or 4, got {self.version}")


@dataclass
class SogOptions:
    sh_iterations: int = field(default=10, metadata={"help": "k-means iterations of the SH compression"})
    gpu: str = field(default="cpu", metadata={"help": "device of the compression: cpu, or a GPU adapter index "
                                                      "(see `splat-transform --list-gpus`)"})

    def __post_init__(self):
        if self.sh_iterations < 1:
            raise ValueError(f"sh_iterations must be at least 1, got {self.sh_iterations}")
        if self.gpu != "cpu" and not str(self.gpu).isdigit():
            raise ValueError(f"gpu must be cpu or an adapter index, got {self.gpu!r}")


def _converted(out_format: str, suffix: str, args: Callable[[Any], list[str]]):
    def convert(source, out, *, progress=None, **options) -> Path:
        from .splat_tools import convert_ply

        out = Path(out)
        model, model_path = load_source(source)
        check_export_target(EXPORTERS.get(out_format), out, model_path)
        return convert_ply(model, out, suffix=suffix, args=args(options), progress=progress)
    return convert


register_exporter(ExporterSpec(
    "ply", export_ply, PlyOptions, "the 3DGS/2DGS PLY every splat tool reads; splatzoo's own properties (Gabor "
    "waves, plugin parameters) ride along so load_ply restores the model exactly", (".ply",)))
register_exporter(ExporterSpec(
    "spz", _converted("spz", ".spz", lambda o: ["--spz-version", str(o.get("version", 3))]), SpzOptions,
    "Niantic's compressed splats (about 10x smaller), through PlayCanvas splat-transform; surfels as flat Gaussians, "
    "Gabor waves as their mean colour", (".spz",)))
register_exporter(ExporterSpec(
    "sog", _converted("sog", ".sog", lambda o: ["-g", str(o.get("gpu", "cpu")), "-i", str(o.get("sh_iterations", 10))]),
    SogOptions, "PlayCanvas SOG (WebP textures in one file, about 15-20x smaller), through splat-transform; "
    "Gabor waves as their mean colour", (".sog",)))
register_exporter(ExporterSpec(
    "compressed-ply", _converted("compressed-ply", ".compressed.ply", lambda o: []), None,
    "PlayCanvas / SuperSplat compressed PLY (chunked, quantised), through splat-transform", (".compressed.ply",)))
register_exporter(ExporterSpec(
    "baked", "splatzoo.bake:export_baked", "splatzoo.bake:BakeOptions",
    "wave models baked into plain 2DGS surfels in a standard PLY, for viewers that know no Gabor waves", (".ply",)))
register_exporter(ExporterSpec(
    "mesh-glb", "splatzoo.mesh_texture:export_textured_mesh", "splatzoo.mesh_texture:TexturedMeshOptions",
    "a textured triangle mesh (glTF binary): the TSDF mesh with a UV atlas and a texture baked from the model's "
    "renders", (".glb",)))
register_exporter(ExporterSpec(
    "mesh-obj", "splatzoo.mesh_texture:export_textured_mesh", "splatzoo.mesh_texture:TexturedMeshOptions",
    "the textured mesh as OBJ + MTL + PNG (written beside each other)", (".obj",)))
