"""What ``/proc`` says about a process: the one reader of it for the daemon and its benchmarks (Linux only).

Every function raises :class:`OSError` when the process (or thread) is gone, so that a caller decides in one
place what a vanished process means.
"""

from __future__ import annotations

import os

CLK_TCK = os.sysconf("SC_CLK_TCK")


def status(pid: int | str, tid: int | str | None = None) -> dict[str, str]:
    """``/proc/PID/status`` (or a thread's, ``/proc/PID/task/TID/status``) as ``{key: value}``, values stripped
    (``VmRSS`` is ``"123456 kB"``)."""
    path = f"/proc/{pid}/status" if tid is None else f"/proc/{pid}/task/{tid}/status"
    out: dict[str, str] = {}
    with open(path, encoding="ascii", errors="replace") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            out[key] = value.strip()
    return out


def kib(value: str) -> int:
    """A ``status`` size (``"123456 kB"``) in KiB."""
    return int(value.split()[0])


def rss_bytes(pid: int | str) -> int:
    """Resident memory now."""
    return kib(status(pid)["VmRSS"]) * 1024


def stat(pid: int | str, tid: int | str | None = None) -> tuple[str, list[str]]:
    """``/proc/PID/stat`` (or a thread's): the name (``comm``, which may hold spaces and parentheses) and the
    fields after it (``fields[0]`` is the state; utime and stime are ``fields[11]`` and ``fields[12]``)."""
    path = f"/proc/{pid}/stat" if tid is None else f"/proc/{pid}/task/{tid}/stat"
    with open(path, encoding="ascii", errors="replace") as fh:
        text = fh.read()
    head, _, tail = text.rpartition(")")
    return head.partition("(")[2], tail.split()


def cpu_ticks(fields: list[str]) -> int:
    """utime + stime of :func:`stat`'s fields, in clock ticks (:data:`CLK_TCK` a second)."""
    return int(fields[11]) + int(fields[12])


def cpu_seconds(pid: int | str) -> float:
    """The CPU time a process has used, user and system."""
    return cpu_ticks(stat(pid)[1]) / CLK_TCK


def threads(pid: int | str) -> list[str]:
    """The process' thread ids."""
    return os.listdir(f"/proc/{pid}/task")


def fds(pid: int | str) -> list[str]:
    """The process' open descriptors (their numbers)."""
    return os.listdir(f"/proc/{pid}/fd")


def children(pid: int | str) -> list[int]:
    """The process' children (of every thread; needs ``CONFIG_PROC_CHILDREN``); threads that vanish are skipped."""
    kids: list[int] = []
    for tid in threads(pid):
        try:
            with open(f"/proc/{pid}/task/{tid}/children", encoding="ascii") as fh:
                kids += [int(p) for p in fh.read().split()]
        except OSError:
            continue
    return kids
