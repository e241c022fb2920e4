"""A batch's manifest: one exam per row, its input and its own options by their command-line names.

A manifest is a CSV file (or TOML, :func:`load_manifest`) with a header. ``id`` names the exam (its folder
``DIR/<id>/``: letters, digits, ``.``, ``_``, ``-``, starting with a letter or digit; unique, also ignoring
case) and ``input`` its data: an input file of the contract (``.h5``), a DICOM folder, or files separated by
``;`` (NIfTI files, DICOM files) that ``wss-nlp import`` reads first. Relative paths are taken from the
manifest's folder. Every other column is an option of ``wss-nlp reconstruct`` or ``wss-nlp import`` by its
long flag without the dashes (``method``, ``viscosity``, ``venc``, ``z-smoothing``; ``_`` may stand for
``-``); an empty cell leaves the option as the command line (or its default) has it. A switch (``no-uncertainty``,
``flip-through-plane``) takes ``true`` or ``false``, ``plane`` six numbers separated by spaces. Columns are
parsed by the same argument declarations as the two subcommands (:mod:`wss_nlp.core.schema`,
:func:`wss_nlp.app.cli.exchange.add_import_arguments`), so a bad value gets the same message, with the row.
"""

from __future__ import annotations

import argparse
import copy
import csv
import hashlib
import json
import os
import re
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

from ... import __version__
from ...core import schema
from ...errors import InputError
from ...pipeline.options import ReconstructionOptions
from ..cli.exchange import add_import_arguments, import_settings

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

#: What an exam id looks like: one folder name, never a path.
ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
#: Names the batch itself writes in its output folder; no exam may take them.
RESERVED = ("summary.csv", "summary.parquet", "report.html", "report_distributions.png", "batch.log")
#: Input files read as they are (anything else is imported first).
HDF5_SUFFIXES = (".h5", ".hdf5")
_TRUE, _FALSE = ("true", "yes", "1", "on"), ("false", "no", "0", "off")


class _RowParser(argparse.ArgumentParser):
    """An argument parser whose errors are exceptions (the row and column are added by the caller)."""

    def error(self, message):
        raise _BadValue(message)


class _BadValue(Exception):
    pass


def _parsers() -> tuple[argparse.ArgumentParser, argparse.ArgumentParser]:
    recon = _RowParser(add_help=False, allow_abbrev=False)
    schema.add_arguments(recon, ReconstructionOptions)
    imp = _RowParser(add_help=False, allow_abbrev=False)
    add_import_arguments(imp)
    return recon, imp


def _long_flags(parser: argparse.ArgumentParser) -> dict:
    """``{name without dashes: action}`` of every long option."""
    return {s[2:]: a for a in parser._actions for s in a.option_strings if s.startswith("--")}


def option_columns() -> dict:
    """``{column: "reconstruct" | "import" | "both"}``: every column a manifest may have besides id and input."""
    recon, imp = (_long_flags(p) for p in _parsers())
    return {name: "both" if name in recon and name in imp else "reconstruct" if name in recon else "import"
            for name in sorted(set(recon) | set(imp))}  # fmt: skip


@dataclass(frozen=True)
class ImportSpec:
    """How an exam's scanner files are imported: the keywords of :func:`wss_nlp.io.importing.import_paths`."""

    settings: dict
    argv: tuple = ()  # the import options as flags, for the input file's provenance


@dataclass(frozen=True)
class Exam:
    """One row of a manifest: the exam's id, its input paths, its options and how its files are imported."""

    id: str
    inputs: tuple  # absolute paths
    options: ReconstructionOptions
    imports: ImportSpec | None = None  # None: the input is an HDF5 input file, read as it is
    row: int = 0  # the line of the manifest (the header is line 1)
    columns: dict = field(default_factory=dict)  # the row's option columns that were set, as written
    input_text: str = ""  # the input as the manifest writes it (the summary shows it; default: the paths)

    def __post_init__(self):
        if not self.input_text:
            object.__setattr__(self, "input_text", ";".join(self.inputs))

    def settings_json(self, outputs: dict) -> str:
        """Everything that decides this exam's results besides its input's content, as canonical JSON."""
        imports = None
        if self.imports is not None:
            s = self.imports.settings
            plane = s["plane"]
            imports = {
                "options": asdict(s["options"]),
                "phase_units": s["phase_units"],
                "frame_interval_ms": s["frame_interval_ms"],
                "plane": None if plane is None else asdict(plane),
            }
        data = {"options": self.options.as_dict(), "import": imports, "outputs": outputs, "version": __version__}
        return json.dumps(data, sort_keys=True, default=str)


