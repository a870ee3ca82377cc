"""A model stored at the precision it needs: the packed model file (`.szp`).

A model's checkpoint (SplatModel.checkpoint(): name, config, render settings, and the state its own loader reads, e.g.
adaptive waves packed surfel by surfel) is written tensor by tensor in one of these precisions:

- `float32`: every value as trained;
- `float16`: positions as 16-bit fixed point over each axis's range, every other float value as a half float (a
  tensor with a value beyond a half float's range as it is);
- `8bit`: positions as 16-bit fixed point over each axis's range, every other float value as an 8-bit code over its
  column's range (a minimum and a step per column, as SPZ and SOG store colours and scales). A tensor's minima and
  steps are half floats where that moves no value of it by more than its code's own rounding (half a step; a
  constant column is its value as a half float), and float32 otherwise (and always for 16-bit codes, whose steps
  are finer than a half float resolves).

Integer buffers (wave counts, slot indices) are stored as they are. What `quantise_state` gives is exactly what the
packed file of the same state loads back as, so a model can be fine-tuned with its stored values in the forward pass
(Trainer, TrainConfig.store) and its numbers reported at the quality of its file. Packing stored values again moves
them by float32 rounding at most (a column's range is recomputed from decoded values).

The file: the 4 bytes `SZPK`, a little-endian uint32 header length, the header (UTF-8 JSON, zlib-compressed: format
version, model, config, precision, per tensor its name, dtype, encoding and shape, and render settings), then each
tensor's bytes in the header's order. The header is compressed with a preset dictionary, the headers of the built-in
models as they were when its version was made: a small budget's file spends on surfels what its header no longer
takes. The zlib stream names its dictionary by checksum (RFC 1950's DICTID), and each dictionary is fixed for good,
since every file written with it needs it:

- version 3 (`packed_header_dictionary_v3.jsonl`): each tensor's entry gives its columns (shape[1:]) and the
  header's `rows` list, last, the first dimension of each (null: a 0-d tensor), so all before it, which every file
  of a model at a precision shares, compresses against the dictionary as a few long runs; half-float column ranges
  (`u8h`);
- version 2 (`packed_header_dictionary.jsonl`): each tensor's shape in its entry;
- version 1: as version 2, without a dictionary.

Every version still loads. A file is read without running code: the header is parsed and checked, and every size is
checked against the file before anything is decoded.
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
VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
# each version's preset header dictionary (module docstring); never edit one a version has used
DICTIONARY_FILES = {2: "packed_header_dictionary.jsonl", 3: "packed_header_dictionary_v3.jsonl"}
SUFFIX = ".szp"
PRECISIONS = ("float32", "float16", "8bit")
POSITION_FIELDS = ("means",)  # stored at 16 bits in the reduced precisions: a step of 1/65535 of the scene's span
MAX_HEADER = 1 << 24
F16_MAX = float(np.finfo(np.float16).max)

# the dtypes a stored tensor may have (by name), and the fixed-point codes (numpy dtype, bits, the dtype of their
# columns' minima and steps)
_DTYPES = {"float32": np.float32, "float64": np.float64, "float16": np.float16, "int64": np.int64,
           "int32": np.int32, "int16": np.int16, "uint8": np.uint8, "bool": np.bool_}
# (u16 never has half-float ranges: its steps are finer than a half float resolves)
_CODES = {"u8": (np.uint8, 8, "<f4"), "u16": (np.uint16, 16, "<f4"), "u8h": (np.uint8, 8, "<f2")}
_FIX = "pass a .szp file written by splatzoo (save_model or a run trained with --store)"


@functools.cache
def header_dictionary(version: int = VERSION) -> bytes:
    """The preset zlib dictionary of `version`'s headers (module docstring). Never edit the file: files name its
    checksum and do not inflate without it."""
    return (Path(__file__).with_name(DICTIONARY_FILES[version])).read_bytes()


@functools.cache
def _dictionaries() -> dict[int, bytes]:
    """Every header dictionary by its Adler-32, the checksum a zlib stream names it by."""
    return {zlib.adler32(d): d for d in map(header_dictionary, DICTIONARY_FILES)}


def _inflater(stream: bytes):
    """A decompressor for the zlib stream `stream`, with the preset dictionary it names (RFC 1950: FLG's bit 5, then
    the dictionary's Adler-32 big-endian), if any."""
    if len(stream) >= 6 and stream[1] & 0x20:
        (checksum,) = struct.unpack_from(">I", stream, 2)
        if checksum not in _dictionaries():
            raise ValueError("it was compressed with a dictionary this splatzoo does not have; update splatzoo")
        return zlib.decompressobj(zdict=_dictionaries()[checksum])
    return zlib.decompressobj()


def read_header(data: bytes) -> dict:
    """The header of a packed file's bytes as parsed JSON (unpack_checkpoint checks it). ValueError (zlib.error is
    one) if it does not inflate to JSON."""
    (length,) = struct.unpack_from("<I", data, 4)
    stream = data[8:8 + length]
    inflate = _inflater(stream)
    text = inflate.decompress(stream, MAX_HEADER)  # bounded: a crafted header cannot balloon
    if inflate.unconsumed_tail or not inflate.eof:
        raise ValueError(f"it does not inflate to a whole header of at most {MAX_HEADER} bytes")
    return strict_json(text.decode())


def check_precision(precision: str) -> str:
    if precision not in PRECISIONS:
        raise SplatzooError(f"unknown storage precision {precision!r}; choose one of {', '.join(PRECISIONS)}")
    return precision


def encoding_for(name: str, tensor: torch.Tensor, precision: str) -> str:
    """How tensor `name` is stored at `precision`: raw, f16, u8, u8h or u16. At float16 a tensor with a value beyond a
    half float's range (65504) stays raw: as a half float it would load back as infinity. At 8bit its column ranges
    are half floats (u8h) where they store it as well as float32 ones (_half_ranges)."""
    if precision == "float32" or not tensor.is_floating_point() or tensor.dim() == 0 or tensor.numel() == 0:
        return "raw"
    if name in POSITION_FIELDS:
        return "u16"
    if precision == "float16":
        return "f16" if float(tensor.detach().abs().max()) <= F16_MAX else "raw"
    return "u8h" if _half_ranges(tensor.detach().cpu().numpy(), 8) is not None else "u8"


def value_bytes(name: str, tensor: torch.Tensor, precision: str) -> int:
    """Bytes one value of tensor `name` takes in the packed file at `precision` (its column's minimum and step,
    shared by every row, not counted)."""
    encoding = encoding_for(name, tensor, precision)
    return {"raw": tensor.element_size(), "f16": 2, "u8": 1, "u8h": 1, "u16": 2}[encoding]


def _columns(array: np.ndarray) -> np.ndarray:
    """[rows, columns]: a per-primitive tensor's first dimension is its rows, the rest its columns."""
    return array.reshape(array.shape[0], -1) if array.ndim > 1 else array.reshape(-1, 1)


def _ranges(x: np.ndarray, bits: int, dtype) -> tuple[np.ndarray, np.ndarray]:
    """(minimum, step) [C] of each column of x [N, C] (float64) over its own range, as `dtype`."""
    lo = x.min(0).astype(dtype)
    step = ((x.max(0) - lo.astype(np.float64)) / ((1 << bits) - 1)).astype(dtype)
    return lo, step


def _half_ranges(array: np.ndarray, bits: int):
    """The half-float (minimum, step) of each column of `array`, or None where a half float would move some value by
    more than a code's own rounding: each column's smallest and largest values must land within 0.49 of a step of
    codes 0 and 2^bits - 1 (a column far from zero against its span, or with a step below a half's resolution, fails;
    so does one beyond a half's range). A constant column is its value as a half float (11 significant bits, finer
    than any 8-bit code). Values stored with them repack to the same ranges."""
    if not np.isfinite(array).all():
        return None
    x = _columns(array.astype(np.float64))
    with np.errstate(over="ignore"):
        lo, step = _ranges(x, bits, np.float16)
    if not (np.isfinite(lo).all() and np.isfinite(step).all()):
        return None
    lo64, step64 = lo.astype(np.float64), step.astype(np.float64)
    ends = np.stack([x.min(0) - lo64, x.max(0) - lo64 - ((1 << bits) - 1) * step64])
    varies = x.max(0) > x.min(0)
    if np.any(np.abs(ends[:, varies]) > 0.49 * step64[varies]):
        return None
    return lo, step


def _encode_fixed(array: np.ndarray, encoding: str):
    """(minimum [C], step [C], codes) of each column over its own range, the ranges in the encoding's dtype."""
    code_type, bits, range_type = _CODES[encoding]
    x = _columns(array.astype(np.float64))
    lo, step = _half_ranges(array, bits) if range_type == "<f2" else _ranges(x, bits, np.float32)
    lo = lo.astype(range_type)
    step = step.astype(range_type)
    levels = (1 << bits) - 1
    safe = np.where(step > 0, step.astype(np.float64), 1.0)
    codes = np.clip(np.rint((x - lo.astype(np.float64)) / safe), 0, levels)
    return lo, step, codes.astype(code_type)


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
        back = _decode_fixed(*_encode_fixed(array, encoding), array.shape)
    return torch.from_numpy(np.ascontiguousarray(back)).to(tensor.device, tensor.dtype)


def quantise_state(state: dict, precision: str) -> dict:
    return {k: quantise_tensor(k, v, precision) for k, v in state.items()}


def pack_checkpoint(ckpt: dict, precision: str) -> bytes:
    """The .szp file of a checkpoint (SplatModel.checkpoint()) at `precision`."""
    header, blobs = packed_parts(ckpt, precision)
    deflate = zlib.compressobj(9, zdict=header_dictionary())
    text = deflate.compress(json.dumps(header, separators=(",", ":")).encode()) + deflate.flush()
    return MAGIC + struct.pack("<I", len(text)) + text + b"".join(blobs)


def packed_parts(ckpt: dict, precision: str) -> tuple[dict, list[bytes]]:
    """(the header, each tensor's bytes) of the .szp file of a checkpoint at `precision`, before the header is
    compressed."""
    check_precision(precision)
    entries, rows, blobs = [], [], []
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
            lo, step, codes = _encode_fixed(array, encoding)
            blobs += [lo.tobytes(), step.tobytes(), codes.tobytes()]
        entries.append({"name": name, "dtype": dtype, "encoding": encoding, "columns": list(array.shape[1:])})
        rows.append(array.shape[0] if array.ndim else None)
    # the rows last: all before them is the same in every file of this model at this precision
    header = {"format": "splatzoo-packed", "version": VERSION, "model": ckpt["model"], "config": ckpt["config"],
              "precision": precision, "tensors": entries,
              **{k: ckpt[k] for k in ("antialias", "background") if k in ckpt}, "rows": rows}
    return header, blobs


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


def _shapes(header: dict, tensors: list, where: str) -> list:
    """Each tensor's shape as the header gives it: version 3 as its rows (None: a 0-d tensor) and its entry's
    columns, older versions in its entry."""
    if header["version"] < 3:
        return [t.get("shape") if isinstance(t, dict) else None for t in tensors]
    rows = header.get("rows")
    if not isinstance(rows, list) or len(rows) != len(tensors):
        raise _fail(where, "its header does not give one row count per tensor")
    shapes = []
    for n, t in zip(rows, tensors):
        columns = t.get("columns") if isinstance(t, dict) else None
        if not isinstance(columns, list) or (n is None and columns):
            shapes.append(None)  # refused by _shape
        else:
            shapes.append([] if n is None else [n, *columns])
    return shapes


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
        header = read_header(data)
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
    shapes = _shapes(header, tensors, where)
    offset, state = 8 + length, {}

    def take(n: int, what: str) -> bytes:
        nonlocal offset
        if offset + n > len(data):
            raise _fail(where, f"the file ends inside {what} (needs {n} bytes at {offset}, has {len(data)}): it is "
                               "truncated")
        chunk = data[offset:offset + n]
        offset += n
        return chunk

    for entry, shape in zip(tensors, shapes):
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise _fail(where, "a tensor entry has no name")
        name = entry["name"]
        if name in state:
            raise _fail(where, f"tensor {name!r} appears twice")
        shape = _shape(shape, where, name)
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
            range_type = np.dtype(_CODES[encoding][2])
            lo = np.frombuffer(take(range_type.itemsize * cols, name), range_type)
            step = np.frombuffer(take(range_type.itemsize * cols, name), range_type)
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
