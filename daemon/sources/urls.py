"""Source URLs: the scheme registry, the options and their checks, :func:`open_source` and :func:`check_source`."""

from __future__ import annotations

import dataclasses
import logging
import math
import urllib.parse
from collections.abc import Callable
from typing import Any

from ballbar.protocol import AsciiFormat
from ballbar.protocol.gauges import PROFILES

from ..errors import SourceConfigError
from .base import DEFAULT_BATCH_S, PYSERIAL_SCHEMES, RATE_MAX_HZ, RATE_MIN_HZ, Source
from .paced import ReplaySource, SimSource
from .serial import SerialSource

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------- registry and URLs

SourceFactory = Callable[[str, str, "_Options"], Source]
_REGISTRY: dict[str, SourceFactory] = {}


def register_source(scheme: str, factory: SourceFactory) -> None:
    """Make ``scheme:`` URLs open with ``factory(url, target, options)``."""
    _REGISTRY[scheme] = factory


def source_schemes() -> list[str]:
    return sorted(_REGISTRY)


class _Options:
    """URL query and keyword options, converted on demand; leftovers are errors."""

    def __init__(self, url: str, query: dict[str, str], kwargs: dict[str, Any], check_only: bool = False) -> None:
        both = sorted(set(query) & set(kwargs))
        if both:
            raise SourceConfigError(f"{url}: option {both[0]!r} given both in the URL and as a keyword")
        self.url = url
        self.values: dict[str, Any] = {**query, **kwargs}
        self.known: list[str] = []
        self.check_only = check_only

    def get(self, key: str, conv: Callable[[Any], Any], default: Any = None) -> Any:
        self.known.append(key)
        if key not in self.values:
            return default
        raw = self.values.pop(key)
        if raw is None:
            return default
        try:
            return conv(raw)
        except (TypeError, ValueError) as err:
            raise SourceConfigError(f"{self.url}: option {key}={raw!r}: {err}") from None

    def require(self, key: str, conv: Callable[[Any], Any], why: str) -> Any:
        if self.values.get(key) is None:
            raise SourceConfigError(f"{self.url}: option {key} is required ({why})")
        return self.get(key, conv)

    def done(self) -> None:
        if self.values:
            key = sorted(self.values)[0]
            raise SourceConfigError(f"{self.url}: unknown option {key!r} (known: {', '.join(sorted(self.known))})")
        if self.check_only:
            raise _Checked


class _Checked(Exception):
    """Raised by :meth:`_Options.done` when only checking: the source is not opened."""


def _pos_float(v: Any) -> float:
    x = float(v)
    if not (math.isfinite(x) and x > 0):
        raise ValueError("must be a finite number > 0")
    return x


def _finite(v: Any) -> float:
    x = float(v)
    if not math.isfinite(x):
        raise ValueError("must be a finite number")
    return x


def _rate(v: Any) -> float:
    x = _pos_float(v)
    if not RATE_MIN_HZ <= x <= RATE_MAX_HZ:
        raise ValueError(f"must be within {RATE_MIN_HZ:g}..{RATE_MAX_HZ:g} Hz")
    return x


def _speed(v: Any) -> float:
    if isinstance(v, str) and v.strip().lower() in ("max", "inf", "fast"):
        return math.inf
    x = float(v)
    if not x > 0:
        raise ValueError("must be > 0 or 'max'")
    return x


def _nonneg_int(v: Any) -> int:
    if isinstance(v, bool):
        raise ValueError("must be an integer")
    x = int(v)
    if x < 0:
        raise ValueError("must be >= 0")
    return x


def _bool(v: Any) -> bool:
    if isinstance(v, bool):
        return v
    s = str(v).strip().lower()
    if s in ("1", "true", "yes", "on"):
        return True
    if s in ("0", "false", "no", "off"):
        return False
    raise ValueError("must be true or false")


def _choice(*allowed: str) -> Callable[[Any], str]:
    def conv(v: Any) -> str:
        s = str(v)
        if s not in allowed:
            raise ValueError(f"must be one of {', '.join(allowed)}")
        return s

    return conv


def _pos_int(v: Any) -> int:
    if isinstance(v, bool):
        raise ValueError("must be an integer")
    x = int(v)
    if x <= 0:
        raise ValueError("must be > 0")
    return x


def _framing(v: Any) -> tuple[int, str, int]:
    """``8N1``, ``7E2``, ...: data bits (5..8), parity (N, E, O), stop bits (1, 2)."""
    if isinstance(v, tuple):
        return v
    s = str(v).strip().upper()
    if len(s) != 3 or s[0] not in "5678" or s[1] not in "NEO" or s[2] not in "12":
        raise ValueError("must be data bits, parity and stop bits, such as 8N1 or 7E2")
    return int(s[0]), s[1], int(s[2])


def _bytes(v: Any) -> bytes:
    if isinstance(v, bytes):
        return v
    return str(v).encode("latin-1")


