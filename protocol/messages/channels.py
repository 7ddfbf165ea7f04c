"""The MCAP channels' schemas: which document each channel registers, read from the shipped files.

The daemon registers these in every MCAP file.  It reads them from
``ballbar/schema/`` (``tests/test_schemas.py`` keeps those files equal to what
the types generate, :mod:`.documents`), so that running needs neither the types
nor the generator: only type-checking and the tests do.
"""

import json
from pathlib import Path
from typing import Any

import ballbar

#: topic -> (schema name in the file, schema document, channel description).
MCAP_CHANNELS: dict[str, tuple[str, str, str]] = {
    "/ballbar/samples": ("ballbar.Samples", "mcap-samples", "ball-bar samples, delta-encoded columns; see the "
                         "ballbar.Samples schema"),
    "/ballbar/events": ("ballbar.Event", "mcap-event", "source, pipeline and logger events"),
    "/ballbar/results": ("ballbar.Result", "result", "analysis results (circle, test, set)"),
    "/ballbar/status": ("ballbar.Status", "status", "daemon status"),
    "/ballbar/config": ("ballbar.Config", "config", "effective configuration, at start and at the head of every file"),
    "/ballbar/controller": ("ballbar.Controller", "controller", "the CNC controller's data over OPC UA "
                            "([controller]): values with the server's timestamps on the daemon's clock"),
    "/ballbar/other": ("ballbar.Message", "mcap-other", "other pipeline messages"),
}


def shipped_schema(name: str) -> dict[str, Any]:
    """The shipped schema file ``ballbar/schema/<name>.schema.json``, parsed."""
    path = Path(ballbar.__file__).parent / "schema" / f"{name}.schema.json"
    out: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return out
