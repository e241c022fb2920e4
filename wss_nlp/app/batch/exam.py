"""One exam of a batch, where a worker runs it: import, reconstruct, export, figures, written to ``DIR/<id>/`` whole.

:func:`run_exam` is the unit of work the executor (:mod:`wss_nlp.app.executor`) sends to a worker. It builds
the exam's folder in ``DIR/.staging`` and moves it to ``DIR/<id>`` in one rename only when it is complete
(:func:`commit`), so an interrupted run (Ctrl-C, a killed process, a lost worker) never leaves half an exam
under its name. The folder holds:

* ``exam.json``: the record (status, the one-line error of a failure, the metrics of the summary, every flag and
  warning, the options, the input's digest and the key a later run compares, seconds, the software version);
* ``result.h5`` (the result format; a cine's time-resolved layout), ``wall.vtu`` (VTK, unless turned off),
  ``input.h5`` (the imported input, for scanner files), ``thumbnail.png`` (the WSS figure, small, for the
  cohort report), ``figures/`` (every figure, when asked), ``exam.log`` (the library's log of this exam).

A failure is a record too (``status`` ``failed``): ``failure`` is ``input`` when the exam's data or options are
at fault (:class:`~wss_nlp.errors.WssNlpError`: the same input fails the same way, so a later run keeps the
record), ``crash`` otherwise (an internal error, a lost worker: run again next time).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
import traceback
import uuid
from dataclasses import dataclass

import numpy as np

from ... import __version__
from ...core import radius as rad
from ...errors import WssNlpError
from ...io import files as wio
from .manifest import Exam

#: The staging folder below the output folder: exams being built.
STAGING = ".staging"
#: Short forms of flags in summary.csv (the record and the report keep the whole text).
FLAG_CHARS = 140


@dataclass(frozen=True)
class ExamTask:
    """What a worker needs for one exam: the exam, where to write, its key and the outputs asked for."""

    exam: Exam
    outdir: str  # absolute
    key: str
    input_sha256: str
    input_stat: list
    figures: bool = False
    vtk: bool = True


def run_exam(task: ExamTask) -> dict:
    """Run one exam into ``DIR/<id>/`` (module notes) and return its record; never raises for the exam's own
    failures (they are its record)."""
    exam = task.exam
    t0 = time.perf_counter()
    staging = os.path.join(task.outdir, STAGING)
    os.makedirs(staging, exist_ok=True)
    stage = tempfile.mkdtemp(prefix=f"{exam.id}.", dir=staging)
    os.chmod(stage, 0o777 & ~_umask())  # mkdtemp's 0700 would make the exam's folder private
    record = _record(task, "ok", "", "")
    logger = logging.getLogger("wss_nlp")
    handler = logging.FileHandler(os.path.join(stage, "exam.log"), encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        record.update(_reconstruct(task, stage))
    except WssNlpError as exc:
        record.update(status="failed", error=_one_line(exc), failure="input")
        logger.error("%s: failed: %s", exam.id, _one_line(exc))
    except Exception as exc:  # a bug or the machine: the exam fails, the batch goes on, and a rerun tries again
        record.update(status="failed", error=f"internal error: {type(exc).__name__}: {_one_line(exc)}", failure="crash")
        logger.error("%s: internal error\n%s", exam.id, traceback.format_exc())
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        handler.close()
    if record["status"] != "ok":  # a failed exam keeps its record and log only: nothing half-made
        for name in os.listdir(stage):
            if name != "exam.log":
                path = os.path.join(stage, name)
                shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)
        record.setdefault("metrics", {})
        record.setdefault("flags", [])
        record.setdefault("warnings", [])
    record["seconds"] = time.perf_counter() - t0
    record["files"] = sorted(os.listdir(stage)) + ["exam.json"]
    with open(os.path.join(stage, "exam.json"), "w") as fh:
        json.dump(record, fh, indent=1, default=_json_default)
    commit(stage, os.path.join(task.outdir, exam.id))
    return record


def commit(stage: str, final: str) -> None:
    """Move the complete folder ``stage`` to ``final`` (replacing an older one): each step one rename, so that
    ``final`` is at any moment the old exam, the new one, or absent, never a mixture."""
    for _ in range(5):  # another process (a worker orphaned by a killed run) may commit the same exam meanwhile
        old = None
        if os.path.exists(final):
            old = f"{final}.old-{uuid.uuid4().hex[:8]}"
            try:
                os.rename(final, old)
            except FileNotFoundError:
                old = None
        try:
            os.rename(stage, final)
        except OSError:
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
            continue
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return
    raise OSError(f"{final}: could not move the finished exam into place")


def _record(task: ExamTask, status: str, error: str, failure: str) -> dict:
    """The part of an exam's record that says which exam, input, options and version it is, and how it ended."""
    exam = task.exam
    return {
        "id": exam.id,
        "status": status,
        "error": error,
        "failure": failure,
        "input": exam.input_text,
        "inputs": list(exam.inputs),
        "columns": dict(exam.columns),
        "key": task.key,
        "input_sha256": task.input_sha256,
        "input_stat": task.input_stat,
        "options": exam.options.as_dict(),
        "wss_nlp_version": __version__,
    }


