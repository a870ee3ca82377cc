"""Every PLY file splatzoo reads or writes (model exports, point clouds of datasets) goes through this module, and
through the `plyfile` library in it. Mesh files written by open3d are the one exception.

Reading never trusts the header: it is parsed and checked here first (every line well formed, each property's type
known, no property declared twice), and the element counts are checked against the file's size before plyfile sizes
anything by them (plyfile allocates `count` rows up front, so a few crafted bytes could otherwise ask for gigabytes).
A binary body must be exactly what the header declares; bytes beyond it mean a wrong count.
"""
from __future__ import annotations

import re
from pathlib import Path

from .atomic import atomic_path
from .errors import SplatzooError

PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint", "f4": "float",
              "f8": "double"}
PLY_FIX = "Export the model again"
_HEADER_LIMIT = 16 << 20  # a header longer than this is not a PLY header (the longest we write is a few kB)


def ply_type_name(dtype) -> str:
    """The PLY name of a property's numpy type ('<f4' -> 'float')."""
    import numpy as np

    return _PLY_NAMES.get(np.dtype(dtype).str[1:], str(dtype))


def _read_head(path: Path) -> tuple[bytes, int]:
    """(the file's bytes up to and including the header's end, or its first _HEADER_LIMIT bytes; the file's size)."""
    with open(path, "rb") as f:
        size = f.seek(0, 2)
        f.seek(0)
        head = b""
        while len(head) < _HEADER_LIMIT:
            chunk = f.read(1 << 16)
            if not chunk:
                break
            head += chunk
            end = head.find(b"end_header", max(0, len(head) - len(chunk) - 16))
            if end >= 0:
                newline = head.find(b"\n", end)
                if newline >= 0 or len(head) == size:
                    break
    return head, size


def _ply_header(path: Path, data: bytes, fix: str, error) -> tuple[str, list[str], list[tuple[str, int, list]], int]:
    """(format, comments, elements as (name, count, [(property, numpy type, count type for lists or None)]), body
    offset). Every field is checked here, before anything is sized by the counts the header claims."""
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
            if len(parts) != 3:
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
                for t in parts[2:4]:
                    if t not in PLY_TYPES:
                        raise error(f"{path}: unknown PLY property type {t!r}")
                if PLY_TYPES[parts[2]][0] not in "iu":
                    raise malformed(i, "a whole-number count type in 'property list <count type> <item type> <name>'")
                elements[-1][2].append((parts[4], PLY_TYPES[parts[3]], PLY_TYPES[parts[2]]))
            elif len(parts) != 3:
                raise malformed(i, "'property <type> <name>'")
            elif parts[1] not in PLY_TYPES:
                raise error(f"{path}: unknown PLY property type {parts[1]!r}")
            else:
                elements[-1][2].append((parts[2], PLY_TYPES[parts[1]], None))
        elif parts[0] not in ("obj_info",):
            raise malformed(i, "'format', 'comment', 'obj_info', 'element' or 'property'")
    if fmt is None:
        raise error(f"{path}: the PLY header has no 'format' line; the file is damaged. {fix}")
    for name, _, props in elements:
        names = [k for k, _, _ in props]
        if len(set(names)) != len(names):
            twice = sorted({k for k in names if names.count(k) > 1})
            raise error(f"{path}: the {name} property {', '.join(twice)} is declared twice; the file is damaged")
    return fmt, comments, elements, body_start


def compressed_ply(path) -> bool:
    """Whether `path` is a PlayCanvas compressed PLY (its first element is `chunk`), from its header alone."""
    try:
        head, _ = _read_head(Path(path))
    except OSError:
        return False
    end = head.find(b"end_header")
    first = re.search(rb"^element\s+(\S+)", head[:max(end, 0)], re.M)
    return head.startswith(b"ply") and first is not None and first.group(1) == b"chunk"


def _row_bytes(props) -> int:
    """Bytes of one binary row: exact for fixed-size properties, the least possible (empty lists) with lists."""
    import numpy as np

    return sum(np.dtype(t if count is None else count).itemsize for _, t, count in props)


