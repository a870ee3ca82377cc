"""Splat models as glTF 2.0 binary files (.glb) with the Khronos `KHR_gaussian_splatting` extension, written and read
back.

The file
--------
One buffer (the GLB's binary chunk), one mesh with one primitive of `mode` 0 (POINTS), one node (no transform: the
positions are splatzoo's world coordinates, whatever the dataset's up axis), one scene. The primitive carries
`extensions.KHR_gaussian_splatting = {kernel: "ellipse", colorSpace: "srgb_rec709_display", projection:
"perspective", sortingMethod: "cameraDistance"}` (splatzoo's colours are display values, blended as they are) and
these float32 attributes, one element per surfel:

  POSITION                                   means, with the min and max glTF asks of POSITION
  KHR_gaussian_splatting:ROTATION            the unit quaternion in glTF's order (x, y, z, w); splatzoo's: (w, x, y, z)
  KHR_gaussian_splatting:SCALE               linear sigmas (exp of the log-scales); the third is 0 (see below)
  KHR_gaussian_splatting:OPACITY             linear opacity (sigmoid of the logit)
  KHR_gaussian_splatting:SH_DEGREE_0_COEF_0  the SH DC coefficient (3DGS's f_dc: colour = 0.5 + 0.2820948 SH0)
  KHR_gaussian_splatting:SH_DEGREE_l_COEF_n  the higher SH degrees of the model, whole degrees, m from -l to l
  COLOR_0                                    the fallback of readers that draw points: linear RGB of the DC colour
                                             (clamped, decoded from sRGB), alpha the opacity (color=false: none)

The third axis. A splatzoo surfel is a flat disc whose normal is the third column of its rotation. It is written
with the third sigma exactly 0, as splatzoo's PLY export writes scale_2 = log 0 (`splatzoo.model_ply.FLAT_LOG_SCALE`,
whose docstring says how the splat viewers read it): the Gaussian's covariance R diag(s0, s1, 0)^2 R^T is the disc,
every `ellipse` reader projects it as the flat ellipse it is, and the spec allows a scale of 0 (only negative ones are
invalid). The surfels are flagged by a nested extension inside KHR_gaussian_splatting (and listed in extensionsUsed),

  "extensions": {"SPLATZOO_gaussian_splatting_surfel": {"antialias": true, "viewer": "exact"}}

which says that the splats are 2D surfels (third rotation column the normal, SCALE's third value 0) and how splatzoo
renders them: antialias, the pixel-footprint filter the model was trained with; viewer, "exact" (the trained surfels)
or "3dgs" (sized for the 0.3 px^2 dilation of 3DGS-style viewers, `splatzoo.export.compensate_viewer_dilation`);
bakedFrom and bakeDb, for a model baked into plain surfels, its name and the bake's error (dB). The kernel stays
"ellipse" so that every reader draws the splats; readers that do not know the flag ignore it.

Coordinates are splatzoo's world coordinates as they are (no node transform): glTF's +y is up, a dataset's world
may have another up axis (COLMAP's often points down), so a viewer that trusts glTF's axes may show the model turned;
turning it on writing would also mean turning the SH coefficients for every reader, which the spec leaves to them.

Readers. The PlayCanvas engine (2.23.3; tests/test_gltf_splats.py) reads the file with its own parser and draws each
splat as 3DGS does, adding 0.3 px^2 to its screen covariance and keeping its opacity (the rule viewer=3dgs sizes for),
its Gaussian cut at 2 sqrt(2) sigma and lowered to reach 0 there. Measured on the sweater protocol of BENCHMARKS.md's
viewer section (2dgs, 3000 steps, 4000 surfels, 128 px, splatzoo 25.51 dB against the truth; 3 test views), its
default draws the exact file at 32.10 dB from splatzoo's render, 0.40 dB under splatzoo against the truth, and the
viewer=3dgs file at 29.44 dB, 1.07 dB under: the exact file is the better one for it. The Khronos glTF validator
(2.0.0-dev.3.10) does not know the extension yet: besides saying so, it reports each `KHR_gaussian_splatting:`
attribute name as an invalid attribute (it allows only glTF's own names and "_"-prefixed ones); it finds nothing
else.

Richer members (gabor, beta, textured, neural-gabor, beta-gabor, plugins) have no place in these attributes: they are
baked into plain surfels first by splatzoo.bake (`bake_model`, fitted to the model's own renders from the given
cameras, or from cameras around the model).

Reading (`read_glb_splats`)
---------------------------
A `2dgs` model. A file with the surfel flag and no node transform reads back as the surfels written, up to float32
(quaternions come back normalised, opacity 0 or 1 as the logit -+SATURATED_LOGIT, as splatzoo.model_ply.load_ply reads
them). Other files (a 3DGS model from another tool) are read the way load_ply reads a 3DGS PLY: each Gaussian becomes
the surfel spanning its two largest axes (`splatzoo.model_ply.flatten_gaussians`), with a note on how many were far from
flat. Node transforms are applied (positions, covariances; SH coefficients turned by the transform's rotation), every
splat primitive of the scene is read into one model, the integer encodings of the spec (normalised bytes and shorts)
are decoded, and `lin_rec709_display` colours are converted to display colours (the DC term exactly). Everything is
checked before it is used: a file that is not a GLB, damaged chunks or JSON, accessors of the wrong type, count or
component type, bytes beyond a buffer (a count far larger than the file), NaN, negative scales, quaternions that are
not unit length, opacities outside 0..1, partial SH degrees, external buffers and required extensions splatzoo does
not know are each a SplatzooError that names the file and the problem.
"""
from __future__ import annotations

