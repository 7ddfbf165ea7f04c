"""The one rounding rule (analysis/numbers.py): a value to what its standard error and its unit allow."""

from __future__ import annotations

import pytest

from ballbar.analysis.numbers import decimals, limit_texts, measured


@pytest.mark.parametrize(
    ("value", "stderr", "unit", "text"),
    [
        # the figures: more digits than they know
        (8.1589, 0.0008, "ms", "8.16 ± 0.01 ms"),  # 0.01 ms at the finest; the error shown as that step
        (141.29, 0.57, "um", "141.3 ± 0.6 µm"),  # first digit 5: one significant digit
        (12.0048, 0.0035, "um", "12.0 ± 0.1 µm"),
        (-0.0, 1.0, "um", "0.0 ± 1.0 µm"),  # no negative zero
        (-0.04, 0.3, "um", "0.0 ± 0.3 µm"),  # rounds to zero: no "-0.0"
        (24.99, 0.3, "urad", "25.0 ± 0.3 µrad"),
        (3.0301, 0.012, "ms", "3.03 ± 0.01 ms"),  # two digits of 0.012 would be finer than 0.01 ms
        (3.0301, 0.12, "ms", "3.03 ± 0.12 ms"),  # first digit 1: two significant digits
        (3.0301, 0.34, "ms", "3.0 ± 0.3 ms"),
        # large values and large errors: the place of the error, tens or hundreds
        (143.27, 37.0, "um", "140 ± 40 µm"),
        (12345.678, 250.0, "um", "12350 ± 250 µm"),
        (98765.4, 0.05, "um", "98765.4 ± 0.1 µm"),
        # tiny uncertainties never show as zero
        (0.1234, 1e-9, "ms", "0.12 ± 0.01 ms"),
        # no standard error: the unit's resolution; a unit without one, three significant digits
        (53.749, None, "um", "53.7 µm"),
        (-2.345, None, "ppm", "-2.3 ppm"),
        (0.000123, None, "", "0.000123"),
        (1770.4, None, "", "1770"),
        # a rate per day takes its quantity's resolution
        (1770.4, 120.0, "um/day", "1770 ± 120 µm/day"),
        (None, 0.1, "um", "–"),
        (float("nan"), 0.1, "um", "–"),
    ],
)
def test_the_rule_by_table(value: float | None, stderr: float | None, unit: str, text: str) -> None:
    assert measured(value, stderr, unit) == text


def test_signs_the_shown_uncertainty_and_ascii() -> None:
    assert measured(-0.04, 0.3, "um", signed=True) == "0.0 ± 0.3 µm"  # zero has no sign
    assert measured(4.02, 0.03, "um", signed=True) == "+4.0 ± 0.1 µm"
    # k standard errors shown at the place of one standard error: the same value reads the same everywhere
    assert measured(3.0301, 0.0014, "ms", shown=0.0028) == "3.03 ± 0.01 ms"
    assert measured(141.29, 0.57, "um", shown=1.14) == "141.3 ± 1.1 µm"
    assert measured(141.29, 0.57, "um", shown=0) == "141.3 µm"
    assert measured(143.27, 0.56, "um", ascii=True) == "143.3 +- 0.6 um"
    assert measured(8.1589, 0.0008, "ms", with_unit=False) == "8.16 ± 0.01"


def test_the_limit_and_the_margin_at_the_values_place() -> None:
    assert limit_texts(8.1589, 0.0008, 2.0, -6.1589, "ms") == ("2.00", "6.16")
    assert limit_texts(141.29, 0.57, 10.0, -131.29, "um") == ("10.0", "131.3")
    # never coarser than whole units, though the value is shown to tens
    assert limit_texts(143.27, 37.0, 25.0, -118.27, "um") == ("25", "118")
    assert limit_texts(1.0, 0.1, None, None, "um") == ("–", "–")


def test_decimals_follow_the_unit_when_there_is_no_error() -> None:
    assert decimals(1.0, None, "um") == 1 and decimals(1.0, None, "ms") == 2 and decimals(1.0, None, "urad") == 1
    assert decimals(1.0, None, "µm") == 1  # the displayed unit is the same unit
    assert decimals(1.0, 0.0, "ms") == 2  # a zero error is no error
