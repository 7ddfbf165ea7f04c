"""What every decoder returns, whatever the wire format.

A decoder turns bytes into :class:`Readings`: columns of numpy arrays, one row
per sample, in wire order.  The fields are the protocol's own numbers; turning
them into timestamped, calibrated samples (unwrapping counters, mapping the
device clock to host time, adding the bar's calibration length) is the
acquisition layer's job (:mod:`ballbar.daemon.sources`).

Drop reasons are plain strings, counted in ``dict[str, int]`` so that they can
be logged and published as they are.  A name ending in ``_bytes`` counts bytes;
every other name counts frames or lines.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntFlag

import numpy as np
from numpy.typing import NDArray


class Status(IntFlag):
    """Per-sample status flags, the same bits in every protocol.

    ``OVER_RANGE``: the displacement is outside the transducer's linear range;
    the value is the clamped reading, not a measurement.  ``SENSOR_FAULT``: the
    LVDT or its excitation failed (open or short coil); the value is meaningless
    (NaN where the protocol has no number).  ``SIMULATED``: the sample comes from
    a simulator, never from a real bar.  Bits 2 to 6 are reserved (sent as 0,
    passed through on receipt).
    """

    OK = 0
    OVER_RANGE = 0x01
    SENSOR_FAULT = 0x02
    SIMULATED = 0x80


#: Status bits that make a sample's value unusable as a measurement.
INVALID = Status.OVER_RANGE | Status.SENSOR_FAULT

# Drop reasons.
BAD_CRC = "bad_crc"  # binary: a sync word whose frame failed its CRC
SKIPPED_BYTES = "skipped_bytes"  # bytes that were not part of any accepted frame or line
BAD_LINE = "bad_line"  # ascii: a line that does not follow the grammar
LONG_LINE = "long_line"  # ascii: a line longer than the format's max_line
BAD_UNIT = "bad_unit"  # ascii: a line whose unit suffix is not the configured unit


@dataclass(frozen=True)
class Readings:
    """Decoded samples, one row each, in wire order.

    ``value_mm``: the transducer reading converted to millimetres (for the binary
    protocol the LVDT displacement; for the ASCII protocol the number on the line
    times the format's unit and scale).  ``status``: :class:`Status` bits.
    ``seq``: the device's raw sample counter, or ``None`` when the protocol has
    none.  ``clock_s``: the device's raw sample clock in seconds, or ``None``.
    Counters and clocks wrap as the protocol says (``seq_modulus`` and
    ``clock_wrap_s`` of the decoder).
    """

    value_mm: NDArray[np.float64]
    status: NDArray[np.uint8]
    seq: NDArray[np.int64] | None = None
    clock_s: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return int(self.value_mm.shape[0])


def empty_readings(with_seq: bool, with_clock: bool) -> Readings:
    return Readings(
        np.empty(0, np.float64),
        np.empty(0, np.uint8),
        np.empty(0, np.int64) if with_seq else None,
        np.empty(0, np.float64) if with_clock else None,
    )


def add_counts(total: dict[str, int], delta: dict[str, int]) -> None:
    for key, value in delta.items():
        if value:
            total[key] = total.get(key, 0) + value


__all__ = [
    "BAD_CRC",
    "BAD_LINE",
    "BAD_UNIT",
    "INVALID",
    "LONG_LINE",
    "SKIPPED_BYTES",
    "Readings",
    "Status",
    "add_counts",
    "empty_readings",
]