import json
import math
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .errors import SplatzooError
from .model_ply import FLAT_LOG_SCALE, SATURATED_LOGIT, flatten_gaussians

EXTENSION = "KHR_gaussian_splatting"
SURFEL_EXTENSION = "SPLATZOO_gaussian_splatting_surfel"
GLB_MAGIC = b"glTF"
SUFFIX = ".glb"
COLOR_SPACE = "srgb_rec709_display"  # splatzoo's colours are display values, blended as they are
SH_C0 = 0.2820947917738781

_JSON_CHUNK, _BIN_CHUNK = 0x4E4F534A, 0x004E4942
_FLOAT, _BYTE, _UBYTE, _SHORT, _USHORT, _UINT = 5126, 5120, 5121, 5122, 5123, 5125
_COMPONENTS = {_BYTE: "<i1", _UBYTE: "<u1", _SHORT: "<i2", _USHORT: "<u2", _UINT: "<u4", _FLOAT: "<f4"}
_COMPONENT_NAMES = {_BYTE: "signed byte", _UBYTE: "unsigned byte", _SHORT: "signed short", _USHORT: "unsigned short",
                    _UINT: "unsigned int", _FLOAT: "float"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_ARRAY_BUFFER = 34962
_SH_COEFS = {1: 3, 2: 5, 3: 7}
# the encodings the spec allows each attribute, as (component type, normalized); POSITION's integer ones come with
# KHR_mesh_quantization
_ALLOWED = {
    "POSITION": ("VEC3", {(_FLOAT, False)}),
    "ROTATION": ("VEC4", {(_FLOAT, False), (_BYTE, True), (_SHORT, True)}),
    "SCALE": ("VEC3", {(_FLOAT, False), (_UBYTE, False), (_UBYTE, True), (_USHORT, False), (_USHORT, True)}),
    "OPACITY": ("SCALAR", {(_FLOAT, False), (_UBYTE, True), (_USHORT, True)}),
    "SH": ("VEC3", {(_FLOAT, False)}),
}
_QUANTIZED_POSITION = {(t, n) for t in (_BYTE, _UBYTE, _SHORT, _USHORT) for n in (False, True)}
# how far from 1 a stored quaternion's length may be: float32 rounding, or the step of a normalised byte / short
_UNIT_TOLERANCE = {_FLOAT: 1e-3, _SHORT: 2e-3, _BYTE: 2.5e-2}
# extensions splatzoo reads (or may ignore) when a file lists them as required
_KNOWN_REQUIRED = {EXTENSION, SURFEL_EXTENSION, "KHR_mesh_quantization"}
_MAX_JSON_BYTES = 64 << 20  # the JSON of a splat file is a few kB: far more is not a splat file
_MAX_NODE_DEPTH = 64
_FIX = "Write it again (splatzoo's glb-splat export, or the tool that made it)"


# --- writing ---------------------------------------------------------------------------------------------------

def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, None)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def _surfel_arrays(model) -> dict[str, np.ndarray]:
    """The glTF attributes of a plain `2dgs` model (float64 numpy, before the cast to float32)."""
    from .model_checks import ZERO_QUATERNION
    from .models.base import LOG_MAX_SCALE

    with torch.no_grad():
        means = model.means.detach().double().cpu().numpy()
        q = model.quats.detach().double().cpu().numpy()
        log_scales = model.log_scales.detach().double().cpu().clamp(max=LOG_MAX_SCALE).numpy()
        logit = model.logit_opacity.detach().double().cpu()
        sh = torch.cat([model.sh_dc, model.sh_rest], 1).detach().double().cpu().numpy()
    norm = np.linalg.norm(q, axis=1)
    zero = norm < ZERO_QUATERNION  # drawn as the identity (model_checks.repair_geometry)
    q = np.where(zero[:, None], np.array([1.0, 0.0, 0.0, 0.0]), q / np.where(zero, 1.0, norm)[:, None])
    # the third sigma: 0, a surfel's thickness as splatzoo's PLY writes it (log 0)
    scales = np.exp(np.concatenate([log_scales, np.full((len(means), 1), FLAT_LOG_SCALE)], 1))
    return {"POSITION": means, "ROTATION": q[:, [1, 2, 3, 0]], "SCALE": scales,
            "OPACITY": torch.sigmoid(logit).numpy(), "SH": sh}


