"""Folders that appear whole or not at all: build in a temporary folder beside the target, then rename it in.

`staged_output(out, overwrite)` is the usual form:

    with staged_output(out, overwrite=False) as tmp:
        ...write everything under tmp...
    # out now holds it; after an error out is unchanged and tmp is gone

Temporary folders are named `.<name>.tmp-<pid>-<random>`, so one left behind by a killed process (SIGKILL runs
no clean-up) is recognised and removed the next time a folder of that name is staged.
"""
from __future__ import annotations

import glob
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from ..errors import DataError


def temp_dir_beside(target: Path) -> Path:
    """A new empty folder next to `target` (same file system, so a rename moves it in)."""
    target = Path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        remove_abandoned_temp(target)
        return Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-{os.getpid()}-", dir=target.parent))
    except OSError as e:
        raise DataError(f"cannot create a folder next to {target}: {e.strerror or e}; choose a writable "
                        "location") from None


def remove_abandoned_temp(target: Path) -> None:
    """Remove temporary folders beside `target` whose process is gone."""
    pattern = re.compile(re.escape(f".{target.name}.tmp-") + r"(\d+)-")
    for p in target.parent.glob(f".{glob.escape(target.name)}.tmp-*"):
        m = pattern.match(p.name)
        if not m or not p.is_dir():
            continue
        try:
            os.kill(int(m.group(1)), 0)
        except ProcessLookupError:
            shutil.rmtree(p, ignore_errors=True)
        except (PermissionError, OverflowError):
            pass  # alive under another user, or not a pid: leave it


def replace_dir(new: Path, target: Path) -> None:
    """Rename `new` over `target`; an old `target` is moved aside first and deleted after."""
    new, target = Path(new), Path(target)
    old = None
    if target.exists():
        old = target.with_name(f".{target.name}.old-{os.getpid()}")
        if old.exists():
            shutil.rmtree(old)
        os.replace(target, old)
    os.replace(new, target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def prepare_output(out: Path, overwrite: bool) -> Path:
    """A fresh temporary folder beside `out`; refuses to replace a non-empty `out` unless `overwrite`."""
    out = Path(out).expanduser()
    if out.exists() and not out.is_dir():
        raise DataError(f"output {out} exists and is a file; choose a folder path")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise DataError(f"output folder {out} already exists and is not empty; choose another --out or pass "
                        "--overwrite to replace it")
    return temp_dir_beside(out)


def finish_output(tmp: Path, out: Path) -> None:
    """Move the finished temporary folder to `out`, replacing an old one only at this last step."""
    out = Path(out).expanduser()
    if out.is_dir() and not any(out.iterdir()):
        out.rmdir()
    replace_dir(tmp, out)


@contextmanager
def staged_output(out, overwrite: bool = False):
    """Yield a temporary folder that becomes `out` when the block ends without an error (see the module doc)."""
    out = Path(out).expanduser()
    tmp = prepare_output(out, overwrite)
    try:
        yield tmp
        finish_output(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
