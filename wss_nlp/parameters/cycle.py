r"""The velocity model of a cine slice over the cycle, chosen from the data, and how its walls are taken in time.

:func:`choose` weighs, by Schwarz's criterion over all voxel values of the cycle, the frames' own fits (each at
its best beta, :class:`~wss_nlp.parameters.layer.PlainCriterion`), the periodic temporal prior
(:mod:`wss_nlp.models.temporal`) and the momentum balance of pulsatile flow with ``K`` harmonics
(:mod:`wss_nlp.models.womersley`); a richer model must win by :data:`EVIDENCE`. :func:`smooth_walls` chooses the
frames' walls' motion in time the same way. :func:`frame_terms` collects what one frame contributes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from ..models import velocity as vel
from ..models.womersley import (
    NONLINEAR,
    CineModelOptions,
    CycleData,
    FrameTerms,
    _columns,
    fit,
    time_factors,
    wall_shapes,
)
from .layer import PlainCriterion
from .viscosity import ViscosityFit, fit_viscosity

#: Parameters of the momentum model beyond its coefficients where they are fitted (viscosity, wall offset).
NONLINEAR_COUNT = len(NONLINEAR)

#: BIC units the momentum model must beat the frames' own fits by (Kass & Raftery 1995: "very strong").
EVIDENCE = 10.0


def frame_terms(
    problem: vel.VelocityProblem, sigma: np.ndarray, index: int, time_s: float,
    k_max: int, omega: float, nu_m2_s: float, radius_mm: float, shapes: np.ndarray | None = None,
) -> FrameTerms:  # fmt: skip
    """One frame's :class:`FrameTerms` from its plain velocity problem (on the wall the model uses) and noise.

    ``radius_mm`` sets the Womersley parameters: one radius for the cycle (harmonics belong to the cycle,
    not to an instant), e.g. the regularized walls' mean equal-area radius
    (:func:`~wss_nlp.pipeline.cine.equal_area_radius`).
    ``shapes``: :func:`wall_shapes` of the problem's wall if already at hand (frames sharing a wall).
    """
    coefficients = np.asarray(problem.disk_map.coefficients, dtype=float)
    center = (float(problem.disk_map.center[0]), float(problem.disk_map.center[1]))
    if shapes is None:
        shapes = wall_shapes(problem, k_max, omega, nu_m2_s, radius_mm)
    phi = _columns(shapes, time_factors(k_max, omega, time_s))
    inv_var = 1.0 / np.asarray(sigma, float) ** 2
    u = problem.data
    chi2, dof, _ = PlainCriterion(problem, sigma).curve()
    nu = 1.0 if problem.noise_correlation is None else float(problem.noise_correlation.effective_fraction)
    return FrameTerms(
        index, float(time_s), coefficients, center,
        phi.T @ (inv_var[:, None] * phi), phi.T @ (inv_var * u), float(u @ (inv_var * u)), int(u.size),
        chi2, dof, nu, float(radius_mm),
    )  # fmt: skip


@dataclass
class CineModelChoice:
    """Which velocity model a cine slice got, and why (stored in the result file)."""

    model: str  # "independent", "temporal" or "momentum"
    harmonics: int = 0
    bic: dict = field(default_factory=dict)  # model name -> BIC
    margin: float = float("nan")  # the chosen model's lead over the runner-up, EVIDENCE included
    frames_used: list = field(default_factory=list)
    criterion: str = ""
    walls: dict = field(default_factory=dict)  # how the walls were taken in time (WallChoice.as_dict)
    viscosity: dict = field(default_factory=dict)  # the viscosity the data imply (ViscosityFit.as_dict)
    sensitivity: dict = field(default_factory=dict)  # what moves the cycle-averaged mean WSS (the momentum model)
    sampling: dict = field(default_factory=dict)  # whether the frames resolve the waveform (pipeline.cine.sampling)
    fitted_viscosity: ViscosityFit | None = field(default=None, repr=False)  # not stored: the record above is

    def as_json(self) -> str:
        return json.dumps(
            {
                "model": self.model,
                "harmonics": self.harmonics,
                "bic": self.bic,
                "margin": None if not np.isfinite(self.margin) else self.margin,
                "evidence_required": EVIDENCE,
                "frames_used": self.frames_used,
                "criterion": self.criterion,
                "walls": self.walls,
                "viscosity": self.viscosity,
                "sensitivity": self.sensitivity,
                "sampling": self.sampling,
            }
        )


def criterion_scale(terms: list[FrameTerms]) -> tuple[float, float]:
    """``(nu, ln(nu N))`` of the criterion over all the frames' voxel values."""
    nu = min(t.nu for t in terms)
    return nu, float(np.log(nu * sum(t.n_data for t in terms)))


