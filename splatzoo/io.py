"""File input and output in one place: atomic writes (a temporary file beside the target, renamed over it), JSON
without non-finite numbers, torch files read without running code, and PLY vertex lists read without trusting their
header (models in splatzoo.export, point clouds in splatzoo.data)."""
from __future__ import annotations

import errno
import json
import math
import os
import re
import tempfile
from contextlib import contextmanager
from pathlib import Path

from .errors import SplatzooError


@contextmanager
def atomic_path(path, suffix: str = ""):
    """Yield a temporary path in the target's folder; on success it replaces `path`, on error it is removed."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise SplatzooError(f"cannot write {path}: {e.strerror or e}. Choose a writable output location.") from e
    try:
        try:
            yield Path(tmp)
        except OSError as e:
            if e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EFBIG):
                raise SplatzooError(f"cannot write {path}: {e.strerror or e}. Free disk space or choose another "
                                    "location; the previous file (if any) is unchanged") from None
            raise
        # mkstemp makes the file private (0600); give the result the permissions a plain open() would
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_json(path, data) -> None:
    """Strict JSON (other tools reject NaN and Infinity): a non-finite number is written as null."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_finite(data), indent=2, sort_keys=False, default=_jsonable, allow_nan=False) + "\n")


def json_line(record) -> str:
    """One strict-JSON line (a log record): non-finite numbers as null."""
    return json.dumps(_finite(record), default=_jsonable, allow_nan=False) + "\n"


def read_json(path, what: str, fix: str) -> object:
    """Parse a JSON file we wrote; a missing, unreadable or malformed one is a SplatzooError that says `fix`."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
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


# --- PLY (binary or ASCII), read without trusting its header ---------------------------------------------------

PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint", "f4": "float",
              "f8": "double"}
PLY_FIX = "Export the model again"


def ply_type_name(dtype) -> str:
    """The PLY name of a property's numpy type ('<f4' -> 'float')."""
    import numpy as np

    return _PLY_NAMES.get(np.dtype(dtype).str[1:], str(dtype))


def _ply_header(path: Path, data: bytes, fix: str, error) -> tuple[str, list[str], list[tuple[str, int, list]], int]:
    """(format, comments, elements as (name, count, [(property, numpy type or None for lists)]), body offset).
    Every field is checked here, before anything is sized by the counts the header claims."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise error(f"{path} is not a PLY file (no 'ply' ... 'end_header' header)")
    newline = data.find(b"\n", end)
    body_start = len(data) if newline < 0 else newline + 1
    try:
        text = data[:end].decode("utf-8")
    except UnicodeDecodeError:
        text = None
    if text is None or "\x00" in text:
        raise error(f"{path}: the PLY header holds binary data, not text; the file is damaged or not a PLY. {fix}")
    lines = text.splitlines()
    if lines[0].strip() != "ply":
        raise error(f"{path} is not a PLY file (its first line is not 'ply')")

    def malformed(number: int, expected: str):
        return error(f"{path}: malformed PLY header line {number + 1} {lines[number].strip()[:80]!r}; expected "
                     f"{expected}. The file is damaged or not a PLY. {fix}")

    fmt, comments, elements = None, [], []
    for i, line in enumerate(lines[1:], 1):
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            if len(parts) < 2:
                raise malformed(i, "'format <ascii|binary_little_endian|binary_big_endian> 1.0'")
            fmt = parts[1]
        elif parts[0] == "comment":
            comments.append(line[len("comment "):])
        elif parts[0] == "element":
            if len(parts) != 3 or not re.fullmatch(r"[0-9]+", parts[2]):
                raise malformed(i, "'element <name> <count>' with a whole count of 0 or more")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise error(f"{path}: property before any element in the PLY header")
            if parts[1:2] == ["list"]:
                if len(parts) != 5:
                    raise malformed(i, "'property list <count type> <item type> <name>'")
                elements[-1][2].append((parts[4], None))
            elif len(parts) != 3:
                raise malformed(i, "'property <type> <name>'")
            elif parts[1] not in PLY_TYPES:
                raise error(f"{path}: unknown PLY property type {parts[1]!r}")
            else:
                elements[-1][2].append((parts[2], PLY_TYPES[parts[1]]))
    if fmt is None:
        raise error(f"{path}: the PLY header has no 'format' line; the file is damaged. {fix}")
    return fmt, comments, elements, body_start


def _ascii_vertices(path: Path, body: bytes, count: int, props: list[tuple[str, str]], only: bool, fix: str,
                    error):
    """The first `count` rows of an ASCII body as floats [count, len(props)]; every row must hold a number for each
    property (extra values on a row are ignored). `only`: vertex is the file's one element, so no row may follow."""
    import numpy as np

    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise error(f"{path}: an ASCII PLY body holds non-ASCII bytes; the file is damaged. {fix}") from None
    values = np.empty((count, len(props)), dtype=np.float64)
    rows = (r for r in text.splitlines() if r.strip())
    for i in range(count):
        row = next(rows, None)
        if row is None:
            raise error(f"{path} is truncated: the header promises {count} vertices but the body holds only {i} "
                        f"row(s). {fix}")
        words = row.split()
        try:
            if len(words) < len(props):
                raise ValueError
            values[i] = [float(w) for w in words[:len(props)]]
        except ValueError:
            raise error(f"{path}: vertex row {i + 1} {row.strip()[:80]!r} does not hold {len(props)} numbers "
                        f"({', '.join(k for k, _ in props[:6])}{' ...' if len(props) > 6 else ''}); "
                        f"the file is damaged. {fix}") from None
    extra = sum(1 for _ in rows) if only else 0
    if extra:
        raise error(f"{path}: the header promises {count} vertices but {count + extra} rows follow; the count is wrong "
                    f"or the file is damaged. {fix}")
    return values


