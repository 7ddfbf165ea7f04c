"""Validate payloads against the shipped JSON Schemas with a real validator (``jsonschema``).

``validate(payload)`` picks the schema by ``kind``; ``validate_recordings(dir)``
checks every record of every MCAP file against the schema its channel
registered (so it checks the registration too).  Errors name the payload's
kind, event and the path of the offending field.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterable
from functools import cache
from pathlib import Path
from typing import Any

from jsonschema import Draft202012Validator
from jsonschema.exceptions import best_match
from mcap.exceptions import EndOfFile
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from ballbar.daemon.schemas import NAMES, schema

BY_KIND = {"circle": "result", "test": "result", "set": "set", "event": "event", "status": "status", "config": "config",
           "alert": "alert", "samples": "samples", "history": "history", "controller": "controller"}


@cache
def validator(name: str) -> Draft202012Validator:
    doc = schema(name)
    Draft202012Validator.check_schema(doc)
    return Draft202012Validator(doc)


def problems(payload: Any, name: str | None = None) -> list[str]:
    """What is wrong with ``payload`` against its schema (empty: valid)."""
    if name is None:
        name = BY_KIND.get(payload.get("kind", "") if isinstance(payload, dict) else "", "")
        if not name:
            return [f"no schema for kind {payload.get('kind') if isinstance(payload, dict) else payload!r}"]
    errors = list(validator(name).iter_errors(payload))
    if not errors:
        return []
    err = best_match(errors)
    path = "/".join(str(p) for p in err.absolute_path)
    what = f"{payload.get('kind')}{':' + str(payload['event']) if 'event' in payload else ''}"
    return [f"{name} schema, {what} at /{path}: {err.message[:300]}"]


def validate(payload: Any, name: str | None = None) -> None:
    bad = problems(payload, name)
    assert not bad, bad[0]


def validate_all(payloads: Iterable[Any]) -> Counter[str]:
    """Validate each; the count by kind (and event) of what was checked."""
    seen: Counter[str] = Counter()
    failures: list[str] = []
    for p in payloads:
        failures += problems(p)
        seen[p.get("kind", "?") + (f":{p['event']}" if p.get("kind") == "event" else "")] += 1
    assert not failures, f"{len(failures)} payloads do not match their schema; first: {failures[0]}"
    return seen


def validate_recordings(directory: Path) -> Counter[str]:
    """Every record of every MCAP file under ``directory`` against its channel's registered schema.

    Read with the streaming reader, so a file a killed daemon left without a footer is checked up to its
    last whole chunk.  The count of records checked, by channel.
    """
    seen: Counter[str] = Counter()
    failures: list[str] = []
    files = sorted(Path(directory).glob("*.mcap"))
    assert files, f"no recordings in {directory}"
    for path in files:
        schemas: dict[int, Draft202012Validator] = {}
        channels: dict[int, tuple[str, Draft202012Validator | None]] = {}
        with open(path, "rb") as fh:
            try:
                for rec in StreamReader(fh, skip_magic=False).records:
                    if isinstance(rec, Schema):
                        assert rec.encoding == "jsonschema", (path, rec.name)
                        doc = json.loads(rec.data)
                        Draft202012Validator.check_schema(doc)
                        schemas[rec.id] = Draft202012Validator(doc)
                    elif isinstance(rec, Channel):
                        channels[rec.id] = (rec.topic, schemas.get(rec.schema_id))
                    elif isinstance(rec, Message):
                        topic, v = channels[rec.channel_id]
                        assert v is not None, f"{path.name}: {topic} has no schema"
                        payload = json.loads(rec.data)
                        errors = list(v.iter_errors(payload))
                        if errors:
                            err = best_match(errors)
                            failures.append(f"{path.name} {topic} /{'/'.join(map(str, err.absolute_path))}: "
                                            f"{err.message[:300]}")
                        seen[topic] += 1
            except EndOfFile:  # a file cut by kill -9: what came before its last whole chunk is checked
                pass
    assert not failures, f"{len(failures)} MCAP records do not match their schema; first: {failures[0]}"
    return seen


__all__ = ["BY_KIND", "NAMES", "problems", "validate", "validate_all", "validate_recordings", "validator"]
