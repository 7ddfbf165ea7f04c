"""The live view's configuration: :class:`ViewerOptions`, from the daemon's ``[rerun]`` section."""

from __future__ import annotations

import ipaddress
import math
import re
import time
import urllib.parse
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Literal, cast

from ballbar.analysis.errors import BallbarError

from ..config import Config, RerunSection

Mode = Literal["serve", "connect", "off"]
Clock = Literal["auto", "device", "host"]

APPLICATION_ID = "ballbar"
# Not the viewer's own 9876: a user's `rerun some.rrd` on this PC must not stream into the daemon's view.
DEFAULT_SERVE_PORT = RerunSection.port
_DEFAULT_MODE = cast(Mode, RerunSection.mode)  # the section's key is a str its check holds to the three modes

class ViewerConfigError(BallbarError, ValueError):
    """An invalid viewer option (unknown key or bad value); the message names it."""


@dataclass(frozen=True)
class ViewerOptions:
    """The streamer's configuration (from the daemon's ``[rerun]`` section: :func:`viewer_options`).

    The fields the section has keys for take its defaults (:class:`~ballbar.daemon.config.RerunSection`, the one
    place they are stated); the others are the streamer's own and no key sets them.

    ``mode``: ``serve``, ``connect`` or ``off``.  ``bind``/``port``: where the
    ``serve`` mode listens (default ``127.0.0.1``: this PC only; ``0.0.0.0``:
    every interface, viewers anywhere on the network, and anyone there can
    push data into the server too).  ``server_rss_cap_mb``: the server
    process is restarted when its resident memory passes this (default
    ``2 x server_memory_limit + 128 MiB``).  ``url``: the viewer to push to in ``connect`` mode,
    ``rerun+http://HOST:PORT/proxy``.  ``server_memory_limit``: the serve
    mode's history buffer (rerun syntax: ``256MiB``, ``10%``).

    ``tolerance_um``: half-width of the tolerance band; ``scale_um``: the
    deviation drawn halfway between the nominal circle and its centre (None:
    automatic, starting at ``AUTO_SCALE_START_UM``);
    ``polar_points``: points per drawn circle; ``polar_update_s``: how often
    the live circle is extended; ``polar_pieces``: how many pieces a live
    circle is sent in (each update sends the growing piece and those
    completed since, never the whole circle again); ``length_hz``: the
    length series' rate, on the host clock, whatever the sample rate;
    ``send_interval_s``: samples are processed and the length series sent
    at most this often (and at each result or event); ``buffer_hz``: rate at
    which the current test's samples are kept for the polar plot, at most
    ``max_buffer_samples`` of them; ``remove_setup``: subtract the latest
    centre and radius estimates from the curves.

    What a viewer that connects late is sent, besides what the server still
    holds of the live stream (see the module docstring): the last
    ``history_tests`` tests whole (polar plots, models, findings), the trends
    of the last ``TRENDS_KEPT`` tests, and the length series at
    ``history_length_hz`` over the last ``history_length_s``.

    ``clock``: which sample time the analysis runs on (``auto``: the device
    clock where the source has one, corrected by the times the analysis
    messages carry).  ``retry_s``: probe/rebind period;
    ``health_s``: how often a pushed stream is checked (a flush that fails
    at once: the viewer restarted between two probes; in ``serve`` mode one
    that times out: the server takes nothing); ``history_refresh_s``: in
    ``serve`` mode the history is sent again at least this often (other
    clients may have pushed it out of the server's buffer); ``stop_timeout_s``:
    bound on :meth:`RerunViewer.stop`.
    """

    mode: Mode = _DEFAULT_MODE
    bind: str = RerunSection.bind
    port: int = RerunSection.port
    url: str = RerunSection.url
    server_memory_limit: str = f"{round(RerunSection.memory_limit_mb)}MiB"  # rerun.memory_limit_mb
    server_rss_cap_mb: float | None = None  # None: 2 x server_memory_limit + 128 MiB
    application_id: str = APPLICATION_ID
    recording_name: str = ""
    tolerance_um: float = RerunSection.tolerance_um
    scale_um: float | None = None  # rerun.magnification
    polar_points: int = 2000
    polar_update_s: float = 0.5
    polar_pieces: int = 16
    length_hz: float = 100.0
    send_interval_s: float = 0.25
    buffer_hz: float = 1000.0
    max_buffer_samples: int = 250_000
    history_tests: int = RerunSection.history_tests
    history_length_hz: float = 1.0
    history_length_s: float = 86_400.0
    remove_setup: bool = True
    clock: Clock = "auto"
    retry_s: float = 2.0
    health_s: float = 10.0
    history_refresh_s: float = 600.0
    stop_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        checks: list[tuple[bool, str]] = [
            (self.mode in ("serve", "connect", "off"), f"rerun.mode must be serve, connect or off, not {self.mode!r}"),
            (_is_ip(self.bind), f"rerun.bind must be an IP address, not {self.bind!r}"),
            (isinstance(self.port, int) and 0 < self.port < 65536, f"rerun.port must be 1..65535, not {self.port!r}"),
            (
                proxy_address(self.url) is not None,
                f"rerun.url must be rerun+http://HOST:PORT/proxy, not {self.url!r}",
            ),
            (
                self.clock in ("auto", "device", "host"),
                f"rerun.clock must be auto, device or host, not {self.clock!r}",
            ),
            (bool(self.application_id), "rerun.application_id must not be empty"),
            (
                memory_bytes(self.server_memory_limit) is not None,
                f"rerun.server_memory_limit must be a size such as 128MiB, not {self.server_memory_limit!r}",
            ),
            (
                self.server_rss_cap_mb is None
                or (isinstance(self.server_rss_cap_mb, int | float) and self.server_rss_cap_mb >= 64),
                f"rerun.server_rss_cap_mb must be at least 64, not {self.server_rss_cap_mb!r}",
            ),
        ]
        for name in (
            "tolerance_um",
            "polar_update_s",
            "length_hz",
            "send_interval_s",
            "buffer_hz",
            "history_length_hz",
            "history_length_s",
            "retry_s",
            "health_s",
            "history_refresh_s",
            "stop_timeout_s",
        ):
            v = getattr(self, name)
            ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0
            checks.append((ok, f"rerun.{name} must be a number > 0, not {v!r}"))
        s = self.scale_um
        ok = s is None or (isinstance(s, int | float) and not isinstance(s, bool) and math.isfinite(s) and s > 0)
        checks.append((ok, f"viewer scale_um must be a number > 0 or unset (automatic), not {s!r}"))
        for name, lo in (("polar_points", 16), ("max_buffer_samples", 10_000), ("polar_pieces", 1),
                         ("history_tests", 0)):
            v = getattr(self, name)
            ok = isinstance(v, int) and not isinstance(v, bool) and v >= lo
            checks.append((ok, f"rerun.{name} must be an integer >= {lo}, not {v!r}"))
        for ok, msg in checks:
            if not ok:
                raise ViewerConfigError(msg)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ViewerOptions:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ViewerConfigError(f"unknown viewer key {unknown[0]!r} (known: {', '.join(sorted(known))})")
        return cls(**dict(data))

    @property
    def server_rss_cap(self) -> int:
        """Bytes of resident memory above which the serve mode's server process is restarted."""
        if self.server_rss_cap_mb is not None:
            return int(self.server_rss_cap_mb * 2**20)
        limit = memory_bytes(self.server_memory_limit)
        return 2 * (limit if limit is not None else 128 * 2**20) + 128 * 2**20

    @property
    def address(self) -> str:
        """Where viewers find the stream: the URL to give ``rerun``."""
        if self.mode == "serve":
            host = "127.0.0.1" if self.bind in ("0.0.0.0", "::") else self.bind
            return f"rerun+http://{host_for_url(host)}:{self.port}/proxy"
        return self.url


