"""What the wheel holds: the product, and not the benchmarks and surveys (``tools/bench/``)."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_wheel_ships_the_product_and_no_benchmarks(tmp_path: Path) -> None:
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q", "-w", str(tmp_path)],
                   check=True, capture_output=True)
    (wheel,) = tmp_path.glob("ballbar-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert not [n for n in names if n.startswith("ballbar/tools/bench")], "benchmarks in the wheel"
    bench = {p.name for p in (ROOT / "tools" / "bench").glob("*.py")} - {"__init__.py"}
    assert bench and not {f"ballbar/tools/{b}" for b in bench} & names
    for needed in ("ballbar/daemon/cli.py", "ballbar/daemon/default.toml", "ballbar/tools/simdevice.py",
                   "ballbar/tools/simulator.py", "ballbar/py.typed", "ballbar/schema/result.schema.json"):
        assert needed in names, needed