def _check_sizes(path: Path, fmt: str, elements, body: int, fix: str, error) -> None:
    """The counts the header claims must fit the bytes that follow it, before plyfile allocates anything by them."""
    _, count, props = elements[0]
    if fmt == "ascii":
        # a value takes a digit and a separator (the file's last may lack it); an element without properties none
        least = sum(n * 2 * len(ps) for _, n, ps in elements)
        if least > body + 1:
            most = (body + 1) // (2 * len(props))
            raise error(f"{path} is truncated or its header is wrong: it promises {count} vertices of {len(props)} "
                        f"values but {body} bytes follow the header (room for at most {most}). {fix}")
        return
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise error(f"{path}: unsupported PLY format {fmt!r} (ascii, binary_little_endian or binary_big_endian)")
    vertex_bytes = _row_bytes(props) * count
    if body < vertex_bytes:
        raise error(f"{path} is truncated: the header promises {count} vertices of {_row_bytes(props)} bytes but the "
                    f"file holds {body} bytes after it. {fix}")
    others = [(name, n, _row_bytes(ps), any(c is not None for _, _, c in ps)) for name, n, ps in elements[1:]]
    total = vertex_bytes + sum(n * size for _, n, size, _ in others)
    lists = any(has for *_, has in others)
    if body < total or (body != total and not lists):
        # with list properties (a mesh's faces) only a full read could tell the size: then it is a lower bound
        more = "".join(f" and {n} {name} of {'at least ' if has else ''}{size} bytes" for name, n, size, has in others)
        raise error(f"{path}: the header promises {count} vertices of {_row_bytes(props)} bytes{more} = "
                    f"{'at least ' if lists else ''}{total} bytes but {body} bytes follow; the count is wrong or the "
                    f"file is damaged. {fix}")


def read_ply_vertices(path, *, fix: str = PLY_FIX, error=SplatzooError):
    """(structured numpy array of the first element's properties, header comments) of a binary or ASCII PLY whose
    first element is `vertex`. The header's counts are checked against the file's size before anything is allocated
    (a few crafted bytes cannot ask for gigabytes), and the body must be exactly what the header declares: bytes or
    rows beyond it mean a wrong count. Every problem is an `error` naming the file and ending in `fix`."""
    import numpy as np
    import plyfile

    path = Path(path)
    try:
        found = path.is_file()
        head, size = _read_head(path) if found else (b"", 0)
    except OSError as e:  # a name longer than the file system allows, no permission, ...
        raise error(f"PLY file {str(path)[:200]} cannot be read ({e.strerror or e})") from None
    if not found:
        hint = "; pass the file written by `splatzoo export`" if fix == PLY_FIX else ""
        raise error(f"no PLY file at {path}{hint}")
    fmt, comments, elements, body_start = _ply_header(path, head, fix, error)
    if elements and elements[0][0] == "chunk":
        raise error(f"{path} is a compressed PLY (PlayCanvas / SuperSplat): convert it to a plain one first, e.g. "
                    f"`splat-transform {path.name} plain.ply` (splatzoo's commands that read model files do this "
                    "themselves when splat-transform is installed)")
    if not elements or elements[0][0] != "vertex":
        raise error(f"{path}: the first PLY element must be 'vertex' (one per point)")
    _, count, props = elements[0]
    if any(c is not None for _, _, c in props):
        raise error(f"{path}: list properties in the vertex element are not supported")
    if not props:
        raise error(f"{path}: the vertex element has no properties. {fix}")
    _check_sizes(path, fmt, elements, size - body_start, fix, error)
    try:
        with open(path, "rb") as f:
            ply = plyfile.PlyData.read(f, mmap="c")
            arr = np.array(ply["vertex"].data)  # a copy: nothing keeps the file mapped
            del ply
    except plyfile.PlyElementParseError as e:
        raise _row_error(path, e, count, props, body_start, fix, error) from None
    except OSError as e:
        raise error(f"PLY file {path} cannot be read ({e.strerror or e})") from None
    except OverflowError as e:  # plyfile casts an ASCII integer out of its type's range without catching this
        bad = _ascii_integer_problem(path, body_start, count, props) if fmt == "ascii" else None
        if bad:
            raise error(f"{path}: {bad}; the file is damaged. {fix}") from None
        raise error(f"{path} cannot be parsed as a PLY file ({str(e)[:200]}); the file is damaged. {fix}") from None
    except (plyfile.PlyParseError, ValueError, TypeError, UnicodeDecodeError) as e:
        raise error(f"{path} cannot be parsed as a PLY file ({str(e)[:200]}); the file is damaged. {fix}") from None
    if fmt == "ascii":
        _check_ascii(path, arr, count, props, len(elements) == 1, body_start, fix, error)
    return arr.astype(arr.dtype.newbyteorder("=")) if fmt == "binary_big_endian" else arr, comments