def failed_record(task: ExamTask, error: str) -> dict:
    """The record of an exam whose worker was lost (``failure`` ``crash``: a later run tries it again)."""
    return {
        **_record(task, "failed", error, "crash"),
        "metrics": {},
        "flags": [],
        "warnings": [],
        "seconds": float("nan"),
    }


# ---------------------------------------------------------------- the exam's steps
def _reconstruct(task: ExamTask, stage: str) -> dict:
    """Import (where needed), reconstruct, write, export and draw one exam into ``stage``; its record's part."""
    exam = task.exam
    final = os.path.join(task.outdir, exam.id)
    argv = ["wss-nlp", "batch", exam.id]
    if exam.imports is not None:
        from ...io import importing, scanner

        imp = importing.import_paths(list(exam.inputs), **exam.imports.settings)
        scanner.write_import(os.path.join(stage, "input.h5"), imp, argv=[*argv, "import", *exam.imports.argv])
        path, shown = os.path.join(stage, "input.h5"), os.path.join(final, "input.h5")
    else:
        path = shown = exam.inputs[0]
    result_path = os.path.join(stage, "result.h5")
    options = exam.options
    if _time_resolved(path):
        out = _cine(path, shown, options, result_path, argv, stage, task.figures)
    else:
        out = _slices(path, shown, options, result_path, argv, stage, task.figures)
    if task.vtk:
        from ...io import export

        export.write_vtk(result_path, os.path.join(stage, "wall.vtu"))
    return out


def _time_resolved(path: str) -> bool:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "trigger_times_ms" in f.attrs
    except OSError:
        return False  # the reader names the problem


def _slices(path, shown, options, result_path, argv, stage, figures) -> dict:
    from ...pipeline.driver import reconstruct
    from ...pipeline.results import SliceResult
    from .. import plotting

    acq = wio.read_acquisition(path)
    acq.source = shown
    results = reconstruct(acq, options)
    extra = {} if acq.slice_spacing_mm is None else {"slice_spacing_mm": float(acq.slice_spacing_mm)}
    import h5py

    with h5py.File(path, "r") as f:  # the import record: wall.vtu in the scanner's world frame (io.export)
        if "import_json" in f.attrs:
            extra["import_json"] = f.attrs["import_json"]
    wio.write_result(result_path, results, options.as_dict(), argv=argv, extra_attrs=extra)
    ok = [r for r in results if not isinstance(r, wio.FailedSlice)]
    failed = [r for r in results if isinstance(r, wio.FailedSlice)]
    if len(results) == 1:
        thumb = plotting.figure_wss(ok[0])
    else:
        thumb = plotting.figure_stack(results, acq.slice_spacing_mm or 1.0)
    plotting.save_figure(thumb, os.path.join(stage, "thumbnail.png"), dpi=THUMBNAIL_DPI)
    if figures:
        folder = os.path.join(stage, "figures")
        for r in ok:
            plotting.save_figures(r, folder, prefix=f"slice_{r.index:03d}_")
        if len(results) > 1:
            plotting.save_figure(thumb, os.path.join(folder, "stack_wall_maps.png"))
    tau = np.concatenate([r.wss.tau for r in ok])
    radius = np.concatenate([r.geometry.radius(r.wss.phi) for r in ok])
    dradius = np.concatenate([rad.evaluate(r.geometry.coefficients, r.wss.phi, 1) for r in ok])
    warnings = [w for r in results for w in r.warnings]
    not_converged = [r.index for r in ok if not r.converged]
    flags = [f"slice {r.index} failed: {r.reason}" for r in failed]
    flags += [f"slice {k} did not converge" for k in not_converged]
    flags += [w for w in warnings if "SUSPECT" in w]
    if results.stack is not None and not results.stack.converged:
        flags.append("stack: the z-coupled solve did not converge")
    models = sorted({r.near_wall.model for r in ok if isinstance(r, SliceResult) and r.near_wall is not None})
    betas = [r.velocity.beta for r in ok if isinstance(r, SliceResult)]
    metrics = {
        "kind": "slice" if len(results) == 1 else "stack",
        "n_slices": len(results),
        "n_frames": 1,
        "failed_slices": len(failed),
        "mean_wss_pa": rad.arc_length_mean(tau, radius, dradius),
        "tawss_pa": float("nan"),
        "osi_mean": float("nan"),
        "osi_max": float("nan"),
        "radius_mm": float(np.mean([r.geometry.coefficients[0] for r in ok])),
        "alpha": float(np.median([r.geometry.alpha for r in ok])),
        "beta": float(np.median(betas)) if betas else float("nan"),
        "near_wall": "/".join(models),
        "method": options.method,
        "solver_status": _status(not_converged, results.stack),
    }
    return {"metrics": metrics, "flags": flags, "warnings": warnings}


