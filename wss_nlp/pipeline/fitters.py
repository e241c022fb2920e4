"""How the slices of a segment are fitted: each alone, or tied along the vessel (paper Sec. 5).

A *segment* is what the driver (:mod:`wss_nlp.pipeline.driver`) takes through the steps at once: one slice,
or a run of consecutive slices of a stack. Its *fitter* solves every step that couples slices:

* :class:`Independent` (one slice): the geometry with alpha from its rule (:mod:`wss_nlp.parameters.alpha`),
  the velocity with the slice's own beta, the coupled NLP of one slice, the slice's band
  (:mod:`wss_nlp.uncertainty.sensitivity`);
* :class:`ZCoupled` (several slices): geometry and velocity coupled along z (:mod:`wss_nlp.models.stack`: one NLP
  or Kaczmarz sweeps), one alpha and one beta per segment (the geometric median of the slices' own choices),
  the segment's coupled NLP and band (:mod:`wss_nlp.uncertainty.stack_band`).

Both act on the segment's :class:`~wss_nlp.pipeline.state.SliceState` records in place, so the driver's
sequence of steps is written once.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..core.solver import SolverStats
from ..errors import WssNlpError
from ..models import acquisition as acq_model
from ..models import geometry as geo
from ..models import near_wall as nw
from ..models import stack as stk
from ..models import velocity as vel
from ..models import wss as wss_mod
from ..parameters import rules as pr
from ..parameters.alpha import choose_alpha
from ..parameters.beta import geometric_median, segment_beta
from ..uncertainty import sensitivity as sens
from ..uncertainty import stack_band
from . import steps
from .band import slice_band
from .options import ReconstructionOptions
from .state import SliceState

#: What a long stack solve is doing (segments, sweeps) goes here at INFO level (the CLI shows it on stderr).
logger = logging.getLogger("wss_nlp.models.stack")


class Fitter:
    """The steps of a segment that couple its slices; :class:`Independent` and :class:`ZCoupled` implement it."""

    #: Stage times of the fitter's solves (seconds, summed over its segments).
    seconds: dict

    def geometry(self, states: list[SliceState], start=None) -> None:
        """Alpha and the geometry of every slice (``start``: radius coefficients to start from)."""
        raise NotImplementedError

    def velocity(self, states: list[SliceState], around: bool = False) -> None:
        """The near-wall model, beta and velocity fit of every slice on its current geometry (``around``: refine
        the models the slices have, after a dephasing pass)."""
        raise NotImplementedError

    def repass(self, states: list[SliceState], corrections: list) -> None:
        """Geometry and velocity again on the dephasing-corrected magnitudes and velocities."""
        raise NotImplementedError

    def components(self, states: list[SliceState], images: list) -> list:
        """Velocity coefficients of another velocity component (``images[i]`` of slice i) with the slices' models
        and betas (4D flow: the in-plane components)."""
        raise NotImplementedError

    def coupled(self, states: list[SliceState]) -> tuple[list, list[dict]]:
        """The coupled NLP (geometry and velocity as one problem) from the decoupled states: results and records."""
        raise NotImplementedError

    def band(self, states: list[SliceState], coupled_results, walls: list) -> tuple:
        """``(bands, note)``: each slice's :class:`Band` (None where the band cannot be computed, ``note`` says
        why); ``walls``: the WSS of each slice, which the band completes."""
        raise NotImplementedError

    def snapshot(self):
        """What :meth:`restore` needs to return to this point (a dephasing pass that is undone)."""
        return None

    def restore(self, snapshot) -> None:
        """Return to :meth:`snapshot`'s point."""

    def _time(self, key: str, t0: float) -> None:
        self.seconds[key] = self.seconds.get(key, 0.0) + time.perf_counter() - t0


@dataclass
class Band:
    """One slice's uncertainty band: the WSS standard deviations and what computed them."""

    tau_std: np.ndarray
    mean_std: float
    sensitivity: sens.Sensitivity | None = None  # single slices
    note: str = ""
    scale_std_log: float = float("nan")  # the law-of-the-wall scale's spread (stacks carry it here)


