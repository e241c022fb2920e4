"""alpha from the data: the geometry problem solved with alpha fixed, from the discrepancy principle
(eq. (disc)) or from balancing on the radius (:mod:`wss_nlp.parameters.rules`)."""

from __future__ import annotations

import numpy as np

from ..core import radius as rad
from ..models import geometry as geo
from ..uncertainty import sensitivity as sens
from . import noise as nl
from . import rules as pr
from .options import ChoiceOptions

ALPHA_STOP = 1e-6  # smallest alpha a balancing search tries (V_N with N = 8 hardly amplifies noise below it)


def choose_alpha(
    problem: geo.GeometryProblem,
    raw,
    norm,
    lumen,
    gopt: geo.GeometryOptions,
    choice: ChoiceOptions,
    where: str,
    start=None,
):
    """Geometry solve with alpha fixed, from the discrepancy principle (eq. (disc)) or from balancing.

    The residual and the noise level are both taken on the annulus voxels
    (see :mod:`wss_nlp.parameters`); each solve starts from the previous one.
    ``start``: radius coefficients near the solution (a neighbouring frame's); a fixed alpha with IPOPT
    then starts there with a small barrier (:data:`wss_nlp.models.geometry.WARM_START`).
    """
    if choice.alpha_rule == "fixed":
        if start is not None and gopt.solver == "ipopt":
            solver = geo.solver_for(problem, gopt, warm=True)
            g = solver.solve(gopt.alpha, np.asarray(start, float), problem, np.zeros(solver.nlp.g.numel()))
        else:
            g = geo.solve(problem, gopt)
        return g, pr.ParameterChoice("alpha", "fixed", g.alpha)
    if gopt.solver == "ipopt":
        solver = geo.solver_for(problem, gopt)
        annulus = solver.nlp.model.annulus

        def run(alpha, prev):
            return solver.solve(alpha, None if prev is None else prev.coefficients, problem)
    else:
        annulus = geo.fitted_voxels(problem, gopt)  # the box annulus, or the k-space window the model fits

        def run(alpha, prev):
            return geo.solve_projected_gauss_newton(problem, gopt, None if prev is None else prev.coefficients, alpha)

    if choice.noise_magnitude is not None:
        noise = nl.NoiseEstimate(choice.noise_magnitude, "given (--noise-magnitude)")
    else:
        noise = nl.magnitude_noise(
            problem.magnitude, raw, lumen.noise_mask, norm.m0, norm.m1, problem.grid.voxel_area, annulus, where.rstrip()
        )
    if not noise.value > 0:
        g = geo.solve(problem, gopt)
        return g, pr.noise_free_choice("alpha", choice.alpha_rule, g.alpha, noise)
    if choice.alpha_rule == "balance":
        return balance_alpha(problem, gopt, run, noise, annulus.size, choice)

    def solve(alpha, prev):
        r = run(alpha, prev)
        return r, r.annulus_residual_norm

    g, picked = pr.discrepancy_search(solve, choice.alpha_start, noise.value, choice.tau_alpha)
    picked.name, picked.noise_method = "alpha", noise.method
    return g, picked


def balance_alpha(
    problem: geo.GeometryProblem,
    gopt: geo.GeometryOptions,
    run,
    noise: nl.NoiseEstimate,
    n_annulus: int,
    choice: ChoiceOptions,
):
    """alpha by the balancing principle on the radius ``R(phi_j)`` (:func:`.rules.balancing_principle`).

    Notes
    -----
    On the grid ``alpha_start 2^-n`` down to :data:`ALPHA_STOP`, each solve
    warm-started from the previous one. The noise part of ``R_alpha`` is
    linearized, ``e_alpha = D (dc/dm) n_m`` with ``dc/dm`` from the implicit
    function theorem on the KKT system (:func:`wss_nlp.uncertainty.sensitivity.geometry_kkt`,
    CasADi derivatives, active box rows included) and independent voxel noise
    of standard deviation ``sigma_m = delta / sqrt(|V| n_annulus)`` (the
    per-voxel level behind ``delta``, eq. (disc)). Units: R in mm.
    """
    alphas = pr.geometric_grid(choice.alpha_start, ALPHA_STOP)
    sigma_m = noise.value / np.sqrt(problem.grid.voxel_area * n_annulus)
    design = rad.design_matrix(gopt.box_angles(), gopt.n_fourier)
    n_box = design.shape[0]
    results, radii, maps, res = [], [], [], []
    prev = None
    for alpha in alphas:
        prev = run(alpha, prev)
        lam = prev.box_multipliers if prev.box_multipliers.size == n_box else np.zeros(n_box)
        dc, annulus = sens.geometry_kkt(problem, gopt, prev.coefficients, alpha, prev.gamma, lam)
        results.append(prev)
        radii.append(design @ prev.coefficients)
        maps.append((design @ dc[:, : annulus.size] * sigma_m).ravel())
        res.append(prev.annulus_residual_norm)
    r_mat, m_mat = np.array(radii), np.array(maps)
    j, ratio = pr.balancing_principle(r_mat @ r_mat.T, m_mat @ m_mat.T, choice.kappa_alpha)
    return results[j], pr.ParameterChoice(
        "alpha",
        "balance",
        float(alphas[j]),
        alphas,
        np.array(res),
        noise.value,
        noise.method,
        choice.kappa_alpha,
        criterion=ratio,
    )
