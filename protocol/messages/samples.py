"""Samples as the daemon sends them: decimated on the bus, every one in the MCAP log (delta-encoded columns)."""

from typing import Annotated, Literal, NotRequired, TypedDict

from .envelope import MachineId, SourceUrl, TWall, Version
from .fields import doc


class Samples(TypedDict):
    """Decimated samples on ballbar/<m>/samples (for display; the first sample of each 1/samples_hz slot)."""

    schema_version: Version
    kind: Annotated[Literal["samples"], doc("what the payload is")]
    machine_id: MachineId
    t_wall: TWall
    source: SourceUrl
    samples_hz: Annotated[float, doc("the decimation rate", "Hz")]
    t_host: Annotated[list[float | None], doc("host monotonic time", "s")]
    t_device: Annotated[list[float | None], doc("the device's sample clock", "s", null="none")]
    length_mm: Annotated[list[float | None], doc("absolute bar length", "mm", null="no reading")]
    seq: Annotated[list[int], doc("sample numbers")]
    status: Annotated[list[int], doc("status bits: 1 over range, 2 sensor fault, 128 simulated")]


class Time(TypedDict):
    """nanoseconds as {sec, nsec}; nsec in 0..999999999"""

    sec: Annotated[int, doc("whole seconds")]
    nsec: Annotated[int, doc("nanoseconds", minimum=0, maximum=999999999)]


Deltas = list[int]


class McapSamples(TypedDict):
    """ballbar.Samples: ball-bar samples in the MCAP log (/ballbar/samples), one message per flush, columns
    delta-encoded: value[0] = X_first, value[i] = value[i-1] + X_delta[i-1]. Lengths in picometres, times in
    nanoseconds (t_host: wall clock, UTC; t_device: the device's sample clock, null when it has none)."""

    source: Annotated[str, doc("the source's URL")]
    count: Annotated[int, doc("number of samples n", minimum=1)]
    preroll: NotRequired[Annotated[bool, doc("repeated at the head of a per-test file; the previous file ended with "
                                             "them")]]
    seq_first: Annotated[int, doc("sample number of the first sample")]
    seq_delta: Annotated[Deltas, doc("n-1 steps of the sample number (>1: samples lost)")]
    t_host_first: Annotated[Time, doc("host wall-clock time of the first sample")]
    t_host_delta_ns: Annotated[Deltas, doc("n-1 steps of the host time", "ns")]
    t_device_first: Annotated[Time | None, doc("device clock of the first sample", null="no device clock")]
    t_device_delta_ns: Annotated[Deltas | None, doc("n-1 steps of the device clock", "ns", null="no device clock")]
    length_first_pm: Annotated[int, doc("absolute bar length", "pm")]
    length_delta_pm: Annotated[Deltas, doc("n-1 steps of the length", "pm")]
    length_missing: NotRequired[Annotated[Deltas, doc("indices of samples without a length (NaN)")]]
    status: Annotated[Deltas, doc("n status bytes: 1 over range, 2 sensor fault, 128 simulated")]
