"""Atomic writes: a temporary file beside the target, renamed over it on success and removed on error, so that no
reader ever sees a half-written file. The floor under every module that writes files (splatzoo.io, splatzoo.ply)."""
from __future__ import annotations

import errno
import os
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
