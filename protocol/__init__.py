"""ballbar.protocol: bytes in, frames out. Pure: no I/O, no threads, no clocks.

Two wire formats for the ball-bar's length transducer (``protocol/README.md``):

- :mod:`.binary`: 17-byte frames with sync word, sample counter, device clock,
  displacement in 10 nm counts, status and CRC-16, for rates up to 10 kHz and more.
- :mod:`.ascii`: one reading per text line, as plain gauge interfaces send it,
  streamed or polled; :mod:`.gauges`: the profiles of real gauge interfaces
  (Mitutoyo, Sylvac, TESA) as formats of that decoder.

Both decoders take any chunking of the byte stream, skip garbage, resynchronise,
count what they dropped and why, and never raise for bad bytes.
"""

from typing import TYPE_CHECKING, Any

from ._common import INVALID, Readings, Status

if TYPE_CHECKING:
    from .ascii import AsciiDecoder, AsciiFormat
    from .binary import BinaryDecoder


def __getattr__(name: str) -> Any:
    """The decoders, imported when first asked for: a reader of recordings needs the status bits alone."""
    if name in ("AsciiDecoder", "AsciiFormat"):
        from . import ascii

        return getattr(ascii, name)
    if name == "BinaryDecoder":
        from .binary import BinaryDecoder

        return BinaryDecoder
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["INVALID", "AsciiDecoder", "AsciiFormat", "BinaryDecoder", "Readings", "Status"]
