"""The shipped JSON Schemas and the payload reference, written from the message types.

The schemas (draft 2020-12) are the contract with plant services; they are
generated from the ``TypedDict``\\ s of :mod:`ballbar.protocol.messages` and
shipped in the package as ``ballbar/schema/<name>.schema.json``
(``importlib.resources.files("ballbar") / "schema"``); the MCAP recordings
register the same documents as their channels' schemas.  ``python -m
ballbar.daemon.schemas --write DIR`` writes them, ``--doc FILE`` the payload
tables (``protocol/messages/README.md``), ``NAME`` prints one.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from ballbar.protocol.messages.documents import NAMES, schema, schema_text
from ballbar.protocol.messages.fields import fields_of
from ballbar.protocol.messages.results import Parameters
from ballbar.protocol.messages.tables import markdown

#: The pattern library's result fields: name -> (unit, description), from :class:`Parameters`.
PARAMETERS: dict[str, tuple[str, str]] = {
    name: (d.unit or "", d.text) for name, (_tp, d, _r) in fields_of(Parameters).items() if d is not None
}


def shipped_dir() -> Path:
    """Where the package ships the files: ``ballbar/schema/`` in the installed package."""
    from importlib.resources import files

    return Path(str(files("ballbar") / "schema"))


def write(directory: str | Path) -> list[Path]:
    out = []
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    for name in NAMES:
        p = d / f"{name}.schema.json"
        p.write_text(schema_text(name), encoding="utf-8")
        out.append(p)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.daemon.schemas", description=__doc__.split("\n\n")[0])
    p.add_argument("--write", metavar="DIR", help="write every schema as DIR/<name>.schema.json")
    p.add_argument("--doc", metavar="FILE", help="write the payload tables (protocol/messages/README.md)")
    p.add_argument("name", nargs="?", choices=NAMES, help="print this schema")
    args = p.parse_args(argv)
    if args.write:
        for path in write(args.write):
            print(path)
    if args.doc:
        Path(args.doc).write_text(markdown(), encoding="utf-8")
        print(args.doc)
    if args.name:
        sys.stdout.write(schema_text(args.name))
    elif not (args.write or args.doc):
        print("\n".join(NAMES))
    return 0


__all__ = ["NAMES", "PARAMETERS", "main", "schema", "schema_text", "shipped_dir", "write"]

if __name__ == "__main__":
    sys.exit(main())
