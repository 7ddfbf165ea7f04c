"""The generated reference (configuration keys, the command's options) equals what the code generates now."""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import pytest

from ballbar.daemon import reference

ROOT = Path(__file__).resolve().parents[1]


def _block(rel: str, name: str) -> str:
    doc = (ROOT / rel).read_text(encoding="utf-8")
    return doc[doc.index(f"<!-- BEGIN {name} -->") : doc.index(f"<!-- END {name} -->")]


def test_the_configuration_reference_is_the_shipped_defaults() -> None:
    doc = (ROOT / "daemon/README.md").read_text(encoding="utf-8")
    assert reference._splice(doc, "config", reference.config_table()) == doc, (
        "daemon/README.md's configuration table is stale: python -m ballbar.daemon.reference --write")


def test_every_default_key_is_in_the_table_with_its_value() -> None:
    """The table is complete: every key the shipped defaults set (tomllib's reading, not the generator's) has a
    row under its section with its value; and every section has a table."""
    block = _block("daemon/README.md", "config")
    defaults = tomllib.loads(reference.DEFAULTS.read_text(encoding="utf-8"))
    for section, keys in defaults.items():
        head = block.index(f"**`[{section}]`**")
        end = block.find("**`[", head + 1)
        table = block[head : end if end > 0 else len(block)]
        for key in keys:
            assert f"| `{key}` |" in table, (section, key)


def test_a_commented_key_is_optional_and_a_continued_comment_joins() -> None:
    text = ("# header\n\n[a]                 # the a section\n"
            "x = 1               # one\n"
            "                    # and more\n"
            "# explains y\n"
            "y = \"s\"\n"
            "# z = 2.5           # an option\n")
    table = reference.config_table(text)
    assert "**`[a]`**: the a section" in table
    assert "| `x` | `1` | one and more |" in table
    assert '| `y` | `"s"` | explains y |' in table
    assert "| `z` | (unset; e.g. `2.5`) | an option |" in table


def test_the_command_reference_is_the_parser() -> None:
    if sys.version_info[:2] != (3, 11):
        pytest.skip("generated with Python 3.11's argparse, whose help layout other versions change")
    doc = (ROOT / "tools/README.md").read_text(encoding="utf-8")
    assert reference._splice(doc, "cli", reference.cli_reference()) == doc, (
        "tools/README.md's command reference is stale: python -m ballbar.daemon.reference --write")


def test_check_names_a_stale_block(tmp_path: Path) -> None:
    for rel in ("daemon/README.md", "tools/README.md"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text((ROOT / rel).read_text(encoding="utf-8"), encoding="utf-8")
    doc = tmp_path / "daemon/README.md"
    doc.write_text(doc.read_text(encoding="utf-8").replace("| `machine_id` |", "| `machine` |"), encoding="utf-8")
    assert reference.stale(tmp_path) == ["daemon/README.md (config)"]
