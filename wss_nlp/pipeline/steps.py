"""The steps of a reconstruction, shared by single slices and z-regularized stacks.

Every slice goes through the same steps, whatever solves its geometry and velocity:

* :func:`prepare`: preprocessing (normalization, lumen, radius box) into a :class:`SliceData` record, which
  also fixes the noise venc the parameter rules and the band use;
* geometry (Sec. 2) and alpha (:mod:`wss_nlp.parameters.choice`);
* :func:`near_wall_model` and :func:`beta_choice`: the velocity model and its beta;
* the velocity fit (Sec. 3);
* :func:`predict_dephasing`: the signal loss that decides a second, corrected pass;
* :func:`coupled_weight`: the coupled method's velocity weight;
* WSS (Sec. 4) and :func:`noise_levels` for the band.

Two drivers run them: :func:`wss_nlp.pipeline.reconstruct.reconstruct_slice` solves each slice alone;
:func:`reconstruct_stack` solves segments of consecutive slices together, with the z-coupled
mathematics of :mod:`wss_nlp.models.stack` (Sec. 5) and the band of :mod:`wss_nlp.uncertainty.stack_band`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from ..models import coupled as cpl
from ..models import dephasing as deph
from ..models import geometry as geo
from ..models import kspace
from ..models import near_wall as nw
from ..models import preprocess as pp
from ..models import surround
from ..uncertainty import sensitivity as sens
from ..uncertainty import stack_band
from ..models import velocity as vel
from ..models import wss as wss_mod
from ..errors import InputError, SolverError, WssNlpError
from ..io.files import Acquisition
from ..models.measurement import VoxelGrid
from ..parameters import noise as nl
from ..parameters import rules as pr
from ..parameters.choice import gcv_beta, geometric_median, layer_model, segment_beta, velocity_beta
from .results import SliceResult
from ..core.solver import SolverStats
from ..models.stack import (
    COUPLED_MAX_SLICES,
    SliceGeometry,
    StackInfo,
    StackOptions,
    z_derivatives,
    coupled_geometry,
    coupled_segment,
    coupled_velocity,
    kaczmarz_geometry,
    kaczmarz_velocity,
    segments_of,
    supports,
    z_operator,
)

if TYPE_CHECKING:
    from .reconstruct import ReconstructionOptions

#: What a long stack solve is doing (segments, sweeps) goes here at INFO level (the CLI shows it on stderr).
logger = logging.getLogger("wss_nlp.models.stack")


@dataclass
class SliceData:
    """One slice's inputs and what preprocessing found: the record every step takes."""

    index: int
    where: str  # "<source> slice <index>", for messages
    raw: np.ndarray  # the measured magnitude (raw units)
    velocity: np.ndarray  # the measured through-plane velocity, m/s
    grid: VoxelGrid
    norm: pp.Normalization
    magnitude: np.ndarray  # normalized
    lumen: pp.Lumen
    venc: float | None  # of the phase data (None: velocity combined from encodings)
    noise_venc: float | None  # the venc of the velocity noise: venc, or the file's noise venc without a plateau
    psf: kspace.PSF | None = None  # the k-space acquisition model (None: voxel means)

    @property
    def problem(self) -> geo.GeometryProblem:
        """The geometry problem of the slice (Sec. 2)."""
        lum = self.lumen
        return geo.GeometryProblem(self.grid, self.magnitude, lum.center, lum.r0, lum.r1, lum.r_area, psf=self.psf)


