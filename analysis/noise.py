"""Noise-type findings computed from the fit's residual (analysis/README.md, "Noise findings").

- Vibration: RMS of the residual above a cut-off in cycles per revolution
  (cpr), with the dominant frequency in Hz and cpr.  The residual of each data
  arc is a sequence uniform in time, so uniform in angle: its FFT bin ``k``
  is ``k * 360 / arc`` cpr.  That RMS includes the sensor's white noise, so a
  vibration is *significant* only where a line stands out of the spectrum's
  noise floor (its bin's power above ``ln(bins) + 10`` times the floor, a
  false alarm about once in 20 000 noise-only arcs) and that line's own RMS
  (``vibration_peak_um``: the power of the peak bin and two bins either side,
  less the floor) reaches ``VIBRATION_MIN_UM``.
- Stick-slip: small steps near an axis reversal, where that axis moves slowly.
  Within ``+-window`` of each reversal (axis speed below ``sin(window)`` of the
  feed) the high-passed residual's RMS is compared with that elsewhere:
  ``sqrt(max(0, rms_near^2 - rms_far^2))`` per axis.  It is tested against the
  noise like the masks: *significant* where the variance ratio's F-test
  (near against far, on the samples' counts) passes ``level`` and the value
  reaches ``STICK_SLIP_MIN_UM`` (noise of 0.3 um lifts the difference past
  0.1 um by chance at low rates, where few samples are near a reversal).

Each arc's residual is taken up to the longest length whose FFT is fast (its
factors 2, 3, 5, 7 and 11; the few samples after it, about 0.2 % at 10 kHz,
are left out, and the arc shortened to match): a length with a large prime
factor costs an FFT many times slower (10 kHz: 0.24 s against 0.01 s per arc).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from . import stats

STICK_SLIP_WINDOW_DEG = 5.0
STICK_SLIP_MIN_UM = 0.1
VIBRATION_MIN_UM = 0.1


LINE_THRESHOLD_EXTRA = 10.0  # the peak bin's power must exceed the floor times ln(bins) + this
LINE_HALF_WIDTH = 2  # bins either side of the peak that hold a line's leakage (rectangular window)


def _highpass(r: np.ndarray, arc_deg: float, cutoff_cpr: float) -> tuple[np.ndarray, np.ndarray, int]:
    n = r.size
    spec = np.fft.rfft(r - r.mean())
    cpr = np.arange(spec.size) * 360.0 / arc_deg
    spec[cpr < cutoff_cpr] = 0.0
    return np.fft.irfft(spec, n), np.abs(spec), int(np.searchsorted(cpr, cutoff_cpr))


def _prev_fast_len(n: int) -> int:
    """The largest length up to ``n`` whose prime factors are 2, 3, 5, 7 and 11 (``scipy.fft.prev_fast_len``'s
    rule; that module costs more to import than the rest of the analysis' start)."""
    m = n
    while m > 1:
        k = m
        for p in (2, 3, 5, 7, 11):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m -= 1
    return max(n, 1)


def _fast_length(u: np.ndarray, r: np.ndarray, arc_deg: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The arc's first samples up to the longest length with a fast FFT, and the arc they span."""
    m = _prev_fast_len(r.size)
    return u[:m], r[:m], arc_deg * m / r.size


def _line(mag: np.ndarray, lo: int, n: int) -> tuple[int, float, bool]:
    """The strongest bin above the cut-off, its line's RMS (um) and whether it stands out of the noise."""
    p = mag[lo:] ** 2
    if p.size < 8:
        return lo, 0.0, False
    floor = float(np.median(p)) / math.log(2.0)  # white noise: bin powers exponential, median = ln 2 * mean
    k = int(np.argmax(p))
    band = p[max(k - LINE_HALF_WIDTH, 0) : k + LINE_HALF_WIDTH + 1]
    rms = math.sqrt(2.0 * float(np.sum(np.maximum(band - floor, 0.0)))) / n
    return lo + k, rms, bool(p[k] > floor * (math.log(p.size) + LINE_THRESHOLD_EXTRA))


def findings(
    circles: list[tuple[np.ndarray, np.ndarray, float, float]], cutoff_cpr: float, level: float = 0.05
) -> dict[str, Any]:
    """From ``[(u_rad, residual_um, arc_deg, sample_hz), ...]`` per data arc; ``level``: the stick-slip test's."""
    hp_sq, hp_n = 0.0, 0
    best_amp, best_cpr, best_hz, best_line, best_stands = 0.0, float("nan"), float("nan"), 0.0, False
    near_sq = {"x": [0.0, 0], "y": [0.0, 0]}
    far_sq = [0.0, 0]
    for u, r, arc_deg, fs in circles:
        if r.size < 16:
            continue
        u, r, arc_deg = _fast_length(u, r, arc_deg)
        hp, mag, lo = _highpass(r, arc_deg, cutoff_cpr)
        hp_sq += float(np.sum(hp**2))
        hp_n += hp.size
        k, line_um, stands = _line(mag, lo, r.size)
        if line_um > best_line or (best_line == 0.0 and mag[k] > best_amp):
            best_amp, best_line, best_stands = float(mag[k]), line_um, stands
            best_cpr = k * 360.0 / arc_deg
            best_hz = k * fs / r.size
        w = math.sin(math.radians(STICK_SLIP_WINDOW_DEG))
        near_x = np.abs(np.sin(u)) < w
        near_y = np.abs(np.cos(u)) < w
        for axis, m in (("x", near_x), ("y", near_y)):
            near_sq[axis][0] += float(np.sum(hp[m] ** 2))
            near_sq[axis][1] += int(m.sum())
        far = ~(near_x | near_y)
        far_sq[0] += float(np.sum(hp[far] ** 2))
        far_sq[1] += int(far.sum())
    vib = math.sqrt(hp_sq / hp_n) if hp_n else None
    rms_far = math.sqrt(far_sq[0] / far_sq[1]) if far_sq[1] else 0.0
    out: dict[str, Any] = {
        "vibration_um": vib,
        "vibration_cutoff_cpr": cutoff_cpr,
        "vibration_peak_cpr": best_cpr if vib is not None and math.isfinite(best_cpr) else None,
        "vibration_peak_hz": best_hz if vib is not None and math.isfinite(best_hz) else None,
        "vibration_peak_um": best_line if vib is not None else None,
        "vibration_significant": bool(vib is not None and best_stands and best_line >= VIBRATION_MIN_UM),
    }
    for axis in ("x", "y"):
        s, n = near_sq[axis]
        if n >= 4:
            val = math.sqrt(max(0.0, s / n - rms_far**2))
            out[f"stick_slip_{axis}_um"] = val
            ratio = (s / n) / rms_far**2 if rms_far > 0 else math.inf
            p = float(stats.f.sf(ratio, n - 1, max(far_sq[1] - 1, 1))) if math.isfinite(ratio) else 0.0
            out[f"stick_slip_{axis}_p_value"] = p
            out[f"stick_slip_{axis}_significant"] = bool(val >= STICK_SLIP_MIN_UM and p < level)
        else:
            out[f"stick_slip_{axis}_um"] = None
            out[f"stick_slip_{axis}_p_value"] = None
            out[f"stick_slip_{axis}_significant"] = False
    out["method"] = (
        f"residual above {cutoff_cpr:g} cycles/rev; vibration significant where its strongest line stands "
        f"out of the noise floor and reaches {VIBRATION_MIN_UM:g} um rms (white noise alone is not "
        f"vibration); stick-slip: within +-{STICK_SLIP_WINDOW_DEG:g} deg of reversals against elsewhere, "
        f"significant where the variance ratio's F-test passes {level:g} and it reaches {STICK_SLIP_MIN_UM:g} um"
    )
    return out