def glb_splat_bytes(model, *, color: bool = True, surfel: dict | None = None) -> bytes:
    """A plain `2dgs` model as a GLB with KHR_gaussian_splatting (the layout of the module docstring); `surfel`: the
    body of the surfel flag (None: {"antialias": model.antialias})."""
    from . import __version__

    if getattr(model, "name", "") != "2dgs":
        raise SplatzooError(f"glb_splat_bytes writes plain 2dgs surfels, not a {getattr(model, 'name', '') or 'model'}"
                            "; bake it first (write_glb_splats does)")
    n = model.num_primitives
    if n == 0:
        raise SplatzooError("the model holds 0 surfels: there is nothing to write")
    arrays = _surfel_arrays(model)
    degree = int(model.config.sh_degree)
    blob = bytearray()
    views, accessors, attributes = [], [], {}

    def add(semantic: str, values: np.ndarray, type_: str, minmax: bool = False) -> None:
        data = np.ascontiguousarray(values, dtype="<f4")
        if not np.isfinite(data).all():
            bad = int((~np.isfinite(data.reshape(n, -1))).any(1).sum())
            raise SplatzooError(f"{bad} of the model's {n} surfels have a non-finite (NaN or inf) {semantic}; the run "
                                "diverged or the model was edited. Export a model without NaN")
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": data.nbytes, "target": _ARRAY_BUFFER})
        blob.extend(data.tobytes())
        accessor = {"bufferView": len(views) - 1, "componentType": _FLOAT, "count": n, "type": type_}
        if minmax:
            flat = data.reshape(n, -1)
            accessor["min"] = [float(v) for v in flat.min(0)]
            accessor["max"] = [float(v) for v in flat.max(0)]
        accessors.append(accessor)
        attributes[semantic] = len(accessors) - 1

    add("POSITION", arrays["POSITION"], "VEC3", minmax=True)
    if color:
        rgb = _srgb_to_linear(np.clip(0.5 + SH_C0 * arrays["SH"][:, 0], 0.0, 1.0))
        add("COLOR_0", np.concatenate([rgb, arrays["OPACITY"][:, None]], 1), "VEC4")
    add(f"{EXTENSION}:ROTATION", arrays["ROTATION"], "VEC4")
    add(f"{EXTENSION}:SCALE", arrays["SCALE"], "VEC3")
    add(f"{EXTENSION}:OPACITY", arrays["OPACITY"], "SCALAR")
    band = 0
    for level in range(degree + 1):
        for coef in range(2 * level + 1):
            add(f"{EXTENSION}:SH_DEGREE_{level}_COEF_{coef}", arrays["SH"][:, band], "VEC3")
            band += 1
    body = {"antialias": bool(getattr(model, "antialias", False))} if surfel is None else dict(surfel)
    doc = {
        "asset": {"version": "2.0", "generator": f"splatzoo {__version__}"},
        "extensionsUsed": [EXTENSION, SURFEL_EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "splatzoo"}],
        "meshes": [{"name": "splatzoo", "primitives": [{
            "attributes": attributes, "mode": 0,
            "extensions": {EXTENSION: {"kernel": "ellipse", "colorSpace": COLOR_SPACE, "projection": "perspective",
                                       "sortingMethod": "cameraDistance",
                                       "extensions": {SURFEL_EXTENSION: body}}}}]}],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
    }
    text = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")
    text += b" " * (-len(text) % 4)
    blob.extend(b"\0" * (-len(blob) % 4))
    total = 12 + 8 + len(text) + 8 + len(blob)
    return b"".join([GLB_MAGIC, struct.pack("<II", 2, total), struct.pack("<II", len(text), _JSON_CHUNK), text,
                     struct.pack("<II", len(blob), _BIN_CHUNK), bytes(blob)])


def save_glb_splats(model, path, *, color: bool = True, surfel: dict | None = None, progress=None) -> Path:
    """Write the plain `2dgs` model to the .glb `path` (atomically), exactly as its surfels stand: the model-file
    format `glb-splat` (splatzoo.model_files). Richer members are baked first by the export (splatzoo.gltf_export's
    write_glb_splats, `splatzoo export --format glb-splat`). Returns the path."""
    from .io import atomic_path, say_progress

    path = check_glb_path(path)
    if getattr(model, "name", "") != "2dgs":
        raise SplatzooError(f"a glb-splat file holds plain 2dgs surfels, not a {getattr(model, 'name', '') or 'model'} "
                            f"model: export it with `splatzoo export RUN --format glb-splat --out {path.name}`, which "
                            "bakes it into plain surfels first")
    data = glb_splat_bytes(model, color=color, surfel=surfel)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    say_progress(progress)(f"{model.num_primitives} surfels written to {path} ({len(data) / 1e6:.2f} MB)")
    return path


def check_glb_path(path) -> Path:
    """`path` as a .glb file to write, or a SplatzooError saying why not (a folder, another suffix)."""
    path = Path(path)
    if path.is_dir():
        raise SplatzooError(f"cannot write the glTF splats to {path}: it is a folder; give a file name such as "
                            f"{path / 'model.glb'}")
    if not path.name.lower().endswith(SUFFIX) or path.name.lower() == SUFFIX:
        raise SplatzooError(f"a glTF binary is written to a .glb file; got {path}. Name it e.g. "
                            f"{path.with_name((path.stem or 'model') + SUFFIX)}")
    return path


