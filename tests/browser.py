"""A headless Chromium driven over the DevTools protocol on a pipe, with the standard library only.

Why a pipe and not a port: ``--remote-debugging-pipe`` needs no free TCP port,
no HTTP handshake and no websocket library, and nothing else on the machine
can talk to the browser.  Chromium reads JSON messages, each ended by a NUL
byte, on its file descriptor 3 and writes its answers and events the same way
on descriptor 4.

The child is started with :func:`os.posix_spawn` (its file actions put our
pipe ends on 3 and 4 without a ``preexec_fn``, which is unsafe with threads),
in a session of its own, so that :meth:`Chromium.close` can kill the whole
process group: Chromium forks a zygote, renderers and utility processes that
would otherwise outlive a test.  Every wait has a deadline; a browser that
hangs fails the test instead of hanging it.
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import json
import os
import select
import shutil
import signal
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--disable-dev-shm-usage",
    "--hide-scrollbars",
    "--mute-audio",
)


class BrowserError(RuntimeError):
    """The browser answered with an error, died, or did not answer in time."""


def find_chromium() -> str | None:
    """The browser to test with: ``$BALLBAR_CHROMIUM`` when set (None if it is not an executable), else
    ``chromium`` on PATH, else Debian's ``/usr/bin/chromium``; None when there is none."""
    forced = os.environ.get("BALLBAR_CHROMIUM")
    if forced:
        return forced if os.access(forced, os.X_OK) else None
    for name in ("chromium", "chromium-browser"):
        exe = shutil.which(name)
        if exe:
            return exe
    return "/usr/bin/chromium" if os.access("/usr/bin/chromium", os.X_OK) else None


