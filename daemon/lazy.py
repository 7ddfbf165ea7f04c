"""A module imported when first used: :class:`LazyModule`."""

from __future__ import annotations

import importlib
import types
from typing import Any


class LazyModule(types.ModuleType):
    """Stands for module ``name`` and imports it at the first attribute looked up on it.

    For a heavy dependency that only some code paths use: ``rr = LazyModule("rerun")``
    costs nothing until ``rr.something`` is evaluated (then the import, once; its
    attributes are copied over, so later look-ups are plain).
    """

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.__dict__["_lazy_target"] = name

    def __getattr__(self, attr: str) -> Any:
        module = importlib.import_module(self.__dict__["_lazy_target"])
        self.__dict__.update({k: v for k, v in vars(module).items() if k not in ("__name__", "__spec__")})
        return getattr(module, attr)


__all__ = ["LazyModule"]