# --- reading ---------------------------------------------------------------------------------------------------

def is_glb(path) -> bool:
    """Whether the file at `path` starts with the GLB magic `glTF`."""
    try:
        with open(path, "rb") as f:
            return f.read(4) == GLB_MAGIC
    except OSError:
        return False


class _Reader:
    """The checked contents of one GLB: its JSON and binary chunk, accessors decoded on demand."""

    def __init__(self, path: Path):
        self.path = path
        try:
            found = path.is_file()
            data = path.read_bytes() if found else b""
        except OSError as e:
            raise self.error(f"cannot be read ({e.strerror or e})", fix=False) from None
        if not found:
            raise SplatzooError(f"no glTF file at {path}")
        self.data = data
        if len(data) < 12 or data[:4] != GLB_MAGIC:
            what = ("a glTF JSON file (.gltf), not a glTF binary: pack it into one .glb (e.g. with gltf-pipeline "
                    "-b)" if data.lstrip()[:1] == b"{" else "not a glTF binary file (it does not start with 'glTF')")
            raise self.error(what, fix=False)
        version, length = struct.unpack_from("<II", data, 4)
        if version != 2:
            raise self.error(f"is a glTF binary of version {version}; splatzoo reads glTF 2.0", fix=False)
        if length > len(data):
            raise self.error(f"is truncated: its header promises {length} bytes but the file holds {len(data)}")
        if length < len(data):
            raise self.error(f"has {len(data) - length} bytes beyond the {length} its header declares; the file is "
                             "damaged")
        chunks, offset = [], 12
        while offset < length:
            if offset + 8 > length:
                raise self.error(f"is truncated inside a chunk header at byte {offset}")
            size, kind = struct.unpack_from("<II", data, offset)
            if offset + 8 + size > length:
                raise self.error(f"is truncated: a chunk at byte {offset} promises {size} bytes but only "
                                 f"{length - offset - 8} follow")
            chunks.append((kind, offset + 8, size))
            offset += 8 + size
        if not chunks or chunks[0][0] != _JSON_CHUNK:
            raise self.error("does not start with a JSON chunk; the file is damaged")
        _, start, size = chunks[0]
        if size > _MAX_JSON_BYTES:
            raise self.error(f"has a JSON chunk of {size / 1e6:.0f} MB, far more than a splat file's; it is not one")
        try:
            doc = json.loads(data[start:start + size].decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as e:
            raise self.error(f"holds JSON that cannot be parsed ({str(e)[:120]})") from None
        except RecursionError:
            raise self.error("holds JSON nested too deeply to be glTF") from None
        if not isinstance(doc, dict):
            raise self.error(f"holds a JSON {type(doc).__name__} where glTF has an object")
        self.doc = doc
        self.bin = None
        if len(chunks) > 1 and chunks[1][0] == _BIN_CHUNK:
            _, start, size = chunks[1]
            self.bin = memoryview(data)[start:start + size]
        asset = doc.get("asset")
        if not isinstance(asset, dict) or not isinstance(asset.get("version"), str):
            raise self.error("has no asset.version; it is not a glTF file")
        if not asset["version"].startswith("2."):
            raise self.error(f"is glTF {asset['version']!r}; splatzoo reads glTF 2.0", fix=False)
        required = self.list_of("extensionsRequired", str)
        unknown = [e for e in required if e not in _KNOWN_REQUIRED]
        if unknown:
            raise self.error(f"requires the glTF extension(s) {', '.join(unknown[:4])}, which splatzoo does not read "
                             "(compressed or quantised splats?); convert it to plain KHR_gaussian_splatting "
                             "attributes first", fix=False)
        self.used = set(self.list_of("extensionsUsed", str))

    def error(self, problem: str, fix: bool = True) -> SplatzooError:
        return SplatzooError(f"{self.path} {problem}" + (f". {_FIX}" if fix else ""))

    def list_of(self, key: str, kind, where=None) -> list:
        where = self.doc if where is None else where
        value = where.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, kind) and not isinstance(v, bool) for v in value):
            raise self.error(f"has a glTF {key!r} that is not a list of {kind.__name__} values")
        return value

    def item(self, key: str, index) -> dict:
        """doc[key][index], checked."""
        items = self.list_of(key, dict)
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(items):
            raise self.error(f"refers to {key}[{index!r}] but holds {len(items)} {key}")
        return items[index]

    @staticmethod
    def whole(value, lo: int = 0) -> bool:
        return isinstance(value, int) and not isinstance(value, bool) and value >= lo

    def accessor(self, index, what: str, kind: str, count: int | None = None) -> np.ndarray:
        """Accessor `index` as float64 [count, width], checked against the encodings the spec allows `kind` (a key
        of _ALLOWED), decoded (normalised integers to -1..1 or 0..1)."""
        acc = self.item("accessors", index)
        type_, allowed = _ALLOWED[kind]
        if kind == "POSITION" and "KHR_mesh_quantization" in self.used:
            allowed = allowed | _QUANTIZED_POSITION
        if acc.get("type") != type_:
            raise self.error(f"has the {what} attribute in an accessor of type {acc.get('type')!r}; the spec wants "
                             f"{type_}")
        component, normalized = acc.get("componentType"), acc.get("normalized", False)
        if not (isinstance(component, int) and isinstance(normalized, bool)) or (component, normalized) not in allowed:
            known = isinstance(component, int) and not isinstance(component, bool) and component in _COMPONENT_NAMES
            name = (_COMPONENT_NAMES[component] if known else f"component type {component!r}") + (
                " normalized" if normalized is True else "")
            ok = ", ".join(_COMPONENT_NAMES[t] + (" normalized" if n else "") for t, n in sorted(allowed))
            raise self.error(f"stores the {what} attribute as {name}; the spec allows {ok}")
        n = acc.get("count")
        if not self.whole(n, 1):
            raise self.error(f"has an accessor for {what} with count {n!r}; a count is a whole number of at least 1")
        if count is not None and n != count:
            raise self.error(f"has {n} {what} values for {count} splats; every attribute holds one per splat")
        if "sparse" in acc:
            raise self.error(f"stores {what} in a sparse accessor, which splatzoo does not read; write it dense")
        if "bufferView" not in acc:
            raise self.error(f"has no bufferView for {what} (an accessor of zeros is no splat data)")
        view = self.item("bufferViews", acc["bufferView"])
        buffer_index = view.get("buffer")
        buffer = self.item("buffers", buffer_index)
        if "uri" in buffer or buffer_index != 0 or self.bin is None:
            raise self.error(f"keeps {what} in a buffer outside the GLB's binary chunk (an external file or a data "
                             "URI), which splatzoo does not read; pack it into one .glb", fix=False)
        declared = buffer.get("byteLength")
        if not self.whole(declared, 1) or declared > len(self.bin):
            raise self.error(f"declares a buffer of {declared!r} bytes but its binary chunk holds {len(self.bin)}")
        v_off, v_len, a_off = view.get("byteOffset", 0), view.get("byteLength"), acc.get("byteOffset", 0)
        if not (self.whole(v_off) and self.whole(v_len, 1) and self.whole(a_off)):
            raise self.error(f"has a malformed bufferView or accessor offset for {what}")
        if v_off + v_len > declared:
            raise self.error(f"has a bufferView for {what} of bytes {v_off}..{v_off + v_len}, past the end of its "
                             f"{declared}-byte buffer; the file is truncated or damaged")
        item = np.dtype(_COMPONENTS[component]).itemsize
        width = _WIDTH[type_]
        element = item * width
        stride = view.get("byteStride", element)
        if not self.whole(stride, element) or stride > 252:
            raise self.error(f"has a byteStride of {stride!r} for {what}; it must lie between the element's "
                             f"{element} bytes and 252")
        needed = a_off + stride * (n - 1) + element
        if needed > v_len:
            raise self.error(f"promises {n} {what} values ({needed} bytes) in a bufferView of {v_len} bytes; the "
                             "count is wrong or the file is truncated")
        raw = np.frombuffer(self.bin, dtype=np.uint8, count=needed, offset=v_off)[a_off:]
        if stride == element:
            values = np.frombuffer(raw.tobytes(), dtype=_COMPONENTS[component], count=n * width).reshape(n, width)
        else:
            rows = np.lib.stride_tricks.as_strided(raw, shape=(n, element), strides=(stride, 1))
            values = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=_COMPONENTS[component]).reshape(n, width)
        out = values.astype(np.float64)
        if normalized:
            info = np.iinfo(values.dtype)
            out = np.maximum(out / info.max, -1.0) if info.min < 0 else out / info.max
        bad = ~np.isfinite(out).all(1)
        if bad.any():
            raise self.error(f"holds {int(bad.sum())} {what} value(s) that are NaN or infinite (of {n})")
        return out


