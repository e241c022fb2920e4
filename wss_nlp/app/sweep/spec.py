"""A study file: its grid of cases and each case's options and acquisition (``problems/*.toml``)."""

from __future__ import annotations

import hashlib
import json
import os
import sys
from typing import Any
from dataclasses import dataclass
import numpy as np
from ...io import files as wio
from ...analysis import metrics as met
from ...synthetic import phantoms
from ...core import schema
from ...errors import InputError
from ...io import ranges
from ...pipeline import limits
from ...pipeline.options import METHODS, ReconstructionOptions


if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


#: Metrics of one case (NaN where they do not apply, e.g. velocity_err of a baseline, errors without a truth).
METRICS = {
    "radius_err": "radius relative L2 error",
    "radius_err_h2": "radius relative H^2 error (paper Table 1)",
    "radius_max_mm": "largest radius error [mm]",
    "velocity_err": "velocity relative L2 error on the reference disk (paper Table 2 uses H^2)",
    "wss_err": "WSS relative L2 error (paper Table 3)",
    "mean_wss_bias": "signed relative error of the mean WSS",
    "mean_wss_pa": "mean WSS [Pa]",
    "mean_wss_true_pa": "true mean WSS [Pa]",
    "mean_wss_std_pa": "linearized standard deviation of the mean WSS [Pa] (with uncertainty = true)",
    "alpha_used": "alpha used",
    "beta_used": "beta used",
    "seconds": "wall time of the case [s]",
}


#: Data keys: which acquisition a case reconstructs.
DATA_KEYS = ("case", "h", "snr", "seed", "venc", "input")


#: Keys of the ``[study]`` table, of each ``[[tables]]`` and each ``[[plots]]`` entry (anything else is refused).
STUDY_KEYS = ("name", "description", "metrics")
TABLE_KEYS = ("name", "rows", "cols", "metric", "where", "agg", "caption", "bold")
PLOT_KEYS = ("name", "x", "y", "by", "panels", "where", "logx", "title")
#: Most cases a study may have: a grid beyond it is a typo in a range, not a study (100000 cases of a few seconds
#: each are weeks on a workstation).
MAX_CASES = 100_000
#: Names of studies, tables and plots: one plain folder or file name (no separators, no leading dot), so that
#: everything a study writes stays inside its output folder.
_PLAIN_NAME = "letters, digits, '-', '_' and '.', not starting with '.'"

#: Option keys of the study grid: every ``toml`` key of the options schema (:func:`wss_nlp.core.schema.toml_keys`), and
#: ``M`` = ``degree`` (Zernike basis) or ``max_eigenvalue`` (eigenfunction basis).
PARAMETERS = (*schema.toml_keys(ReconstructionOptions), "M")


@dataclass(frozen=True)
class Study:
    """A parsed study file."""

    name: str
    description: str
    grid: dict  # key -> list of values (scalars already wrapped)
    metrics: tuple
    tables: tuple = ()
    plots: tuple = ()
    source: str = ""
    base_dir: str = "."

    @property
    def varying(self) -> list[str]:
        return [k for k, v in self.grid.items() if len(v) > 1]


