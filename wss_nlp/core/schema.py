"""The options schema: one declaration per option, from which the CLI arguments and the TOML study keys follow.

Every user-facing option is a dataclass field declared with :func:`option`,
next to the code that uses it (``GeometryOptions`` in :mod:`wss_nlp.models.geometry`,
``VelocityOptions`` in :mod:`wss_nlp.models.velocity`, ...). Its metadata say how
the command line spells it (``cli``), which study keys set it (``toml``),
its help text, its choices and how a text is parsed. :func:`add_arguments`
turns a (nested) options dataclass into argparse arguments, :func:`from_args`
builds the options back from the parsed arguments, :func:`toml_keys` lists
the study keys and :func:`build` makes options from ``{key: value}``. A new
option is one field: the CLI, the sweep files and the stored options follow.

A field's ``parse`` may return a dict ``{path: value}`` to set several fields
at once (``--alpha auto`` sets the rule and keeps the default value), and
``also`` names further fields that take the same value (``--quad-order``
sets the geometry's and the velocity's).
"""

from __future__ import annotations

import argparse
from dataclasses import MISSING, field, fields, is_dataclass
from typing import Any
from collections.abc import Callable

from ..errors import InputError

_KEY = "wss_nlp"


def option(
    default: Any = MISSING,
    help: str = "",
    *,
    cli: str | None = None,
    toml: tuple = (),
    choices: tuple | None = None,
    parse: Callable | None = None,
    metavar: str | None = None,
    flag_off: bool = False,
    flag_on: bool = False,
    const: Any = None,
    also: tuple = (),
    group: str | None = None,
    default_text: str | None = None,
    default_factory: Any = MISSING,
):
    """A dataclass field with schema metadata.

    Parameters
    ----------
    default, default_factory
        As for :func:`dataclasses.field`.
    help : str
        One line for ``--help``; ``(default ...)`` is appended.
    cli : str or None
        The option's spelling on the command line (``--n-fourier``); None:
        not on the command line.
    toml : tuple of str
        Study-file keys that set this field (``("N", "n_fourier")``).
    choices : tuple or None
        Allowed values (checked by argparse; the dataclass checks again).
    parse : callable or None
        Text (or TOML value) -> value, or -> ``{field path: value}``.
    flag_off : bool
        A boolean that is on by default: the CLI flag (``--no-...``) turns it off.
    flag_on : bool
        A boolean that is off by default: the CLI flag turns it on.
    const : object
        The value the CLI flag stands for when it is given without one (``--allow-unphysical`` alone:
        ``"all"``); None: the flag takes a value.
    also : tuple of str
        Paths of further fields (from the root options) set to the same value.
    group : str or None
        Argument group title; default: the dataclass's ``schema_group``.
    default_text : str or None
        What ``--help`` shows as the default (when the field's own default
        is not what a user types, e.g. a rule field set by ``--alpha``).
    """
    meta = {
        _KEY: {
            "help": help,
            "cli": cli,
            "toml": tuple(toml),
            "choices": choices,
            "parse": parse,
            "metavar": metavar,
            "flag_off": flag_off,
            "flag_on": flag_on,
            "const": const,
            "also": tuple(also),
            "group": group,
            "default_text": default_text,
        }
    }
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata=meta)
    return field(default=default, metadata=meta)


def _leaves(cls, prefix: str = ""):
    """``(path, field, owner class)`` of every schema field, depth first; nested options dataclasses are entered."""
    for f in fields(cls):
        path = prefix + f.name
        meta = f.metadata.get(_KEY)
        if meta is None and f.default_factory is not MISSING and is_dataclass(f.default_factory):
            yield from _leaves(f.default_factory, path + ".")
        elif meta is not None:
            yield path, f, cls


def _default(f):
    return f.default_factory() if f.default_factory is not MISSING else f.default


def integer(text) -> int:
    """An integer from text or a number, written as one may type it: ``360``, ``3.6e2``; ``2.5`` is refused."""
    if isinstance(text, bool):
        raise ValueError(f"{text!r} is not a whole number")
    if not isinstance(text, float):
        try:
            return int(text)
        except (TypeError, ValueError):
            pass
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"invalid integer {text!r}") from None
    if not value.is_integer():
        raise ValueError(f"{text!r} is not a whole number")
    return int(value)


integer.__name__ = "int"  # argparse's message: "invalid int value"


def _type_parser(f) -> Callable:
    """int (:func:`integer`), float or str from the annotation (``float | None`` -> float)."""
    if f.type in (bool, int, float):  # evaluated annotations
        return integer if f.type is int else f.type
    first = str(f.type).split("|")[0].strip()  # postponed ones are strings: "float | None"
    parsers: dict[str, Callable] = {"bool": bool, "int": integer, "float": float}
    return parsers.get(first, str)


