"""The reconstruction of one acquisition: every segment of slices through one sequence of steps.

:func:`reconstruct` screens the acquisition (:mod:`wss_nlp.pipeline.plausibility`), resolves the measurement
model (box or k-space), preprocesses every slice (:func:`wss_nlp.pipeline.steps.prepare`) and takes each
*segment* through the steps of :func:`run_segment`:

1. geometry and alpha (Sec. 2),
2. the near-wall model, beta and the velocity fit (Sec. 3),
3. the dephasing passes: the signal loss the velocity predicts, and geometry and velocity again on the
   corrected images while that changes the wall (one pass with voxel means, up to :data:`KSPACE_PASSES` with
   the k-space model; a pass that explains the magnitude worse is undone),
4. the coupled NLP (``--method coupled``),
5. the WSS (Sec. 4), its vector from in-plane components where the data have them (4D flow),
6. the uncertainty band (now, or deferred to :meth:`SliceResult.finish_band`),
7. the results, with what screening and the consistency check found.

A segment is one slice, or a run of consecutive slices of a stack tied along z; its
:class:`~wss_nlp.pipeline.fitters.Fitter` (:class:`~wss_nlp.pipeline.fitters.Independent` or
:class:`~wss_nlp.pipeline.fitters.ZCoupled`) solves the steps that couple slices. Cine frames are
acquisitions of their own, run by :mod:`wss_nlp.pipeline.cine` through :func:`reconstruct`. The classical
baselines (:mod:`wss_nlp.models.baselines`) are fits of their own, slice by slice (:mod:`wss_nlp.pipeline.methods`).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import time

import numpy as np

from ..core import radius as rad
from ..core.solver import report_progress, solve_progress
from ..errors import InputError, WssNlpError
from ..io import ranges
from ..io.files import Acquisition, FailedSlice
from ..models import acquisition as acq_model
from ..models import dephasing as deph
from ..models import geometry as geo
from ..models import kspace
from ..models import near_wall as nw
from ..models import stack as stk
from ..models import steady
from ..models import wss as wss_mod
from ..parameters.kspace_filter import kspace_filter
from . import limits, methods, obliquity
from . import plausibility as plaus
from . import steps
from .fitters import Band, Fitter, Independent, ZCoupled, wss_vectors
from .options import ReconstructionOptions
from .results import SliceResult, make_result
from .state import SliceState

#: Largest number of dephasing passes with the k-space model, and the wall movement (in voxels) that ends them.
KSPACE_PASSES, KSPACE_PASS_TOL = 3, 1e-3
#: Skip a pass predicted to move the wall less than KSPACE_PASS_TOL (False: run it; ``scripts/kspace_passes.py``).
KSPACE_PASS_PREDICTION = True


class Results(list):
    """The per-slice results of :func:`reconstruct`, with ``stack`` (a :class:`wss_nlp.models.stack.StackInfo`
    or None) and ``psf`` (the acquisition model used, resolved: a :class:`wss_nlp.models.kspace.PSF`, or None
    for the box)."""

    stack: stk.StackInfo | None = None
    psf: kspace.PSF | None = None


def stack_applies(acq: Acquisition, options: ReconstructionOptions) -> bool:
    """Whether the slices of a stack are tied along z (else each slice is a segment of its own).

    The z-penalty needs a velocity model on every slice: the classical baselines fit each slice alone.
    """
    ell = options.stack.z_smoothing_mm
    if acq.nz == 1 or ell == 0:
        return False
    supported = methods.of(options).ties_slices
    if ell is not None and not supported:
        raise InputError(
            f"{acq.source}: z-regularization (--z-smoothing {ell:g}) supports the decoupled and coupled methods "
            f"(not {options.method!r}); pass --z-smoothing 0 for independent slices"
        )
    return supported


def blas_threads(n: int):
    """A context limiting the BLAS to ``n`` threads (threadpoolctl); ``n = 0`` changes nothing."""
    if n == 0:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency; tolerate its absence
        return contextlib.nullcontext()
    # threadpoolctl limits only the libraries already loaded: SciPy ships its own OpenBLAS, loaded on the
    # first import of scipy.linalg, which would otherwise run the first solve of a process unlimited (and
    # with other rounding than every later one)
    import scipy.linalg  # noqa: F401

    return threadpool_limits(limits=n, user_api="blas")


#: How the independent segments of a reconstruction are mapped (None: one after the other); see segments_in_parallel.
_SEGMENT_MAP: contextvars.ContextVar = contextvars.ContextVar("wss_nlp_segment_map", default=None)


@contextlib.contextmanager
def segments_in_parallel(map_in_order):
    """A context in which every reconstruction solves its independent segments through ``map_in_order``.

    ``map_in_order(fn, items)`` returns ``fn(item)`` for every item in the items' order, running them where it
    likes (``wss_nlp.app.executor.Executor.map``: worker processes or a Dask cluster); ``fn`` and the items are
    picklable. Only slices each a segment of their own are mapped (independent slices, the classical baselines'
    fits excepted): segments tied along z keep one fitter across the stack, and deferred bands hold closures,
    so those run in the loop as before. A slice is solved by the same steps either way, so the results are the
    serial ones, bit for bit.
    """
    token = _SEGMENT_MAP.set(map_in_order)
    try:
        yield
    finally:
        _SEGMENT_MAP.reset(token)


def reconstruct(
    acq: Acquisition,
    options: ReconstructionOptions | None = None,
    progress=None,
    boxes: dict | None = None,
    defer_band: bool = False,
) -> Results:
    """Reconstruct every slice of an acquisition.

    A stack (``nz > 1``) is tied along z (:class:`~wss_nlp.pipeline.fitters.ZCoupled`) unless
    ``options.stack.z_smoothing_mm == 0`` or the method is a classical baseline; each run of consecutive
    usable slices is then one segment (a single usable slice is a segment of its own, solved as a slice). In
    a stack a slice that cannot be reconstructed (NaN or Inf, no vessel, solver failure) becomes a
    :class:`wss_nlp.io.files.FailedSlice` and the others are still solved; a single slice raises instead.

    Returns :class:`SliceResult` objects, or :class:`wss_nlp.models.baselines.BaselineResult` for the
    classical methods (``options.method`` "oyre" or "stalder").

    Parameters
    ----------
    progress : callable or None
        Called as ``progress(done, total, slice_result)`` after each slice. If it has a ``stage`` attribute,
        ``progress.stage(text)`` is called while a z-tied segment is solved, as the joint solve advances (its
        stages, IPOPT iterations and sweeps, each text naming the segment's slices): the slices of a segment
        are done together at its end.
    boxes : dict or None
        Slice index -> :class:`wss_nlp.models.preprocess.LumenBox` replacing that slice's own origin and
        radius box (cine frames: the frames of a slice share one, with its built solvers and a warm start).
    defer_band : bool
        Leave each slice's uncertainty band to :meth:`SliceResult.finish_band` (cine: only the model the series
        keeps needs one). The slices of a z-tied segment share one band computation.

    Notes
    -----
    Long stack solves report their stages to the ``wss_nlp.models.stack`` logger (INFO); the command line shows
    them on stderr.
    """
    options = options or ReconstructionOptions()
    with blas_threads(options.blas_threads):
        return _reconstruct(acq, options, progress, boxes or {}, defer_band)


def reconstruct_stack(acq: Acquisition, options: ReconstructionOptions, stack=None, progress=None):
    """Every slice of a stack with the z-coupled solvers of :class:`~wss_nlp.pipeline.fitters.ZCoupled`, whatever
    the smoothing length (``l = 0``: zero weights, the same optimum as independent slices, reached by the stack's
    solvers) and segment length (a segment of one slice too): for studies of the solvers themselves.

    Returns ``(results, info)``: ``results[k]`` is slice k's :class:`SliceResult`, or None where it failed
    (``info.failed[k]`` says why), and ``info`` the :class:`wss_nlp.models.stack.StackInfo`.
    """
    from dataclasses import replace

    options = replace(options, stack=stack or options.stack)
    if not methods.of(options).ties_slices:
        raise InputError(
            f"{acq.source}: the stack's solvers need the decoupled or coupled method, not {options.method!r}"
        )
    with blas_threads(options.blas_threads):
        out = _reconstruct(acq, options, progress, {}, False, tie=True)
    return [r if isinstance(r, SliceResult) else None for r in out], out.stack


def _reconstruct(
    acq: Acquisition, options: ReconstructionOptions, progress, boxes: dict, defer_band: bool, tie: bool = False
) -> Results:
    acq.validate()
    range_notes = _range_notes(acq, options)
    mu = acq.viscosity(options.viscosity_pa_s)
    density = acq.density(options.density_kg_m3)
    acq, screens = plaus.screen(acq, options.screen)
    lumen = max((f.record.get("lumen_voxels", 0) for f in screens.values()), default=None) or None
    radius = max((f.record.get("lumen_radius_mm", 0.0) for f in screens.values()), default=0.0)
    if radius:  # the lumen as read rules out length slips that would make it wider than any vessel
        range_notes = _range_notes(acq, options, radius)
    limits.check_cost(options, acq.magnitude.shape, acq.source, lumen, min(acq.nz, stk.COUPLED_MAX_SLICES))
    psf = options.acquisition.psf(acq.voxel_size_mm, acq.acquired_voxel_size_mm, f"{acq.source}: ")
    if psf is not None and psf.filter == "auto":
        psf = kspace_filter(acq.magnitude, acq.grid, psf, options.geometry, options.screen.vessel, f"{acq.source}: ")
    out = Results()
    out.psf = psf
    method = methods.of(options)
    tied = tie or stack_applies(acq, options)  # first: refuses z-regularization asked of a method without it
    if isinstance(method, methods.Baseline):
        out.extend(method.reconstruct(acq, mu, options, progress))
        return _with_screens(out, screens, acq, psf, range_notes)
    results: list = [None] * acq.nz
    t0 = time.perf_counter()
    prepared, failed = _prepare(acq, options, psf, boxes)
    seconds_prepare = time.perf_counter() - t0
    if not prepared:
        reasons = "; ".join(f"{k}: {v}" for k, v in failed.items())
        raise InputError(f"{acq.source}: no usable slice: {reasons}")
    for k, why in failed.items():
        results[k] = FailedSlice(k, why, options.n_phi, options.geometry.n_fourier)
    info: stk.StackInfo | None = None
    if tied:
        r_ref = float(np.mean([d.lumen.r_area for d in prepared.values()]))
        segments = stk.segments_of(sorted(prepared))
        info = stk.StackInfo("", 0.0, 0.0, 0.0, segments, dict(failed))
        dz = float(acq.slice_spacing_mm or 1.0)  # validate() requires it for nz > 1
        zc = ZCoupled(options, mu, density, acq.grid, dz, r_ref, info)
        ell = options.stack.z_smoothing_mm
        info.z_smoothing_mm = dz if ell is None else float(ell)
        info.kappa, info.kappa_velocity = zc.kappa, zc.kappa_v
    else:
        segments = [[k] for k in sorted(prepared)]
    independent = Independent(options, mu, density)
    dz = float(acq.slice_spacing_mm or 1.0)
    first_of = {seg[0]: seg for seg in segments}
    mapper = _SEGMENT_MAP.get()
    ahead = None  # independent slices solved elsewhere, in slice order (segments_in_parallel)
    if mapper is not None and not tied and not defer_band and len(segments) > 1:
        alone = functools.partial(solve_alone, options=options, mu=mu, density=density, dz=dz)
        ahead = iter(mapper(alone, [prepared[seg[0]] for seg in segments]))
    done = 0
    for iz in range(acq.nz):  # in slice order, each segment when its first slice comes
        if iz in failed:
            seg, seg_results = [iz], [results[iz]]
        elif iz in first_of:
            seg = first_of[iz]
            fitter: Fitter = zc if tied and (len(seg) > 1 or tie) else independent
            try:
                if ahead is not None:
                    seg_results = _raised(next(ahead))
                else:
                    with solve_progress(_stage_report(progress, seg, fitter)):
                        seg_results = run_segment([prepared[k] for k in seg], fitter, options, mu, dz, defer_band)
            except WssNlpError as exc:
                if acq.nz == 1:
                    raise
                seg_results = [FailedSlice(k, str(exc), options.n_phi, options.geometry.n_fourier) for k in seg]
                if info is not None:
                    info.failed.update({k: str(exc) for k in seg})
        else:
            continue
        for k, res in zip(seg, seg_results):
            results[k] = res
            if isinstance(res, SliceResult) and not defer_band:
                res.problem = None  # about a megabyte a slice; kept only where a deferred band holds it anyway
            done += 1
            if progress is not None:
                progress(done, acq.nz, res)
    if info is not None:
        if not info.converged:
            for r in results:
                if isinstance(r, SliceResult):
                    r.notes.append(
                        "stack: Kaczmarz sweeps stopped before the coupled optimality residual reached "
                        f"{options.stack.tol:g}"
                    )
        info.seconds = {"preprocess": seconds_prepare, **zc.seconds}
        out.stack = info
    out.extend(results)
    if all(isinstance(r, FailedSlice) for r in out):
        raise WssNlpError(f"{acq.source}: no slice could be reconstructed: " + "; ".join(r.reason for r in out))
    return _with_screens(out, screens, acq, psf, range_notes)


def _stage_report(progress, seg: list[int], fitter: Fitter):
    """What a z-tied segment's solve reports as it advances (:func:`wss_nlp.core.solver.solve_progress`):
    ``progress.stage("slices a-b: <text>")``, where the progress callback has a ``stage``; None otherwise."""
    stage = getattr(progress, "stage", None)
    if stage is None or not isinstance(fitter, ZCoupled):
        return None
    name = f"slices {seg[0]}-{seg[-1]}" if len(seg) > 1 else f"slice {seg[0]}"
    return lambda text: stage(f"{name}: {text}")


def _range_notes(acq: Acquisition, options: ReconstructionOptions, radius_mm: float | None = None) -> list[str]:
    """The plausibility ranges of the file's fields and of the physical options (:mod:`wss_nlp.io.ranges`): a value
    outside its range is refused (unless allowed); the notes say which reading was taken where a unit slip cannot
    be told from a real value, and what was allowed."""
    allow = options.screen.allow_unphysical
    notes = ranges.check_acquisition(
        acq,
        allow,
        viscosity_given=options.viscosity_pa_s is not None,
        density_given=options.density_kg_m3 is not None,
        radius_mm=radius_mm,
    )
    for name, value, flag in (("viscosity", options.viscosity_pa_s, "--viscosity"),
                              ("density", options.density_kg_m3, "--density")):  # fmt: skip
        if value is not None and (note := ranges.check(name, value, flag, allow)) and note not in notes:
            notes.append(note)
    return notes


def solve_alone(data: steps.SliceData, options: ReconstructionOptions, mu: float, density, dz: float):
    """One slice as a segment of its own (:func:`run_segment` with an :class:`Independent` fitter), where a worker
    of :func:`segments_in_parallel` runs it; a :class:`~wss_nlp.errors.WssNlpError` is returned, not raised, so
    that the driver fails this slice as its own loop would."""
    with blas_threads(options.blas_threads):
        try:
            out = run_segment([data], Independent(options, mu, density), options, mu, dz)
        except WssNlpError as exc:
            return exc
    for r in out:
        r.problem = None  # the driver drops it too; here it would also travel back
    return out


def _raised(got):
    if isinstance(got, WssNlpError):
        raise got
    return got


def _prepare(acq: Acquisition, options: ReconstructionOptions, psf, boxes: dict):
    """``(prepared, failed)``: each usable slice's :class:`~wss_nlp.pipeline.steps.SliceData`, and why the others
    are not (a single slice raises instead)."""
    velocity = acq.velocity_images()
    bad = set(acq.nonfinite_slices())  # any image of the slice, in-plane velocity components included
    prepared: dict = {}
    failed: dict = {}
    for iz in range(acq.nz):
        t0 = time.perf_counter()
        try:
            if iz in bad:
                raise InputError(f"{acq.source} slice {iz}: the images contain NaN or Inf")
            prepared[iz] = steps.prepare(
                acq.magnitude[iz], velocity[iz], acq.grid, iz, acq.source, options.screen.vessel, psf,
                acq.venc_m_s, acq.noise_venc_m_s, boxes.get(iz),
                None if acq.velocity_inplane is None else acq.velocity_inplane[:, iz], options.tissue,
            )  # fmt: skip
            prepared[iz].seconds = time.perf_counter() - t0
        except WssNlpError as exc:
            if acq.nz == 1:
                raise
            failed[iz] = str(exc)
    return prepared, failed


def run_segment(
    slices: list[steps.SliceData],
    fitter: Fitter,
    options: ReconstructionOptions,
    mu: float,
    dz: float = 1.0,
    defer_band: bool = False,
) -> list[SliceResult]:
    """The steps of the module notes on one segment (one slice, or consecutive slices of a stack ``dz`` mm apart).

    A slice's data may carry a lumen box with a warm start (cine frames), used by a segment of one slice.
    """
    states = [SliceState.start(d) for d in slices]
    first, last = slices[0].index, slices[-1].index
    if isinstance(fitter, ZCoupled):
        fitter.start(len(slices))
        stk.logger.info(f"slices {first}-{last}: {fitter.strategy} solve of {len(slices)} slice(s)")
    report_progress("geometry")  # each stage as it starts; the solves report their iterations within it
    fitter.geometry(states, slices[0].start if len(slices) == 1 else None)
    report_progress("velocity")
    fitter.velocity(states)
    _dephasing_passes(states, fitter, options, slices[0].venc)

    t0 = time.perf_counter()
    if options.method == "coupled":
        report_progress("coupled geometry+velocity")
    coupled_results, coupled_info = methods.of(options).refine(states, fitter)
    if coupled_results is not None:
        _add_time(states, fitter, "coupled", t0)

    walls = []
    for s in states:
        t0 = time.perf_counter()
        w = wss_mod.from_reconstruction(s.velocity, options.n_phi, mu)
        s.seconds["wss"] = time.perf_counter() - t0
        if not np.all(np.isfinite(w.tau)):
            raise WssNlpError(f"{s.data.where}: wall shear stress is not finite; the reconstruction is unusable")
        walls.append(w)
    inplane = [s.data.inplane for s in states]
    if all(u is not None for u in inplane):
        t0 = time.perf_counter()
        wss_vectors(fitter, states, [[u[c] for u in inplane] for c in range(2)], walls, dz, mu)  # type: ignore[index]
        _add_time(states, fitter, "velocity_inplane", t0)

    checks = [steady_check(s, options) for s in states]
    pending: list = [None] * len(states)
    bands: list = [None] * len(states)
    band_note = ""
    if options.uncertainty:
        band = functools.partial(fitter.band, states, coupled_results, walls)
        if defer_band:
            pending = _deferred(band, states, walls)
        else:
            report_progress("uncertainty band")
            t0 = time.perf_counter()
            bands, band_note = band()
            if isinstance(fitter, ZCoupled):
                fitter._time("uncertainty", t0)
            else:
                states[0].seconds["uncertainty"] = time.perf_counter() - t0
    out = []
    for i, (s, w) in enumerate(zip(states, walls)):
        b: Band | None = bands[i]
        notes = list(s.notes)
        check = checks[i]
        if check is not None and check.unsteady:
            notes.append(check.note())
        if b is not None:
            w.tau_std, w.mean_std = b.tau_std, b.mean_std
            if s.near is not None and np.isfinite(b.scale_std_log):
                s.near.scale_std_log = b.scale_std_log
            if b.note:
                notes.append(b.note)
            elif isinstance(fitter, ZCoupled) and (note := nw.scale_ambiguity_note(s.near, w.mean, w.mean_std)):
                notes.append(note)
        elif band_note:
            notes.append(band_note)
        beta_choice = s.beta_choice
        if isinstance(fitter, ZCoupled):
            if note := fitter.segment_beta_note(i, s, first, last):
                notes.append(note)
            beta_choice = _with_chosen(beta_choice, fitter.beta_used(i))
        s.dephasing.min_factor = float(np.min(s.factors, initial=1.0)) if s.factors is not None else 1.0
        out.append(
            make_result(
                state=s,
                wss=w,
                grid=s.data.grid,
                beta_choice=beta_choice,
                method=options.method,
                coupled_info=coupled_info[i],
                sensitivity=None if b is None else b.sensitivity,
                notes=notes,
                pending_band=pending[i],
                seconds={} if isinstance(fitter, ZCoupled) else s.seconds,
                steady=checks[i],
            )
        )
    return out


def steady_check(s: SliceState, options: ReconstructionOptions) -> steady.SteadyCheck | None:
    """Whether the slice's velocity data can come from steady flow (:mod:`wss_nlp.models.steady`); None where
    no steady family was chosen from the data (``--near-wall off``: cine frames, whose cycle model judges them)
    or the velocity noise is unknown."""
    problem = s.velocity_problem
    if s.near is None or problem is None or s.near.criterion.startswith("no velocity noise"):
        return None
    try:
        sigma = steps.noise_levels(s.data, options, problem.voxels.index, s.lumen)[1]
    except WssNlpError:  # no background to estimate the noise from: the check would weigh the rings blindly
        return None
    vox = problem.voxels
    return steady.check(
        problem.data, sigma, vox.px.mean(axis=1), vox.py.mean(axis=1), s.geometry.coefficients, s.geometry.center,
        float(s.data.grid.h), s.near.reynolds, s.near,
    )  # fmt: skip


def _with_chosen(choice, value: float):
    from dataclasses import replace

    return replace(choice, chosen=value)


def _deferred(band, states: list[SliceState], walls: list) -> list:
    """Each slice's pending band: the segment's band computed once, when the first slice asks for it."""
    cache: list = []

    def finish(i: int):
        if not cache:
            cache.append(band())
        bands, note = cache[0]
        b = bands[i]
        if b is None:
            return None, note
        w = walls[i]
        w.tau_std, w.mean_std = b.tau_std, b.mean_std
        near = states[i].near
        if near is not None and np.isfinite(b.scale_std_log):
            near.scale_std_log = b.scale_std_log
        return b.sensitivity, b.note

    return [functools.partial(finish, i) for i in range(len(states))]


def _dephasing_passes(states: list[SliceState], fitter: Fitter, options: ReconstructionOptions, venc) -> None:
    """The dephasing passes of a segment (module notes, step 3); the states hold the last accepted pass.

    With voxel means one corrective pass (the factors hardly move after it); with the k-space model the phase
    mixing reaches further than a wall voxel, so passes repeat until the wall stops moving, each judged by how
    well its state explains the measured magnitude (a pass that explains any slice's magnitude worse is undone).
    """
    if not (options.dephasing_correction and venc is not None):
        for s in states:
            s.seconds.setdefault("dephasing_check", 0.0)
        return
    model = acq_model.of(states[0].data.psf)
    judged = model.dephasing_passes > 1  # repeated passes must explain the magnitude better than the last
    passes = KSPACE_PASSES if judged else model.dephasing_passes
    previous: tuple[list[SliceState], object] | None = None
    windows: list = [None] * len(states)
    explained = [float("inf")] * len(states)
    h = states[0].data.grid.h
    for k in range(passes + 1):
        t0 = time.perf_counter()
        checks = [
            steps.predict_dephasing(s.data, s.velocity_problem, s.velocity, s.geometry, options, windows[i])
            for i, s in enumerate(states)
        ]
        _add_time(states, fitter, "dephasing_check", t0)
        corrections = [c for c, _ in checks]
        if judged:
            if k == 0:  # the first geometry assumed no phase: its own model is the one a pass must beat
                windows = [c.window for c in corrections]
                explained = [c.misfit_still for c in corrections]
            elif any(c.misfit_moving >= e for c, e in zip(corrections, explained)):
                assert previous is not None  # k >= 1: a pass was run
                states[:] = previous[0]
                fitter.restore(previous[1])
                for s in states:
                    s.dephasing.passes = k - 1
                    if k == 1:  # later passes that do not help just end the iteration
                        s.notes.append(deph.UNEXPLAINED_NOTE)
                return
            else:
                explained = [c.misfit_moving for c in corrections]
            for s, c in zip(states, corrections):
                s.lumen = _replace_signal(s.lumen, c.signal)  # the phases' prediction of the background tails
        for s, c, (_, v_deph) in zip(states, corrections, checks):
            s.factors = c.factors if s.factors is None else s.factors
            s.dephasing.beta = float(v_deph.beta)
        # a further pass only pays where some wall voxel loses more than 1 % of its magnitude
        if k == passes or not any(c.worth_a_pass for c in corrections):
            return
        if judged and k > 0 and KSPACE_PASS_PREDICTION:
            # the pass would end the iteration if it moved the wall less than the tolerance: predicted to first
            # order (within 1 % of such small moves on the phantoms), it need not be run
            t0 = time.perf_counter()
            moves = []
            for s, c in zip(states, corrections):
                change = geo.predicted_change(s.problem, options.geometry, s.geometry, c.magnitude)
                if change is not None:
                    s.dephasing.next_move = float(np.max(np.abs(rad.evaluate(change, rad.uniform_angles(72))))) / h
                moves.append(s.dephasing.next_move if change is not None else None)
            _add_time(states, fitter, "dephasing_check", t0)
            if all(m is not None and m < KSPACE_PASS_TOL for m in moves):
                return
        t0 = time.perf_counter()
        previous = ([s.snapshot() for s in states], fitter.snapshot())
        report_progress(f"dephasing pass {k + 1}")
        fitter.repass(states, corrections)
        _add_time(states, fitter, "dephasing_pass", t0)
        angles = rad.uniform_angles(72)
        moved = max(
            float(np.max(np.abs(s.geometry.radius(angles) - p.geometry.radius(angles))))
            for s, p in zip(states, previous[0])
        )
        for s in states:
            s.dephasing.passes = k + 1
        if not judged or moved < KSPACE_PASS_TOL * h:
            return


def _replace_signal(lumen, signal):
    from dataclasses import replace

    return replace(lumen, signal=signal)


def _add_time(states: list[SliceState], fitter: Fitter, key: str, t0: float) -> None:
    if isinstance(fitter, ZCoupled):
        fitter._time(key, t0)
    else:
        for s in states:
            s.seconds[key] = s.seconds.get(key, 0.0) + time.perf_counter() - t0


#: Acquired / reported voxel size above which a file counts as zero-filled (the box model then misdescribes it).
ZERO_FILL_TOLERANCE = 1.05
ZERO_FILLED_NOTE = (
    "SUSPECT: the file states an acquired resolution of {acquired} mm for {voxel} mm voxels (zero-filled "
    "k-space), which the box model does not describe; use --acquisition kspace (or auto)"
)

#: What every slice of an input cut from a volume (``resampled_from``) says.
RESAMPLED_NOTE = (
    "the images were cut from a 4D-flow volume (wss-nlp import --plane): each voxel is the nearest volume "
    "voxel's, up to half a voxel from where it was measured; radius errors of several percent and WSS errors "
    "of 3-15 % are typical (docs, 'Your own data': scripts/results/plane_extraction.md)"
)
#: A lumen cut from a volume with a mean radius under this many plane voxels is flagged SUSPECT: with radius
#: 3.6 voxels the WSS missed by up to 1700 %, mostly where no other check fired; with 5.5 voxels by at most
#: 14.5 % on unflagged slices (scripts/results/plane_extraction.md).
RESAMPLED_MIN_RADIUS_VOXELS = 5.0


def _with_screens(results, screens: dict, acq: Acquisition, psf=None, range_notes=()):
    """Attach what the plausibility screen found, and the fit's consistency check, to each slice.

    Also what the acquisition model implies: a file that states zero-filling (``acquired_voxel_size_mm``
    above the voxel size) reconstructed with the box model is SUSPECT (the model does not describe such
    images: ``scripts/results/kspace.md``), and an ambiguous k-space filter choice is said.
    """
    acquired = acq.acquired_voxel_size_mm
    zero_filled = acquired is not None and any(a > v * ZERO_FILL_TOLERANCE for a, v in zip(acquired, acq.voxel_size_mm))
    voxel_means = isinstance(acq_model.of(psf), acq_model.VoxelMeans)
    for r in results:
        if isinstance(r, FailedSlice):
            continue
        box_on_kspace = zero_filled and voxel_means and isinstance(r, SliceResult)
        note = ZERO_FILLED_NOTE.format(acquired=acquired, voxel=acq.voxel_size_mm)
        if box_on_kspace and note not in r.notes:
            r.notes.append(note)
        choice = None if psf is None else psf.choice
        if choice and choice["ambiguous"] and isinstance(r, SliceResult):
            r.notes.append(
                f"k-space filter chosen from the data: {choice['chosen']}, but {choice['runner_up']} fits the "
                f"magnitude almost as well ({100 * choice['margin']:.1f} % more misfit); pass --kspace-filter if "
                "you know the scanner's"
            )
        found = screens.get(r.index)
        if found is not None:
            r.notes.extend(n for n in found.notes if n not in r.notes)
            r.screen = dict(found.record)
        if range_notes:  # the readings taken and what was allowed, on every slice (docs, "Input checks")
            r.notes.extend(n for n in range_notes if n not in r.notes)
            r.screen = {**(r.screen or {}), "ranges": list(range_notes)}
        coarse = False
        if acq.resampled_from and RESAMPLED_NOTE not in r.notes:
            r.notes.append(RESAMPLED_NOTE)
            radius_voxels = float(r.geometry.coefficients[0]) / acq.grid.h
            if radius_voxels < RESAMPLED_MIN_RADIUS_VOXELS:
                coarse = True
                r.notes.append(
                    f"SUSPECT: a lumen of {radius_voxels:.1f} voxels' radius cut from a volume: too coarse for "
                    f"resampled data (under {RESAMPLED_MIN_RADIUS_VOXELS:g}); its WSS is not trustworthy"
                )
        if isinstance(r, SliceResult):
            warning, ratio = plaus.check_fit(r, acq.magnitude[r.index], acq.venc_m_s)
            # issue 42: strong dephasing in wall voxels biases the WSS with a residual at the noise level
            dephased = "" if not voxel_means else plaus.check_dephasing(
                r.dephasing.min_factor, acq.venc_m_s, bool((r.screen or {}).get("unwrapped"))
            )  # fmt: skip
            unresolved = r.near_wall is not None and bool(np.isfinite(r.near_wall.unresolved_mm))
            unbalanced = r.beta_choice is not None and r.beta_choice.rule == "balance" and not r.beta_choice.satisfied
            unsteady = r.steady is not None and r.steady.unsteady
            suspect = bool(warning) or bool(dephased) or unresolved or unbalanced or coarse or box_on_kspace or unsteady
            r.screen.update(velocity_residual_to_noise=ratio, suspect=suspect, dephasing_suspect=bool(dephased))
            if r.steady is not None:
                r.screen["steady"] = r.steady.as_dict()
            for w in (warning, dephased):
                if w:
                    r.notes.append(w)
        obliquity.apply(r, acq)  # a plane off the vessel's axis: corrected (in-plane velocity) or flagged
    return results
