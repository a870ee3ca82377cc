"""A model stored at the precision it needs: the packed model file (`.szp`).

A model's checkpoint (SplatModel.checkpoint(): name, config, render settings, and the state its own loader reads, e.g.
adaptive waves packed surfel by surfel) is written tensor by tensor in one of these precisions:

- `float32`: every value as trained;
- `float16`: positions as 16-bit fixed point over each axis's range, every other float value as a half float (a
  tensor with a value beyond a half float's range as it is);
- `8bit`: positions as 16-bit fixed point over each axis's range, every other float value as an 8-bit code over its
  column's range (one float32 minimum and step per column, as SPZ and SOG store colours and scales).

Integer buffers (wave counts, slot indices) are stored as they are. What `quantise_state` gives is exactly what the
packed file of the same state loads back as, so a model can be fine-tuned with its stored values in the forward pass
(Trainer, TrainConfig.store) and its numbers reported at the quality of its file. Packing stored values again moves
them by float32 rounding at most (a column's range is recomputed from decoded values).

The file: the 4 bytes `SZPK`, a little-endian uint32 header length, the header (UTF-8 JSON, zlib-compressed: format
version, model, config, render settings, precision, and per tensor its name, shape, dtype and encoding), then each
tensor's bytes in the header's order. Version 2 compresses the header with a preset dictionary,
`packed_header_dictionary.jsonl` (the headers of the built-in models as they were when version 2 was made; fixed for
good, since every version-2 file needs it): a beta-gabor header shrinks from about 390 bytes to about 100, which is
what a small budget's file spends on surfels instead. Version 1 files (no dictionary) still load. It is read without running code: the header is parsed and checked, and every
size is checked against the file before anything is decoded.
"""
from __future__ import annotations

import functools
import json
import math
import struct
import zlib
from pathlib import Path

import numpy as np
import torch

from .errors import SplatzooError
from .io import strict_json

MAGIC = b"SZPK"
VERSION = 2
READABLE_VERSIONS = (1, 2)
SUFFIX = ".szp"
PRECISIONS = ("float32", "float16", "8bit")
POSITION_FIELDS = ("means",)  # stored at 16 bits in the reduced precisions: a step of 1/65535 of the scene's span
MAX_HEADER = 1 << 24
F16_MAX = float(np.finfo(np.float16).max)

# the dtypes a stored tensor may have (by name), and the fixed-point codes (numpy dtype, bits)
_DTYPES = {"float32": np.float32, "float64": np.float64, "float16": np.float16, "int64": np.int64,
           "int32": np.int32, "int16": np.int16, "uint8": np.uint8, "bool": np.bool_}
_CODES = {"u8": (np.uint8, 8), "u16": (np.uint16, 16)}
_FIX = "pass a .szp file written by splatzoo (save_model or a run trained with --store)"


@functools.cache
def header_dictionary() -> bytes:
    """The preset zlib dictionary of version-2 headers (module docstring). Never edit the file: files name its
    checksum and do not inflate without it."""
    return (Path(__file__).with_name("packed_header_dictionary.jsonl")).read_bytes()


def check_precision(precision: str) -> str:
    if precision not in PRECISIONS:
        raise SplatzooError(f"unknown storage precision {precision!r}; choose one of {', '.join(PRECISIONS)}")
    return precision


def encoding_for(name: str, tensor: torch.Tensor, precision: str) -> str:
    """How tensor `name` is stored at `precision`: raw, f16, u8 or u16. At float16 a tensor with a value beyond a
    half float's range (65504) stays raw: as a half float it would load back as infinity."""
    if precision == "float32" or not tensor.is_floating_point() or tensor.dim() == 0 or tensor.numel() == 0:
        return "raw"
    if name in POSITION_FIELDS:
        return "u16"
    if precision == "float16":
        return "f16" if float(tensor.detach().abs().max()) <= F16_MAX else "raw"
    return "u8"


def value_bytes(name: str, tensor: torch.Tensor, precision: str) -> int:
    """Bytes one value of tensor `name` takes in the packed file at `precision` (its column's minimum and step,
    shared by every row, not counted)."""
    encoding = encoding_for(name, tensor, precision)
    return {"raw": tensor.element_size(), "f16": 2, "u8": 1, "u16": 2}[encoding]


