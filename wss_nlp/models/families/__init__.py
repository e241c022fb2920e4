"""The near-wall layer families, one module each, and their registry.

:data:`MODULES` lists the family modules in the order ``--near-wall auto`` tries them; each registers one
:class:`~wss_nlp.models.families.base.WallFamily` when imported. A new family is a module here (see
:mod:`wss_nlp.models.families.base`) and its name in :data:`MODULES`. A family whose shape depends on the
friction Reynolds number has a member per Re_tau, named ``"<name>@<Re_tau>"`` (:func:`at_reynolds`), which
:func:`get` resolves like a registered name.
"""

from __future__ import annotations

import functools
import importlib

from ...errors import InputError
from .base import WallFamily

#: The family modules, in the order the automatic choice tries them.
MODULES = ("wall_law", "low_re", "exponential")

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
    """The registered family ``name``, or the member ``"<family>@<Re_tau>"`` of a Reynolds-number-dependent one;
    an :class:`~wss_nlp.errors.InputError` lists the known ones."""
    try:
        return _REGISTRY[name]
    except KeyError:
        pass
    family, _, re_tau = name.partition("@")
    if family in _REGISTRY and _REGISTRY[family].reynolds_dependent and re_tau:
        try:
            return _member(family, float(re_tau))
        except ValueError:
            pass
    raise InputError(f"near-wall family must be one of {', '.join(NAMES)}, got {name!r}") from None


@functools.lru_cache(maxsize=1024)  # a slice scores a few dozen scales; members are small
def _member(family: str, re_tau: float) -> WallFamily:
    return _REGISTRY[family].at(re_tau)


def at_reynolds(name: str, re_tau: float) -> str:
    """The name of family ``name``'s profile at friction Reynolds number ``re_tau``: ``"<name>@<re_tau>"`` for a
    family whose shape depends on it (:attr:`~wss_nlp.models.families.base.WallFamily.reynolds_dependent`),
    else ``name``. A member's name resolves to the same member (:func:`get`)."""
    family = base_name(name)
    if not get(family).reynolds_dependent:
        return family
    return get(f"{family}@{float(re_tau)!r}").name


def base_name(name: str) -> str:
    """The registered family of a name or of a member's name (``"low_re@183.2"`` -> ``"low_re"``)."""
    return name.partition("@")[0]
