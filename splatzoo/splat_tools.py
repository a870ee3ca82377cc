"""PlayCanvas splat-transform, the program behind the model file formats spz, sog and compressed-ply (written from our
PLY by `convert_file`) and the reader of SPZ, SOG, compressed PLY, .splat and .ksplat files (`read_splat_file`), for
splatzoo.model_files: this module knows files, not models. When it fails, a message gives its own Error line (never
its Node.js stack) and names the user's file and its format.

The CLI is a Node.js program, pinned in tools/splat-transform/package.json (installed with
`npm ci --prefix tools/splat-transform`, which scripts/install.sh does). It is found, in order, at:
  1. the path in the environment variable SPLATZOO_SPLAT_TRANSFORM,
  2. tools/splat-transform/node_modules/.bin/splat-transform in this source checkout,
  3. `splat-transform` on PATH (`npm install -g @playcanvas/splat-transform`).
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

from .errors import SplatzooError

PINNED_VERSION = "3.7.0"
ENV = "SPLATZOO_SPLAT_TRANSFORM"
TIMEOUT_S = 3600  # a conversion of millions of splats takes minutes; a hung one must not block forever
_CHECKOUT_CLI = Path(__file__).resolve().parents[1] / "tools" / "splat-transform" / "node_modules" / ".bin" / \
    "splat-transform"
_HOW = (f"install it with `bash scripts/install.sh` (or `npm ci --prefix tools/splat-transform` in the splatzoo "
        f"checkout), or `npm install -g @playcanvas/splat-transform@{PINNED_VERSION}`; it needs Node.js, or set "
        f"{ENV} to the splat-transform program")


def find_splat_transform() -> Path:
    """The splat-transform program (see the module docstring), or a SplatzooError saying how to install it."""
    given = os.environ.get(ENV)
    if given:
        path = Path(given).expanduser()
        if not (path.is_file() and os.access(path, os.X_OK)):
            raise SplatzooError(f"{ENV}={given} is not an executable file; point it at the splat-transform program "
                                f"or unset it. To install splat-transform: {_HOW}")
        return path
    if _CHECKOUT_CLI.is_file() and os.access(_CHECKOUT_CLI, os.X_OK):
        return _CHECKOUT_CLI
    found = shutil.which("splat-transform")
    if found:
        return Path(found)
    raise SplatzooError(f"this export needs PlayCanvas splat-transform, which is not installed: {_HOW}")


class SplatTransformError(SplatzooError):
    """splat-transform ran and failed; `tool_message` holds its own words (its Error lines, without the stack)."""

    def __init__(self, message: str, tool_message: str = ""):
        super().__init__(message)
        self.tool_message = tool_message


# a line of Node.js's error report that names the error: "Error: ...", "SyntaxError: ...", "RangeError [CODE]: ..."
# (splat-transform marks its own with a cross)
_ERROR_LINE = re.compile(r"^(?:[✗×!]\s*)?(?:Uncaught\s+)?((?:[A-Z][A-Za-z]*)?Error(?:\s*\[[A-Z0-9_]+\])?:\s*\S.*)$")
_NOISE = re.compile(r"^(?:at\s|✗\s*failed in\b|Node\.js v\d|\^+$|file://|node:)")


def tool_message(stderr: str, stdout: str = "") -> str:
    """What splat-transform (a Node.js program) said was wrong, from its output: the Error line(s), without the stack
    frames, its timing line or Node's source excerpt; failing that, its last lines that are not stack frames."""
    text = stderr.strip() or stdout.strip()
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    found = []
    for line in lines:
        m = _ERROR_LINE.match(line)
        if m and m.group(1) not in found:
            found.append(m.group(1))
    if not found:
        found = [line.lstrip("✗×! ").strip() for line in lines if not _NOISE.match(line)][-3:]
    message = "; ".join(found[:3])
    return message if len(message) <= 600 else message[:600] + " ..."


def run_splat_transform(args: list[str], *, what: str) -> str:
    """Run splat-transform with `args`; its output, or a SplatTransformError with its own message (the Error line,
    not its stack)."""
    cli = find_splat_transform()
    try:
        done = subprocess.run([str(cli), *args], capture_output=True, text=True, timeout=TIMEOUT_S)
    except OSError as e:
        raise SplatzooError(f"cannot run {cli} ({e.strerror or e}); {_HOW}") from None
    except subprocess.TimeoutExpired:
        raise SplatzooError(f"splat-transform did not finish {what} in {TIMEOUT_S} s; try a smaller model") from None
    if done.returncode != 0:
        said = tool_message(done.stderr, done.stdout)
        # Node too old to parse the program: a SyntaxError before splat-transform's own error report (its cross)
        old = "SyntaxError" in said and "✗" not in done.stderr
        hint = " (Node.js too old? splat-transform needs Node 20 or newer)" if old else ""
        raise SplatTransformError(f"splat-transform failed {what} (exit {done.returncode}){hint}: "
                                  f"{said or 'it printed nothing'}", said)
    return done.stdout


def convert_file(src, out, *, args=(), suffix: str | None = None, label: str | None = None) -> Path:
    """Convert the splat file `src` to `out` with splat-transform (the format follows the names' suffixes), writing
    `out` atomically: splat-transform writes a temporary file beside it, which then replaces `out`. `label` names
    `src` in messages (default: its file name)."""
    from .io import atomic_path

    src, out = Path(src), Path(out)
    if suffix is None:
        suffix = ".compressed.ply" if out.name.lower().endswith(".compressed.ply") else out.suffix
    with atomic_path(out, suffix=suffix) as tmp:
        run_splat_transform(["-q", "-w", str(src), *args, str(tmp)],
                            what=f"converting {label or src.name} to {out.name}")
        if not tmp.is_file() or tmp.stat().st_size == 0:
            raise SplatzooError(f"splat-transform wrote nothing converting {label or src} to {out}")
    return out


