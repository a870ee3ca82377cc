"""File input and output in one place: atomic writes (splatzoo.atomic, re-exported here), JSON without non-finite
numbers, torch files read without running code, and (re-exported from splatzoo.ply, where all PLY reading and writing
lives) PLY vertex lists read without trusting their header."""
from __future__ import annotations

import json
import math
import os
import re
import sys
from pathlib import Path
from typing import Callable

from .atomic import atomic_path
from .errors import SplatzooError


def say_progress(progress) -> Callable[[str], None]:
    """Where a long job's progress lines go: `progress` itself when callable, stderr when it is otherwise true
    (progress=True), nowhere when false."""
    if callable(progress):
        return progress
    if progress:
        return lambda msg: print(msg, file=sys.stderr, flush=True)
    return lambda msg: None


def write_json(path, data) -> None:
    """Strict JSON (other tools reject NaN and Infinity): a non-finite number is written as null."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_finite(data), indent=2, sort_keys=False, default=_jsonable, allow_nan=False) + "\n")


def json_line(record) -> str:
    """One strict-JSON line (a log record): non-finite numbers as null."""
    return json.dumps(_finite(record), default=_jsonable, allow_nan=False) + "\n"


def _unique_keys(pairs: list) -> dict:
    out = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"the key {key[:60]!r} appears more than once in one object")
        out[key] = value
    return out


def strict_json(text: str | bytes) -> object:
    """JSON that splatzoo wrote: an object that names a key twice is refused (ValueError). json.loads keeps the last
    one silently, so an edited or crafted file could say one thing to a reader that checks the first."""
    return json.loads(text, object_pairs_hook=_unique_keys)


def read_json(path, what: str, fix: str) -> object:
    """Parse a JSON file we wrote; a missing, unreadable or malformed one (keys named twice included) is a
    SplatzooError that says `fix`."""
    path = Path(path)
    try:
        return strict_json(path.read_text())
    except FileNotFoundError:
        raise SplatzooError(f"{what} {path} does not exist; {fix}") from None
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise SplatzooError(f"{what} {path} is damaged ({e}); {fix}") from None
    except RecursionError:  # a nesting bomb ([[[[...): no file we write nests deeper than a few levels
        raise SplatzooError(f"{what} {path} is damaged (its JSON nests too deeply); {fix}") from None


def read_torch(path, what: str, fix: str) -> object:
    """Load a torch file with weights_only=True: tensors and plain containers only, so a crafted file cannot run
    code. Any failure (missing, truncated, empty, not ours, a pickle that asks for code) is a SplatzooError."""
    import torch

    path = Path(path)
    try:
        found = path.is_file()
        empty = found and path.stat().st_size == 0
    except OSError as e:  # a name longer than the file system allows, a folder we may not read, ...
        raise SplatzooError(f"{what} {str(path)[:200]} cannot be looked up ({e.strerror or e}); {fix}") from None
    if not found:
        raise SplatzooError(f"{what} {path} does not exist; {fix}")
    if empty:
        raise SplatzooError(f"{what} {path} is empty (0 bytes); {fix}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types here: UnpicklingError, RuntimeError, EOFError, ...
        text = str(e).strip()
        if "Weights only load failed" in text:
            # torch's own advice (load with weights_only=False) would run whatever code the file carries: name only
            # what it holds that is not data
            found = re.search(r"Unsupported global: GLOBAL ([\w.]+)", text)
            reason = (f"it holds Python objects that are not tensors or plain containers"
                      f"{f' ({found.group(1)})' if found else ''}, and unpickling them could run code from the file")
        else:
            reason = text.splitlines()[0][:200] if text else type(e).__name__
        raise SplatzooError(f"{what} {path} cannot be read safely ({reason}); {fix}") from None


def write_text(path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def torch_save(obj, path) -> None:
    import torch

    with atomic_path(path) as tmp:
        try:
            torch.save(obj, tmp)
        except RuntimeError as e:
            # torch's zip writer reports a failed write (a full disk, a quota) as RuntimeError ("unexpected pos",
            # "failed writing file data"), not as OSError: say it as the disk error it is
            free = _free_bytes(tmp.parent)
            reason = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
            full = f"the disk is full ({free / 1e6:.0f} MB free)" if free is not None and free < 64e6 else reason
            raise SplatzooError(f"cannot write {path}: {full}. Free disk space or choose another location; the "
                                "previous file (if any) is unchanged") from None


def _free_bytes(folder) -> int | None:
    try:
        st = os.statvfs(folder)
        return st.f_bavail * st.f_frsize
    except (OSError, AttributeError):
        return None


def _finite(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    return o


def _jsonable(o):
    if hasattr(o, "tolist"):
        return _finite(o.tolist())
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"cannot store {type(o).__name__} in JSON")


# --- PLY: one module, splatzoo.ply (through plyfile); its readers are re-exported here ------------------------

from .ply import PLY_FIX, PLY_TYPES, ply_type_name, read_ply_vertices, write_ply_vertices  # noqa: E402,F401
