"""What a message field says about itself: :class:`Doc`, carried in ``Annotated``.

A field of a message ``TypedDict`` is written ``name: Annotated[T, Doc(text,
unit)]``; the JSON Schemas and the payload tables are generated from these
(:mod:`.jsonschema`, :mod:`.tables`).  ``text`` says what the value is, without
its unit; ``unit`` is the unit (``um``, ``ms``, ``deg``...), written once;
``null`` what a null value means, for a field that may be null.  The schema's
description is ``"<text>, <unit> (null: <null>)"``.  Extra JSON Schema keywords
(``minimum``, ``exclusiveMinimum``, ``minLength``...) go in ``schema``.
"""

import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, NotRequired, Required, Union, get_args, get_origin


@dataclass(frozen=True)
class Doc:
    """A field's description, unit, the meaning of null, and extra schema keywords."""

    text: str
    unit: str | None = None
    null: str | None = None
    schema: Mapping[str, Any] = field(default_factory=dict)

    @property
    def description(self) -> str:
        out = ", ".join(s for s in (self.text, self.unit) if s)
        return f"{out} (null: {self.null})" if self.null else out


def doc(text: str, unit: str | None = None, *, null: str | None = None, **schema: Any) -> Doc:
    """``Annotated[float | None, doc("the lag", "ms", null="not estimated", minimum=0)]``."""
    return Doc(text, unit, null, dict(schema))


def unwrap(tp: Any) -> tuple[Any, Doc | None]:
    """The bare type of an annotation and its :class:`Doc` (``Annotated``, ``Required`` and ``NotRequired`` off)."""
    found: Doc | None = None
    while True:
        origin = get_origin(tp)
        if origin is Annotated:
            for m in tp.__metadata__:
                if isinstance(m, Doc):
                    found = m
            tp = tp.__origin__
        elif origin in (Required, NotRequired):
            tp = get_args(tp)[0]
        else:
            return tp, found


def is_union(tp: Any) -> bool:
    return get_origin(tp) in (Union, types.UnionType)


def fields_of(td: type) -> dict[str, tuple[Any, Doc | None, bool]]:
    """A ``TypedDict``'s fields in order: name -> (bare type, doc, required)."""
    hints = typing.get_type_hints(td, include_extras=True)
    required: frozenset[str] = td.__required_keys__  # type: ignore[attr-defined]
    out = {}
    for name, tp in hints.items():
        bare, d = unwrap(tp)
        out[name] = (bare, d, name in required)
    return out


def description_of(td: type) -> str:
    """A ``TypedDict``'s own description: its docstring, as one line."""
    text = td.__doc__ or ""
    return " ".join(text.split())