@dataclass
class _Splats:
    """Splats of one primitive in world coordinates."""

    means: np.ndarray           # [N,3]
    quats: np.ndarray           # [N,4] (w, x, y, z), unit
    scales: np.ndarray          # [N,3] linear sigmas
    opacity: np.ndarray         # [N]
    sh: np.ndarray              # [N, (degree+1)^2, 3]
    surfel: dict | None         # the body of the surfel flag, or None
    exact: bool                 # untransformed: a surfel file's values are the model's
    notes: list = field(default_factory=list)


def _node_matrix(reader: _Reader, node: dict) -> np.ndarray:
    """A node's local transform [4,4] (float64)."""
    def numbers(key, count, default):
        value = node.get(key, default)
        if (not isinstance(value, list) or len(value) != count
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
                or not all(math.isfinite(v) for v in value)):
            raise reader.error(f"has a node whose {key} is not {count} finite numbers")
        return np.array(value, dtype=np.float64)

    if "matrix" in node:
        return numbers("matrix", 16, None).reshape(4, 4).T  # glTF stores it column by column
    t = numbers("translation", 3, [0, 0, 0])
    x, y, z, w = numbers("rotation", 4, [0, 0, 0, 1])
    s = numbers("scale", 3, [1, 1, 1])
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(norm - 1) > 1e-3:
        raise reader.error(f"has a node rotation of length {norm:.6g}; glTF rotations are unit quaternions")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = R * s[None, :]
    m[:3, 3] = t
    return m