def _open_serial(url: str, target: str, opt: _Options) -> Source:
    if target.startswith("///"):
        target = target[2:]
    if not target:
        raise SourceConfigError(f"{url}: no port (serial:/dev/ttyUSB0, serial:socket://host:port, ...)")
    protocol = opt.get("protocol", _choice("binary", "ascii", *PROFILES), "binary")
    gauge = PROFILES.get(protocol)
    base = gauge.fmt if gauge is not None else AsciiFormat()
    default_mode = "poll" if gauge is not None and gauge.polled else "stream"
    mode = opt.get("mode", _choice("stream", "poll"), default_mode)
    cal_mm = opt.require("cal_mm", _finite, "the bar's length at zero displacement, from its calibration")
    rate = opt.get("rate", _rate)
    if mode == "poll" and protocol == "binary":
        raise SourceConfigError(f"{url}: mode=poll needs protocol=ascii or a gauge profile")
    if mode == "stream" and gauge is not None and not gauge.streams:
        raise SourceConfigError(f"{url}: a {protocol} gauge does not stream: it answers requests (mode=poll)")
    if mode == "poll" and rate is None:
        raise SourceConfigError(f"{url}: mode=poll needs rate (the polling rate in Hz)")
    ts = opt.get("timestamp", _choice("s", "ms", "us", "none"), "none")
    try:
        fmt = dataclasses.replace(
            base,
            unit=opt.get("unit", _choice("mm", "um", "nm", "in"), base.unit),
            scale=opt.get("scale", _finite, base.scale),
            ts_unit=None if ts == "none" else ts,
            max_line=opt.get("max_line", int, base.max_line),
            request=opt.get("request", _bytes, base.request),
        )
    except ValueError as err:
        raise SourceConfigError(f"{url}: {err}") from None
    baud = opt.get("baud", _pos_int, gauge.baud if gauge is not None else 2_000_000)
    framing = opt.get("framing", _framing, (gauge.bytesize, gauge.parity, gauge.stopbits) if gauge else (8, "N", 1))
    if gauge is not None and rate is not None:
        line = dataclasses.replace(gauge, bytesize=framing[0], parity=framing[1], stopbits=framing[2])
        why = line.check_rate(rate, baud, mode == "poll", fmt.request)
        if why is not None:
            raise SourceConfigError(f"{url}: {why}")
    kwargs = {
        "baud": baud,
        "bytesize": framing[0],
        "parity": framing[1],
        "stopbits": framing[2],
        "batch_s": opt.get("batch_s", _pos_float, DEFAULT_BATCH_S),
        "stall_s": opt.get("stall_s", _pos_float),
        "poll_timeout_s": opt.get("poll_timeout_s", _pos_float),
        "retry_min_s": opt.get("retry_min_s", _pos_float, 0.05),
        "retry_max_s": opt.get("retry_max_s", _pos_float, 2.0),
        "exclusive": opt.get("exclusive", _bool, True),
    }
    opt.done()
    return SerialSource(url, target, cal_mm=cal_mm, protocol=protocol, mode=mode, rate_hz=rate, fmt=fmt, **kwargs)


def _open_sim(url: str, target: str, opt: _Options) -> Source:
    if target.strip("/"):
        raise SourceConfigError(f"{url}: sim: takes no path, only options (sim:?rate=1000&speedup=10)")
    kwargs = {
        "plan": opt.get("plan", lambda v: v),
        "machine": opt.get("machine", lambda v: v),
        "library": opt.get("library", lambda v: v),
        "run_plans": opt.get("run_plans", lambda v: v),
        "rate_hz": opt.get("rate", _rate),
        "speedup": opt.get("speedup", _speed, 1.0),
        "seed": opt.get("seed", _nonneg_int, 0),
        "repeat": opt.get("repeat", _nonneg_int, 1),
        "gap_s": opt.get("gap_s", lambda v: max(0.0, _finite(v)), 0.0),
        "batch_s": opt.get("batch_s", _pos_float, DEFAULT_BATCH_S),
    }
    opt.done()
    return SimSource(url, **kwargs)


def _open_replay(url: str, target: str, opt: _Options) -> Source:
    if target.startswith("///"):
        target = target[2:]
    path = urllib.parse.unquote(target)
    if not path:
        raise SourceConfigError(f"{url}: no file (replay:recording.csv?speed=10)")
    kwargs = {
        "speed": opt.get("speed", _speed, 1.0),
        "rate_hz": opt.get("rate", _rate),
        "batch_s": opt.get("batch_s", _pos_float, DEFAULT_BATCH_S),
    }
    opt.done()
    return ReplaySource(url, path, **kwargs)


register_source("serial", _open_serial)
register_source("sim", _open_sim)
register_source("replay", _open_replay)


def split_url(url: str) -> tuple[str, str, dict[str, str]]:
    """``scheme, target, query`` of a source URL (see the module docstring)."""
    head, _, query = url.partition("?")
    if head.startswith("/"):
        scheme, target = "serial", head
    else:
        scheme, _, target = head.partition(":")
        if scheme in PYSERIAL_SCHEMES and target.startswith("//"):
            scheme, target = "serial", head
    if scheme not in _REGISTRY:
        raise SourceConfigError(
            f"{url}: unknown source {scheme!r} (known: {', '.join(source_schemes())}, a /dev path or a pyserial URL)"
        )
    opts: dict[str, str] = {}
    for k, v in urllib.parse.parse_qsl(query, keep_blank_values=True):
        if k in opts:
            raise SourceConfigError(f"{url}: option {k!r} given twice")
        opts[k] = v
    return scheme, target, opts


def open_source(url: str, **options: Any) -> Source:
    """Open the source that ``url`` names; keyword ``options`` complement the URL's query."""
    scheme, target, query = split_url(url)
    opt = _Options(url, query, {k: v for k, v in options.items() if v is not None})
    return _REGISTRY[scheme](url, target, opt)


def check_source(url: str, **options: Any) -> None:
    """What :func:`open_source` checks of ``url`` and ``options``, without opening anything.

    Raises :class:`SourceConfigError` naming the problem.  (A source registered
    by a plug-in that never calls ``opt.done()`` would be opened: the built-in
    ones all do.)
    """
    scheme, target, query = split_url(url)
    opt = _Options(url, query, {k: v for k, v in options.items() if v is not None}, check_only=True)
    try:
        src = _REGISTRY[scheme](url, target, opt)
    except _Checked:
        return
    src.close()
