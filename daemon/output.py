"""Writing the files the commands produce (NC programs, reports): whole or not at all."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from ballbar.analysis.errors import DataError


def write_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file beside it and a rename.

    A reader sees the old file or the whole new one, never a half-written
    one.  The parent directory is created if missing.  Every failure (no such
    directory and no right to make it, a full disk, a file where a directory
    should be) is one-line :class:`DataError` naming the path.
    """
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    except OSError as err:
        raise DataError(f"{p}: cannot write: {err.strerror or err}") from err
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, p)
    except BaseException as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(err, OSError):
            raise DataError(f"{p}: cannot write: {err.strerror or err}") from err
        raise
