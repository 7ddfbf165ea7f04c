"""Whether the model fits the test at all: a result is right within its uncertainty or says why it cannot be.

The fit's uncertainties hold where the model describes the machine and the
test ran as planned.  Where it does not (the feed override changed between
the arcs, a ball seated anew and stepped the bar's length, an error this
library has no pattern for), the least-squares values are still numbers, and
with tens of thousands of samples every one of them looks significant.  So
the residual is checked against what the test's own data say about the noise:

- **noise**: the sensor's noise from the data alone, the scatter of second
  differences of consecutive samples (robust: their median absolute value),
  which no smooth misfit moves, and at least the quantisation noise
  ``q / sqrt(12)`` of the step ``q`` the readings sit on (:func:`reading_step`):
  a gauge whose own noise is below its resolution repeats its reading, and
  second differences are then mostly 0;
- **misfit**: the fit's residual rms far above that noise (more than
  ``MISFIT_RATIO`` times it and by more than ``MISFIT_MIN_UM``): the model
  leaves out most of what the bar saw;
- **feed**: the last arc ran at another feed than the first (by more than
  ``FEED_MIN`` and ``FEED_SIGMAS`` standard errors: a score test of the
  one timing the schedule does not have, the feed override changed between
  the arcs);
- **level change** (judged only where the misfit passed): the residual steps at one sample, by more than
  ``STEP_SIGMAS`` of its standard error over the windows either side (each
  ``STEP_WINDOW_DEG`` of travel) and by more than ``STEP_MIN_UM``, away from
  the reversals and changeovers the model describes.

A test that fails a check keeps its values, but ``fit.valid`` is false with
``fit.invalid_reasons``, and no parameter is significant (each says why):
it is a finding about the test, not the machine.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .fit import FitResult

MISFIT_RATIO = 3.0  # residual rms against the sensor noise beyond which the model does not describe the test
MISFIT_MIN_UM = 0.25  # ... and by at least this much (um): tiny absolute misfits are the model's fine detail
STEP_WINDOW_DEG = 2.0  # each side of a candidate level change (deg of travel) ...
STEP_WINDOW_SAMPLES = 16  # ... and at least this many samples
STEP_SIGMAS = 12.0  # a level change this many standard errors of the windows' difference
STEP_MIN_UM = 0.2  # ... and at least this large (um)
FEED_SIGMAS = 8.0  # the last arc's feed differs from the first's by this many standard errors ...
FEED_MIN = 0.002  # ... and by more than this share: the control holds a feed far better between two arcs
FEATURE_DEG = 3.0  # level changes whose windows come this close to a 45 deg point (reversals, changeovers) are
# not judged: what the model leaves there is its own fine detail


STEP_SHARE = 0.99  # the share of the values that must sit on a step for the readings to be quantised by it
STEP_TOLERANCE = 0.05  # ... each within this share of the step (a CSV's decimals parse to the nearest double)
STEP_QUANTILE = 0.01  # the candidate step: this quantile of the nonzero differences of consecutive values


def reading_step(y: np.ndarray) -> float:
    """The step (the values' unit) that the readings sit on, 0 where they sit on none.

    A digital gauge reports multiples of its resolution: the differences of
    consecutive readings are then multiples of it too, and the smallest common
    one (a low quantile of the nonzero differences, so that a few glitches do
    not set it) is the step.  It is trusted only where nearly all values
    (``STEP_SHARE``) lie on one grid of that step, whatever its origin (the
    values' circular mean phase): where the gauge's noise is many steps, the
    smallest differences are a fraction of a step, and the grid does not hold.
    """
    y = y[np.isfinite(y)]
    if y.size < 16:
        return 0.0
    d = np.abs(np.diff(y))
    d = d[d > 1e-12 * max(float(np.max(np.abs(y))), 1e-300)]  # a difference of round-off is no step
    if d.size < 8:
        return 0.0
    q = float(np.quantile(d, STEP_QUANTILE))
    if not q > 0:
        return 0.0
    phase = 2.0 * math.pi * np.mod(y / q, 1.0)
    origin = math.atan2(float(np.mean(np.sin(phase))), float(np.mean(np.cos(phase)))) / (2.0 * math.pi)
    frac = y / q - origin
    on = np.abs(frac - np.round(frac)) < STEP_TOLERANCE
    return q if float(np.mean(on)) >= STEP_SHARE else 0.0


def quantisation_bias(step: float, noise: float) -> float:
    """The rms over values of the mean quantisation error at each value (um): the part of a quantised
    reading's error that follows the signal, not white.

    ``Q(s + n) - s`` is a sawtooth in ``s`` of period ``step`` (rms ``step / sqrt(12)``); the gauge's own
    noise ``n`` (rms ``noise``) damps its ``k``-th harmonic by ``exp(-2 pi^2 k^2 noise^2 / step^2)``.  Where
    the signal stands near an extreme for long (a slow part of the profile), that mean error stands with it
    and reads as a pattern; a noise of half a step leaves 0.6 % of it.
    """
    if not step > 0:
        return 0.0
    k = np.arange(1.0, 65.0)
    damp = np.exp(-4.0 * math.pi**2 * k**2 * (noise / step) ** 2)
    return float(step / (math.pi * math.sqrt(2.0)) * math.sqrt(float(np.sum(damp / k**2))))


def sensor_noise(y: np.ndarray, step: float = 0.0) -> float:
    """The white noise (um rms) of consecutive samples: ``median |second difference| / 0.6745 / sqrt(6)``, and
    at least ``step / sqrt(12)``, the quantisation noise of readings on that step (um)."""
    if y.size < 8:
        return math.nan
    d2 = y[2:] - 2.0 * y[1:-1] + y[:-2]
    return max(float(np.median(np.abs(d2)) / 0.6745 / math.sqrt(6.0)), step / math.sqrt(12.0))


def level_change(u: np.ndarray, r: np.ndarray, d: int, sample_deg: float, sigma: float) -> tuple[float, float]:
    """The residual's largest step between two windows of ``STEP_WINDOW_DEG``, away from the 45 deg points:
    its angle (deg) and size (um), in standard errors of the windows' difference ``(step, z)``... returned as
    ``(angle_deg, step_um)`` with the step's z-score compared by the caller."""
    w = _window(sample_deg)
    if r.size < 4 * w:
        return math.nan, 0.0
    c = np.concatenate([[0.0], np.cumsum(r)])
    n = r.size
    mid = c[w : n - w + 1]  # the sums before each candidate k = w .. n - w (slices: no copies)
    diff = (c[2 * w : n + 1] - mid) / w - (mid - c[: n - 2 * w + 1]) / w
    deg = np.degrees(u[w : n - w + 1])
    past = np.mod(deg, 45.0)
    # both windows clear of every 45 deg point (reversals, changeovers), by FEATURE_DEG
    ok = np.minimum(past, 45.0 - past) > FEATURE_DEG + w * sample_deg
    if not ok.any():
        return math.nan, 0.0
    i = int(np.argmax(np.where(ok, np.abs(diff), -1.0)))
    return float(deg[i]), float(diff[i])


def _window(sample_deg: float) -> int:
    """Samples either side of a candidate level change."""
    return max(round(STEP_WINDOW_DEG / max(sample_deg, 1e-9)), STEP_WINDOW_SAMPLES)


def check_model(
    res: dict[str, Any], per_dir: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]], sample_hz: float,
    fit: FitResult, feed: tuple[float, float] = (math.nan, 0.0), step_um: float = 0.0,
) -> None:
    """Mark ``res`` invalid where the model does not describe the test (see the module docstring).  ``feed``:
    how much faster the last arc ran than the first, as a share, and that in its standard errors; ``step_um``:
    the step the readings sit on (:func:`reading_step`, 0: none)."""
    reasons: list[str] = []
    noises, sq, n = [], 0.0, 0
    for _, y, r in per_dir.values():
        s = sensor_noise(y, step_um)
        if math.isfinite(s):
            noises.append((s, y.size))
        sq += float(r @ r)
        n += r.size
    noise = math.sqrt(sum(s * s * k for s, k in noises) / sum(k for _, k in noises)) if noises else math.nan
    rms = math.sqrt(sq / n) if n else math.nan
    checks: dict[str, Any] = {"sensor_noise_um": noise, "reading_step_um": step_um or None, "residual_rms_um": rms}
    if math.isfinite(noise) and math.isfinite(rms) and rms > MISFIT_RATIO * noise and rms - noise > MISFIT_MIN_UM:
        reasons.append(
            f"the residual, {rms:.3g} um rms, is {rms / max(noise, 1e-9):.3g} times the sensor's noise seen in the "
            f"samples themselves ({noise:.2g} um): the model does not describe this test (was it run as planned, at "
            "one feed? an error the pattern library lacks?)"
        )
    rho, z_feed = feed
    checks["last_arc_feed_ratio"] = 1.0 + rho if math.isfinite(rho) else None
    checks["last_arc_feed_z"] = z_feed if math.isfinite(rho) else None
    misfit = bool(reasons)
    if math.isfinite(rho) and z_feed > FEED_SIGMAS and abs(rho) > FEED_MIN and not misfit:
        reasons.append(
            f"the last arc ran at {100.0 * (1.0 + rho):.2f} % of the first one's feed ({z_feed:.3g} standard "
            "errors): the program was not run as planned (the feed override changed between the arcs?)"
        )
    steps = []
    for d, (u, _, r) in per_dir.items():
        if r.size < 16 or not math.isfinite(noise):
            continue
        sample_deg = abs(float(np.degrees(u[-1] - u[0]))) / max(u.size - 1, 1)
        at, step = level_change(u, r, d, sample_deg, noise)
        if not math.isfinite(at):
            continue  # too few samples clear of the 45 deg points to judge a level change
        se = noise * math.sqrt(2.0 / _window(sample_deg))
        z = abs(step) / se if se > 0 else 0.0
        steps.append({"direction": "ccw" if d > 0 else "cw", "at_deg": at, "step_um": step, "z": z})
        if z > STEP_SIGMAS and abs(step) > STEP_MIN_UM and not misfit:
            reasons.append(
                f"the {'CCW' if d > 0 else 'CW'} residual changes its level by {step:+.3g} um at {at:.1f} deg "
                f"({z:.3g} standard errors), away from any reversal: the bar's length stepped during the test (a "
                "ball seating anew, a loose pivot or cup)"
            )
    checks["level_change"] = steps
    res["fit"]["checks"] = checks
    res["fit"]["valid"] = not reasons
    res["fit"]["invalid_reasons"] = reasons
    if not reasons:
        return
    why = "the test is marked invalid: " + "; ".join(reasons)
    for p in res["parameters"].values():
        if p.get("significant"):
            p["significant"] = False
        if p.get("value") is not None:
            p["significance_reason"] = why
    for r_ in res["ranking"]:
        r_["significant"] = False
        r_["significance_reason"] = why
    res["advice"] = []
    warnings = res.setdefault("warnings", [])
    warnings.append(why)
    _ = fit
