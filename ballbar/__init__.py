"""ballbar: a ball-bar contouring monitor.

The distribution maps the repository's top-level folders to subpackages:
``protocol/`` -> ``ballbar.protocol``, ``analysis/`` -> ``ballbar.analysis``,
``daemon/`` -> ``ballbar.daemon``, ``tools/`` -> ``ballbar.tools``.
"""

from __future__ import annotations  # SCHEMA_VERSION's annotation is mypy's alone: nothing imports typing at start

import os as _os

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing (ballbar run's first milliseconds)
if TYPE_CHECKING:
    from typing import Final

# One BLAS and OpenMP thread unless the caller chose: the fit's least squares are tall and thin (thousands of rows,
# tens of columns), where OpenBLAS's other threads add nothing but their spinning, and on a PC beside the machine
# (two cores, the daemon, the viewer) that spinning competes with the daemon itself.  Set here, before numpy
# loads OpenBLAS: the daemon, its analysis worker and every tool import this package first.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
#: The version of every payload's shape (``schema_version``; the JSON Schemas in ``ballbar/schema/``, generated
#: from ``ballbar.protocol.messages``, whose ``SchemaVersion`` is ``Literal`` of it).
#: 2: the status' duplicate top-level ``zenoh`` block went (``outputs.zenoh`` stays), its rates and device
#: clock figures are in device terms with ``speedup``; the schemas were written.
SCHEMA_VERSION: Final = 2