class Independent(Fitter):
    """One slice on its own: the paper's 2D method with the parameter rules of :mod:`wss_nlp.parameters`."""

    def __init__(self, options: ReconstructionOptions, mu: float, density: tuple[float, str]):
        self.options, self.mu, self.density = options, mu, density
        self.seconds: dict = {}

    def geometry(self, states, start=None):
        options = self.options
        for s in states:
            t0 = time.perf_counter()
            s.geometry, s.alpha_choice = choose_alpha(
                s.problem, s.data.raw, s.data.norm, s.lumen, options.geometry, options.choice, s.data.where, start
            )
            if acq_model.of(s.data.psf).background_tails:  # they reach into the background the noise estimates use
                image = geo.model_image(s.problem, options.geometry, s.geometry)
                s.lumen = replace(s.lumen, signal=s.data.norm.m1 * image)
            s.seconds["geometry"] = time.perf_counter() - t0

    def velocity(self, states, around=False):
        options = self.options
        for s in states:
            t0 = time.perf_counter()
            g = s.geometry
            vp = vel.assemble(s.data.grid, s.velocity_image, g.coefficients, g.center, options.velocity, psf=s.data.psf)
            s.velocity_problem, s.near = steps.near_wall_model(
                s.data, vp, options, self.mu, self.density, lumen=s.lumen
            )
            s.beta_choice = steps.beta_choice(s.data, s.velocity_problem, s.near, options, self.mu, lumen=s.lumen)
            s.velocity = vel.solve(s.velocity_problem, options.velocity, beta=s.beta_choice.chosen)
            s.seconds["velocity"] = time.perf_counter() - t0

    def repass(self, states, corrections):
        options = self.options
        for s, corr in zip(states, corrections):
            s.problem = replace(s.problem, magnitude=corr.magnitude)
            g = s.geometry
            s.geometry = geo.solve(s.problem, geo.with_options(options.geometry, alpha=g.alpha), x0=g.coefficients)
            s.velocity_image = corr.velocity
            vp = s.velocity_problem
            s.velocity_problem = vel.assemble(
                s.data.grid, corr.velocity, s.geometry.coefficients, s.geometry.center, options.velocity,
                basis=getattr(vp.basis, "base", vp.basis), psf=s.data.psf,
            )  # fmt: skip
            if s.near is not None and s.near.model != "plain":
                # the first pass's geometry was biased by the dephasing just corrected, and the layer scale with it
                s.velocity_problem, s.near = steps.near_wall_model(
                    s.data, s.velocity_problem, options, self.mu, self.density, lumen=s.lumen, around=s.near
                )
                s.beta_choice = steps.beta_choice(s.data, s.velocity_problem, s.near, options, self.mu, lumen=s.lumen)
            s.velocity = vel.solve(s.velocity_problem, options.velocity, beta=s.beta_choice.chosen)

    def components(self, states, images):
        out = []
        for s, image in zip(states, images):
            vp = s.velocity_problem
            vp_c = replace(vp, data=np.asarray(image, float).ravel()[vp.voxels.index], data_image=image)
            out.append(vel.solve(vp_c, self.options.velocity, beta=s.beta_choice.chosen))
        return out

    def coupled(self, states):
        results, records = [], []
        for s in states:
            cres, info = solve_coupled(s, self.options)
            results.append(cres)
            records.append(info)
        return results, records

    def band(self, states, coupled_results, walls):
        (s,), (w,) = states, walls  # a segment of one slice
        cres = None if coupled_results is None else coupled_results[0]
        sensitivity, note = slice_band(s, w, self.mu, self.options, cres)
        if sensitivity is None:
            return [None], note
        return [Band(w.tau_std, w.mean_std, sensitivity, note)], ""


def solve_coupled(s: SliceState, options: ReconstructionOptions):
    """The coupled NLP of one slice started from its decoupled state, with the same alpha and beta.

    Returns the :class:`wss_nlp.models.coupled.CoupledResult` and a dict with the weight, how it was chosen
    (:func:`wss_nlp.parameters.coupled_weight.coupled_weight`) and the decoupled start's mean radius.
    """
    from ..models import coupled as cpl

    g, v, image = s.geometry, s.velocity, s.velocity_problem.data_image
    weight, how = steps.coupled_weight(s.data, s.problem, image, options, s.lumen)
    res = cpl.solve(s.problem, options.geometry, image, options.velocity, g, v, weight, options.coupled)
    info = {
        "velocity_weight": weight,
        **how,
        "decoupled_mean_radius_mm": float(g.coefficients[0]),
        "decoupled_converged": bool(g.stats.converged and v.stats.converged),
    }
    return res, info


