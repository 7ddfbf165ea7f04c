"""One daemon per state directory: an exclusive ``flock`` on the state directory itself.

Two daemons on one state directory would each run retention over the other's
recordings (the other's open file included), "recover" the other's open file
by rewriting it, and interleave two devices' files under one machine id.
:class:`StateLock` takes the lock at start, before the source or any output
opens; a second ``ballbar run`` then fails with one line naming the holder's
PID (exit code 2).

The lock is held on the directory's own descriptor, not on a file in it: no
``rm`` of a file can take it away (a lock on ``STATE_DIR/ballbar.lock`` was
lost when an operator deleted that file as stale, and a second daemon then
rewrote the first one's open recording).  ``ballbar.lock`` only holds the
holder's PID for the refusal's message.  The kernel drops an ``flock`` when
its holder's descriptor closes, so a daemon killed with ``kill -9`` (or by the
OOM killer) leaves a PID file but no lock: the next start takes it at once.
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
            fd = os.open(self.state_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        except OSError as err:
            raise StateLockError(f"{where}: cannot open the directory: {err.strerror or err}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            os.close(fd)
            if err.errno in (errno.EWOULDBLOCK, errno.EACCES):
                holder = _read_pid(self.path)
                who = f"PID {holder}" if holder else "another process"
                raise StateLockError(f"{where} is in use by another ballbar daemon ({who}, "
                                     f"its PID in {self.path}; the lock is the directory's)") from None
            raise StateLockError(f"{where}: cannot lock the directory: {err.strerror or err}") from None
        try:
            pid_fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o640)
            try:
                os.write(pid_fd, f"{os.getpid()}\n".encode())
            finally:
                os.close(pid_fd)
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


def _read_pid(path: Path) -> int | None:
    try:
        with open(path, "rb") as fh:
            text = fh.read(32).decode("ascii", "replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


__all__ = ["LOCK_NAME", "StateLock", "StateLockError"]
