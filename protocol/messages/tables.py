"""The payload tables of ``protocol/messages/README.md``, generated from the message types.

One table per ``TypedDict`` (each once, in the order the documents reach
them): field, type, unit, description; an optional field is marked ``?``.
"""

from collections.abc import Iterator
from typing import Any, Literal, get_args, get_origin, is_typeddict

from .channels import MCAP_CHANNELS
from .documents import DOCUMENTS
from .fields import Doc, description_of, fields_of, is_union, unwrap

HEADER = """\
# Messages

Every message ballbar publishes or records, field by field. Generated from the
types in `protocol/messages/*.py` (`python -m ballbar.daemon.schemas --doc
protocol/messages/README.md`; `tests/test_schemas.py` checks this file is
current): edit those, not this. The JSON Schemas in `ballbar/schema/` come from
the same types.

Every payload is one JSON object. Numbers the daemon cannot give as finite go
as `null`; a field marked `?` may be absent. `schema_version` changes, and with
it the schemas' `$id` (`urn:ballbar:schema:<version>:<name>`), when a payload
changes in a way that can break a reader (a field removed, renamed, retyped or
given another meaning); a new optional field does not change it.

In the code, a producer annotates what it builds with the message's type and
takes the envelope from `stamp()` (`msg: Status = {**stamp(machine_id), "kind":
"status", ...}`; an analysis output goes out through `publish.published()`), so
that mypy checks every field; a consumer narrows on `kind` (and `event`) and
reads the typed fields. The daemon imports the types under `TYPE_CHECKING`
only: at run time it handles plain dicts. `tests/test_schemas.py` runs the
daemon's producers and validates what they make against these schemas.
"""

WHERE = {
    "result": "`ballbar/<m>/result/circle`, `.../result/test`, `.../result/set`, `last/*`, `history/*`; MCAP "
              "`/ballbar/results`",
    "analysis": "`ballbar analyze --json`",
    "event": "`ballbar/<m>/event`, `last/event`, `history/event`",
    "status": "`ballbar/<m>/status`, `last/status`; MCAP `/ballbar/status`",
    "config": "`ballbar/<m>/config`, `last/config`; MCAP `/ballbar/config`",
    "samples": "`ballbar/<m>/samples`",
    "history": "the reply of `ballbar/<m>/history/<topic>`",
    "alert": "`ballbar/<m>/alert`, `last/alert`, `history/alert`; MCAP `/ballbar/other`",
    "error": "an error reply of `ballbar/<m>/history/<topic>`",
    "monitor-history": "`STATE_DIR/monitor/<m>-history.jsonl`, a line per test",
    "mcap-samples": "MCAP `/ballbar/samples`",
    "controller": "MCAP `/ballbar/controller` ([controller])",
    "set": "`ballbar/<m>/result/set`, `last/set`, `history/set`; MCAP `/ballbar/results` (also in `result`)",
    "mcap-event": "MCAP `/ballbar/events`: the events without `kind` (a source's without the envelope), and `LogGap`",
    "mcap-other": "MCAP `/ballbar/other`: any other kind, as it came",
}


def _roots(tp: Any) -> list[Any]:
    return [a for a in get_args(tp)] if is_union(tp) else [tp]


def _walk(tp: Any, seen: dict[Any, None]) -> None:
    """The ``TypedDict``\\ s under ``tp``, each once, in order."""
    tp = unwrap(tp)[0]
    if is_typeddict(tp):
        if tp in seen:
            return
        seen[tp] = None
        for ftp, _d, _r in fields_of(tp).values():
            _walk(ftp, seen)
    elif get_origin(tp) is not Literal:
        for a in get_args(tp):
            _walk(a, seen)


def _link(td: type) -> str:
    return f"[{td.__name__}](#{td.__name__.lower()})"


def _type(tp: Any) -> str:
    tp = unwrap(tp)[0]
    if is_typeddict(tp):
        return _link(tp)
    names = {float: "number", int: "integer", str: "string", bool: "boolean", type(None): "null", object: "any"}
    if tp in names:
        return names[tp]
    origin, args = get_origin(tp), get_args(tp)
    if origin is Literal:
        return " or ".join(f"`{a!r}`".replace("'", '"') if isinstance(a, str) else f"`{a!r}`" for a in args)
    if is_union(tp):
        return " or ".join(_type(a) for a in args)
    if origin is list:
        return f"list of {_type(args[0])}"
    if origin is dict:
        return f"map of {_type(args[1])}"
    return str(tp)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _table(td: type) -> Iterator[str]:
    yield f"### {td.__name__}"
    yield ""
    if description_of(td):
        yield _cell(description_of(td))
        yield ""
    yield "| field | type | unit | description |"
    yield "|---|---|---|---|"
    for name, (tp, d, required) in fields_of(td).items():
        bare = unwrap(tp)[0]
        if d is None:
            d = Doc(description_of(bare)) if is_typeddict(bare) else Doc("")
        text = d.text + (f" (null: {d.null})" if d.null else "")
        yield (f"| `{name}`{'' if required else '?'} | {_cell(_type(tp))} | {_cell(d.unit or '')} | "
               f"{_cell(text)} |")
    yield ""


def markdown() -> str:
    """The whole of ``protocol/messages/README.md``."""
    lines = [HEADER, "## Documents", "",
             "| schema | message | where |", "|---|---|---|"]
    seen: dict[Any, None] = {}
    for name, d in DOCUMENTS.items():
        roots = _roots(d.root)
        lines.append(f"| `{name}` | {', '.join(_link(r) for r in roots)} | {WHERE[name]} |")
        for r in roots:
            _walk(r, seen)
    lines.append(f"| `mcap-event` | the events above | {WHERE['mcap-event']} |")
    lines.append(f"| `mcap-other` | any | {WHERE['mcap-other']} |")
    from .events import LogGap

    _walk(LogGap, seen)
    lines += ["", "MCAP channels (each JSON, with its schema registered under the name given):", "",
              "| topic | schema name | schema |", "|---|---|---|"]
    lines += [f"| `{topic}` | `{sname}` | `{doc}` |" for topic, (sname, doc, _desc) in MCAP_CHANNELS.items()]
    lines += ["", "## Types", ""]
    names = [td.__name__ for td in seen]
    assert len(names) == len(set(names)), "two message types share a name"
    for td in seen:
        lines += list(_table(td))
    return "\n".join(lines).rstrip("\n") + "\n"
