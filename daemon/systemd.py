"""systemd notification: READY=1, WATCHDOG=1, STOPPING=1, STATUS=...

``sd_notify`` is one datagram to the AF_UNIX socket named in ``$NOTIFY_SOCKET``
(a leading ``@`` is the abstract namespace).  Outside systemd the variable is
unset and every call does nothing.  The watchdog is pinged from the daemon's
working loop (the loop that reads the source), never from a side thread, so a
hung loop is what systemd sees.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


class Notifier:
    def __init__(self, env: dict[str, str] | None = None) -> None:
        env = dict(os.environ) if env is None else env
        self.address = env.get("NOTIFY_SOCKET") or None
        usec = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        self.watchdog_s: float | None = None
        if usec and (not pid or pid == str(os.getpid())):
            try:
                self.watchdog_s = int(usec) / 1e6
            except ValueError:
                log.warning("ignoring WATCHDOG_USEC=%r", usec)
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, message: str) -> bool:
        if not self.address:
            return False
        addr = "\0" + self.address[1:] if self.address.startswith("@") else self.address
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                # Never wait on the manager: a receiver that stops reading would block the working loop.
                self._sock.setblocking(False)
            self._sock.sendto(message.encode(), addr)
            return True
        except BlockingIOError:
            log.debug("sd_notify: the receiver's queue is full; %r dropped", message.split("\n", 1)[0])
            return False
        except OSError as err:
            log.warning("sd_notify failed: %s", err)
            return False

    def ready(self, status: str = "") -> None:
        self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> None:
        self.notify("WATCHDOG=1")

    def status(self, text: str) -> None:
        self.notify(f"STATUS={text}")

    def stopping(self) -> None:
        self.notify("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