def prepare(
    raw,
    velocity,
    grid: VoxelGrid,
    index: int,
    source: str,
    vessel=None,
    psf: kspace.PSF | None = None,
    venc: float | None = None,
    noise_venc: float | None = None,
    box: pp.LumenBox | None = None,
    tissue: surround.TissueOptions | None = None,
) -> SliceData:
    """Preprocess one slice (:func:`wss_nlp.models.preprocess.preprocess`) into its :class:`SliceData`.

    ``box`` replaces the lumen's own origin and radius box (cine frames). ``noise_venc`` sets the velocity
    noise when there is no ``venc`` and the lumen has no plateau to measure it on (the plateau's level is
    preferred: it also holds what the data's placement adds). ``tissue``: the surround model and the offset
    correction (:func:`wss_nlp.models.surround.preprocess`; None: their defaults).
    """
    where = f"{source} slice {index}"
    # hook (issue 39): the surround model, flow-aware lumen and background offset correction; the velocity the
    # fits use comes back with the offset removed and the partial-volume voxels' lumen phase, and the raw
    # magnitude with the magnitude that carries that phase (the noise estimates' |d_i|)
    near = None if box is None else box.center  # cine: the series' vessel, also in a frame of slow flow
    norm, m, lumen, velocity, raw = surround.preprocess(raw, velocity, grid, where, vessel, venc, psf, tissue, near)
    if box is not None:
        lumen = box.apply(lumen)
    nvenc = venc
    if venc is None and nl.velocity_plateau(lumen.noise_mask).sum() < nl.MIN_PLATEAU_VOXELS:
        nvenc = noise_venc
    return SliceData(index, where, raw, np.asarray(velocity, float), grid, norm, m, lumen, venc, nvenc, psf)


def near_wall_model(
    data: SliceData, vp: vel.VelocityProblem, options: ReconstructionOptions, mu: float, density, lumen=None,
    around=None,
):  # fmt: skip
    """``(velocity problem, NearWallChoice)``: the slice's near-wall model (``--near-wall``; ``around``: an
    earlier choice on a nearby geometry to refine), or ``(vp, None)`` with ``--near-wall off``."""
    if options.velocity.near_wall == "off":
        return vp, None
    lumen = data.lumen if lumen is None else lumen
    return layer_model(vp, data.raw, lumen, data.noise_venc, options, data.where, mu, density, around=around)


def beta_choice(data: SliceData, vp, near, options: ReconstructionOptions, mu: float, lumen=None):
    """The slice's beta (:func:`wss_nlp.parameters.choice.velocity_beta`: the rule's, or a layer's BIC beta)."""
    lumen = data.lumen if lumen is None else lumen
    return velocity_beta(vp, near, data.raw, lumen, data.noise_venc, options, data.where, mu)


def predict_dephasing(
    data: SliceData, vp: vel.VelocityProblem, v, geometry, options: ReconstructionOptions, window=None
):  # fmt: skip
    """``(Correction, the velocity it used)``: the dephasing factors of the wall voxels and the corrected images
    (:func:`wss_nlp.models.dephasing.correct`) from the velocity ``v`` or, by default (``--dephasing-beta gcv``, or
    without ``v``), from a GCV-beta fit: dephasing is set by the velocity variation inside wall voxels, which
    a beta tuned for WSS may smooth away (turbulent layers). ``window``: the k-space misfit window. Needs the
    phase data's venc (the drivers call it only then)."""
    if data.venc is None:
        raise InputError(f"{data.where}: the dephasing correction needs the venc of the phase data")
    if v is None or options.dephasing_beta_rule == "gcv":
        v = vel.solve(vp, replace(options.velocity, solver="cholesky"), beta=gcv_beta(vp, options).chosen)
    corr = deph.correct(
        data.magnitude, data.raw, data.norm.m0, data.velocity, vp, v.evaluate_physical, data.venc,
        geometry.coefficients, geometry.center, data.grid, data.psf, window,
    )  # fmt: skip
    return corr, v


def coupled_weight(data: SliceData, problem, velocity_image, options: ReconstructionOptions, lumen=None):
    """``(weight, how)``: the coupled method's velocity weight, ``--velocity-weight`` or the likelihood weight
    from the estimated noise levels (:func:`wss_nlp.models.coupled.weight_from_data`)."""
    if options.coupled.velocity_weight is not None:
        return options.coupled.velocity_weight, {"weight_method": "given (--velocity-weight)"}
    lumen = data.lumen if lumen is None else lumen
    weight, how = cpl.weight_from_data(
        problem, options.geometry, data.raw, data.norm, lumen.noise_mask, velocity_image, data.noise_venc,
        data.where, lumen.signal,
    )  # fmt: skip
    how["weight_method"] = "likelihood: W sigma_m^2 / sigma_u^2 from the estimated noise levels"
    return weight, how


