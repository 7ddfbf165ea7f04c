"""Plans as a library, and which plan a test ran, from the recording alone.

A machine's check is a set of tests: XY over 360 deg, the vertical planes ZX
and YZ over 220 deg, often at two feeds.  The daemon knows them as a library
of named plans (``[plans.<name>]``; a single ``[plan]`` is a library of one,
named ``default``), and tells which plan each test ran without an operator.

The result fields a set stands on (the contract with the set result)
--------------------------------------------------------------------
Every circle and test result names its plan beside the plan's keys:

``result["plan"]["name"]``
    the plan's name in the library (``"default"`` for a single ``[plan]``).
``result["plan"]["plane"]``
    ``XY``, ``YZ`` or ``ZX``, as before.
``result["plan"]["axes"]``
    the machine axes of the plane's first and second axis, ``["X", "Y"]``,
    ``["Y", "Z"]`` or ``["Z", "X"]``.  Every ``_x`` field of the result
    (``backlash_x_um``, ``reversal_spike_x_*``, ``lateral_play_x_um``, ...) is
    about ``axes[0]``, every ``_y`` field about ``axes[1]``;
    ``servo_mismatch_ms`` is ``lag(axes[0]) - lag(axes[1])``,
    ``scale_mismatch_ppm`` is ``e(axes[0]) - e(axes[1])`` and
    ``squareness_urad`` is ``S`` of ``D(axes[0]) = S * axes[1]`` (urad).  So
    the three planes' squareness values are, on one convention,
    ``S_XY: DX = S Y``, ``S_YZ: DY = S Z``, ``S_ZX: DZ = S X``
    (analysis/README.md, "Three planes, one machine").
``result["recognition"]``
    how the plan was known: ``method`` (``only``: a library of one;
    ``signature``: the code its program carries before the feed-in;
    ``timing``: the only plan whose timing fits the test; ``chosen``: named
    by an operator or service), ``signature`` (the code read, or null),
    ``feed_ratio`` (the feed-in to feed-out span's feed over the plan's, or
    null), ``candidates`` (the plans that fitted the timing) and ``message``.

A test that matches no plan, or more than one, gets no result: an event
``test_unrecognised`` (``reason``: ``no_match`` or ``ambiguous``,
``candidates``, ``message``) says why.  The monitor's history
(``<state_dir>/monitor/<m>-history.jsonl``) keeps each test's
``conditions.plan``; trends, limits and alerts are per plan.

The configuration (``Config.plans``, ``Config.sets``; recorded as
``config["plans"]`` and ``config["sets"]``): ``plans`` maps each name to
its plan's keys plus ``signature`` (the code, 0..124) and ``limits`` (its
own ``[limits]`` over the global one, or absent); ``sets`` maps each name to
``plans`` (names) and ``window_minutes`` (the time within which a set's tests
must all have run).
"""

from __future__ import annotations