def load_manifest(path: str, defaults: argparse.Namespace | Sequence[str] | None = None) -> list[Exam]:
    """The exams of a manifest (module notes), checked: ids, columns and every option value.

    ``defaults``: reconstruction options every exam starts from (a row's columns override them): the parsed
    command line of ``wss-nlp batch`` (a namespace), or flags (``["--method", "coupled"]``).

    Raises :class:`~wss_nlp.errors.InputError` naming the manifest, the row and the column.
    """
    rows = _read_rows(path)
    if not rows:
        raise InputError(f"{path}: no exams (a header with id,input and one row per exam)")
    recon, imp = _parsers()
    recon_flags, imp_flags = _long_flags(recon), _long_flags(imp)
    base = _base_namespace(recon, defaults, path)
    folder = os.path.dirname(os.path.abspath(path))
    exams: list[Exam] = []
    seen: dict = {}
    for line, row in rows:
        where = f"{path}: row {line}"
        exam_id = str(row.get("id") or "").strip()
        _check_id(exam_id, where)
        where = f"{path}: row {line} (id {exam_id})"
        if exam_id.lower() in seen:
            raise InputError(f"{where}: id {exam_id!r} is taken by row {seen[exam_id.lower()]} (ids are folder names)")
        seen[exam_id.lower()] = line
        text = str(row.get("input") or "").strip()
        inputs = tuple(os.path.normpath(os.path.join(folder, p.strip())) for p in text.split(";") if p.strip())
        if not inputs:
            raise InputError(f"{where}: empty 'input' (an .h5 file, a DICOM folder, or files separated by ';')")
        imported = not (len(inputs) == 1 and inputs[0].lower().endswith(HDF5_SUFFIXES))
        recon_argv: list[str] = []
        imp_argv: list[str] = []
        resets: dict = {}  # switches a cell turns off again (a row may undo the command line's --no-uncertainty)
        columns = {}
        for column, value in row.items():
            if column in ("id", "input"):
                continue
            value = "" if value is None else str(value).strip()
            if not value:
                continue
            name = column.strip().replace("_", "-")
            if name not in recon_flags and name not in imp_flags:
                raise InputError(
                    f"{path}: column {column!r} is not an option of 'wss-nlp reconstruct' or 'wss-nlp import' (by "
                    "its long flag without the dashes, e.g. method, viscosity, venc, z-smoothing); join other data "
                    "to summary.csv by id"
                )
            columns[column] = value
            if name in imp_flags and name not in recon_flags and not imported:
                raise InputError(
                    f"{where}: column {column!r} is an import option, but the input is an HDF5 file that is read "
                    "as it is; leave the cell empty"
                )
            if name in recon_flags:
                recon_argv += _flag(recon_flags[name], name, value, f"{where}: column {column!r}", resets)
            if name in imp_flags and imported:
                imp_argv += _flag(imp_flags[name], name, value, f"{where}: column {column!r}", {})
        options = _options(recon, base, recon_argv, resets, where)
        imports = None
        if imported:
            try:
                ns = imp.parse_args(imp_argv)
            except _BadValue as exc:
                raise InputError(f"{where}: {exc}") from None
            imports = ImportSpec(_import_settings(ns, where), tuple(imp_argv))
        exams.append(Exam(exam_id, inputs, options, imports, line, columns, text))
    return exams