# ------------------------------------------------------------------ parsing
def _values(key: str, spec, src: str) -> list:
    """A grid entry: a scalar, a list, ``{range = [a, b]}`` (integers, b excluded) or ``{start, stop, num, log}``.

    Empty or inverted ranges, grids beyond :data:`MAX_CASES` values and unknown keys are refused before anything
    is expanded (a ``range`` is sized without being built).
    """
    if isinstance(spec, list):
        if not spec:
            raise InputError(f"{src}: grid.{key} is an empty list")
        if len(spec) > MAX_CASES:
            raise InputError(f"{src}: grid.{key} lists {len(spec)} values; a study has at most {MAX_CASES} cases")
        return spec
    if isinstance(spec, dict):
        if "range" in spec:
            extra = sorted(set(spec) - {"range"})
            if extra:
                raise InputError(f"{src}: grid.{key}: unknown key(s) {extra} next to 'range'; known: range")
            r = spec["range"]
            if not (isinstance(r, list) and len(r) in (2, 3) and all(type(x) is int for x in r)):
                raise InputError(f"{src}: grid.{key}.range must be [start, stop] or [start, stop, step] integers")
            if len(r) == 3 and r[2] == 0:
                raise InputError(f"{src}: grid.{key}.range {r}: the step must not be 0")
            n = len(range(*r))
            if n == 0:
                flip = f"; did you mean [{r[1]}, {r[0]}]?" if len(r) == 2 and r[0] > r[1] else ""
                raise InputError(f"{src}: grid.{key}.range {r} is empty (stop excluded, start < stop){flip}")
            if n > MAX_CASES:
                raise InputError(f"{src}: grid.{key}.range {r} has {n} values; a study has at most {MAX_CASES} cases")
            return list(range(*r))
        if {"start", "stop", "num"} <= set(spec):
            extra = sorted(set(spec) - {"start", "stop", "num", "log"})
            if extra:
                raise InputError(f"{src}: grid.{key}: unknown key(s) {extra}; known: start, stop, num, log")
            num = spec["num"]
            if type(num) is not int or not 1 <= num <= MAX_CASES:
                raise InputError(f"{src}: grid.{key}.num must be a whole number in 1-{MAX_CASES}, got {num!r}")
            ends = (spec["start"], spec["stop"])
            if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in ends):
                raise InputError(f"{src}: grid.{key}: start and stop must be finite numbers, got {ends}")
            log = spec.get("log", False)
            if not isinstance(log, bool):
                raise InputError(f"{src}: grid.{key}.log must be true or false, got {log!r}")
            if log and not min(ends) > 0:
                raise InputError(f"{src}: grid.{key}: a log grid needs start and stop > 0, got {ends}")
            f = np.geomspace if log else np.linspace
            return [float(x) for x in f(spec["start"], spec["stop"], num)]
        raise InputError(
            f"{src}: grid.{key} must be a value, a list, {{range = [a, b]}} or {{start, stop, num, log}}; got {spec!r}"
        )
    return [spec]


def _plain_name(value, what: str, src: str) -> str:
    """A study's, table's or plot's name: a single file name, so that its outputs stay inside the output folder."""
    name = str(value)
    bad = (
        not name
        or name.startswith(".")
        or os.path.isabs(name)
        or any(sep in name for sep in ("/", "\\", os.sep, "\0"))
        or not all(c.isalnum() or c in "-_." for c in name)
    )
    if bad:
        raise InputError(
            f"{src}: {what} {name!r}: must be a plain name ({_PLAIN_NAME}); it names a folder or file inside the "
            "output folder, never a path"
        )
    return name


def _unknown(keys, known: tuple, what: str, src: str) -> None:
    extra = [k for k in keys if k not in known]
    if extra:
        raise InputError(f"{src}: unknown key(s) {extra} in {what}; known: {', '.join(known)}")


def _check_data(grid: dict, src: str) -> None:
    """Types and ranges of the data keys (voxel size, SNR, seeds, venc), before anything runs."""
    for h in grid.get("h", []):
        ranges.check("voxel_size", h, f"{src}: grid.h", fix="use")
        limits.check_phantom(25.0, float(h), 1, f"{src}: grid.h")
    for snr in grid.get("snr", []):
        if snr is None or (isinstance(snr, (int, float)) and not isinstance(snr, bool) and snr == 0):
            continue  # 0: noise-free
        if isinstance(snr, bool) or not isinstance(snr, (int, float)):
            raise InputError(f"{src}: grid.snr {snr!r}: must be a number (the magnitude's signal-to-noise ratio; 0: "
                             "no noise)")  # fmt: skip
        ranges.check("snr", snr, f"{src}: grid.snr", fix="use")
    for seed in grid.get("seed", []):
        if type(seed) is not int or seed < 0:
            raise InputError(f"{src}: grid.seed {seed!r}: seeds must be whole numbers >= 0 (e.g. seed = {{range = "
                             "[0, 5]}})")  # fmt: skip
    for venc in grid.get("venc", []):
        if venc is not None:
            ranges.check("venc", venc, f"{src}: grid.venc", fix="use")