@dataclass
class _Solve:
    """A z-coupled segment's solve state beyond its slices': the geometry pieces and the betas used."""

    slices: list = field(default_factory=list)  # stack.SliceGeometry per slice (box multipliers for the band)
    coefficients: np.ndarray | None = None  # radius coefficients, (n_slices, n)
    betas: list = field(default_factory=list)  # the betas used: one per segment when the z-coupling needs it


class ZCoupled(Fitter):
    """Consecutive slices of a stack tied along z (:mod:`wss_nlp.models.stack`): Sec. 5's penalties.

    The weights come from the smoothing length (``kappa = (l / dz)^(2m) R / h`` for the geometry,
    ``kappa_v = (l / dz)^(2m)`` for the velocity, R the slices' mean reference radius). Segments of at most
    :data:`wss_nlp.models.stack.COUPLED_MAX_SLICES` slices are solved as one NLP with ``strategy = "auto"``,
    longer ones by Kaczmarz sweeps. Alpha: each slice's rule on the slice alone (a fixed alpha needs no such
    solve), then their geometric median for the segment, as beta.
    """

    def __init__(self, options, mu, density, grid, dz: float, r_ref: float, info: stk.StackInfo):
        self.options, self.mu, self.density, self.grid, self.dz = options, mu, density, grid, dz
        stack = options.stack
        ell = dz if stack.z_smoothing_mm is None else float(stack.z_smoothing_mm)
        self.order = stack.z_order
        self.kappa = (ell / dz) ** (2 * self.order) * r_ref / grid.h
        self.kappa_v = (ell / dz) ** (2 * self.order)
        self.info = info
        self.basis = options.velocity.make_basis()
        self.gram0 = self.basis.laplacian_gram(0)
        self.seconds: dict = {}
        self.strategy = "coupled"
        self._solve = _Solve()

    def snapshot(self):
        return replace(self._solve), self.info.dephasing_pass

    def restore(self, snapshot) -> None:
        self._solve, self.info.dephasing_pass = snapshot

    def start(self, n: int) -> None:
        """A new segment of ``n`` slices: its strategy (``auto``: coupled up to COUPLED_MAX_SLICES slices)."""
        strategy = self.options.stack.strategy
        if strategy == "auto":
            strategy = "coupled" if n <= stk.COUPLED_MAX_SLICES else "kaczmarz"
        info = self.info
        info.strategy = strategy if not info.strategy or info.strategy == strategy else "mixed"
        self.strategy = strategy
        self._solve = _Solve()

    def _alpha(self, states, start) -> float:
        """The segment's alpha: the fixed one, or the geometric median of each slice's rule on the slice alone."""
        options = self.options
        if options.choice.alpha_rule == "fixed":
            for s in states:
                s.alpha_choice = pr.ParameterChoice("alpha", "fixed", options.geometry.alpha)
            return options.geometry.alpha
        Independent(options, self.mu, self.density).geometry(states, start)
        alpha = geometric_median([s.alpha_choice.chosen for s in states])
        for s in states:
            if not np.isclose(alpha, s.alpha_choice.chosen, rtol=1e-9, atol=0.0):
                s.notes.append(
                    f"stack: alpha = {alpha:.3g}, the geometric median of the {s.alpha_choice.rule} choices of the "
                    f"segment's slices (this slice alone: {s.alpha_choice.chosen:.3g})"
                )
            s.alpha_choice = replace(s.alpha_choice, chosen=alpha)
        return alpha

    def geometry(self, states, start=None):
        alpha = self._alpha(states, start)  # the z-coupled solve itself starts from each slice's half-maximum contour
        x0 = np.array([geo.initial_guess(s.problem, self.options.geometry.n_fourier) for s in states])
        self._geometry(states, x0, alpha)

    def _geometry(self, states, x0, alpha: float) -> None:
        gopt, stack, info = self.options.geometry, self.options.stack, self.info
        gopt_a = gopt if alpha == gopt.alpha else geo.with_options(gopt, alpha=alpha)
        t0 = time.perf_counter()
        sg = [stk.SliceGeometry(s.problem, gopt_a, self.kappa) for s in states]
        self._time("geometry_build", t0)
        t0 = time.perf_counter()
        if self.strategy == "coupled":
            coef, stats = stk.coupled_geometry(sg, alpha, x0, self.order)
            gstats = [stats] * len(states)
            info.sweeps.setdefault("geometry", []).append(0)
        else:
            coef, sweeps, hist, gstats = stk.kaczmarz_geometry(sg, alpha, x0, stack.tol, stack.max_sweeps, self.order)
            info.sweeps.setdefault("geometry", []).append(sweeps)
            info.residuals["geometry"] = hist
            if hist[-1] >= stack.tol and len(states) > 1:
                info.converged = False
        self._time("geometry", t0)
        for i, (s, sl) in enumerate(zip(states, sg)):
            s.geometry = geo.finish(s.problem, gopt_a, sl.nlp, coef[i], gstats[i], alpha)
        self._solve.slices, self._solve.coefficients = sg, coef

    def velocity(self, states, around=False):
        t0 = time.perf_counter()
        options = self.options
        vps = [
            vel.assemble(self.grid, s.velocity_image, s.geometry.coefficients, s.geometry.center, options.velocity,
                         basis=self.basis, psf=s.data.psf)
            for s in states
        ]  # fmt: skip
        for s, vp in zip(states, vps):
            before = s.near if around else None
            if options.velocity.near_wall == "off":
                s.velocity_problem, s.near = vp, None
            elif before is not None and before.model == "plain":  # as a single slice: a plain slice stays plain
                s.velocity_problem = vp
            else:
                s.velocity_problem, s.near = steps.near_wall_model(
                    s.data, vp, options, self.mu, self.density, around=before
                )
        for s in states:
            s.beta_choice = steps.beta_choice(s.data, s.velocity_problem, s.near, options, self.mu)
        choices = [s.beta_choice for s in states]
        if self.kappa_v == 0 or len({c.chosen for c in choices}) == 1:
            betas = [c.chosen for c in choices]
        else:
            betas = [segment_beta(choices)] * len(states)
        self._solve.betas = betas
        coefficients, stats = self._fit([s.velocity_problem for s in states], betas)
        for s, c, st, b in zip(states, coefficients, stats, betas):
            s.velocity = vel.result(s.velocity_problem, options.velocity, c, b, st)
        self._time("velocity", t0)

    def _fit(self, vps, betas, record: bool = True):
        """The z-coupled velocity fit of one segment (any component: the data sit in ``vps``)."""
        stack, info = self.options.stack, self.info
        if self.strategy == "coupled":
            vcoef, vstats = stk.coupled_velocity(vps, betas, self.kappa_v, self.gram0, self.order)
            return vcoef, [vstats] * len(vps)
        vcoef, sweeps, hist = stk.kaczmarz_velocity(
            vps, betas, self.kappa_v, self.gram0, stack.tol, stack.max_sweeps, self.order
        )
        ok = hist[-1] < stack.tol or len(vps) == 1
        if record:
            info.sweeps.setdefault("velocity", []).append(sweeps)
            info.residuals["velocity"] = hist
        info.converged &= ok
        status = "Solve_Succeeded" if ok else "Maximum_Iterations_Exceeded"
        stats = SolverStats("kaczmarz (block Gauss-Seidel, Cholesky)", status, ok, sweeps, float("nan"), 0.0)
        return vcoef, [stats] * len(vps)

    def repass(self, states, corrections):
        for s, corr in zip(states, corrections):
            s.problem = replace(s.problem, magnitude=corr.magnitude)
            s.velocity_image = corr.velocity
        self._geometry(states, self._solve.coefficients, states[0].alpha_choice.chosen)
        self.velocity(states, around=True)
        self.info.dephasing_pass = True

    def components(self, states, images):
        vps = [
            replace(vp, data=np.asarray(u, float).ravel()[vp.voxels.index], data_image=u)
            for vp, u in zip((s.velocity_problem for s in states), images)
        ]
        coefficients, stats = self._fit(vps, self._solve.betas, record=False)
        vopt = self.options.velocity
        return [vel.result(vp, vopt, c, b, st) for vp, c, st, b in zip(vps, coefficients, stats, self._solve.betas)]

    def coupled(self, states):
        """The segment's coupled NLP (:func:`wss_nlp.models.stack.coupled_segment`) from its decoupled solution,
        with one velocity weight: ``--velocity-weight``, or the geometric median of the slices' likelihood weights
        (:func:`wss_nlp.pipeline.steps.coupled_weight`)."""
        options, copt = self.options, self.options.coupled
        images = [s.velocity_problem.data_image for s in states]
        starts = [(s.geometry, s.velocity) for s in states]
        own = [steps.coupled_weight(s.data, s.problem, u, options) for s, u in zip(states, images)]
        weight = geometric_median([w for w, _ in own])
        res, _ = stk.coupled_segment(
            [s.problem for s in states], images, starts, options.geometry, options.velocity, weight,
            self._solve.betas, self.kappa, self.kappa_v, self.order, copt,
        )  # fmt: skip
        records = [
            {
                "velocity_weight": weight,
                **how,
                "velocity_weight_slice_alone": w,
                "decoupled_mean_radius_mm": float(g.coefficients[0]),
                "decoupled_converged": bool(g.stats.converged and v.stats.converged),
            }
            for (w, how), (g, v) in zip(own, starts)
        ]
        first, last = states[0].data.index, states[-1].data.index
        if len(states) > 1 and copt.velocity_weight is None:
            for d in records:
                d["weight_method"] += f"; the geometric median over slices {first}-{last}"
        return res, records

    def band(self, states, coupled_results, walls):
        """The band of the solved segment (:mod:`wss_nlp.uncertainty.stack_band`)."""
        options, zop = self.options, stk.z_operator(len(states), self.order)
        sol = self._solve
        try:
            if coupled_results is not None:
                bands = stack_band.coupled_segment_band(
                    coupled_results, [s.problem for s in states],
                    lambda i, _, u_index: steps.noise_levels(states[i].data, options, u_index)[:2],
                    options.geometry, options.velocity, self.kappa, self.kappa_v, zop, self.mu, options.n_phi,
                )  # fmt: skip
            else:
                band_slices = []
                for s, sl, b in zip(states, sol.slices, sol.betas):
                    sigma_m, sigma_u, _ = steps.noise_levels(s.data, options, s.velocity_problem.voxels.index)
                    band_slices.append(
                        stack_band.BandSlice(s.problem, s.geometry, sl.lam_g, s.velocity_problem,
                                             s.velocity.coefficients, b, s.near, sigma_m, sigma_u)
                    )  # fmt: skip
                bands = stack_band.segment_band(
                    band_slices, options.geometry, options.velocity, self.kappa, self.kappa_v, zop, self.mu,
                    options.n_phi,
                )  # fmt: skip
        except WssNlpError as exc:
            return [None] * len(states), f"no uncertainty band: {exc}"
        return [Band(b.tau_std, b.mean_std, None, "", b.scale_std_log) for b in bands], ""

    def segment_beta_note(self, i: int, s: SliceState, first: int, last: int) -> str:
        """The note of a slice whose beta is the segment's median rather than its own choice ("" otherwise)."""
        beta, chosen = self._solve.betas[i], s.beta_choice
        if np.isclose(beta, chosen.chosen, rtol=1e-9, atol=0.0):  # exp(median(log)) rounds a shared choice
            return ""
        return (
            f"stack: beta = {beta:.3g}, the geometric median of the {chosen.rule} choices "
            f"of slices {first}-{last} (this slice alone: {chosen.chosen:.3g})"
        )

    def beta_used(self, i: int) -> float:
        return float(self._solve.betas[i])


