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
    """A grid entry: a scalar, a list, ``{range = [a, b]}`` (integers, b excluded) or ``{start, stop, num, log}``."""
    if isinstance(spec, list):
        if not spec:
            raise InputError(f"{src}: grid.{key} is an empty list")
        return spec
    if isinstance(spec, dict):
        if "range" in spec:
            r = spec["range"]
            if not (isinstance(r, list) and len(r) in (2, 3) and all(isinstance(x, int) for x in r)):
                raise InputError(f"{src}: grid.{key}.range must be [start, stop] or [start, stop, step] integers")
            return list(range(*r))
        if {"start", "stop", "num"} <= set(spec):
            f = np.geomspace if spec.get("log", False) else np.linspace
            return [float(x) for x in f(spec["start"], spec["stop"], int(spec["num"]))]
        raise InputError(
            f"{src}: grid.{key} must be a value, a list, {{range = [a, b]}} or {{start, stop, num, log}}; got {spec!r}"
        )
    return [spec]


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
    if "name" not in head:
        raise InputError(f"{src}: [study] needs a name")
    grid_doc = doc.get("grid", {})
    unknown = [k for k in grid_doc if k not in DATA_KEYS and k not in PARAMETERS]
    if unknown:
        raise InputError(f"{src}: unknown grid key(s) {unknown}; known: {', '.join(DATA_KEYS + tuple(PARAMETERS))}")
    grid = {k: _values(k, v, src) for k, v in grid_doc.items()}
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
    bad = [m for m in grid.get("method", []) if m not in METHODS]
    if bad:
        raise InputError(f"{src}: unknown method(s) {bad}; choose from {', '.join(METHODS)}")
    names = tuple(head.get("metrics", METRICS))
    bad = [m for m in names if m not in METRICS]
    if bad:
        raise InputError(f"{src}: unknown metric(s) {bad}; known: {', '.join(METRICS)}")
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
    for params in expand(study):  # fail now, not after an hour of computing, on options that cannot be built
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
        return schema.build(ReconstructionOptions, keys, where)
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
