"""JSON Schema (draft 2020-12) from the message ``TypedDict``\\ s.

A small generator of our own rather than pydantic's ``TypeAdapter``: it needs
no dependency at run time (the daemon registers these schemas in every MCAP
file), works with ``typing.TypedDict`` on Python 3.11, and writes the shapes
the schemas have always had: every ``TypedDict`` a closed object
(``additionalProperties: false``), a nullable scalar ``"type": [T, "null"]``,
no titles, the nested objects inline unless a document names them in its
``$defs``.

Mapping: ``float`` number, ``int`` integer, ``str`` string, ``bool`` boolean,
``None`` null; ``Literal[v]`` ``const``, ``Literal[a, b]`` ``enum``;
``list[T]`` array; ``dict[str, T]`` an object of open keys (``dict[str,
object]``: any object); ``A | B`` ``oneOf``; ``T | None`` nullable; a
``TypedDict`` a closed object whose ``required`` are its required keys and
whose description is its docstring, or the field's :class:`~.fields.Doc`.
"""

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, get_args, get_origin, is_typeddict

from .fields import Doc, description_of, fields_of, is_union, unwrap

DRAFT = "https://json-schema.org/draft/2020-12/schema"

Schema = dict[str, Any]

_SCALARS: dict[Any, str] = {float: "number", int: "integer", str: "string", bool: "boolean", type(None): "null"}
_FIRST = ("type", "const", "$ref")  # keys written before the description, the rest after it


def _ordered(node: Schema, description: str | None) -> Schema:
    out = {k: node[k] for k in _FIRST if k in node}
    if description:
        out["description"] = description
    out.update((k, v) for k, v in node.items() if k not in out and k != "description")
    if "description" in node and not description:
        out["description"] = node["description"]
    return out


def _json_type(values: tuple[Any, ...]) -> str | None:
    names = {_SCALARS.get(type(v)) for v in values}
    return names.pop() if len(names) == 1 else None


def _nullable(node: Schema) -> Schema:
    """``node`` or null."""
    t = node.get("type")
    if "$ref" not in node and "oneOf" not in node and t is not None and "const" not in node:
        out = dict(node)
        out["type"] = [*(t if isinstance(t, list) else [t]), "null"]
        if "enum" in out:
            out["enum"] = [*out["enum"], None]
        return out
    return {"oneOf": [node, {"type": "null"}]}


@dataclass
class Builder:
    """Schemas of types, the ``TypedDict``\\ s in ``defs`` (name -> type) as ``$ref``\\ s to ``#/$defs/<name>``."""

    defs: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._names = {tp: name for name, tp in self.defs.items()}

    def definitions(self) -> dict[str, Schema]:
        return {name: self.node(tp, inline=True) for name, tp in self.defs.items()}

    def field(self, tp: Any, doc: Doc | None) -> Schema:
        node = self.node(tp)
        if doc is None:
            return node
        return _ordered({**node, **doc.schema}, doc.description)

    def node(self, tp: Any, inline: bool = False) -> Schema:
        tp, doc = unwrap(tp)
        if doc is not None:
            return self.field(tp, doc)
        if not inline and tp in self._names:
            return {"$ref": f"#/$defs/{self._names[tp]}"}
        if is_typeddict(tp):
            return self.object(tp)
        if tp in _SCALARS:
            return {"type": _SCALARS[tp]}
        if tp is object or tp is Any:
            return {}
        origin, args = get_origin(tp), get_args(tp)
        if origin is Literal:
            if len(args) == 1:
                return {"const": args[0]}
            t = _json_type(args)
            return {"type": t, "enum": list(args)} if t else {"enum": list(args)}
        if is_union(tp):
            rest = [a for a in args if a is not type(None)]
            inner = self.node(rest[0]) if len(rest) == 1 else {"oneOf": [self.node(a) for a in rest]}
            return _nullable(inner) if len(rest) < len(args) else inner
        if origin is list:
            return {"type": "array", "items": self.node(args[0])}
        if origin is dict:
            value = unwrap(args[1])[0]
            if value is object or value is Any:
                return {"type": "object"}
            return {"type": "object", "additionalProperties": self.node(args[1])}
        raise TypeError(f"no JSON Schema for {tp!r}")

    def object(self, td: type) -> Schema:
        fields = fields_of(td)
        node: Schema = {"type": "object"}
        if description_of(td):
            node["description"] = description_of(td)
        node["properties"] = {name: self.field(tp, d) for name, (tp, d, _req) in fields.items()}
        node["required"] = [name for name, (_tp, _d, req) in fields.items() if req]
        node["additionalProperties"] = False
        return node


def document(name: str, version: int, description: str, body: Schema, defs: Mapping[str, Schema] | None = None
             ) -> Schema:
    """A schema file: ``$id`` ``urn:ballbar:schema:<version>:<name>``, the body, its ``$defs``."""
    doc: Schema = {
        "$schema": DRAFT,
        "$id": f"urn:ballbar:schema:{version}:{name}",
        "title": f"ballbar {name} (schema_version {version})",
        "description": description,
        **body,
    }
    if defs:
        doc["$defs"] = dict(defs)
    return doc