def _check_inputs(grid: dict, base_dir: str, src: str) -> None:
    """Every input file readable, a single slice (a case scores one), its ranges valid, and its truth (if any) of
    the same layout, before the first case runs."""
    seen: set = set()
    for entry in grid.get("input", []):
        if isinstance(entry, dict):
            _unknown(entry, ("file", "truth"), "an input entry", src)
            if "file" not in entry:
                raise InputError(f"{src}: input entry {entry} needs 'file'")
        elif not isinstance(entry, str):
            raise InputError(f"{src}: grid.input entries are file names or {{file, truth}}, got {entry!r}")
        key = json.dumps(entry, sort_keys=True)
        if key in seen:
            continue
        seen.add(key)
        path = os.path.join(base_dir, _input_path(entry))
        try:
            acq = wio.read_acquisition(path)
            ranges.check_acquisition(acq)
        except InputError as exc:
            raise InputError(f"{src}: grid.input: {exc}") from None
        if acq.nz > 1:
            raise InputError(
                f"{src}: grid.input: {path} has {acq.nz} slices; a study case reconstructs and scores one slice "
                "(split the stack, or run wss-nlp reconstruct on it)"
            )
        if isinstance(entry, dict) and entry.get("truth"):
            truth = os.path.join(base_dir, entry["truth"])
            try:
                n_truth = len(met.TruthTable.all_from_file(truth))
            except InputError as exc:
                raise InputError(f"{src}: grid.input truth: {exc}") from None
            except (KeyError, OSError, ValueError) as exc:
                raise InputError(f"{src}: grid.input truth {truth}: not a truth file ({exc})") from None
            if n_truth != acq.nz:
                raise InputError(
                    f"{src}: grid.input: the truth {truth} has {n_truth} slice(s) but {path} has {acq.nz}: a truth "
                    "describes its input slice by slice; pair each input with its own truth"
                )


def load_study(path) -> Study:
    """Read and check a study file; every problem is reported with the file and the key."""
    src = str(path)
    if not os.path.exists(src):
        raise InputError(f"{src}: no such study file")
    try:
        with open(src, "rb") as fh:
            doc = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{src}: not valid TOML ({exc})") from exc
    except UnicodeDecodeError:
        raise InputError(f"{src}: not a TOML study file (not UTF-8 text); see problems/README.md") from None
    except IsADirectoryError:
        raise InputError(f"{src}: is a folder; name a study file (problems/*.toml)") from None
    unknown_tables = set(doc) - {"study", "grid", "tables", "plots"}
    if unknown_tables:
        raise InputError(
            f"{src}: unknown table(s) {sorted(unknown_tables)}; expected [study], [grid], [[tables]], [[plots]]"
        )
    head = doc.get("study", {})
    if not isinstance(head, dict):
        raise InputError(f"{src}: [study] must be a table with a name")
    _unknown(head, STUDY_KEYS, "[study]", src)
    if "name" not in head:
        raise InputError(f"{src}: [study] needs a name")
    _plain_name(head["name"], "[study] name", src)
    grid_doc = doc.get("grid", {})
    if not isinstance(grid_doc, dict):
        raise InputError(f"{src}: [grid] must be a table of keys")
    unknown = [k for k in grid_doc if k not in DATA_KEYS and k not in PARAMETERS]
    if unknown:
        raise InputError(f"{src}: unknown grid key(s) {unknown}; known: {', '.join(DATA_KEYS + tuple(PARAMETERS))}")
    grid = {k: _values(k, v, src) for k, v in grid_doc.items()}
    total = int(np.prod([len(v) for v in grid.values()], dtype=float)) if grid else 0
    if total > MAX_CASES:
        raise InputError(
            f"{src}: the grid crosses to {total:.3g} cases; a study has at most {MAX_CASES} (check the ranges)"
        )
    if ("case" in grid) == ("input" in grid):
        raise InputError(f"{src}: the grid needs exactly one of 'case' (phantoms) and 'input' (files)")
    if "input" in grid:
        extra = [k for k in ("h", "snr", "seed", "venc") if k in grid]
        if extra:
            raise InputError(f"{src}: {extra} describe phantoms and cannot be combined with 'input'")
    else:
        bad = [c for c in grid["case"] if c not in phantoms.CASES]
        if bad:
            raise InputError(f"{src}: unknown phantom case(s) {bad}; choose from {', '.join(phantoms.CASES)}")
        grid.setdefault("h", [1.0])
        grid.setdefault("snr", [25.0])
        grid.setdefault("seed", [0])
        _check_data(grid, src)
    bad = [m for m in grid.get("method", []) if m not in METHODS]
    if bad:
        raise InputError(f"{src}: unknown method(s) {bad}; choose from {', '.join(METHODS)}")
    metrics = head.get("metrics", list(METRICS))
    if isinstance(metrics, str) or not isinstance(metrics, list):
        raise InputError(f"{src}: [study] metrics must be a list of metric names, got {metrics!r}")
    names = tuple(metrics)
    bad = [m for m in names if m not in METRICS]
    if bad:
        raise InputError(f"{src}: unknown metric(s) {bad}; known: {', '.join(METRICS)}")
    for what, specs, known in (("[[tables]]", doc.get("tables", []), TABLE_KEYS),
                               ("[[plots]]", doc.get("plots", []), PLOT_KEYS)):  # fmt: skip
        if not isinstance(specs, list) or not all(isinstance(v, dict) for v in specs):
            raise InputError(f"{src}: {what} must be an array of tables ([[{what.strip('[]')}]] entries)")
        for spec in specs:
            _unknown(spec, known, what, src)
            if "name" in spec:
                _plain_name(spec["name"], f"{what} name", src)
    study = Study(
        name=str(head["name"]),
        description=str(head.get("description", "")),
        grid=grid,
        metrics=names,
        tables=tuple(doc.get("tables", ())),
        plots=tuple(doc.get("plots", ())),
        source=src,
        base_dir=os.path.dirname(os.path.abspath(src)),
    )
    for spec in study.tables + study.plots:
        _check_view(study, spec)
    if "input" in grid:
        _check_inputs(grid, study.base_dir, src)
    checked: set = set()
    for params in expand(study):  # fail now, not after an hour of computing, on options that cannot be built
        key = json.dumps({k: v for k, v in params.items() if k not in DATA_KEYS}, sort_keys=True, default=str)
        if key not in checked:  # the options depend on the option keys alone
            checked.add(key)
            options_for(params, src)
    return study


