"""Choosing alpha and beta from the data: the rules of :mod:`wss_nlp.analysis` applied to the problems.

:func:`choose_alpha` solves the geometry problem with alpha fixed, from the
discrepancy principle (eq. (disc)) or from balancing on the radius;
:func:`choose_beta` picks beta for the velocity problem (fixed, eq. (disc2),
GCV, the L-curve or balancing on the WSS); :func:`parse_rule` turns a
user's word into a rule. Used by single slices (:mod:`wss_nlp.reconstruct`)
and stacks (:mod:`wss_nlp.stack`) alike.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from . import analysis as an
from . import geometry as geo
from . import measurement as meas
from . import radius as rad
from . import sensitivity as sens
from . import velocity as vel
from . import wss as wss_mod
from .errors import InputError
from .tikhonov import BETA_MIN

if TYPE_CHECKING:
    from .reconstruct import ReconstructionOptions

#: Smallest beta of the GCV, L-curve, balancing and discrepancy grids (:data:`wss_nlp.tikhonov.BETA_MIN`).
BETA_STOP = BETA_MIN

ALPHA_RULES = ("fixed", "discrepancy", "balance")
ALPHA_STOP = 1e-6  # smallest alpha a balancing search tries (V_N with N = 8 hardly amplifies noise below it)
BETA_RULES = ("fixed", "discrepancy", "gcv", "lcurve", "balance")
DEPHASING_BETA_RULES = ("gcv", "same")
#: What ``auto`` means for alpha and beta: the rule closest to the oracle in scripts/accuracy.py --auto (docs).
AUTO_RULE = "balance"


def parse_rule(word: str, rules: tuple, name: str) -> str:
    """The rule a user's word names (``auto`` -> :data:`AUTO_RULE`); InputError lists the accepted words."""
    word = word.strip().lower()
    if word == "auto":
        return AUTO_RULE
    if word in rules and word != "fixed":
        return word
    words = ["auto"] + [r for r in rules if r != "fixed"]
    raise InputError(f"{name} must be a number or one of {', '.join(words)}; got {word!r}")


def _noise_free_choice(name: str, rule: str, fixed: float, noise: an.NoiseEstimate) -> an.ParameterChoice:
    """The fixed value, recorded as such, when the estimated noise is zero (noise-free synthetic data).

    There is no noise to balance against or to match a residual to; the
    choice says so (``SliceResult.warnings`` reports it) instead of guessing.
    """
    return an.ParameterChoice(
        name,
        "fixed",
        fixed,
        noise=0.0,
        noise_method=f"{rule} needs noise, the estimate is zero ({noise.method}); the fixed value is used",
    )


def choose_alpha(problem: geo.GeometryProblem, raw, norm, lumen, options: ReconstructionOptions, where: str):
    """Geometry solve with alpha fixed, from the discrepancy principle (eq. (disc)) or from balancing.

    The residual and the noise level are both taken on the annulus voxels
    (see :mod:`wss_nlp.analysis`); each solve starts from the previous one.
    """
    gopt = options.geometry
    if options.alpha_rule == "fixed":
        g = geo.solve(problem, gopt)
        return g, an.ParameterChoice("alpha", "fixed", g.alpha)
    if gopt.solver == "ipopt":
        solver = geo.IpoptGeometrySolver(problem, gopt)
        annulus = solver.nlp.model.annulus

        def run(alpha, prev):
            return solver.solve(alpha, None if prev is None else prev.coefficients)
    else:
        annulus = meas.annulus_model(
            problem.grid, problem.center, problem.r0, problem.r1, geo.quad_order(problem, gopt)
        ).annulus

        def run(alpha, prev):
            return geo.solve_projected_gauss_newton(problem, gopt, None if prev is None else prev.coefficients, alpha)

    if options.noise_magnitude is not None:
        noise = an.NoiseEstimate(options.noise_magnitude, "given (--noise-magnitude)")
    else:
        noise = an.magnitude_noise(
            problem.magnitude, raw, lumen.noise_mask, norm.m0, norm.m1, problem.grid.voxel_area, annulus, where.rstrip()
        )
    if not noise.value > 0:
        g = geo.solve(problem, gopt)
        return g, _noise_free_choice("alpha", options.alpha_rule, g.alpha, noise)
    if options.alpha_rule == "balance":
        return balance_alpha(problem, gopt, run, noise, annulus.size, options)

    def solve(alpha, prev):
        r = run(alpha, prev)
        return r, r.annulus_residual_norm

    g, choice = an.discrepancy_search(solve, options.alpha_start, noise.value, options.tau_alpha)
    choice.name, choice.noise_method = "alpha", noise.method
    return g, choice