class Chromium:
    """One headless browser; use as a context manager (``with Chromium(exe, 30) as b``).

    ``events`` keeps every event received, in order, as ``(sessionId, method,
    params)``, so a test can look back at what happened during a load
    (requests, console messages, exceptions).
    """

    def __init__(self, exe: str, timeout_s: float, window: tuple[int, int] = (1200, 900)) -> None:
        self.exe = exe
        self.deadline = time.monotonic() + timeout_s
        self.window = window
        self.events: list[tuple[str | None, str, dict[str, Any]]] = []
        self._buf = b""
        self._next_id = 0
        self._pid: int | None = None
        self._to: int | None = None
        self._from: int | None = None
        self._profile: tempfile.TemporaryDirectory[str] | None = None
        self._log: Path | None = None

    # ------------------------------------------------------------------ process

    def __enter__(self) -> Chromium:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        self._profile = tempfile.TemporaryDirectory(prefix="ballbar-chromium-")
        profile = Path(self._profile.name)
        self._log = profile / "stderr.log"
        to_r, to_w = os.pipe()  # we write, the browser reads on 3
        from_r, from_w = os.pipe()  # the browser writes on 4, we read
        # Copies above 10 so that putting them on 3 and 4 cannot clobber one another.
        hi_r = fcntl.fcntl(to_r, fcntl.F_DUPFD_CLOEXEC, 10)
        hi_w = fcntl.fcntl(from_w, fcntl.F_DUPFD_CLOEXEC, 10)
        os.close(to_r)
        os.close(from_w)
        argv = [
            self.exe,
            *FLAGS,
            f"--user-data-dir={profile / 'profile'}",
            f"--window-size={self.window[0]},{self.window[1]}",
            "--remote-debugging-pipe",
            "about:blank",
        ]
        actions = [
            (os.POSIX_SPAWN_OPEN, 0, "/dev/null", os.O_RDONLY, 0),
            (os.POSIX_SPAWN_OPEN, 1, str(self._log), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600),
            (os.POSIX_SPAWN_DUP2, 1, 2),
            (os.POSIX_SPAWN_DUP2, hi_r, 3),
            (os.POSIX_SPAWN_DUP2, hi_w, 4),
        ]
        try:
            self._pid = os.posix_spawn(self.exe, argv, dict(os.environ), file_actions=actions, setsid=True)
        except BaseException:
            for fd in (hi_r, hi_w, to_w, from_r):
                os.close(fd)
            self._profile.cleanup()
            raise
        os.close(hi_r)
        os.close(hi_w)
        self._to, self._from = to_w, from_r

    def close(self) -> None:
        """Ask the browser to quit, then kill its whole process group and reap it; always safe to call."""
        pid, self._pid = self._pid, None
        if pid is not None:
            with contextlib.suppress(OSError, BrowserError):
                self._send("Browser.close", {}, None)
            end = time.monotonic() + 3.0
            exited = False
            while time.monotonic() < end:
                done, _ = os.waitpid(pid, os.WNOHANG)
                if done:
                    exited = True
                    break
                time.sleep(0.05)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(pid, signal.SIGKILL)  # its zygote, renderers and helpers too
            if not exited:
                os.waitpid(pid, 0)
        for fd in (self._to, self._from):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._to = self._from = None
        if self._profile is not None:
            self._profile.cleanup()
            self._profile = None

    def stderr_tail(self, n: int = 2000) -> str:
        """The end of the browser's own output, for a failure message."""
        try:
            return self._log.read_text(errors="replace")[-n:] if self._log else ""
        except OSError:
            return ""

    # ------------------------------------------------------------------ protocol

    def _remaining(self) -> float:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise BrowserError("the browser did not finish within the time box")
        return left

    def _send(self, method: str, params: dict[str, Any], session: str | None) -> int:
        if self._to is None:
            raise BrowserError("the browser is not running")
        self._next_id += 1
        msg: dict[str, Any] = {"id": self._next_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        data = json.dumps(msg).encode() + b"\0"
        while data:
            _, ready, _ = select.select([], [self._to], [], self._remaining())
            if ready:
                data = data[os.write(self._to, data):]
        return self._next_id

    def _messages(self) -> Iterator[dict[str, Any]]:
        """Messages as they arrive, until the deadline; raises when the browser closes the pipe."""
        assert self._from is not None
        while True:
            while b"\0" in self._buf:
                raw, self._buf = self._buf.split(b"\0", 1)
                yield json.loads(raw)
            ready, _, _ = select.select([self._from], [], [], self._remaining())
            if ready:
                chunk = os.read(self._from, 1 << 20)
                if not chunk:
                    raise BrowserError(f"the browser closed its pipe; its output:\n{self.stderr_tail()}")
                self._buf += chunk

    def call(self, method: str, params: dict[str, Any] | None = None, session: str | None = None) -> dict[str, Any]:
        """Send one command and return its result, keeping the events that arrive meanwhile."""
        mid = self._send(method, params or {}, session)
        for msg in self._messages():
            if msg.get("id") == mid:
                if "error" in msg:
                    raise BrowserError(f"{method}: {msg['error']}")
                result: dict[str, Any] = msg.get("result", {})
                return result
            if "method" in msg:
                self.events.append((msg.get("sessionId"), msg["method"], msg.get("params", {})))
        raise AssertionError("unreachable")  # pragma: no cover

    def wait_event(self, method: str, session: str | None) -> dict[str, Any]:
        """The next event ``method`` of ``session`` (one already received counts)."""
        for i, (sid, m, params) in enumerate(self.events):
            if sid == session and m == method:
                del self.events[i]
                return params
        for msg in self._messages():
            if "method" in msg:
                if msg["method"] == method and msg.get("sessionId") == session:
                    return dict(msg.get("params", {}))
                self.events.append((msg.get("sessionId"), msg["method"], msg.get("params", {})))
        raise AssertionError("unreachable")  # pragma: no cover

    # ------------------------------------------------------------------ page helpers

    def open_page(self) -> str:
        """A new page target, attached (flat protocol); returns its session id, domains enabled."""
        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = str(self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"])
        for domain in ("Page", "Runtime", "Log", "Network"):
            self.call(f"{domain}.enable", {}, session)
        self.call("Emulation.setDeviceMetricsOverride",
                  {"width": self.window[0], "height": self.window[1], "deviceScaleFactor": 1, "mobile": False},
                  session)
        return session

    def load(self, session: str, url: str) -> None:
        """Navigate and wait for the load event (every subresource loaded or failed)."""
        self.events.clear()
        result = self.call("Page.navigate", {"url": url}, session)
        if result.get("errorText"):
            raise BrowserError(f"navigation to {url} failed: {result['errorText']}")
        self.wait_event("Page.loadEventFired", session)

    def evaluate(self, session: str, expression: str) -> Any:
        """A JavaScript expression's value (returned by value, so JSON-like)."""
        res = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True}, session)
        if "exceptionDetails" in res:
            raise BrowserError(f"script failed: {res['exceptionDetails']}")
        return res["result"].get("value")

    def screenshot(self, session: str) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"}, session)["data"])

    def requests(self, session: str) -> list[str]:
        """URLs the page requested since the last :meth:`load`."""
        return [p["request"]["url"] for s, m, p in self.events if s == session and m == "Network.requestWillBeSent"]

    def errors(self, session: str) -> list[str]:
        """Console errors, uncaught exceptions and error log entries since the last :meth:`load`."""
        out = []
        for s, m, p in self.events:
            if s != session:
                continue
            if m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                out.append("console: " + " ".join(str(a.get("value", a.get("description", ""))) for a in p["args"]))
            elif m == "Runtime.exceptionThrown":
                out.append("exception: " + str(p.get("exceptionDetails", {}).get("text", "")))
            elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                out.append("log: " + str(p["entry"].get("text", "")))
        return out