def _check_view(study: Study, spec: dict) -> None:
    keys = set(study.grid) | {"seed"}
    for role in ("rows", "cols", "x", "by"):
        if role in spec and spec[role] not in keys and spec[role] != "metric":
            raise InputError(f"{study.source}: table/plot {role} = {spec[role]!r} is not a grid key")
    metric = spec.get("metric", spec.get("y"))
    if metric is None or metric not in METRICS:
        raise InputError(f"{study.source}: table/plot needs 'metric' (or 'y') from {', '.join(METRICS)}")


def expand(study: Study) -> list[dict]:
    """The cases of the grid: the cross product of all lists, in the order the keys appear."""
    keys = list(study.grid)
    cases: list[dict] = [{}]
    for k in keys:
        cases = [{**c, k: v} for c in cases for v in study.grid[k]]
    return cases


def case_id(params: dict) -> str:
    """A readable, stable identifier: the data keys, then a hash of every parameter."""
    digest = hashlib.sha1(json.dumps(params, sort_keys=True, default=str).encode()).hexdigest()[:10]
    if "case" in params:
        head = f"{params['case']}_h{params['h']:g}_snr{params['snr']:g}_s{params['seed']}"
    else:
        head = os.path.splitext(os.path.basename(_input_path(params["input"])))[0]
    return f"{head}_{params.get('method', 'decoupled')}_{digest}"


def _input_path(entry) -> str:
    return entry["file"] if isinstance(entry, dict) else str(entry)


def options_for(params: dict, where: str = "") -> ReconstructionOptions:
    """ReconstructionOptions for one case (defaults for everything the case does not set)."""
    keys = {k: v for k, v in params.items() if k not in DATA_KEYS}
    if "M" in keys:
        keys["max_eigenvalue" if params.get("basis") == "eigen" else "degree"] = keys.pop("M")
    try:
        return schema.build(ReconstructionOptions, keys, where, check=limits.check_values)
    except InputError as exc:
        raise InputError(f"{where}: {exc} (case {params})") from exc


# ------------------------------------------------------------------ one case
def _acquisition(params: dict, base_dir: str):
    if "case" in params:
        return phantoms.make_phantom(
            params["case"],
            h_mm=float(params["h"]),
            snr=None if params["snr"] in (None, 0) else float(params["snr"]),
            seed=int(params["seed"]),
            venc=params.get("venc"),
        )
    entry = params["input"]
    path = os.path.join(base_dir, _input_path(entry))
    truth = None
    if isinstance(entry, dict) and entry.get("truth"):
        truth = met.TruthTable.from_file(os.path.join(base_dir, entry["truth"]))
    return wio.read_acquisition(path), truth


AGGREGATES: dict[str, Any] = {"mean": np.mean, "median": np.median, "max": np.max, "min": np.min}