def noise_levels(data: SliceData, options: ReconstructionOptions, u_index: np.ndarray, lumen=None):
    """``(sigma_m, sigma_u on u_index, how)`` of the band (:func:`wss_nlp.uncertainty.sensitivity.noise_levels`)."""
    lumen = data.lumen if lumen is None else lumen
    return sens.noise_levels(
        data.raw, lumen.noise_mask, data.norm.m0, data.norm.m1, u_index, data.noise_venc, options.noise_sigma,
        lumen.signal,
    )  # fmt: skip


# ------------------------------------------------------------------ stacks
def reconstruct_stack(acq: Acquisition, options, stack: StackOptions | None = None, progress=None, psf=None):
    """Reconstruct all slices of a stack with z-regularization.

    Parameters
    ----------
    acq : Acquisition with ``nz >= 1`` and ``slice_spacing_mm`` when ``nz > 1``.
    options : :class:`wss_nlp.pipeline.reconstruct.ReconstructionOptions` (alpha, beta, bases, ...).
    stack : StackOptions
    progress : callable ``(done, total, slice_result)`` or None, called per finished slice.
    psf : wss_nlp.models.kspace.PSF or None
        The k-space acquisition model of every slice (None: voxel means).

    Returns
    -------
    (results, info): ``results[k]`` is a :class:`wss_nlp.pipeline.reconstruct.SliceResult`
    or None for a slice that failed (``info.failed[k]`` says why).

    Notes
    -----
    A slice whose data are unusable (NaN or Inf, no vessel found) is reported by index, left out, and splits
    the stack into independent segments, each solved by :class:`StackRun`. What a long solve is doing
    (segments, sweeps) goes to the ``wss_nlp.models.stack`` logger at INFO level.
    """
    run = StackRun(acq, options, stack or StackOptions(), psf)
    for seg in run.info.segments:
        run.segment(seg, progress)
    if not run.info.converged:
        for r in run.results:
            if r is not None:
                r.notes.append(
                    f"stack: Kaczmarz sweeps stopped before the coupled optimality residual reached {run.stack.tol:g}"
                )
    run.info.seconds = run.t
    return run.results, run.info


@dataclass
class Segment:
    """One solve of a segment's slices: geometry, velocity problems and fits, and the choices made."""

    problems: list  # the geometry problems solved (dephasing-corrected magnitudes in a second pass)
    slices: list  # their stack.SliceGeometry (box multipliers for the band)
    coefficients: np.ndarray  # radius coefficients, (n_slices, n)
    geometries: list
    velocity_problems: list
    velocity: list  # coefficients per slice
    stats: list  # velocity solver statistics per slice
    choices: list  # each slice's own beta choice
    betas: list  # the betas used (one per segment when the z-coupling needs it)
    nears: list  # near-wall choices (None with --near-wall off)

    def velocity_results(self, vopt) -> list:
        return [
            vel.result(vp, vopt, c, b, st)
            for vp, c, b, st in zip(self.velocity_problems, self.velocity, self.betas, self.stats)
        ]


