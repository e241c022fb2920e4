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
    CineModelOptions,
    FrameTerms,
    _columns,
    fit,
    time_factors,
    wall_shapes,
)
from .layer import PlainCriterion

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
            }
        )


def criterion_scale(terms: list[FrameTerms]) -> tuple[float, float]:
    """``(nu, ln(nu N))`` of the criterion over all the frames' voxel values."""
    nu = min(t.nu for t in terms)
    return nu, float(np.log(nu * sum(t.n_data for t in terms)))


def choose(terms: list[FrameTerms], omega: float, nu_m2_s: float, options: CineModelOptions, prior_bic=None):
    """The slice's velocity model over the cycle by the BIC (module notes); ``(CineModelChoice, fit or None)``.

    ``prior_bic``: the criterion of the temporal prior (:mod:`wss_nlp.models.temporal`) where it applies. The
    momentum model must beat the better plain candidate (the frames' own fits, the prior) by
    :data:`EVIDENCE`, the prior the frames' own fits; otherwise the frames keep their own fits.
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
    # the frames' own fits: each at its best beta, weighed with the series' ln N
    bic["independent"] = float(sum(np.min(t.nu * t.plain_chi2 + log_n * t.plain_dof) for t in terms))
    if prior_bic is not None:
        bic["temporal"] = float(prior_bic)
    if options.model == "momentum":
        return CineModelChoice("momentum", best, bic, float("nan"), used, criterion + "; forced"), fits[best]
    if options.model == "temporal":
        if prior_bic is None:
            why = "; the temporal prior needs every frame (at least 3, equally spaced): independent frames"
            return CineModelChoice("independent", 0, bic, float("nan"), used, criterion + why), None
        return CineModelChoice("temporal", 0, bic, float("nan"), used, criterion + "; forced"), None
    # a richer model must beat every simpler one by the evidence: the momentum model both plain candidates,
    # the temporal prior the frames' own fits; otherwise the frames keep their own fits
    independent = bic["independent"]
    prior = bic.get("temporal", np.inf)
    lead = min(independent, prior) - bics[best] - EVIDENCE
    if lead > 0:
        return CineModelChoice("momentum", best, bic, float(lead), used, criterion), fits[best]
    prior_lead = independent - prior - EVIDENCE
    if prior_lead > 0:
        return CineModelChoice("temporal", 0, bic, float(min(prior_lead, -lead)), used, criterion), None
    return CineModelChoice("independent", 0, bic, float(min(-lead, -prior_lead)), used, criterion), None


@dataclass
class WallChoice:
    """How the cycle's models took the frames' walls: the temporal degree and the criterion values."""

    degree: int | None  # trigonometric degree in time (0: one shared wall); None: each frame's own
    how: str
    bic: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"degree": self.degree, "how": self.how, "bic": self.bic}


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
    if mode == "frames" or walls.shape[0] < 3:
        return walls, WallChoice(None, "each frame's own wall")
    m, p = walls.shape
    top = 0 if mode == "shared" else int(max(0, min(max_degree, (m - 2) // 2)))  # keep residual degrees of freedom
    n_all = m * p
    fits, bic = [], {}
    for d in range(top + 1):
        cols = [np.ones(m)]
        for n in range(1, d + 1):
            cols += [np.cos(n * omega * times_s), np.sin(n * omega * times_s)]
        basis = np.array(cols).T
        fitted = basis @ np.linalg.lstsq(basis, walls, rcond=None)[0]
        rss = float(np.sum((walls - fitted) ** 2))
        bic[f"degree {d}"] = float(n_all * np.log(max(rss, 1e-300) / n_all) + p * (2 * d + 1) * np.log(n_all))
        fits.append(fitted)
    if mode == "shared":
        return fits[0], WallChoice(0, "one shared wall: the frames' mean (--cine-walls shared)", bic)
    best = int(np.argmin([bic[f"degree {d}"] for d in range(top + 1)]))
    how = "one shared wall (no motion the BIC resolves)" if best == 0 else f"wall motion of degree {best} in time"
    return fits[best], WallChoice(best, how + ", chosen by the BIC over the frames' radius coefficients", bic)