def add_arguments(parser: argparse.ArgumentParser, cls) -> None:
    """Add an argument for every field of ``cls`` (and its nested options) that has a ``cli`` spelling."""
    groups: dict = {}
    for path, f, owner in _leaves(cls):
        meta = f.metadata[_KEY]
        if not meta["cli"]:
            continue
        title = meta["group"] or getattr(owner, "schema_group", owner.__name__)
        grp = groups.setdefault(title, parser.add_argument_group(title))
        default = _default(f)
        dest = "opt__" + path.replace(".", "__")
        text = meta["help"].replace("%", "%%")  # argparse formats help strings
        if meta["flag_off"]:
            grp.add_argument(meta["cli"], dest=dest, action="store_false", default=True, help=text)
            continue
        if meta["flag_on"]:
            grp.add_argument(meta["cli"], dest=dest, action="store_true", default=False, help=text)
            continue
        shown = meta["default_text"] if meta["default_text"] is not None else default
        if shown is not None:
            text += f" (default {shown})"
        kwargs = {"dest": dest, "default": None, "help": text}
        if meta["parse"] is None:
            kwargs["type"] = _type_parser(f)
        if meta["const"] is not None:
            kwargs.update(nargs="?", const=meta["const"])
        if meta["choices"] is not None:
            kwargs["choices"] = list(meta["choices"])
        else:
            kwargs["metavar"] = meta["metavar"] or meta["cli"].lstrip("-").upper().replace("-", "_")
        grp.add_argument(meta["cli"], **kwargs)


def _parsed(path: str, f, value, where: str) -> dict:
    """``{path: value}`` assignments for one field's raw value (text from the CLI, or a TOML value)."""
    meta = f.metadata[_KEY]
    if meta["parse"] is not None:
        got = meta["parse"](value)
        if isinstance(got, dict):
            return got
        value = got
    elif isinstance(value, str) and _type_parser(f) is not str:
        try:
            value = _type_parser(f)(value)
        except ValueError:
            raise InputError(f"{where}: {value!r} is not a valid {_type_parser(f).__name__}") from None
    elif _type_parser(f) is integer and isinstance(value, float):
        try:
            value = integer(value)
        except ValueError:
            raise InputError(f"{where}: {value!r} is not a whole number") from None
    return {p: value for p in (path, *meta["also"])}


def given(cls, args: argparse.Namespace) -> dict:
    """``{path: (flag, value)}`` of the options of class ``cls`` set on the command line (values as argparse read).

    A value option counts when it was given (not None); a switch (``store_true`` / ``store_false``) when it differs
    from its default. Options without a command-line flag, or whose arguments ``args`` lacks, are left out.
    """
    out: dict = {}
    for path, f, _ in _leaves(cls):
        meta = f.metadata[_KEY]
        if not meta["cli"]:
            continue
        value = getattr(args, "opt__" + path.replace(".", "__"), None)
        if meta["flag_off"] or meta["flag_on"]:
            if value is (not meta["flag_off"]):
                out[path] = (meta["cli"], value)
        elif value is not None:
            out[path] = (meta["cli"], value)
    return out


def cli_flag(cls, path: str) -> str:
    """The command-line flag of the option at ``path`` of class ``cls`` (``path`` itself when it has none)."""
    for p, f, _ in _leaves(cls):
        if p == path and f.metadata[_KEY]["cli"]:
            return str(f.metadata[_KEY]["cli"])
    return path


def from_args(cls, args: argparse.Namespace, check: Callable | None = None):
    """Options of class ``cls`` from the arguments :func:`add_arguments` added (unset ones keep their defaults).

    ``check(values, spelled)``, if given, sees the values set (``{path: value}``) and how the user spelled each
    (``{path: "--n-fourier"}``) before the options are built, to refuse a value in the user's own words.
    """
    values: dict = {}
    spelled: dict = {}
    leaves = {path: f for path, f, _ in _leaves(cls)}
    for path, (flag, value) in given(cls, args).items():
        meta = leaves[path].metadata[_KEY]
        if meta["flag_off"] or meta["flag_on"]:
            values[path] = value
            spelled[path] = flag
            continue
        got = _parsed(path, leaves[path], value, flag)
        values.update(got)
        spelled.update(dict.fromkeys(got, flag))
    if check is not None:
        check(values, spelled)
    return assemble(cls, values)


def toml_keys(cls) -> dict:
    """``{study key: (path, field)}`` of every field with ``toml`` keys."""
    out = {}
    for path, f, _ in _leaves(cls):
        for key in f.metadata[_KEY]["toml"]:
            out[key] = (path, f)
    return out


def build(cls, params: dict, where: str = "", check: Callable | None = None):
    """Options of class ``cls`` from study keys ``{key: value}`` (see :func:`toml_keys`); unknown keys are errors.

    ``check`` as for :func:`from_args` (the spellings are the study keys).
    """
    keys = toml_keys(cls)
    values: dict = {}
    spelled: dict = {}
    for key, value in params.items():
        if key not in keys:
            raise InputError(f"{where}: unknown option key {key!r}; known: {', '.join(keys)}")
        path, f = keys[key]
        got = _parsed(path, f, value, f"{where}: {key}")
        values.update(got)
        spelled.update(dict.fromkeys(got, key))
    if check is not None:
        check(values, spelled)
    return assemble(cls, values)


def assemble(cls, values: dict):
    """``cls`` with the fields at dotted ``values`` paths set; nested options are rebuilt (and so validated)."""
    kwargs: dict = {}
    nested: dict = {}
    for path, value in values.items():
        head, _, rest = path.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            kwargs[head] = value
    for f in fields(cls):
        if f.name in nested:
            kwargs[f.name] = assemble(f.default_factory, nested[f.name])
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise InputError(f"bad option: {exc}") from None