def _mesh_instances(reader: _Reader) -> list[tuple[int, np.ndarray]]:
    """(mesh index, global transform) of every node of the file's scene that holds a mesh; with no scenes, every
    root node; with no nodes at all, every mesh untransformed."""
    doc = reader.doc
    nodes = reader.list_of("nodes", dict)
    scenes = reader.list_of("scenes", dict)
    if not nodes:
        return [(i, np.eye(4)) for i in range(len(reader.list_of("meshes", dict)))]
    if scenes:
        scene = reader.item("scenes", doc.get("scene", 0))
        roots = reader.list_of("nodes", int, scene)
    else:
        children = {c for node in nodes for c in reader.list_of("children", int, node)}
        roots = [i for i in range(len(nodes)) if i not in children]
    out, seen = [], set()

    def visit(index, parent, depth):
        node = reader.item("nodes", index)
        if index in seen or depth > _MAX_NODE_DEPTH:
            raise reader.error(f"has a node hierarchy that loops or nests deeper than {_MAX_NODE_DEPTH} (node {index})")
        seen.add(index)
        matrix = parent @ _node_matrix(reader, node)
        if "mesh" in node:
            reader.item("meshes", node["mesh"])
            out.append((node["mesh"], matrix))
        for child in reader.list_of("children", int, node):
            visit(child, matrix, depth + 1)

    for root in roots:
        visit(root, np.eye(4), 0)
    return out


def _sh_rotation(R: np.ndarray, degree: int) -> list[np.ndarray]:
    """Per SH degree l >= 1, the matrix D_l [2l+1, 2l+1] that turns a splat's coefficients of that degree when its
    directions turn by the rotation R: coefficients k' = D_l k make sum k'_j Y_j(R d) = sum k_j Y_j(d). Fitted on
    directions spread over the sphere with splatzoo's own SH basis (geometry.eval_sh), so it follows its
    convention."""
    from .geometry import eval_sh

    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    bands = (degree + 1) ** 2

    def basis(d: np.ndarray) -> np.ndarray:  # [K, bands]: every basis function at each direction
        k = len(d)
        coeffs = torch.zeros(k * bands, bands, 3, dtype=torch.float64)
        coeffs[torch.arange(k * bands), torch.arange(bands).repeat(k), 0] = 1.0
        d_rep = torch.from_numpy(d).repeat_interleave(bands, 0)
        return eval_sh(degree, coeffs, d_rep)[:, 0].reshape(k, bands).numpy()

    before, after = basis(dirs), basis(dirs @ R)  # Y(R^T d) for each row d
    out = []
    for level in range(1, degree + 1):
        cols = slice(level * level, (level + 1) ** 2)
        D, *_ = np.linalg.lstsq(before[:, cols], after[:, cols], rcond=None)  # Y(d) D = Y(R^T d)
        out.append(D)
    return out


