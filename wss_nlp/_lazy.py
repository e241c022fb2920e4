"""SciPy's submodules imported at their first use, so that the command line starts without them (issue 19).

``from ._lazy import scipy`` gives a stand-in for the package: ``scipy.linalg``,
``scipy.sparse`` and the rest are imported when first touched (importing
them costs 0.1-0.3 s, more than the rest of ``wss-nlp --help``; measured by
``scripts/bench_startup.py``), and then behave as usual.
"""

from __future__ import annotations

import importlib
import types
from typing import Any


class _Package(types.ModuleType):
    """A package whose submodules are imported on attribute access."""

    def __getattr__(self, name: str) -> Any:
        try:
            value: Any = importlib.import_module(f"{self.__name__}.{name}")
        except ModuleNotFoundError:  # not a submodule: an attribute of the package itself
            value = getattr(importlib.import_module(self.__name__), name)
        setattr(self, name, value)
        return value


scipy: Any = _Package("scipy")
