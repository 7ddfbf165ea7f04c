"""The replies of the daemon's queryables: ``history/<topic>``, and an error."""

from typing import Annotated, Literal, TypedDict

from .envelope import Version
from .fields import doc

HistoryTopic = Literal["circle", "test", "set", "event", "alert"]


class HistoryReply(TypedDict):
    """A reply of ballbar/<m>/history/<topic>."""

    schema_version: Version
    kind: Annotated[Literal["history"], doc("a history reply")]
    topic: Annotated[HistoryTopic, doc("circle, test, set, event or alert")]
    machine_id: Annotated[str, doc("the daemon's machine_id")]
    count: Annotated[int, doc("results in this reply")]
    more: Annotated[bool, doc("more after the last: ask again with since = its t_wall")]
    results: Annotated[list[dict[str, object]], doc(
        "payloads as published (result, event or alert schema), oldest first; results seeded from the recordings "
        "keep the schema_version they were logged with")]


class QueryError(TypedDict):
    """A query the daemon could not answer (reply_err of history/<topic>: a bad since or limit)."""

    schema_version: Version
    kind: Annotated[Literal["error"], doc("an error reply")]
    error: Annotated[str, doc("what was wrong with the query, in words")]
