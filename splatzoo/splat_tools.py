"""PlayCanvas splat-transform, the converter behind `splatzoo export --format spz | sog | compressed-ply`.

The CLI is a Node.js program, pinned in tools/splat-transform/package.json (installed with
`npm ci --prefix tools/splat-transform`, which scripts/install.sh does). It is found, in order, at:
  1. the path in the environment variable SPLATZOO_SPLAT_TRANSFORM,
  2. tools/splat-transform/node_modules/.bin/splat-transform in this source checkout,
  3. `splat-transform` on PATH (`npm install -g @playcanvas/splat-transform`).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
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


def run_splat_transform(args: list[str], *, what: str) -> str:
    """Run splat-transform with `args`; its output, or a SplatzooError with its last lines."""
    cli = find_splat_transform()
    try:
        done = subprocess.run([str(cli), *args], capture_output=True, text=True, timeout=TIMEOUT_S)
    except OSError as e:
        raise SplatzooError(f"cannot run {cli} ({e.strerror or e}); {_HOW}") from None
    except subprocess.TimeoutExpired:
        raise SplatzooError(f"splat-transform did not finish {what} in {TIMEOUT_S} s; try a smaller model") from None
    if done.returncode != 0:
        tail = "\n".join((done.stderr.strip() or done.stdout.strip()).splitlines()[-6:])
        hint = " (Node.js too old? splat-transform needs Node 20 or newer)" if "SyntaxError" in tail else ""
        raise SplatzooError(f"splat-transform failed {what} (exit {done.returncode}){hint}:\n{tail}")
    return done.stdout


def convert_file(src, out, *, args=(), suffix: str | None = None) -> Path:
    """Convert the splat file `src` to `out` with splat-transform (the format follows the names' suffixes), writing
    `out` atomically: splat-transform writes a temporary file beside it, which then replaces `out`."""
    from .io import atomic_path

    src, out = Path(src), Path(out)
    if suffix is None:
        suffix = ".compressed.ply" if out.name.lower().endswith(".compressed.ply") else out.suffix
    with atomic_path(out, suffix=suffix) as tmp:
        run_splat_transform(["-q", "-w", str(src), *args, str(tmp)], what=f"converting {src.name} to {out.name}")
        if not tmp.is_file() or tmp.stat().st_size == 0:
            raise SplatzooError(f"splat-transform wrote nothing converting {src} to {out}")
    return out


def convert_ply(model, out, *, suffix: str, args=(), progress=None) -> Path:
    """Write `model` as our standard PLY (splatzoo.export.save_ply) to a temporary file and convert it to `out`."""
    from .export import save_ply

    out = Path(out)
    cli = find_splat_transform()  # before any work: a missing tool is the likeliest failure
    with tempfile.TemporaryDirectory(prefix="splatzoo-export-") as folder:
        ply = save_ply(model, Path(folder) / "model.ply")
        if progress:
            progress(f"converting {model.num_primitives} primitives with {cli}")
        convert_file(ply, out, args=list(args), suffix=suffix)
    if progress:
        progress(f"wrote {out}")
    return out