class StackRun:
    """The steps of this module on the segments of one stack, with the z-coupled solvers of :mod:`wss_nlp.models.stack`.

    Holds what every segment shares (the preprocessed slices, the z-weights, the velocity basis) and what the
    solve records (:class:`wss_nlp.models.stack.StackInfo`, stage times, the results).
    """

    def __init__(self, acq: Acquisition, options, stack: StackOptions, psf=None):
        if not supports(options):
            raise InputError(
                "stacks with z-regularization support the decoupled and coupled methods with a fixed alpha; "
                "pass --z-smoothing 0 for independent slices with other settings"
            )
        self.acq, self.stack, self.psf = acq, stack, psf
        self.mu = acq.viscosity(options.viscosity_pa_s)
        self.density = acq.density(options.density_kg_m3)
        self.dz = float(acq.slice_spacing_mm or 1.0) if acq.nz > 1 else 1.0  # validate() requires it for nz > 1
        ell = self.dz if stack.z_smoothing_mm is None else float(stack.z_smoothing_mm)
        velocity = acq.velocity_images()
        self.t = {"preprocess": time.perf_counter()}
        self.prepared: dict[int, SliceData] = {}
        failed = {}
        bad = set(acq.nonfinite_slices())  # any image of the slice, in-plane velocity components included
        for iz in range(acq.nz):
            try:
                if iz in bad:
                    raise InputError(f"{acq.source} slice {iz}: the images contain NaN or Inf")
                self.prepared[iz] = prepare(
                    acq.magnitude[iz], velocity[iz], acq.grid, iz, acq.source, options.screen.vessel, psf,
                    acq.venc_m_s, acq.noise_venc_m_s, tissue=options.tissue,
                )  # fmt: skip
            except WssNlpError as exc:
                failed[iz] = str(exc)
        if not self.prepared:
            raise InputError(f"{acq.source}: no usable slice: " + "; ".join(f"{k}: {v}" for k, v in failed.items()))
        self.t["preprocess"] = time.perf_counter() - self.t["preprocess"]
        r_ref = float(np.mean([s.lumen.r_area for s in self.prepared.values()]))
        self.order = stack.z_order
        self.kappa = (ell / self.dz) ** (2 * self.order) * r_ref / acq.grid.h
        self.kappa_v = (ell / self.dz) ** (2 * self.order)
        self.info = StackInfo("", ell, self.kappa, self.kappa_v, segments_of(sorted(self.prepared)), failed)
        self.results: list = [None] * acq.nz
        self.options = options
        self.basis = options.velocity.make_basis()
        self.gram0 = self.basis.laplacian_gram(0)
        self.unexplained: list[int] = []  # slices whose k-space dephasing prediction was rejected
        self.done = 0

    def _time(self, key: str, t0: float) -> None:
        self.t[key] = self.t.get(key, 0.0) + time.perf_counter() - t0

    # -- the steps on a segment
    def velocity_models(self, seg, vps, around=None):
        """Each slice's near-wall model (as a single slice chooses it; ``around``: the first pass's choices,
        refined on the corrected geometry where they took a layer) and the velocity problems it gives."""
        nears: list = [None] * len(seg)
        if self.options.velocity.near_wall == "off":
            return vps, nears
        out = []
        for i, (k, vp) in enumerate(zip(seg, vps)):
            before = None if around is None else around[i]
            if before is not None and before.model == "plain":  # as reconstruct_slice: a plain slice stays plain
                out.append(vp)
                nears[i] = before
                continue
            problem, nears[i] = near_wall_model(
                self.prepared[k], vp, self.options, self.mu, self.density, around=before
            )
            out.append(problem)
        return out, nears

    def betas(self, seg, vps, nears):
        """Each slice's own beta choice (the rule of the options, or its layer's BIC beta) and the betas used:
        one per segment if z-coupled (:func:`wss_nlp.parameters.choice.segment_beta`)."""
        choices = [
            beta_choice(self.prepared[k], vp, near, self.options, self.mu) for k, vp, near in zip(seg, vps, nears)
        ]
        if self.kappa_v == 0 or len({c.chosen for c in choices}) == 1:
            return choices, [c.chosen for c in choices]
        return choices, [segment_beta(choices)] * len(seg)

    def fit_velocity(self, vps, strategy, betas, record=True):
        """The z-coupled velocity fit of one segment (any component: the data sit in ``vps``)."""
        stack, info = self.stack, self.info
        if strategy == "coupled":
            vcoef, vstats = coupled_velocity(vps, betas, self.kappa_v, self.gram0, self.order)
            return vcoef, [vstats] * len(vps)
        vcoef, sweeps, hist = kaczmarz_velocity(
            vps, betas, self.kappa_v, self.gram0, stack.tol, stack.max_sweeps, self.order
        )
        ok = hist[-1] < stack.tol or len(vps) == 1
        if record:
            info.sweeps.setdefault("velocity", []).append(sweeps)
            info.residuals["velocity"] = hist
        info.converged &= ok
        status = "Solve_Succeeded" if ok else "Maximum_Iterations_Exceeded"
        return vcoef, [
            SolverStats("kaczmarz (block Gauss-Seidel, Cholesky)", status, ok, sweeps, float("nan"), 0.0)
        ] * len(vps)

    def dephasing(self, seg, sol: Segment, windows=None):
        """Each slice's :class:`wss_nlp.models.dephasing.Correction` (windows: k-space misfits), from a GCV-beta
        velocity or, with ``--dephasing-beta same``, from the segment's own fit (as :func:`predict_dephasing`)."""
        own = self.options.dephasing_beta_rule != "gcv"
        vs = sol.velocity_results(self.options.velocity) if own else [None] * len(seg)
        return [
            predict_dephasing(self.prepared[k], vp, v, g, self.options, None if windows is None else windows[i])[0]
            for i, (k, vp, v, g) in enumerate(zip(seg, sol.velocity_problems, vs, sol.geometries))
        ]

    def solve(self, seg, problems, x0, strategy, velocity_images=None, around=None) -> Segment:
        """Geometry, then the velocity model, beta and fit of one segment (z-coupled)."""
        gopt, vopt, stack, info = self.options.geometry, self.options.velocity, self.stack, self.info
        t0 = time.perf_counter()
        sg = [SliceGeometry(pb, gopt, self.kappa) for pb in problems]
        self._time("geometry_build", t0)
        t0 = time.perf_counter()
        if strategy == "coupled":
            coef, stats = coupled_geometry(sg, gopt.alpha, x0, self.order)
            gstats = [stats] * len(seg)
            info.sweeps.setdefault("geometry", []).append(0)
        else:
            coef, sweeps, hist, gstats = kaczmarz_geometry(sg, gopt.alpha, x0, stack.tol, stack.max_sweeps, self.order)
            info.sweeps.setdefault("geometry", []).append(sweeps)
            info.residuals["geometry"] = hist
            if hist[-1] >= stack.tol and len(seg) > 1:
                info.converged = False
        self._time("geometry", t0)
        t0 = time.perf_counter()
        geoms = [
            geo.finish(pb, gopt, sl.nlp, coef[i], gstats[i], gopt.alpha) for i, (pb, sl) in enumerate(zip(problems, sg))
        ]
        images = velocity_images or [self.prepared[k].velocity for k in seg]
        vps = [
            vel.assemble(self.acq.grid, u, g.coefficients, g.center, vopt, basis=self.basis, psf=self.psf)
            for u, g in zip(images, geoms)
        ]
        vps, nears = self.velocity_models(seg, vps, around)
        choices, betas = self.betas(seg, vps, nears)
        vcoef, vstats = self.fit_velocity(vps, strategy, betas)
        self._time("velocity", t0)
        return Segment(problems, sg, coef, geoms, vps, vcoef, vstats, choices, betas, nears)

    def coupled_method(self, seg, sol: Segment):
        """The segment's coupled NLP (:func:`~.stack.coupled_segment`) from its decoupled solution, with one
        velocity weight: ``--velocity-weight``, or the geometric median of the slices' likelihood weights
        (:func:`coupled_weight`). Returns the results and each slice's record of the weight."""
        options, copt = self.options, self.options.coupled
        images = [vp.data_image for vp in sol.velocity_problems]
        starts = list(zip(sol.geometries, sol.velocity_results(options.velocity)))
        own = [coupled_weight(self.prepared[k], pb, u, options) for k, pb, u in zip(seg, sol.problems, images)]
        weight = geometric_median([w for w, _ in own])
        res, _ = coupled_segment(
            sol.problems, images, starts, options.geometry, options.velocity, weight, sol.betas, self.kappa,
            self.kappa_v, self.order, copt,
        )  # fmt: skip
        info = [
            {
                "velocity_weight": weight,
                **how,
                "velocity_weight_slice_alone": w,
                "decoupled_mean_radius_mm": float(g.coefficients[0]),
                "decoupled_converged": bool(g.stats.converged and v.stats.converged),
            }
            for (w, how), (g, v) in zip(own, starts)
        ]
        if len(seg) > 1 and copt.velocity_weight is None:
            for d in info:
                d["weight_method"] += f"; the geometric median over slices {seg[0]}-{seg[-1]}"
        return res, info

    def band(self, seg, sol: Segment, coupled=None):
        """The band of a solved segment (:mod:`~.stack_band`): ``(bands, "")``, or ``(None, why)`` when it
        cannot be computed (the reconstruction itself stands)."""
        options, zop = self.options, z_operator(len(seg), self.order)
        slices = [self.prepared[k] for k in seg]
        try:
            if coupled is not None:
                bands = stack_band.coupled_segment_band(
                    coupled, sol.problems, lambda i, _, u_index: noise_levels(slices[i], options, u_index)[:2],
                    options.geometry, options.velocity, self.kappa, self.kappa_v, zop, self.mu, options.n_phi,
                )  # fmt: skip
            else:
                band_slices = []
                for p, pb, g, sl, vp, cv, b, near in zip(
                    slices, sol.problems, sol.geometries, sol.slices, sol.velocity_problems, sol.velocity, sol.betas,
                    sol.nears,
                ):  # fmt: skip
                    sigma_m, sigma_u, _ = noise_levels(p, options, vp.voxels.index)
                    band_slices.append(stack_band.BandSlice(pb, g, sl.lam_g, vp, cv, b, near, sigma_m, sigma_u))
                bands = stack_band.segment_band(
                    band_slices, options.geometry, options.velocity, self.kappa, self.kappa_v, zop, self.mu,
                    options.n_phi,
                )  # fmt: skip
        except WssNlpError as exc:
            return None, f"no uncertainty band: {exc}"
        return bands, ""

    def inplane(self, seg, sol: Segment, strategy, geoms):
        """The WSS of the in-plane velocity components (4D flow) on each slice and the walls' z-derivatives."""
        mu, vopt = self.mu, self.options.velocity
        assert self.acq.velocity_inplane is not None  # called for 4D-flow input only
        planar = []
        for comp in self.acq.velocity_inplane:
            vps_c = [
                replace(vp, data=comp[k].ravel()[vp.voxels.index], data_image=comp[k])
                for k, vp in zip(seg, sol.velocity_problems)
            ]
            coef_c, st_c = self.fit_velocity(vps_c, strategy, sol.betas, record=False)
            planar.append(
                [
                    wss_mod.from_reconstruction(vel.result(vp, vopt, cc, b, st), self.options.n_phi, mu).tau
                    for vp, cc, st, b in zip(vps_c, coef_c, st_c, sol.betas)
                ]
            )
        dcoef, dcenter = z_derivatives(
            np.array([g.coefficients for g in geoms]), np.array([g.center for g in geoms]), np.array(seg) * self.dz
        )
        return planar, dcoef, dcenter

    # -- one segment, start to end
    def segment(self, seg, progress=None) -> None:
        """Solve one segment (both passes, the coupled method, the band) and store its slices' results."""
        acq, options, stack, info = self.acq, self.options, self.stack, self.info
        strategy = stack.strategy
        if strategy == "auto":
            strategy = "coupled" if len(seg) <= COUPLED_MAX_SLICES else "kaczmarz"
        info.strategy = strategy if not info.strategy or info.strategy == strategy else "mixed"
        logger.info(f"slices {seg[0]}-{seg[-1]}: {strategy} solve of {len(seg)} slice(s)")
        problems = [self.prepared[k].problem for k in seg]
        x0 = np.array([geo.initial_guess(pb, options.geometry.n_fourier) for pb in problems])
        sol = self.solve(seg, problems, x0, strategy)
        factors: list[Any] = [None] * len(seg)
        if options.dephasing_correction and acq.venc_m_s is not None:
            # as reconstruct_slice (one pass): predict the signal loss, then solve again
            t0 = time.perf_counter()
            corrections = self.dephasing(seg, sol)
            factors = [c.factors for c in corrections]
            self._time("dephasing_check", t0)
            if any(c.worth_a_pass for c in corrections):
                logger.info(f"slices {seg[0]}-{seg[-1]}: second pass on dephasing-corrected magnitudes")
                before = sol
                corrected = [replace(pb, magnitude=c.magnitude) for pb, c in zip(problems, corrections)]
                sol = self.solve(
                    seg, corrected, sol.coefficients, strategy, [c.velocity for c in corrections], around=sol.nears
                )
                info.dephasing_pass = True
                if self.psf is not None:  # judged as in reconstruct_slice: undone if it explains the magnitude worse
                    after = self.dephasing(seg, sol, [c.window for c in corrections])
                    if any(a.misfit_moving >= c.misfit_still for a, c in zip(after, corrections)):
                        sol = before
                        self.unexplained.extend(seg)
                        info.dephasing_pass = False
        geoms, cres = sol.geometries, None
        cinfo: list[dict] = [{} for _ in seg]
        if options.method == "coupled":
            t0 = time.perf_counter()
            cres, cinfo = self.coupled_method(seg, sol)
            geoms = [c.geometry for c in cres]
            self._time("coupled", t0)
        planar = None
        if acq.velocity_inplane is not None:
            t0 = time.perf_counter()
            planar, dcoef, dcenter = self.inplane(seg, sol, strategy, geoms)
            self._time("velocity_inplane", t0)
        bands, band_note = None, ""
        if options.uncertainty:
            t0 = time.perf_counter()
            bands, band_note = self.band(seg, sol, cres)
            self._time("uncertainty", t0)
        velocities = sol.velocity_results(options.velocity) if cres is None else [c.velocity for c in cres]
        for i, k in enumerate(seg):
            v, near = velocities[i], sol.nears[i]
            w = wss_mod.from_reconstruction(v, options.n_phi, self.mu)
            if bands is not None:
                w.tau_std, w.mean_std = bands[i].tau_std, bands[i].mean_std
                if near is not None and np.isfinite(bands[i].scale_std_log):
                    near.scale_std_log = bands[i].scale_std_log
            if planar is not None:
                tau3 = np.stack([planar[0][i], planar[1][i], w.tau], axis=1)
                w.vector = wss_mod.wss_vector(w.phi, geoms[i].coefficients, dcoef[i], dcenter[i], tau3, self.mu)
            if not np.all(np.isfinite(w.tau)):
                raise SolverError(f"{acq.source} slice {k}: wall shear stress is not finite")
            p = self.prepared[k]
            dep = {"min_factor": float(np.min(factors[i], initial=1.0)) if factors[i] is not None else 1.0}
            notes = [deph.UNEXPLAINED_NOTE] if k in self.unexplained else []
            notes += surround.notes(p.lumen.tissue)  # hook (issue 39)
            notes += [band_note] if band_note else []
            if bands is not None and (scale_note := nw.scale_ambiguity_note(near, w.mean, w.mean_std)):
                notes.append(scale_note)
            chosen, beta = sol.choices[i], sol.betas[i]
            if not np.isclose(beta, chosen.chosen, rtol=1e-9, atol=0.0):  # exp(median(log)) rounds a shared choice
                notes.append(
                    f"stack: beta = {beta:.3g}, the geometric median of the {chosen.rule} choices "
                    f"of slices {seg[0]}-{seg[-1]} (this slice alone: {chosen.chosen:.3g})"
                )
            self.results[k] = SliceResult(
                k,
                geoms[i],
                v,
                w,
                p.norm,
                p.lumen,
                acq.grid,
                p.magnitude,
                p.velocity,
                {},
                pr.ParameterChoice("alpha", "fixed", options.geometry.alpha),
                replace(chosen, chosen=beta),
                options.method,
                cinfo[i],
                None,
                notes,
                near_wall=near,
                dephasing=dep,
            )
            self.done += 1
            if progress is not None:
                progress(self.done, len(self.prepared), self.results[k])