def choose(
    terms: list[FrameTerms], omega: float, nu_m2_s: float, options: CineModelOptions, prior_bic=None,
    data: CycleData | None = None,
):  # fmt: skip
    """The slice's velocity model over the cycle by the BIC (module notes); ``(CineModelChoice, fit or None)``.

    ``prior_bic``: the criterion of the temporal prior (:mod:`wss_nlp.models.temporal`) where it applies. The
    momentum model must beat the better plain candidate (the frames' own fits, the prior) by
    :data:`EVIDENCE`, the prior the frames' own fits; otherwise the frames keep their own fits.

    ``data``: the frames' voxel data (:class:`~wss_nlp.models.womersley.CycleData`); with it and
    ``options.viscosity == "fit"`` the momentum model's viscosity is fitted too
    (:func:`~wss_nlp.parameters.viscosity.fit_viscosity`): the harmonics are chosen at the stated viscosity,
    the viscosity fitted with them, the harmonics chosen again at the fitted viscosity (and the viscosity
    refitted if they changed); the candidate's criterion counts the viscosity as one more parameter.
    """
    n_total = sum(t.n_data for t in terms)
    nu, log_n = criterion_scale(terms)
    fits = fit(terms, omega, nu_m2_s)
    for f in fits:  # correlated (k-space) noise: N voxels carry about nu N independent values
        f.covariance = f.covariance / nu
    bics = [nu * f.chi2 + log_n * (2 * f.harmonics + 1) for f in fits]
    best = int(np.argmin(bics))
    used = [t.index for t in terms]
    criterion = f"BIC = nu chi^2 + ln(nu N) dof over N = {n_total} voxel values of {len(terms)} frames"
    bic = {f"momentum K={f.harmonics}": float(b) for f, b in zip(fits, bics)}
    chosen_fit, fitted = fits[best], None
    if data is not None and options.viscosity == "fit":
        fitted = fit_viscosity(data, fits[best].harmonics, nu_m2_s, nu, voxel_mm=data.voxel_mm)
        refits = data.fits(fitted.nu, fits[-1].harmonics, fitted.offset_mm)
        refit_bics = [nu * f.chi2 + log_n * (2 * f.harmonics + 1 + NONLINEAR_COUNT) for f in refits]
        again = int(np.argmin(refit_bics))
        if refits[again].harmonics != fitted.fit.harmonics:
            start = (fitted.theta, fitted.offset_mm)
            fitted = fit_viscosity(data, refits[again].harmonics, nu_m2_s, nu, start, data.voxel_mm)
        bic = {f"momentum K={f.harmonics} (stated viscosity)": float(b) for f, b in zip(fits, bics)}
        bic.update({f"momentum K={f.harmonics}": float(b) for f, b in zip(refits, refit_bics)})
        k_fit = fitted.fit.harmonics
        bic[f"momentum K={k_fit}"] = float(nu * fitted.fit.chi2 + log_n * (2 * k_fit + 1 + NONLINEAR_COUNT))
        chosen_fit = fitted.fit
        criterion += "; the momentum model's viscosity and wall offset fitted (two more parameters)"
    k_best = chosen_fit.harmonics
    momentum = bic[f"momentum K={k_best}"]
    # the frames' own fits: each at its best beta, weighed with the series' ln N
    bic["independent"] = float(sum(np.min(t.nu * t.plain_chi2 + log_n * t.plain_dof) for t in terms))
    if prior_bic is not None:
        bic["temporal"] = float(prior_bic)

    def made(model: str, harmonics: int, margin: float, how: str = "") -> CineModelChoice:
        choice = CineModelChoice(model, harmonics, bic, margin, used, criterion + how)
        choice.fitted_viscosity = fitted
        return choice

    if options.model == "momentum":
        return made("momentum", k_best, float("nan"), "; forced"), chosen_fit
    if options.model == "temporal":
        if prior_bic is None:
            why = "; the temporal prior needs every frame (at least 3, equally spaced): independent frames"
            return made("independent", 0, float("nan"), why), None
        return made("temporal", 0, float("nan"), "; forced"), None
    # a richer model must beat every simpler one by the evidence: the momentum model both plain candidates,
    # the temporal prior the frames' own fits; otherwise the frames keep their own fits
    independent = bic["independent"]
    prior = bic.get("temporal", np.inf)
    lead = min(independent, prior) - momentum - EVIDENCE
    if lead > 0:
        return made("momentum", k_best, float(lead)), chosen_fit
    prior_lead = independent - prior - EVIDENCE
    if prior_lead > 0:
        return made("temporal", 0, float(min(prior_lead, -lead))), None
    return made("independent", 0, float(min(-lead, -prior_lead))), None