def _cine(path, shown, options, result_path, argv, stage, figures) -> dict:
    from ...pipeline import cine
    from .. import plotting

    frames, times, period = wio.read_frames(path)
    for k, frame in enumerate(frames):
        frame.source = f"{shown} (frame {k})"
    result = cine.reconstruct_cine(frames, times, period, options)
    series = cine.write_result(result_path, result, options.as_dict(), argv=argv)
    usable = [s for s in series if not s.failed.all()]
    plotting.save_figure(
        plotting.figure_cine(usable[0], times), os.path.join(stage, "thumbnail.png"), dpi=THUMBNAIL_DPI
    )
    if figures:
        plotting.save_cine_figures(series, result, os.path.join(stage, "figures"))
    phi = usable[0].phi
    tawss, osi, radius, dradius, means, weights = [], [], [], [], [], []
    for s in usable:
        wall = np.nanmean(s.coefficients, axis=0)  # the wall over the cycle: its frames' mean
        r, dr = rad.evaluate(wall, phi), rad.evaluate(wall, phi, 1)
        radius.append(r)
        dradius.append(dr)
        tawss.append(s.tawss)
        osi.append(s.osi)
        means.append(s.time_average_mean)
        weights.append(np.sum(np.sqrt(r**2 + dr**2)))  # the slice's perimeter, up to the factor 2 pi / n_phi
    radius_all, dradius_all = np.concatenate(radius), np.concatenate(dradius)
    warnings = [f"frame {k}: {w}" for k, frame in enumerate(result.frames) for r in frame for w in r.warnings]
    warnings += [f"slice {s.index}: {n}" for s in series for n in s.notes]
    not_converged = sorted({r.index for frame in result.frames for r in frame if not r.converged})
    flags = [f"slice {s.index}: every frame failed" for s in series if s.failed.all()]
    flags += [f"slice {s.index}: frames {np.nonzero(s.failed)[0].tolist()} failed" for s in usable if s.failed.any()]
    flags += [f"slice {k} did not converge in every frame" for k in not_converged]
    flags += [w for w in warnings if "SUSPECT" in w]
    metrics = {
        "kind": "cine" if len(series) == 1 else "cine stack",
        "n_slices": len(series),
        "n_frames": len(frames),
        "failed_slices": len(series) - len(usable),
        "mean_wss_pa": float(np.sum(np.multiply(means, weights)) / np.sum(weights)),
        "tawss_pa": rad.arc_length_mean(np.concatenate(tawss), radius_all, dradius_all),
        "osi_mean": rad.arc_length_mean(np.concatenate(osi), radius_all, dradius_all),
        "osi_max": float(np.max(np.concatenate(osi))),
        "radius_mm": float(np.nanmean(np.concatenate([s.coefficients[:, 0] for s in usable]))),
        "alpha": float(np.nanmedian(np.concatenate([s.alpha for s in usable]))),
        "beta": float(np.nanmedian(np.concatenate([s.beta for s in usable]))),
        "near_wall": "",
        "method": options.method,
        "solver_status": _status(not_converged, None),
    }
    models = sorted({s.model.model for s in usable if s.model is not None})
    metrics["cycle_model"] = "/".join(models)
    return {"metrics": metrics, "flags": flags, "warnings": warnings}


#: Resolution of the thumbnails in the cohort report (the figures are 8 x 4 inches or wider).
THUMBNAIL_DPI = 40


def _status(not_converged: list, stack) -> str:
    if stack is not None and not stack.converged:
        return "stack not converged"
    if not_converged:
        return f"not converged (slices {', '.join(map(str, not_converged))})"
    return "converged"


def short_flag(text: str) -> str:
    """A flag's first clause, at most :data:`FLAG_CHARS` characters (summary.csv; the record keeps it whole)."""
    for stop in ("; ", " ("):
        if stop in text:
            text = text.split(stop)[0]
    return text if len(text) <= FLAG_CHARS else text[: FLAG_CHARS - 3] + "..."


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def _json_default(x):
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return str(x)
