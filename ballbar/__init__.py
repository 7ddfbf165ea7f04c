"""ballbar: a ball-bar contouring monitor.

The distribution maps the repository's top-level folders to subpackages:
``protocol/`` -> ``ballbar.protocol``, ``analysis/`` -> ``ballbar.analysis``,
``daemon/`` -> ``ballbar.daemon``, ``tools/`` -> ``ballbar.tools``.
"""

__version__ = "0.1.0"
SCHEMA_VERSION = 1