@dataclass
class WallChoice:
    """How the cycle's models took the frames' walls: the temporal degree and the criterion values.

    ``coefficients`` (rows: the trigonometric basis ``1, cos t, sin t, ...``; columns: the radius coefficients
    and the centre) give the walls at any time of the cycle (:meth:`at`); None where each frame keeps its own.
    """

    degree: int | None  # trigonometric degree in time (0: one shared wall); None: each frame's own
    how: str
    bic: dict = field(default_factory=dict)
    coefficients: np.ndarray | None = field(default=None, repr=False)

    def as_dict(self) -> dict:
        return {"degree": self.degree, "how": self.how, "bic": self.bic}

    def at(self, times_s, omega: float) -> np.ndarray | None:
        """The walls (one row per time: radius coefficients then centre, mm) at ``times_s``; None without a
        temporal fit (each frame's own wall)."""
        if self.coefficients is None or self.degree is None:
            return None
        return _trigonometric(np.atleast_1d(np.asarray(times_s, dtype=float)), omega, self.degree) @ self.coefficients


def _trigonometric(times_s: np.ndarray, omega: float, degree: int) -> np.ndarray:
    """The basis ``1, cos(n omega t), sin(n omega t)`` (n = 1..degree) at ``times_s``, one row per time."""
    cols = [np.ones(times_s.size)]
    for n in range(1, degree + 1):
        cols += [np.cos(n * omega * times_s), np.sin(n * omega * times_s)]
    return np.array(cols).T


def smooth_walls(times_s: np.ndarray, omega: float, walls: np.ndarray, mode: str, max_degree: int):
    r"""The frames' walls regularized in time: ``(walls, WallChoice)``.

    ``walls`` holds one row per frame, the radius coefficients followed by the centre (mm). Each column is
    fitted by a trigonometric polynomial of degree ``d`` in time (least squares on the frames' times; for
    ``d = 0`` the mean: one shared wall). ``mode`` "frames" keeps the rows, "shared" takes ``d = 0``,
    "auto" the ``d <= max_degree`` minimizing the Gaussian BIC with the noise level profiled out,
    :math:`N \ln(\mathrm{RSS}_d/N) + p(2d+1)\ln N` over all :math:`N` numbers (:math:`p` columns): a
    rigid vessel gets one wall from all frames (its noise averaged), a distending one a smooth wall motion.
    """
    walls = np.asarray(walls, dtype=float)
    times_s = np.asarray(times_s, dtype=float)
    if mode == "frames" or walls.shape[0] < 3:
        return walls, WallChoice(None, "each frame's own wall")
    m, p = walls.shape
    top = 0 if mode == "shared" else int(max(0, min(max_degree, (m - 2) // 2)))  # keep residual degrees of freedom
    n_all = m * p
    fits, bic, solutions = [], {}, []
    for d in range(top + 1):
        basis = _trigonometric(times_s, omega, d)
        solution = np.linalg.lstsq(basis, walls, rcond=None)[0]
        fitted = basis @ solution
        rss = float(np.sum((walls - fitted) ** 2))
        bic[f"degree {d}"] = float(n_all * np.log(max(rss, 1e-300) / n_all) + p * (2 * d + 1) * np.log(n_all))
        fits.append(fitted)
        solutions.append(solution)
    if mode == "shared":
        how = "one shared wall: the frames' mean (--cine-walls shared)"
        return fits[0], WallChoice(0, how, bic, solutions[0])
    best = int(np.argmin([bic[f"degree {d}"] for d in range(top + 1)]))
    how = "one shared wall (no motion the BIC resolves)" if best == 0 else f"wall motion of degree {best} in time"
    how += ", chosen by the BIC over the frames' radius coefficients"
    return fits[best], WallChoice(best, how, bic, solutions[best])