# --- reading other tools' splat files -----------------------------------------------------------------------------

# the splat files splat-transform reads for splatzoo, by suffix (longest first), with the name a message gives them
SPLAT_FORMATS = {".compressed.ply": "PlayCanvas compressed PLY", ".spz": "SPZ", ".sog": "PlayCanvas SOG",
                 ".ksplat": "GaussianSplats3D .ksplat", ".splat": ".splat (antimatter15)"}
# SPZ positions are 24-bit fixed point: with more fractional bits than this every splat would lie within
# 2^(23 - bits) of the origin (at 255, exactly on it)
SPZ_MAX_FRACTIONAL_BITS = 24
_SPLAT_RECORD = 32  # bytes of one .splat record: 3 float32 position, 3 float32 scale, RGBA, 4 rotation bytes


def splat_format(path) -> str:
    """The name of the splat file format of `path`, from its suffix (a PLY whose first element is `chunk`: a
    compressed PLY)."""
    name = Path(path).name.lower()
    for suffix, fmt in SPLAT_FORMATS.items():
        if name.endswith(suffix):
            return fmt
    return SPLAT_FORMATS[".compressed.ply"] if name.endswith(".ply") else Path(path).suffix or "splat"


def spz_header(path) -> dict | None:
    """version, count and fractional_bits of an SPZ file's header (v2/v3: inside its gzip stream; v4: plain), or
    None when the file does not start like an SPZ (splat-transform then says what is wrong)."""
    import gzip
    import struct
    import zlib

    try:
        with open(path, "rb") as f:
            start = f.read(32)
            if start[:2] == b"\x1f\x8b":
                f.seek(0)
                with gzip.GzipFile(fileobj=f) as g:
                    start = g.read(16)
    except (OSError, EOFError, zlib.error):
        return None
    if len(start) < 16 or start[:4] != b"NGSP":
        return None
    _, version, count, _, bits = struct.unpack_from("<4sIIBB", start)
    return {"version": version, "count": count, "fractional_bits": bits}


def splat_zero_rotations(path):
    """[N] bool of a .splat file: which records hold no rotation (all four rotation bytes 127 or 128, a zero
    quaternion, which splat-transform turns into an arbitrary one), or None when the file is not whole records."""
    import numpy as np

    try:
        size = os.path.getsize(path)
        if size == 0 or size % _SPLAT_RECORD:
            return None
        rot = np.memmap(path, dtype=np.uint8, mode="r").reshape(-1, _SPLAT_RECORD)[:, 28:32]
        return ((rot == 127) | (rot == 128)).all(1)
    except (OSError, ValueError):
        return None


def _give_zero_rotations(ply: Path, zero) -> None:
    """Rewrite the converted PLY with a zero quaternion where the .splat file held none (splat-transform keeps the
    records' order), so that reading it says how many there were and what was done with them."""
    import numpy as np

    from .ply import read_ply_vertices, write_ply_vertices

    arr, comments = read_ply_vertices(ply)
    if arr.shape[0] != zero.shape[0] or not all(f"rot_{i}" in arr.dtype.names for i in range(4)):
        return
    for i in range(4):
        arr[f"rot_{i}"][np.asarray(zero)] = 0.0
    write_ply_vertices(ply, arr, comments)


def read_splat_file(src, out) -> Path:
    """Convert the splat file `src` (SPZ, SOG, compressed PLY, .splat, .ksplat) to a plain PLY `out` for
    splatzoo.model_ply.load_ply. A file splat-transform cannot read is a SplatzooError that names `src`, its format and
    splat-transform's own message; so are an SPZ header with absurd fractional bits and a file without splats."""
    src = Path(src)
    fmt = splat_format(src)
    a = "an" if fmt == "SPZ" else "a"
    fix = f"the file is damaged, truncated or not {a} {fmt} file: export or download it again"
    fix_sentence = "T" + fix[1:]
    header = spz_header(src) if fmt == "SPZ" else None
    if header and header["fractional_bits"] > SPZ_MAX_FRACTIONAL_BITS:
        bits = header["fractional_bits"]
        raise SplatzooError(f"cannot read {src} as an SPZ file: its header gives positions {bits} fractional bits, "
                            f"but they are 24-bit fixed point (at most {SPZ_MAX_FRACTIONAL_BITS}); every one of its "
                            f"{header['count']} splats would lie within 2^{23 - bits} of the origin. {fix_sentence}")
    try:
        convert_file(src, out, label=src.name)
    except SplatTransformError as e:
        said = e.tool_message
        if said.endswith("No Gaussians to write"):  # what splat-transform says of an input without splats
            declared = ""
            if header:
                declared = f" (its header declares {header['count']}" + (
                    ", so the file is damaged)" if header["count"] else ")")
            raise SplatzooError(f"cannot read {src} as {a} {fmt} file: splat-transform found no splats in it"
                                f"{declared}, so it would draw nothing. {fix_sentence}") from None
        raise SplatzooError(f"cannot read {src} as {a} {fmt} file: splat-transform stops with "
                            f"\"{said or 'no message'}\"; {fix}") from None
    if fmt.startswith(".splat"):
        zero = splat_zero_rotations(src)
        if zero is not None and bool(zero.any()):
            _give_zero_rotations(Path(out), zero)
    return Path(out)