def _columns(array: np.ndarray) -> np.ndarray:
    """[rows, columns]: a per-primitive tensor's first dimension is its rows, the rest its columns."""
    return array.reshape(array.shape[0], -1) if array.ndim > 1 else array.reshape(-1, 1)


def _encode_fixed(array: np.ndarray, bits: int):
    """(minimum [C] float32, step [C] float32, codes) of each column over its own range."""
    x = _columns(array.astype(np.float64))
    lo = x.min(0).astype(np.float32)
    span = x.max(0) - lo.astype(np.float64)
    levels = (1 << bits) - 1
    step = (span / levels).astype(np.float32)
    safe = np.where(step > 0, step.astype(np.float64), 1.0)
    codes = np.clip(np.rint((x - lo.astype(np.float64)) / safe), 0, levels)
    return lo, step, codes.astype(_CODES["u8" if bits == 8 else "u16"][0])


def _decode_fixed(lo: np.ndarray, step: np.ndarray, codes: np.ndarray, shape) -> np.ndarray:
    x = lo.astype(np.float32)[None] + codes.astype(np.float32) * step.astype(np.float32)[None]
    return x.reshape(shape)


def quantise_tensor(name: str, tensor: torch.Tensor, precision: str) -> torch.Tensor:
    """The values tensor `name` loads back as when stored at `precision` (same dtype, shape and device)."""
    encoding = encoding_for(name, tensor, precision)
    if encoding == "raw":
        return tensor
    array = tensor.detach().cpu().numpy()
    if encoding == "f16":
        back = array.astype(np.float16).astype(array.dtype)
    else:
        back = _decode_fixed(*_encode_fixed(array, _CODES[encoding][1]), array.shape)
    return torch.from_numpy(np.ascontiguousarray(back)).to(tensor.device, tensor.dtype)


def quantise_state(state: dict, precision: str) -> dict:
    return {k: quantise_tensor(k, v, precision) for k, v in state.items()}


def pack_checkpoint(ckpt: dict, precision: str) -> bytes:
    """The .szp file of a checkpoint (SplatModel.checkpoint()) at `precision`."""
    check_precision(precision)
    entries, blobs = [], []
    for name, tensor in ckpt["state"].items():
        array = tensor.detach().cpu().contiguous().numpy()
        dtype = str(array.dtype)
        if dtype not in _DTYPES:
            raise SplatzooError(f"cannot pack {name}: dtype {dtype} is not storable")
        encoding = encoding_for(name, tensor, precision)
        if encoding == "raw":
            blobs.append(array.tobytes())
        elif encoding == "f16":
            blobs.append(array.astype(np.float16).tobytes())
        else:
            lo, step, codes = _encode_fixed(array, _CODES[encoding][1])
            blobs += [lo.astype("<f4").tobytes(), step.astype("<f4").tobytes(), codes.tobytes()]
        entries.append({"name": name, "shape": list(array.shape), "dtype": dtype, "encoding": encoding})
    header = {"format": "splatzoo-packed", "version": VERSION, "model": ckpt["model"], "config": ckpt["config"],
              "precision": precision, "tensors": entries,
              **{k: ckpt[k] for k in ("antialias", "background") if k in ckpt}}
    deflate = zlib.compressobj(9, zdict=header_dictionary())
    text = deflate.compress(json.dumps(header, separators=(",", ":")).encode()) + deflate.flush()
    return MAGIC + struct.pack("<I", len(text)) + text + b"".join(blobs)


