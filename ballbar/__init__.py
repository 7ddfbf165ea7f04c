"""ballbar: a ball-bar contouring monitor.

The distribution maps the repository's top-level folders to subpackages:
``protocol/`` -> ``ballbar.protocol``, ``analysis/`` -> ``ballbar.analysis``,
``daemon/`` -> ``ballbar.daemon``, ``tools/`` -> ``ballbar.tools``.
"""

from __future__ import annotations  # SCHEMA_VERSION's annotation is mypy's alone: nothing imports typing at start

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing (ballbar run's first milliseconds)
if TYPE_CHECKING:
    from typing import Final

__version__ = "0.1.0"
#: The version of every payload's shape (``schema_version``; the JSON Schemas in ``ballbar/schema/``, generated
#: from ``ballbar.protocol.messages``, whose ``SchemaVersion`` is ``Literal`` of it).
#: 2: the status' duplicate top-level ``zenoh`` block went (``outputs.zenoh`` stays), its rates and device
#: clock figures are in device terms with ``speedup``; the schemas were written.
SCHEMA_VERSION: Final = 2