def _read_rows(path: str) -> list[tuple[int, dict]]:
    """``(line, {column: value})`` of every exam: CSV with a header, or TOML with ``[[exam]]`` tables."""
    try:
        if path.lower().endswith(".toml"):
            with open(path, "rb") as fh:
                data = tomllib.load(fh)
            exams = data.get("exam")
            if not isinstance(exams, list) or not all(isinstance(e, dict) for e in exams):
                raise InputError(f"{path}: a TOML manifest has one [[exam]] table per exam (id = ..., input = ...)")
            return [(k + 1, {str(c): _toml_text(v) for c, v in e.items()}) for k, e in enumerate(exams)]
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            header = [h.strip() for h in reader.fieldnames or []]
            if "id" not in header or "input" not in header:
                raise InputError(f"{path}: the header must name the columns 'id' and 'input' (got {header})")
            reader.fieldnames = header
            out = []
            for row in reader:
                if None in row:
                    raise InputError(f"{path}: row {reader.line_num} has more cells than the header has columns")
                if any((v or "").strip() for v in row.values()):  # blank lines are not exams
                    out.append((reader.line_num, row))
            return out
    except OSError as exc:
        raise InputError(f"{path}: cannot read the manifest ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a CSV manifest ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None


def _toml_text(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return ";".join(str(v) for v in value) if all(isinstance(v, str) for v in value) else " ".join(map(str, value))
    return str(value)


def _check_id(exam_id: str, where: str) -> None:
    if not exam_id:
        raise InputError(f"{where}: empty 'id'")
    if not ID_PATTERN.match(exam_id) or ".." in exam_id:
        raise InputError(
            f"{where}: id {exam_id!r} must be one folder name: letters, digits, '.', '_' and '-', starting with a "
            "letter or digit (no path separators, no '..')"
        )
    if exam_id.lower() in RESERVED:
        raise InputError(f"{where}: id {exam_id!r} is the name of a file the batch writes; choose another")


def _flag(action: argparse.Action, name: str, value: str, where: str, resets: dict) -> list[str]:
    """The command-line words that set option ``name`` to the cell's ``value`` (a switch set to false goes to
    ``resets``: its destination and default)."""
    flag = "--" + name
    if action.nargs == 0:  # a switch
        if value.lower() in _TRUE:
            return [flag]
        if value.lower() in _FALSE:
            resets[action.dest] = action.default
            return []
        raise InputError(f"{where}: {value!r}: a switch takes true or false")
    if action.nargs not in (None, "?"):
        return [flag, *value.replace(",", " ").split()]
    return [flag, value]


def _base_namespace(parser: argparse.ArgumentParser, defaults, path: str) -> argparse.Namespace:
    if isinstance(defaults, argparse.Namespace):
        return argparse.Namespace(**{k: v for k, v in vars(defaults).items() if k.startswith("opt__")})
    try:
        return parser.parse_args(list(defaults or []))
    except _BadValue as exc:
        raise InputError(f"{path}: the options for every exam: {exc}") from None


def _options(parser: argparse.ArgumentParser, base: argparse.Namespace, argv: list, resets: dict, where: str):
    ns = copy.copy(base)  # argparse keeps attributes already set: the row's flags override the defaults only
    for dest, value in resets.items():
        setattr(ns, dest, value)
    try:
        ns = parser.parse_args(argv, namespace=ns)
        return schema.from_args(ReconstructionOptions, ns)
    except _BadValue as exc:
        raise InputError(f"{where}: {exc}") from None
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _import_settings(ns: argparse.Namespace, where: str) -> dict:
    try:
        return import_settings(ns)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


# ---------------------------------------------------------------- the input's content
def input_files(inputs: Sequence[str]) -> list[str]:
    """The files an exam reads: the inputs, every file under a folder (hidden ones aside, as the DICOM reader
    does), and a NIfTI file's JSON sidecar."""
    files: list[str] = []
    for p in inputs:
        if os.path.isdir(p):
            for root, dirs, names in os.walk(p):
                dirs.sort()
                files += [os.path.join(root, n) for n in sorted(names) if not n.startswith(".")]
            continue
        files.append(p)
        stem = re.sub(r"\.nii(\.gz)?$", "", p, flags=re.IGNORECASE)
        if stem != p and os.path.exists(stem + ".json"):
            files.append(stem + ".json")
    return files


def input_stat(inputs: Sequence[str]) -> list:
    """``[path, size, mtime_ns]`` of every file an exam reads (``[path, None, None]`` for a missing one)."""
    out = []
    for f in input_files(inputs):
        try:
            st = os.stat(f)
            out.append([f, st.st_size, st.st_mtime_ns])
        except OSError:
            out.append([f, None, None])
    return out


def input_digest(inputs: Sequence[str], previous: dict | None = None) -> tuple[str, list]:
    """``(sha256, stat)`` of the content of every file an exam reads (names relative to their input, so a
    moved cohort keeps its digests); a missing file enters as such.

    ``previous``: an earlier record with ``input_stat`` and ``input_sha256``; when every file still has the size
    and modification time it had then, its digest is taken without reading the files again (as ``make`` and
    ``git`` trust a file that did not change on disk).
    """
    stat = input_stat(inputs)
    if previous and previous.get("input_stat") == stat and previous.get("input_sha256"):
        return str(previous["input_sha256"]), stat
    h = hashlib.sha256()
    roots = [os.path.abspath(p) for p in inputs]
    for path, size, _ in stat:
        rel = next((os.path.relpath(path, r) for r in roots if path.startswith(r + os.sep)), os.path.basename(path))
        h.update(rel.encode() + b"\0")
        if size is None:
            h.update(b"missing\0")
            continue
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        h.update(b"\0")
    return h.hexdigest(), stat
