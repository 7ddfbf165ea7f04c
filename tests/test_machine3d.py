"""The 3D simulated machine: each plane's test sees its two axes' errors and its own squareness."""

from __future__ import annotations

import pytest

from ballbar.analysis.errors import PlanError
from ballbar.tools.machine3d import Machine3D

M = Machine3D.from_settings(dict(
    backlash_x_um=1.0, backlash_y_um=2.0, backlash_z_um=3.0, kv_x_per_s=31.0, kv_y_per_s=32.0, kv_z_per_s=33.0,
    scale_x_ppm=4.0, scale_y_ppm=5.0, scale_z_ppm=6.0, centre_x_um=7.0, centre_y_um=8.0, centre_z_um=9.0,
    squareness_xy_urad=10.0, squareness_yz_urad=11.0, squareness_zx_urad=12.0, noise_um=0.2, feed_override=0.9))


@pytest.mark.parametrize("plane, first, second, squareness", [
    ("XY", "x", "y", 10.0), ("YZ", "y", "z", 11.0), ("ZX", "z", "x", 12.0)])
def test_each_plane_sees_its_first_and_second_axis(plane: str, first: str, second: str, squareness: float) -> None:
    m = M.project(plane)
    value = {"x": 1.0, "y": 2.0, "z": 3.0}
    assert (m.backlash_x_um, m.backlash_y_um) == (value[first], value[second])
    assert (m.kv_x_per_s, m.kv_y_per_s) == (30.0 + value[first], 30.0 + value[second])
    assert (m.scale_x_ppm, m.scale_y_ppm) == (3.0 + value[first], 3.0 + value[second])
    assert (m.centre_x_um, m.centre_y_um) == (6.0 + value[first], 6.0 + value[second])
    assert m.squareness_urad == squareness and m.noise_um == 0.2 and m.feed_override == 0.9
    truth = M.truth(plane)
    assert truth["scale_mismatch_ppm"] == pytest.approx(value[first] - value[second])
    assert truth["servo_mismatch_ms"] == pytest.approx(1000 * (1 / (30 + value[first]) - 1 / (30 + value[second])))


def test_keys_that_belong_to_one_plane_are_refused() -> None:
    with pytest.raises(PlanError, match="unknown 3D machine key 'lateral_play_x_um'"):
        Machine3D.from_settings({"lateral_play_x_um": 1.0})
    with pytest.raises(PlanError, match="unknown 3D machine key 'squareness_urad'"):
        Machine3D.from_settings({"squareness_urad": 1.0})
    with pytest.raises(PlanError, match="must be > 0"):
        Machine3D.from_settings({"kv_z_per_s": -1.0})
    assert Machine3D.from_settings(M.to_dict()) == M
    assert M.with_(backlash_z_um=5.0, noise_um=0.3).project("ZX").backlash_x_um == 5.0