def wss_vectors(fitter: Fitter, states: list[SliceState], planar_images: list, walls: list, dz: float, mu: float):
    """The WSS vector of each slice from its in-plane components (4D flow) and the walls' slopes along z.

    ``planar_images[c][i]``: component ``c`` (x, y of the image) of slice ``i``. The slopes are the z-derivatives
    of the cubic-spline interpolants of the segment's walls (:func:`wss_nlp.models.stack.z_derivatives`; zero for a
    single slice: its wall is taken as straight along the normal, the record of the vector says so).
    """
    n_phi = walls[0].phi.size
    planar = [
        [wss_mod.from_reconstruction(v, n_phi, mu).tau for v in fitter.components(states, images)]
        for images in planar_images
    ]
    coefficients = np.array([s.geometry.coefficients for s in states])
    centers = np.array([s.geometry.center for s in states])
    z = np.array([s.data.index for s in states]) * dz
    dcoef, dcenter = stk.z_derivatives(coefficients, centers, z)
    for i, w in enumerate(walls):
        tau3 = np.stack([planar[0][i], planar[1][i], w.tau], axis=1)
        w.vector = wss_mod.wss_vector(w.phi, coefficients[i], dcoef[i], dcenter[i], tau3, mu)


__all__ = ["Band", "Fitter", "Independent", "ZCoupled", "nw", "solve_coupled", "wss_vectors"]