def _primitive_splats(reader: _Reader, primitive: dict, matrix: np.ndarray, where: str) -> _Splats:
    ext = primitive["extensions"][EXTENSION]
    if not isinstance(ext, dict):
        raise reader.error(f"has a {EXTENSION} extension on {where} that is not a JSON object")
    notes = []
    mode = primitive.get("mode", 4)
    if mode != 0:
        raise reader.error(f"has Gaussian splats on {where} with mode {mode!r}; {EXTENSION} needs POINTS (0)")
    kernel, space = ext.get("kernel"), ext.get("colorSpace")
    if kernel != "ellipse":
        if not isinstance(kernel, str):
            raise reader.error(f"has no kernel in the {EXTENSION} extension of {where} (it is required)")
        notes.append(f"{reader.path}: {where} uses the kernel {kernel!r}, which splatzoo does not know; read as "
                     "'ellipse', as the spec asks of readers")
    if space not in ("srgb_rec709_display", "lin_rec709_display"):
        raise reader.error(f"has the colorSpace {space!r} on {where}; splatzoo reads srgb_rec709_display and "
                           "lin_rec709_display")
    nested = ext.get("extensions", {})
    surfel = nested.get(SURFEL_EXTENSION) if isinstance(nested, dict) else None
    surfel = surfel if isinstance(surfel, dict) else None
    attributes = primitive.get("attributes")
    if not isinstance(attributes, dict):
        raise reader.error(f"has no attributes on {where}")
    required = ("POSITION", f"{EXTENSION}:ROTATION", f"{EXTENSION}:SCALE", f"{EXTENSION}:OPACITY",
                f"{EXTENSION}:SH_DEGREE_0_COEF_0")
    missing = [k for k in required if k not in attributes]
    if missing:
        raise reader.error(f"lacks the attribute(s) {', '.join(missing)} that {EXTENSION} requires on {where}")
    means = reader.accessor(attributes["POSITION"], "POSITION", "POSITION")
    n = len(means)
    rot = reader.accessor(attributes[f"{EXTENSION}:ROTATION"], "ROTATION", "ROTATION", n)
    scales = reader.accessor(attributes[f"{EXTENSION}:SCALE"], "SCALE", "SCALE", n)
    opacity = reader.accessor(attributes[f"{EXTENSION}:OPACITY"], "OPACITY", "OPACITY", n)[:, 0]
    component = reader.item("accessors", attributes[f"{EXTENSION}:ROTATION"])["componentType"]
    length = np.linalg.norm(rot, axis=1)
    off = np.abs(length - 1) > _UNIT_TOLERANCE[component]
    if off.any():
        i = int(np.argmax(off))
        raise reader.error(f"holds {int(off.sum())} rotation(s) that are not unit quaternions (splat {i} has length "
                           f"{length[i]:.6g}); the spec stores unit quaternions")
    negative = (scales < 0).any(1)
    if negative.any():
        raise reader.error(f"holds {int(negative.sum())} negative scale(s) (of {n} splats); scales are sigmas, "
                           "never negative")
    outside = (opacity < 0) | (opacity > 1)
    if outside.any():
        raise reader.error(f"holds {int(outside.sum())} opacities outside 0..1 (e.g. {opacity[outside][0]:.6g}); the "
                           "spec stores linear opacity in 0..1")
    degree = 0
    for level in (1, 2, 3):
        present = [f"{EXTENSION}:SH_DEGREE_{level}_COEF_{c}" in attributes for c in range(_SH_COEFS[level])]
        if any(present) and not all(present):
            raise reader.error(f"defines SH degree {level} partially ({sum(present)} of its {_SH_COEFS[level]} "
                               f"coefficients) on {where}; degrees are whole or absent")
        if all(present):
            if degree != level - 1:
                raise reader.error(f"defines SH degree {level} without degree {level - 1} on {where}")
            degree = level
    later = [k for k in attributes if k.startswith(f"{EXTENSION}:SH_DEGREE_")
             and k not in {f"{EXTENSION}:SH_DEGREE_{lv}_COEF_{c}" for lv in range(degree + 1)
                           for c in range(2 * lv + 1)}]
    if later:
        raise reader.error(f"has SH attributes {', '.join(sorted(later)[:3])} beyond whole degrees 0..{degree} on "
                           f"{where}")
    sh = np.stack([reader.accessor(attributes[f"{EXTENSION}:SH_DEGREE_{lv}_COEF_{c}"], f"SH_DEGREE_{lv}_COEF_{c}",
                                   "SH", n) for lv in range(degree + 1) for c in range(2 * lv + 1)], 1)
    quats = (rot / length[:, None])[:, [3, 0, 1, 2]]
    if space == "lin_rec709_display":
        display = _linear_to_srgb(0.5 + SH_C0 * sh[:, 0])
        sh[:, 0] = (display - 0.5) / SH_C0
        notes.append(f"{reader.path}: {where} holds linear colours (lin_rec709_display); their DC term was converted "
                     "to display colours, the view-dependent terms kept as they are")
    identity = bool(np.array_equal(matrix, np.eye(4)))
    if not identity:
        means, quats, scales, sh = _transformed(reader, matrix, means, quats, scales, sh, degree)
    return _Splats(means, quats, scales, opacity, sh, surfel, identity, notes)


def _transformed(reader, matrix, means, quats, scales, sh, degree):
    """Splats carried through a node's global transform: positions by the affine map, covariances M S S^T M^T
    (split again into a rotation and three sigmas), SH coefficients turned by the map's rotation."""
    from .geometry import quat_to_rotmat, rotmat_to_quat

    M = matrix[:3, :3]
    if abs(np.linalg.det(M)) < 1e-30 or not np.isfinite(M).all():
        raise reader.error("places its splats under a node transform that flattens space (determinant 0)")
    means = means @ M.T + matrix[:3, 3]
    R = quat_to_rotmat(torch.from_numpy(quats)).numpy()
    A = M @ (R * scales[:, None, :])                   # M R diag(s): the covariance is A A^T
    cov = A @ A.transpose(0, 2, 1)
    values, vectors = np.linalg.eigh(cov)              # ascending
    values, vectors = values[:, ::-1], vectors[:, :, ::-1].copy()
    flip = np.linalg.det(vectors) < 0
    vectors[flip, :, 2] *= -1                          # a rotation, not a mirror
    quats = rotmat_to_quat(torch.from_numpy(vectors)).numpy()
    scales = np.sqrt(np.clip(values, 0.0, None))
    if degree:
        U, _, Vt = np.linalg.svd(M)
        rotation = U @ Vt                              # the rotation (or mirror) part of the transform
        for level, D in enumerate(_sh_rotation(rotation, degree), start=1):
            cols = slice(level * level, (level + 1) ** 2)
            sh[:, cols] = np.einsum("ij,njc->nic", D, sh[:, cols])
    return means, quats, scales, sh


