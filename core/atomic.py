"""Atomic file writes: every file the package writes is complete or absent, never half-written."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; it replaces ``path`` only if the block ends.

    The rename (``os.replace``) is atomic on one file system, so a reader sees the old file
    or the new one; on any exception (KeyboardInterrupt included) the temporary file is
    removed and ``path`` is left as it was.  The file gets the usual umask permissions
    (``mkstemp`` would leave it 0600).
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