def _row_error(path: Path, e, count: int, props, body_start: int, fix: str, error):
    """A plyfile parse error of the vertex element in splatzoo's words."""
    element = getattr(getattr(e, "element", None), "name", "")
    row = e.row if isinstance(e.row, int) else None
    if element != "vertex" or row is None:
        return error(f"{path} cannot be parsed as a PLY file ({str(e)[:200]}); the file is damaged. {fix}")
    if e.message == "early end-of-file":
        return error(f"{path} is truncated: the header promises {count} vertices but the body holds only {row} "
                     f"row(s). {fix}")
    names = ", ".join(k for k, _, _ in props[:6]) + (" ..." if len(props) > 6 else "")
    text = ""
    try:  # the row as the file holds it (ASCII: plyfile reads one line per row)
        with open(path, "rb") as f:
            f.seek(body_start)
            for i, line in enumerate(f):
                if i == row:
                    text = f" {line.decode('ascii', 'replace').strip()[:80]!r}"
                    break
    except OSError:
        pass
    prop = next(((k, t) for k, t, _ in props if k == getattr(e.prop, "name", None)), None)
    if e.message == "malformed input" and prop is not None and prop[1][0] in "iu":
        bad = _ascii_integer_problem(path, body_start, count, props)
        if bad:
            return error(f"{path}: {bad}; the file is damaged. {fix}")
    if e.message == "expected end-of-line":
        return error(f"{path}: vertex row {row + 1}{text} holds more than the {len(props)} values its properties "
                     f"declare ({names}); the file is damaged. {fix}")
    return error(f"{path}: vertex row {row + 1}{text} does not hold {len(props)} numbers ({names}); the file is "
                 f"damaged or a value does not fit its type. {fix}")


def _ascii_integer_problem(path: Path, body_start: int, count: int, props) -> str | None:
    """Which integer property of an ASCII vertex list holds a number that is not a whole number in its type's range
    (plyfile only says that a value did not fit), or None."""
    import numpy as np

    ints = [(i, k, t) for i, (k, t, _) in enumerate(props) if t[0] in "iu"]
    with open(path, "rb") as f:
        f.seek(body_start)
        for row, line in zip(range(count), f):
            words = line.split()
            for i, k, t in ints:
                try:
                    value = float(words[i])
                except (IndexError, ValueError):
                    continue
                info = np.iinfo(t)
                whole = bool(np.isfinite(value)) and value == int(value)
                if not (whole and info.min <= value <= info.max):
                    return (f"the {ply_type_name(t)} property {k} holds values that are not whole numbers in "
                            f"{info.min}..{info.max} (vertex row {row + 1})")
    return None


def _check_ascii(path: Path, arr, count: int, props, only: bool, body_start: int, fix: str, error) -> None:
    """ASCII values were parsed by plyfile, which refuses fractions and out-of-range values in integer properties;
    when the vertex element is the file's one element, no row may follow its last."""
    if not only:
        return
    with open(path, "rb") as f:
        f.seek(body_start)
        rows = sum(1 for line in f if line.strip())
    if rows > count:
        raise error(f"{path}: the header promises {count} vertices but {rows} rows follow; the count is wrong or the "
                    f"file is damaged. {fix}")


def write_ply_vertices(path, arr, comments=(), *, text: bool = False) -> Path:
    """Write the structured array `arr` as the vertex element of a little-endian binary (or ASCII) PLY, atomically,
    with `comments` as header comments in order. Returns the path."""
    import plyfile

    path = Path(path)
    element = plyfile.PlyElement.describe(arr, "vertex")
    data = plyfile.PlyData([element], text=text, byte_order="<", comments=list(comments))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            data.write(f)
    return path