def balance_alpha(
    problem: geo.GeometryProblem,
    gopt: geo.GeometryOptions,
    run,
    noise: an.NoiseEstimate,
    n_annulus: int,
    options: ReconstructionOptions,
):
    """alpha by the balancing principle on the radius ``R(phi_j)`` (:func:`wss_nlp.analysis.balancing_principle`).

    Notes
    -----
    On the grid ``alpha_start 2^-n`` down to :data:`ALPHA_STOP`, each solve
    warm-started from the previous one. The noise part of ``R_alpha`` is
    linearized, ``e_alpha = D (dc/dm) n_m`` with ``dc/dm`` from the implicit
    function theorem on the KKT system (:func:`wss_nlp.sensitivity.geometry_kkt`,
    CasADi derivatives, active box rows included) and independent voxel noise
    of standard deviation ``sigma_m = delta / sqrt(|V| n_annulus)`` (the
    per-voxel level behind ``delta``, eq. (disc)). Units: R in mm.
    """
    alphas = an.geometric_grid(options.alpha_start, ALPHA_STOP)
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
    j, ratio = an.balancing_principle(r_mat @ r_mat.T, m_mat @ m_mat.T, options.kappa_alpha)
    return results[j], an.ParameterChoice(
        "alpha",
        "balance",
        float(alphas[j]),
        alphas,
        np.array(res),
        noise.value,
        noise.method,
        options.kappa_alpha,
        criterion=ratio,
    )


def choose_beta(
    vp: vel.VelocityProblem, raw, lumen, venc, options: ReconstructionOptions, where: str, viscosity_pa_s: float
):
    """beta fixed, from the discrepancy principle (eq. (disc2), with the residual), GCV, the L-curve or balancing.

    The searches use direct Cholesky solves of the (linear) velocity problem;
    the chosen beta is then solved with the configured solver.
    """
    rule = options.beta_rule
    if rule == "fixed":
        return an.ParameterChoice("beta", "fixed", options.velocity.beta)
    if rule == "gcv":
        return gcv_beta(vp, options)
    betas = an.geometric_grid(options.beta_start, BETA_STOP)
    if rule == "lcurve":
        _, res, pen = an.gcv_curve(vp.operator, vp.weights, vp.data, vp.gram, betas)
        i, k = an.lcurve_corner(res, pen)
        return an.ParameterChoice("beta", "lcurve", float(betas[i]), betas, res, criterion=k)
    if options.noise_velocity is not None:
        noise = an.NoiseEstimate(
            options.noise_velocity,
            "given (--noise-velocity)",
            {"per_voxel": np.full(vp.data.size, options.noise_velocity)},
        )
    else:
        noise = an.velocity_noise(
            vp.data_image, raw, lumen.noise_mask, vp.voxels.index, vp.weights, venc, where.rstrip()
        )
    if not noise.value > 0:
        return _noise_free_choice("beta", rule, options.velocity.beta, noise)
    if rule == "balance":
        smat, _ = wss_mod.wss_matrix(vp.basis, vp.disk_map, viscosity_pa_s, options.n_phi)
        i, ratio, res = an.wss_balance(
            vp.operator, vp.weights, vp.data, vp.gram, betas, smat, noise.details["per_voxel"], options.kappa_beta
        )
        return an.ParameterChoice(
            "beta",
            "balance",
            float(betas[i]),
            betas,
            res,
            noise.value,
            noise.method,
            options.kappa_beta,
            criterion=ratio,
        )

    def solve(beta, prev):
        c = vel.solve_cholesky(vp, beta)
        return c, vp.residual_norm(c)

    _, choice = an.discrepancy_search(solve, options.beta_start, noise.value, options.tau_beta, smallest=BETA_STOP)
    choice.name, choice.noise_method = "beta", noise.method
    return choice


def gcv_beta(vp: vel.VelocityProblem, options: ReconstructionOptions) -> an.ParameterChoice:
    """beta minimizing GCV on the grid ``beta_start 2^-n`` down to ``BETA_STOP``."""
    betas = an.geometric_grid(options.beta_start, BETA_STOP)
    gcv, res, _ = an.gcv_curve(vp.operator, vp.weights, vp.data, vp.gram, betas)
    i = int(np.argmin(gcv))
    return an.ParameterChoice("beta", "gcv", float(betas[i]), betas, res, criterion=gcv)