def memory_bytes(text: str) -> int | None:
    """``128MiB``, ``1GB``, ``512kB`` as bytes (rerun's size syntax, without its percentages), or None."""
    m = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]+)?)\s*([kMGT]i?B|B)\s*", str(text))
    if not m:
        return None
    mult = {"B": 1, "kB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12,
            "kiB": 2**10, "KiB": 2**10, "MiB": 2**20, "GiB": 2**30, "TiB": 2**40}.get(m[2])
    return int(float(m[1]) * mult) if mult else None


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


def host_for_url(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def proxy_address(url: str) -> tuple[str, int] | None:
    """``(host, port)`` of a ``rerun+http://HOST:PORT/proxy`` URL, None if it is not one."""
    try:
        p = urllib.parse.urlsplit(url)
        port = p.port
    except ValueError:
        return None
    if p.scheme not in ("rerun", "rerun+http", "rerun+https") or not p.hostname or p.path != "/proxy":
        return None
    return p.hostname, port or 9876


def viewer_options(cfg: Config) -> ViewerOptions:
    """The :class:`ViewerOptions` of the daemon's configuration: ``[rerun]``, ``plan``, ``daemon.machine_id``.

    Each key of the section sets its field (the configuration has checked the values it can check alone);
    ``memory_limit_mb`` (MiB) sets ``server_memory_limit`` and ``magnification`` (0: automatic) how many times a
    deviation is drawn larger than the radius (``r/R0 = 1 + M dR/R``), i.e. ``scale_um = 200 R / M`` (a division,
    drawn at 0.2 R0).  Raises :class:`ViewerConfigError` naming a bad value.
    """
    sec = cfg.rerun
    machine_id = cfg.daemon.machine_id or ""
    return ViewerOptions(
        mode=cast(Mode, sec.mode),
        bind=sec.bind,
        port=sec.port,
        url=sec.url,
        server_memory_limit=f"{round(float(sec.memory_limit_mb))}MiB",
        tolerance_um=sec.tolerance_um,
        scale_um=200.0 * cfg.plan.radius_mm / float(sec.magnification) if sec.magnification else None,
        history_tests=sec.history_tests,
        recording_name=f"ballbar {machine_id} {time.strftime('%Y-%m-%d %H:%M:%S')}".strip(),
    )


__all__ = ["APPLICATION_ID", "DEFAULT_SERVE_PORT", "ViewerConfigError", "ViewerOptions", "viewer_options"]
