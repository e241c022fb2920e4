"""The near-wall layer families, one module each, and their registry.

:data:`MODULES` lists the family modules in the order ``--near-wall auto`` tries them; each registers one
:class:`~wss_nlp.models.families.base.WallFamily` when imported. A new family is a module here (see
:mod:`wss_nlp.models.families.base`) and its name in :data:`MODULES`.
"""

from __future__ import annotations

import importlib

from ...errors import InputError
from .base import WallFamily

#: The family modules, in the order the automatic choice tries them.
MODULES = ("wall_law", "exponential")

_REGISTRY: dict[str, WallFamily] = {}


def register(family: WallFamily) -> WallFamily:
    """Add ``family`` to the registry under its name (a module of this package calls it when imported)."""
    if not family.name or family.name in ("plain", "off", "auto", "inside"):
        raise ValueError(f"a near-wall family needs its own name, got {family.name!r}")
    _REGISTRY[family.name] = family
    return family


for _module in MODULES:
    importlib.import_module(f"{__name__}.{_module}")

#: The registered families' names, in :data:`MODULES` order.
NAMES: tuple[str, ...] = tuple(_REGISTRY)


def get(name: str) -> WallFamily:
    """The registered family ``name``; an :class:`~wss_nlp.errors.InputError` lists the known ones."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise InputError(f"near-wall family must be one of {', '.join(NAMES)}, got {name!r}") from None
