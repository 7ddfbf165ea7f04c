"""The generated parts of the reference documentation, so that no copy can drift from what it describes.

* ``daemon/README.md``, between ``<!-- BEGIN config -->`` and ``<!-- END config -->``: every key of the shipped
  defaults (:file:`daemon/default.toml`) with its default and its comment, a table per section;
* ``tools/README.md``, between ``<!-- BEGIN cli -->`` and ``<!-- END cli -->``: the ``ballbar`` command's
  subcommands and their options, as ``--help`` prints them.

``python -m ballbar.daemon.reference --write`` rewrites both blocks in a checkout; ``--check`` exits 1 naming
each block that differs (``tests/test_reference.py`` does the same).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path

DEFAULTS = Path(__file__).with_name("default.toml")
_SECTION = re.compile(r"^(?P<off>#\s*)?\[(?P<name>[^\]]+)\]\s*(?:#\s*(?P<comment>.*))?$")
_KEY = re.compile(r"^(?P<off>#\s*)?(?P<key>[A-Za-z_][A-Za-z0-9_]*)\s*=\s*(?P<value>.+?)\s*(?:#\s*(?P<comment>.*))?$")


def config_table(text: str | None = None) -> str:
    """Markdown tables of the defaults' keys: ``key | default | what`` per section.  A key shipped commented out
    is optional and shows its example value under "default" as ``(unset; e.g. ...)``, and so does a section shipped
    commented out (``# [controller]``), which gets its own table; an indented comment line
    continues the previous key's comment, and full-line comments just above a key without one describe it."""
    text = DEFAULTS.read_text(encoding="utf-8") if text is None else text
    out: list[str] = []
    last: list[str] | None = None
    above: list[str] = []  # full-line comments just above a key: its description where it has none inline
    for raw in text.splitlines():
        line = raw.strip()
        m = _SECTION.match(line)
        if m:
            optional = " (optional: shipped commented out)" if m["off"] else ""
            comment = m["comment"] or (" ".join(above) if m["off"] else "")  # the lines above say what it is
            out += ["", f"**`[{m['name']}]`**{optional}" + (f": {comment}" if comment else ""), "",
                    "| key | default | what |", "|---|---|---|"]
            last, above = None, []
            continue
        if not out:
            continue  # the file's header
        k = _KEY.match(line)
        if k and (k["off"] is None or " " not in k["value"].split("#")[0].strip().strip('"')):
            default = f"(unset; e.g. `{k['value']}`)" if k["off"] else f"`{k['value']}`"
            what = re.sub(r"\s{2,}", " ", k["comment"] or "; ".join(above))
            last, above = [f"`{k['key']}`", default, what], []
            out.append(_row(last))
        elif line.startswith("#") and last is not None and raw.startswith(" "):
            last[2] = (last[2] + " " + line.lstrip("# ")).strip()
            out[-1] = _row(last)
        elif line.startswith("#"):
            last = None
            above.append(line.lstrip("# "))
        else:
            last, above = None, []
    return "\n".join(out).strip() + "\n"


def _row(cells: list[str]) -> str:
    """A table row, each cell's ``|`` escaped."""
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def cli_reference() -> str:
    """Each subcommand's ``--help``, 100 columns wide, in a code block under its name."""
    from .commands import build_parser

    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal; the document must not depend on it
    parser = build_parser()
    out = ["```", parser.format_help().rstrip(), "```"]
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in subs.choices.items():
        out += ["", f"**`ballbar {name}`**", "", "```", sub.format_help().rstrip(), "```"]
    return "\n".join(out) + "\n"


BLOCKS = {"config": ("daemon/README.md", config_table), "cli": ("tools/README.md", cli_reference)}


def _splice(doc: str, name: str, body: str) -> str:
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    i, j = doc.index(begin) + len(begin), doc.index(end)
    return doc[:i] + "\n" + body + doc[j:]


def _root() -> Path:
    return Path(__file__).resolve().parents[1]


def stale(root: Path | None = None) -> list[str]:
    """The documents whose generated block differs from what the code generates now."""
    root = _root() if root is None else root
    bad = []
    for name, (rel, make) in BLOCKS.items():
        doc = (root / rel).read_text(encoding="utf-8")
        if _splice(doc, name, make()) != doc:
            bad.append(f"{rel} ({name})")
    return bad


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.daemon.reference", description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", action="store_true", help="rewrite the generated blocks in this checkout")
    g.add_argument("--check", action="store_true", help="exit 1 if a generated block is stale")
    args = p.parse_args(argv)
    root = _root()
    if args.check:
        bad = stale(root)
        for b in bad:
            print(f"stale generated reference: {b}; run python -m ballbar.daemon.reference --write", file=sys.stderr)
        return 1 if bad else 0
    for name, (rel, make) in BLOCKS.items():
        path = root / rel
        path.write_text(_splice(path.read_text(encoding="utf-8"), name, make()), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