def read_glb_splats(path):
    """The `2dgs` model of a glTF binary with KHR_gaussian_splatting splats (see the module docstring). Notes on
    what was converted (3DGS Gaussians flattened, transforms applied, surfels repaired) are warnings and land in
    `model.notes`."""
    from .model_checks import check_draws, repair_geometry
    from .zoo import create_model

    path = Path(path)
    reader = _Reader(path)
    instances = _mesh_instances(reader)
    parts: list[_Splats] = []
    for mesh_index, matrix in instances:
        mesh = reader.item("meshes", mesh_index)
        for p, primitive in enumerate(reader.list_of("primitives", dict, mesh)):
            extensions = primitive.get("extensions")
            if isinstance(extensions, dict) and EXTENSION in extensions:
                parts.append(_primitive_splats(reader, primitive, matrix, f"mesh {mesh_index} primitive {p}"))
    if not parts:
        raise reader.error(f"holds no Gaussian splats (no mesh primitive of its scene has the {EXTENSION} "
                           "extension): it is a mesh or point cloud, not a splat model", fix=False)
    degree = max(round(math.sqrt(p.sh.shape[1])) - 1 for p in parts)
    bands = (degree + 1) ** 2

    def padded(sh):  # a primitive of a lower degree has no view dependence in the higher ones: zeros
        return np.concatenate([sh, np.zeros((len(sh), bands - sh.shape[1], 3))], 1)

    means = np.concatenate([p.means for p in parts])
    quats = np.concatenate([p.quats for p in parts])
    scales = np.concatenate([p.scales for p in parts])
    opacity = np.concatenate([p.opacity for p in parts])
    sh = np.concatenate([padded(p.sh) for p in parts])
    notes = [note for p in parts for note in p.notes]
    n = len(means)
    if n and (np.abs(means) > np.finfo(np.float32).max).any():
        raise reader.error("places splats beyond the range of float32 (after its node transforms)")
    tiny = float(np.finfo(np.float32).smallest_subnormal)
    with np.errstate(divide="ignore"):
        log_scales = np.log(np.maximum(scales, tiny * 0.5))   # a sigma of 0 is below every float32 log
    # the surfels written by splatzoo, untransformed, read back as they are; everything else is flattened
    exact = np.concatenate([np.full(len(p.means), p.surfel is not None and p.exact) for p in parts])
    thick = exact & (scales[:, 2] > 0)
    if thick.any():
        raise reader.error(f"flags its splats as splatzoo surfels ({SURFEL_EXTENSION}) but {int(thick.sum())} have a "
                           "third scale above 0; the file is damaged")
    out_log, out_quats = log_scales[:, :2].copy(), quats.copy()
    rest = ~exact
    if rest.any():
        flat_log, flat_quats, far = flatten_gaussians(log_scales[rest], quats[rest])
        out_log[rest], out_quats[rest] = flat_log, flat_quats
        foreign = np.concatenate([np.full(len(p.means), p.surfel is None) for p in parts])
        if (scales[foreign, 2] > 0).any():
            notes.append(f"{path} holds 3D Gaussians (three scales): each was read as the 2D surfel spanning its two "
                         f"largest axes, its thinnest axis becoming the normal; {far} of {int(rest.sum())} were far "
                         "from flat (thinnest axis over a tenth of the next), so renders differ from a 3DGS "
                         "renderer's there")
    with np.errstate(divide="ignore"):
        logit = np.log(opacity) - np.log1p(-opacity)
    logit = np.clip(logit, -SATURATED_LOGIT, SATURATED_LOGIT)  # opacity 0 or 1: as a PLY's -inf / +inf logit
    model = create_model("2dgs", sh_degree=degree)
    model.replace_parameters({
        "means": torch.from_numpy(means.astype(np.float32)),
        "quats": torch.from_numpy(out_quats.astype(np.float32)),
        "log_scales": torch.from_numpy(out_log.astype(np.float32)),
        "logit_opacity": torch.from_numpy(logit.astype(np.float32)),
        "sh_dc": torch.from_numpy(sh[:, :1].astype(np.float32)),
        "sh_rest": torch.from_numpy(sh[:, 1:].astype(np.float32)),
    })
    bodies = [p.surfel for p in parts if p.surfel is not None]
    model.antialias = bool(bodies) and all(b.get("antialias") is True for b in bodies)
    if any(b.get("viewer") not in (None, "exact") for b in bodies):
        notes.append(f"{path}: its surfels were sized for the dilation of 3DGS-style viewers (viewer="
                     f"{bodies[0].get('viewer')}), not as trained, so splatzoo's renders of it are thinner")
    check_draws(model, str(path), "pass another file")
    notes += [f"{path}: {note}" for note in repair_geometry(model)]
    model.notes = notes
    for note in notes:
        warnings.warn(note, UserWarning, stacklevel=2)
    return model