def is_packed(path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(4) == MAGIC
    except OSError:
        return False


def _fail(where: str, problem: str) -> SplatzooError:
    return SplatzooError(f"{where}: {problem}; {_FIX}")


def _shape(value, where: str, name: str) -> tuple[int, ...]:
    if not isinstance(value, list) or len(value) > 8 or not all(
            isinstance(d, int) and not isinstance(d, bool) and 0 <= d < 2**40 for d in value):
        raise _fail(where, f"tensor {name!r} has an invalid shape {str(value)[:80]}")
    return tuple(value)


def unpack_checkpoint(data: bytes, where: str = "packed model") -> dict:
    """The checkpoint dict of a .szp file's bytes (then checked as any checkpoint by zoo.model_from_checkpoint).
    A damaged or crafted file is a SplatzooError naming the problem."""
    if len(data) < 8 or data[:4] != MAGIC:
        raise _fail(where, "not a splatzoo packed model (no SZPK header)")
    (length,) = struct.unpack_from("<I", data, 4)
    if length > MAX_HEADER or 8 + length > len(data):
        raise _fail(where, f"its header claims {length} bytes but the file holds {len(data) - 8} after the magic: "
                           "the file is truncated or damaged")
    try:
        inflate = zlib.decompressobj(zdict=header_dictionary())  # used only by a stream that asks for it (v2)
        text = inflate.decompress(data[8:8 + length], MAX_HEADER)  # bounded: a crafted header cannot balloon
        if inflate.unconsumed_tail or not inflate.eof:
            raise ValueError(f"it does not inflate to a whole header of at most {MAX_HEADER} bytes")
        header = strict_json(text.decode())
    except (zlib.error, UnicodeDecodeError, ValueError) as e:
        raise _fail(where, f"its header is not valid compressed JSON ({str(e)[:100]})") from None
    if not isinstance(header, dict) or header.get("format") != "splatzoo-packed":
        raise _fail(where, "its header is not a splatzoo packed model's")
    if header.get("version") not in READABLE_VERSIONS:
        raise _fail(where, f"format version {str(header.get('version'))[:20]} is not one this splatzoo reads "
                           f"({', '.join(map(str, READABLE_VERSIONS))}); update splatzoo")
    if header.get("precision") not in PRECISIONS:
        raise _fail(where, f"unknown precision {str(header.get('precision'))[:40]!r}")
    tensors = header.get("tensors")
    if not isinstance(tensors, list):
        raise _fail(where, "its header lists no tensors")
    offset, state = 8 + length, {}

    def take(n: int, what: str) -> bytes:
        nonlocal offset
        if offset + n > len(data):
            raise _fail(where, f"the file ends inside {what} (needs {n} bytes at {offset}, has {len(data)}): it is "
                               "truncated")
        chunk = data[offset:offset + n]
        offset += n
        return chunk

    for entry in tensors:
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise _fail(where, "a tensor entry has no name")
        name = entry["name"]
        if name in state:
            raise _fail(where, f"tensor {name!r} appears twice")
        shape = _shape(entry.get("shape"), where, name)
        dtype, encoding = entry.get("dtype"), entry.get("encoding")
        if dtype not in _DTYPES:
            raise _fail(where, f"tensor {name!r} has an unknown dtype {str(dtype)[:40]!r}")
        count = math.prod(shape)
        np_dtype = np.dtype(_DTYPES[dtype])
        if encoding == "raw":
            array = np.frombuffer(take(count * np_dtype.itemsize, name), np_dtype).reshape(shape)
        elif encoding == "f16" and np_dtype.kind == "f":
            array = np.frombuffer(take(count * 2, name), np.float16).astype(np_dtype).reshape(shape)
        elif encoding in _CODES and np_dtype.kind == "f" and count > 0:
            cols = math.prod(shape[1:]) if len(shape) > 1 else 1
            lo = np.frombuffer(take(4 * cols, name), "<f4")
            step = np.frombuffer(take(4 * cols, name), "<f4")
            code_type = np.dtype(_CODES[encoding][0])
            codes = np.frombuffer(take(count * code_type.itemsize, name), code_type).reshape(-1, cols)
            array = _decode_fixed(lo, step, codes, shape).astype(np_dtype)
        else:
            raise _fail(where, f"tensor {name!r} has an unknown encoding {str(encoding)[:40]!r} for {dtype}")
        state[name] = torch.from_numpy(np.array(array))
    if offset != len(data):
        raise _fail(where, f"{len(data) - offset} bytes follow the last tensor: the file is damaged")
    ckpt = {"model": header.get("model"), "config": header.get("config"), "state": state,
            "precision": header["precision"]}
    for key in ("antialias", "background"):
        if key in header:
            ckpt[key] = header[key]
    return ckpt


def read_packed(path) -> dict:
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise SplatzooError(f"packed model {path} cannot be read ({e.strerror or e}); {_FIX}") from None
    return unpack_checkpoint(data, f"packed model {path}")