def read_ply_vertices(path, *, fix: str = PLY_FIX, error=SplatzooError):
    """(structured numpy array of the first element's properties, header comments) of a binary or ASCII PLY whose
    first element is `vertex`. The header's counts are checked against the file's size before anything is allocated
    (a few crafted bytes cannot ask for gigabytes), and the body must be exactly what the header declares: bytes or
    rows beyond it mean a wrong count. Every problem is an `error` naming the file and ending in `fix`."""
    import numpy as np

    path = Path(path)
    try:
        found = path.is_file()
        data = path.read_bytes() if found else b""
    except OSError as e:  # a name longer than the file system allows, no permission, ...
        raise error(f"PLY file {str(path)[:200]} cannot be read ({e.strerror or e})") from None
    if not found:
        hint = "; pass the file written by `splatzoo export`" if fix == PLY_FIX else ""
        raise error(f"no PLY file at {path}{hint}")
    fmt, comments, elements, body_start = _ply_header(path, data, fix, error)
    if not elements or elements[0][0] != "vertex":
        raise error(f"{path}: the first PLY element must be 'vertex' (one per point)")
    _, count, props = elements[0]
    if any(t is None for _, t in props):
        raise error(f"{path}: list properties in the vertex element are not supported")
    if not props:
        raise error(f"{path}: the vertex element has no properties. {fix}")
    names = [k for k, _ in props]
    if len(set(names)) != len(names):
        twice = sorted({k for k in names if names.count(k) > 1})
        raise error(f"{path}: the vertex property {', '.join(twice)} is declared twice; the file is damaged")
    body = len(data) - body_start
    if fmt == "ascii":
        most = (body + 1) // (2 * len(props))  # a value takes a digit and a separator (the file's last may lack it)
        if count > most:
            raise error(f"{path} is truncated or its header is wrong: it promises {count} vertices of {len(props)} "
                        f"values but {body} bytes follow the header (room for at most {most}). {fix}")
        values = _ascii_vertices(path, data[body_start:], count, props, len(elements) == 1, fix, error)
        arr = np.empty(count, dtype=[(k, t) for k, t in props])
        for i, (k, t) in enumerate(props):
            column = values[:, i]
            if np.dtype(t).kind != "f":
                if not np.isfinite(column).all():
                    raise error(f"{path}: the integer property {k} holds NaN or inf; the file is damaged. {fix}")
                info = np.iinfo(t)
                if count and (not np.array_equal(column, np.round(column)) or column.min() < info.min
                              or column.max() > info.max):
                    raise error(f"{path}: the {ply_type_name(t)} property {k} holds values that are not whole "
                                f"numbers in {info.min}..{info.max}; the file is damaged. {fix}")
            with np.errstate(over="ignore"):  # a float property beyond float32 reads as inf, as in a binary file
                arr[k] = column
        return arr, comments
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise error(f"{path}: unsupported PLY format {fmt!r} (ascii, binary_little_endian or binary_big_endian)")
    endian = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(k, endian + t) for k, t in props])
    vertex_bytes = dtype.itemsize * count
    if body < vertex_bytes:
        raise error(f"{path} is truncated: the header promises {count} vertices of {dtype.itemsize} bytes but the "
                    f"file holds {body} bytes after it. {fix}")
    if all(t is not None for _, _, element_props in elements for _, t in element_props):
        # every element has a fixed size: the body is exactly their sum (with list properties, as in a mesh's faces,
        # only a full read could tell, so then the vertices alone must be there)
        others = [(name, n, sum(np.dtype(t).itemsize for _, t in ps)) for name, n, ps in elements[1:]]
        total = vertex_bytes + sum(n * size for _, n, size in others)
        if body != total:
            more = "".join(f" and {n} {name} of {size} bytes" for name, n, size in others)
            raise error(f"{path}: the header promises {count} vertices of {dtype.itemsize} bytes{more} = {total} bytes "
                        f"but {body} bytes follow; the count is wrong or the file is damaged. {fix}")
    return np.frombuffer(data, dtype=dtype, count=count, offset=body_start), comments
