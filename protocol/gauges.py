"""Device profiles: real gauge interfaces as formats of the ASCII line decoder.

A profile is data (``protocol/README.md``, "Gauge profiles"): the framing of
the device's answer (an :class:`~.ascii.AsciiFormat`: header template, line
end, error words and the status bits they mean, unit), the request the host
sends in polled mode and whether polling is the default, the serial line's
settings, and the answer's length for the link budget.  Every profile is
decoded by :class:`~.ascii.AsciiDecoder`: adding one is adding an entry to
:data:`PROFILES`, not a decoder.

Why a link budget: a polled gauge is half duplex, the request and the answer
take turns on the line, so the line alone caps the rate at
``baud / ((request + answer bytes) * bits per character)``; a rate asked
beyond that is refused before the port opens (:meth:`GaugeProfile.check_rate`).
"""

from __future__ import annotations

from dataclasses import dataclass

from ._common import Status
from .ascii import AsciiFormat

OVER = int(Status.OVER_RANGE)
FAULT = int(Status.SENSOR_FAULT)


@dataclass(frozen=True)
class GaugeProfile:
    """One kind of gauge interface.

    ``fmt``: how its answers are framed and decoded (``fmt.request``: what the
    host sends to ask for one reading); ``prefix``: the header the simulated
    device writes (an instance of ``fmt.header``); ``polled``: the host must ask
    (the default mode is ``poll``); ``streams``: the device can also send on its
    own (``mode=stream``); ``baud``, ``bytesize``, ``parity`` (``N``, ``E``,
    ``O``), ``stopbits``: the line's default settings; ``answer_bytes``: the
    length of one answer, line end included (the longest the format writes at
    its width), for the link budget; ``source``: where the format comes from.
    """

    name: str
    title: str
    fmt: AsciiFormat
    prefix: str
    polled: bool
    streams: bool
    baud: int
    bytesize: int
    parity: str
    stopbits: int
    answer_bytes: int
    source: str

    @property
    def bits_per_char(self) -> int:
        """Start bit, data bits, parity bit, stop bits."""
        return 1 + self.bytesize + (self.parity != "N") + self.stopbits

    def line_time_s(self, baud: int | None = None, polled: bool | None = None, request: bytes | None = None) -> float:
        """Seconds the line is busy per reading: the request (polled) and the answer, back to back."""
        polled = self.polled if polled is None else polled
        req = len(self.fmt.request if request is None else request) if polled else 0
        return (req + self.answer_bytes) * self.bits_per_char / float(baud or self.baud)

    def max_rate_hz(self, baud: int | None = None, polled: bool | None = None, request: bytes | None = None) -> float:
        """The highest reading rate the line carries (no time left for the device to answer)."""
        return 1.0 / self.line_time_s(baud, polled, request)

    def check_rate(
        self, rate_hz: float, baud: int | None = None, polled: bool | None = None, request: bytes | None = None
    ) -> str | None:
        """Why ``rate_hz`` cannot be carried at ``baud``, or ``None`` if it can."""
        top = self.max_rate_hz(baud, polled, request)
        if rate_hz <= top:
            return None
        polled = self.polled if polled is None else polled
        req = len(self.fmt.request if request is None else request) if polled else 0
        what = f"{req} request + {self.answer_bytes} answer bytes" if polled else f"{self.answer_bytes} bytes a line"
        return (
            f"rate={rate_hz:g} Hz is more than a {self.name} gauge's line carries at {baud or self.baud} baud: "
            f"{what} of {self.bits_per_char} bits take {1e3 * self.line_time_s(baud, polled, request):.2f} ms, "
            f"at most {top:.1f} Hz; ask for less, or raise the device's and the URL's baud"
        )


def _fmt(**kw: object) -> AsciiFormat:
    return AsciiFormat(**kw)  # type: ignore[arg-type]


#: The profiles by name (the source URL's ``protocol=``).
PROFILES: dict[str, GaugeProfile] = {
    p.name: p
    for p in (
        GaugeProfile(
            name="mitutoyo",
            title="Mitutoyo Digimatic data output (USB and RS-232 interfaces)",
            # 01A+0000.123<CR>: D1 code, D2 channel, D3 item, D4 sign, D5-D12 eight characters with a floating
            # point, D13 CR.  Width 9 (sign and 8 characters), 4 decimals: 0.1 um in mm.
            fmt=_fmt(header="99A", eol=b"\r", request=b"1", width=9, decimals=4, max_line=32),
            prefix="01A",
            polled=True,
            streams=False,
            baud=9600,
            bytesize=8,
            parity="N",
            stopbits=1,
            answer_bytes=13,
            source="Mitutoyo Digimatic data output format, as the issue quotes it (D1..D13)",
        ),
        GaugeProfile(
            name="sylvac",
            title="Sylvac instruments (simplex: streamed; duplex: asked with ?<CR>)",
            # [sign | digits "." decimals | CR]; the sign is "+", "-" or a space.  ERR3: out of the measuring
            # range; ERR0: sensor error; another ERR<n>: a sensor fault (not a measurement).
            fmt=_fmt(eol=b"\r", request=b"?\r", decimals=4, width=8, plus=" ", errors=(("ERR3", OVER), ("ERR0", FAULT)),
                     error_prefix="ERR", over_word="ERR3", fault_word="ERR0", max_line=32),
            prefix="",
            polled=True,
            streams=True,
            baud=4800,
            bytesize=7,
            parity="E",
            stopbits=2,
            answer_bytes=9,
            source="Sylvac data format [sign | digits . decimals | CR] and error words ERR0, ERR3",
        ),
        GaugeProfile(
            name="tesa",
            title="TESA TT-series LVDT amplifiers (TT80, TT90 and compatible)",
            # Every command ends with CR; ?<CR> requests the displayed value, answered as a signed number and
            # CR LF.  Errors are ERR<n> (a sensor fault: not a measurement).
            fmt=_fmt(eol=b"\r\n", request=b"?\r", decimals=5, width=9, error_prefix="ERR", max_line=32),
            prefix="",
            polled=True,
            streams=True,
            baud=4800,
            bytesize=7,
            parity="E",
            stopbits=2,
            answer_bytes=11,
            source="TESA TT80/TT90 user manual, chapter 11 (RS232): 4800 Bd, 7 bits, even parity, 2 stop bits",
        ),
    )
}


def profile(name: str) -> GaugeProfile:
    """The profile called ``name``; :class:`KeyError` names the known ones."""
    try:
        return PROFILES[name]
    except KeyError:
        raise KeyError(f"unknown gauge profile {name!r} (known: {', '.join(sorted(PROFILES))})") from None


__all__ = ["PROFILES", "GaugeProfile", "profile"]
