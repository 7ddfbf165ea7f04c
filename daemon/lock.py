"""One daemon per state directory: an exclusive ``flock`` on ``STATE_DIR/ballbar.lock``.

Two daemons on one state directory would each run retention over the other's
recordings (the other's open file included) and interleave two devices' files
under one machine id.  :class:`StateLock` takes the lock at start, before the
source or any output opens; a second ``ballbar run`` then fails with one line
naming the holder's PID (exit code 2).

The kernel drops an ``flock`` when its holder's descriptor closes, so a daemon
killed with ``kill -9`` (or by the OOM killer) leaves a file but no lock: the
next start takes it at once.  The file holds the holder's PID for the message;
it is never deleted (deleting it would let a second daemon lock a new inode
while the first still holds the old one).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from pathlib import Path

from ballbar.analysis.errors import BallbarError

LOCK_NAME = "ballbar.lock"


class StateLockError(BallbarError, RuntimeError):
    """The state directory is locked by another daemon, or cannot be locked at all (exit code 2)."""


class StateLock:
    """An exclusive lock on a state directory, held until :meth:`release` or the process ends."""

    def __init__(self, state_dir: str | os.PathLike[str]) -> None:
        self.state_dir = Path(state_dir)
        self.path = self.state_dir / LOCK_NAME
        self._fd: int | None = None

    def acquire(self) -> StateLock:
        """Create the directory if needed and take the lock, or raise :class:`StateLockError`."""
        where = f"daemon.state_dir {self.state_dir}"
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
        except OSError as err:
            raise StateLockError(f"{where}: cannot create {self.path.name}: {err.strerror or err}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            holder = _read_pid(fd)
            os.close(fd)
            if err.errno in (errno.EWOULDBLOCK, errno.EACCES):
                who = f"PID {holder}" if holder else "another process"
                raise StateLockError(
                    f"{where} is in use by another ballbar daemon ({who}, lock {self.path})"
                ) from None
            raise StateLockError(f"{where}: cannot lock {self.path.name}: {err.strerror or err}") from None
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as err:  # a full disk: the lock holds all the same, only the PID is missing
            if err.errno not in (errno.ENOSPC, errno.EDQUOT):
                os.close(fd)
                raise StateLockError(f"{where}: cannot write {self.path.name}: {err.strerror or err}") from None
        self._fd = fd
        return self

    def release(self) -> None:
        """Drop the lock (closing the descriptor drops it); safe twice."""
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> StateLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


__all__ = ["LOCK_NAME", "StateLock", "StateLockError"]
