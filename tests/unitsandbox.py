"""Run a command under the seccomp filters that systemd (252) installs for a unit's settings, without systemd.

::

    python tests/unitsandbox.py systemd/ballbar.service -- ballbar run --simulate

What it applies, each as its own filter as systemd does (the kernel takes the strictest answer):

- ``SystemCallFilter=`` (allow list, then the ``~`` lists taken out; groups expanded by
  ``systemd-analyze syscall-filter``), ``SystemCallErrorNumber=`` for the rest;
- ``RestrictAddressFamilies=``: ``socket()`` of any other family fails with ``EAFNOSUPPORT``;
- ``MemoryDenyWriteExecute=yes``: ``mmap`` with write and execute, ``mprotect``/``pkey_mprotect``
  adding execute, ``shmat`` with ``SHM_EXEC`` fail with ``EPERM``;
- ``RestrictNamespaces=yes``: ``clone``/``unshare`` with a namespace flag fail with ``EPERM``, ``clone3``
  with ``ENOSYS`` (so that the C library falls back to ``clone``), ``setns`` with ``EPERM``.

Not applied: everything that is not seccomp (namespaces, mounts, the device cgroup, users), and
``LockPersonality=`` (nothing here calls ``personality``).  libseccomp is used through ctypes, so only
its shared library is needed (``libseccomp2``, present wherever systemd is).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import re
import socket
import subprocess
import sys
from collections.abc import Sequence

ALLOW = 0x7FFF0000
EQ, GE, MASKED_EQ = 4, 5, 7
NS_FLAGS = (0x00020000, 0x02000000, 0x04000000, 0x08000000, 0x10000000, 0x20000000, 0x40000000)
ALWAYS = {"execve", "exit", "exit_group", "getrlimit", "rt_sigreturn", "sigreturn"}  # systemd adds these


def _errno_action(e: int) -> int:
    return 0x00050000 | e


class _Cmp(ctypes.Structure):
    _fields_ = [("arg", ctypes.c_uint), ("op", ctypes.c_int), ("a", ctypes.c_uint64), ("b", ctypes.c_uint64)]


def library() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("seccomp") or "libseccomp.so.2"
    try:
        lib = ctypes.CDLL(name, use_errno=True)
    except OSError:
        return None
    lib.seccomp_init.restype = ctypes.c_void_p
    lib.seccomp_init.argtypes = [ctypes.c_uint32]
    lib.seccomp_syscall_resolve_name.argtypes = [ctypes.c_char_p]
    lib.seccomp_load.argtypes = [ctypes.c_void_p]
    lib.seccomp_release.argtypes = [ctypes.c_void_p]
    lib.seccomp_rule_add_array.argtypes = [
        ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int, ctypes.c_uint, ctypes.POINTER(_Cmp),
    ]
    return lib


def settings(unit: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    with open(unit, encoding="utf-8") as fh:
        for line in fh:
            m = re.match(r"^([A-Za-z]+)=(.*)$", line.strip())
            if m:
                out.setdefault(m.group(1), []).append(m.group(2))
    return out


def syscall_group(name: str, seen: set[str] | None = None) -> set[str]:
    """The system calls of ``@group``, nested groups expanded (``systemd-analyze syscall-filter``)."""
    seen = set() if seen is None else seen
    text = subprocess.run(["systemd-analyze", "syscall-filter", name], capture_output=True, text=True,
                          check=True).stdout
    out: set[str] = set()
    for line in text.splitlines()[1:]:
        word = line.strip()
        if not word or word.startswith("#"):
            continue
        if word.startswith("@"):
            if word not in seen:
                seen.add(word)
                out |= syscall_group(word, seen)
        else:
            out.add(word)
    return out


class _Filter:
    def __init__(self, lib: ctypes.CDLL, default: int) -> None:
        self.lib = lib
        self.ctx = lib.seccomp_init(default)
        if not self.ctx:
            raise OSError("seccomp_init failed")

    def rule(self, action: int, name: str, *cmps: tuple[int, int, int, int]) -> None:
        nr = self.lib.seccomp_syscall_resolve_name(name.encode())
        if nr < 0:
            return  # not on this architecture
        arr = (_Cmp * max(1, len(cmps)))(*[_Cmp(*c) for c in cmps])
        r = self.lib.seccomp_rule_add_array(self.ctx, action, nr, len(cmps), arr)
        if r < 0:
            raise OSError(-r, f"seccomp rule for {name} {cmps}")

    def load(self) -> None:
        r = self.lib.seccomp_load(self.ctx)
        self.lib.seccomp_release(self.ctx)
        if r < 0:
            raise OSError(-r, "seccomp_load")


def apply(unit: str) -> list[str]:
    """Install the unit's filters in this process (and so in what it executes); what was applied."""
    lib = library()
    if lib is None:
        raise OSError("libseccomp is not installed")
    s = settings(unit)
    done = []
    families = [int(getattr(socket, f)) for v in s.get("RestrictAddressFamilies", []) for f in v.split()]
    if families:
        f = _Filter(lib, ALLOW)
        refuse = _errno_action(errno.EAFNOSUPPORT)
        top = max(families)
        for fam in range(top):
            if fam not in families:
                f.rule(refuse, "socket", (0, EQ, fam, 0))
        f.rule(refuse, "socket", (0, GE, top + 1, 0))
        f.load()
        done.append(f"address families {sorted(families)}")
    if s.get("MemoryDenyWriteExecute", ["no"])[-1] == "yes":
        prot_wx, prot_x, shm_exec = 6, 4, 0o100000
        f = _Filter(lib, ALLOW)
        eperm = _errno_action(errno.EPERM)
        f.rule(eperm, "mmap", (2, MASKED_EQ, prot_wx, prot_wx))
        f.rule(eperm, "mprotect", (2, MASKED_EQ, prot_x, prot_x))
        f.rule(eperm, "pkey_mprotect", (2, MASKED_EQ, prot_x, prot_x))
        f.rule(eperm, "shmat", (2, MASKED_EQ, shm_exec, shm_exec))
        f.load()
        done.append("no W+X memory")
    if s.get("RestrictNamespaces", ["no"])[-1] == "yes":
        f = _Filter(lib, ALLOW)
        eperm = _errno_action(errno.EPERM)
        for bit in NS_FLAGS:
            f.rule(eperm, "clone", (0, MASKED_EQ, bit, bit))
            f.rule(eperm, "unshare", (0, MASKED_EQ, bit, bit))
        f.rule(eperm, "setns", (1, GE, 0, 0))
        f.rule(_errno_action(errno.ENOSYS), "clone3")
        f.load()
        done.append("no namespaces")
    allow: set[str] = set()
    deny: set[str] = set()
    for v in s.get("SystemCallFilter", []):
        target = deny if v.startswith("~") else allow
        for word in v.lstrip("~").split():
            target |= syscall_group(word) if word.startswith("@") else {word}
    if allow:
        # Last: the allow list may not include what loading a filter needs.
        code = getattr(errno, s.get("SystemCallErrorNumber", ["EPERM"])[-1])
        f = _Filter(lib, _errno_action(code))
        for name in sorted((allow - deny) | ALWAYS):
            f.rule(ALLOW, name)
        f.load()
        done.append(f"{len((allow - deny) | ALWAYS)} system calls")
    return done


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) < 3 or args[1] != "--":
        print("usage: unitsandbox.py UNIT -- COMMAND [ARGS...]", file=sys.stderr)
        return 2
    done = apply(args[0])
    print(f"unitsandbox: {'; '.join(done)}", file=sys.stderr, flush=True)
    os.execvp(args[2], args[2:])
    return 127  # not reached


if __name__ == "__main__":
    sys.exit(main())
