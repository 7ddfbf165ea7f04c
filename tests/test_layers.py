"""The layers hold: tools over daemon over analysis over protocol, and the product never imports the benchmarks.

import-linter reads the contracts from ``pyproject.toml`` and the code under the package names it is installed
as (``.typecheck/ballbar``); CI runs the same command.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_no_package_imports_one_above_it() -> None:
    lint = Path(sys.executable).with_name("lint-imports")
    out = subprocess.run([str(lint), str(ROOT / "pyproject.toml")], cwd=ROOT / ".typecheck", capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "2 kept, 0 broken" in out.stdout, out.stdout[-2000:]
