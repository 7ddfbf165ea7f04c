"""The position loops' mean lag for the physical servo model (analysis/README.md, "Physical servo model").

Where it comes from, in this order: the configured gains; the settling that
ends the feed-in and feed-out; none where the sample rate would have shown a
loop slower than ``FAST_LOOP_S`` and none was seen (the loops are fast);
otherwise a default gain, which the test's fit then refines with the timing
where the data arcs tell it (:mod:`.testfit`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .detect import StepEvent
from .plan import AnalysisOptions, MachineConfig, TestPlan, plane_keys
from .program import arc_start_deg

DEFAULT_KV_PER_S = 30.0
TAIL_SAMPLES = 1.8  # samples per loop time constant the settling fit needs (6 within ~3.4 tau)
FAST_LOOP_S = 0.02  # a loop lag the settling fit must be able to see before "none seen" means "fast"


class Lag(NamedTuple):
    """The position loops' mean lag for the physical servo model (:func:`loop_lag`).

    ``tau`` (s): ``(1/KX + 1/KY)/2``, None for no servo correction; ``cos2``:
    where it was measured along the feed-in/out's radial direction, that
    direction's mean ``cos 2u`` (the lag there is ``tau_bar + (m/2) cos 2u``).
    ``origin``: ``configured``, ``feed_in``, ``fast`` (no settling seen where
    it would have been), ``linear`` (chosen), ``assumed`` (a default gain) or
    ``fitted`` (to the data arcs, :func:`_profile_lag`); ``source`` says it in words.
    """

    tau: float | None
    cos2: float | None
    source: str
    origin: str


def loop_lag(
    plan: TestPlan, machine: MachineConfig, options: AnalysisOptions, fi: StepEvent, fo: StepEvent, sample_hz: float
) -> Lag:
    """Position-loop lag for the physical servo model.

    From configured gains, or measured on the feed-in/out's approach to the
    circle.  Where no settling was seen although the rate would have shown a
    loop slower than ``FAST_LOOP_S``, the loops are fast: no correction.  Else
    the lag is assumed (a common default gain), and the result says so.
    """
    if options.servo_model == "linear":
        return Lag(None, None, "linear model chosen", "linear")
    if machine.kv_x_per_s and machine.kv_y_per_s:
        tau = 0.5 * (1.0 / machine.kv_x_per_s + 1.0 / machine.kv_y_per_s)
        return Lag(tau, None, f"configured gains {plane_keys('kv', plan.plane)}", "configured")
    u_in = math.radians(arc_start_deg(plan, plan.direction_list[0]))
    resolvable_s = TAIL_SAMPLES / sample_hz if sample_hz > 0 else math.inf
    u_last = math.radians(arc_start_deg(plan, plan.direction_list[-1]))
    u_out = u_last + plan.direction_list[-1] * math.radians(plan.arc_deg)
    found = [(e.tau_s, math.cos(2 * u)) for e, u in ((fi, u_in), (fo, u_out)) if math.isfinite(e.tau_s)]
    if found:
        return Lag(
            float(np.mean([f[0] for f in found])),
            float(np.mean([f[1] for f in found])),
            "approach of the feed-in/feed-out to the circle (first-order loop fit)",
            "feed_in",
        )
    if resolvable_s <= FAST_LOOP_S:
        # A loop as slow as machines' usually are would have shown its settling at this rate.
        return Lag(None, None, (
            f"no loop settling after the feed-in: the position loops are faster than {resolvable_s * 1000:.0f} ms "
            "at this sample rate (no servo dynamics to correct)"
        ), "fast")
    return Lag(
        1.0 / DEFAULT_KV_PER_S,
        None,
        f"assumed {DEFAULT_KV_PER_S:g}/s (a common default position gain): the feed-in's settling is not "
        f"resolved at this sample rate and no {plane_keys('kv', plan.plane)} is configured",
        "assumed",
    )
