"""beta from the data: fixed, the discrepancy principle (eq. (disc2)), GCV, the L-curve or balancing on the WSS
(:mod:`wss_nlp.parameters.rules`) for one velocity problem, a layer's BIC beta, and one beta for a z-coupled
segment."""

from __future__ import annotations

import numpy as np

from ..core.tikhonov import BETA_MIN
from ..models import velocity as vel
from ..models import wss as wss_mod
from . import noise as nl
from . import rules as pr
from .options import ChoiceOptions

#: Smallest beta of the GCV, L-curve, balancing and discrepancy grids (:data:`wss_nlp.core.tikhonov.BETA_MIN`).
BETA_STOP = BETA_MIN
#: A balancing choice among the last this many grid betas has too few smaller ones to balance against.
BALANCE_TAIL = 3


def velocity_beta(
    vp, near, raw, lumen, venc, choice: ChoiceOptions, vopt: vel.VelocityOptions, n_phi: int, where: str,
    viscosity_pa_s: float,
):  # fmt: skip
    """beta of the velocity fit: the rule's (:func:`choose_beta`), or the BIC's for a chosen near-wall layer.

    Balancing weighs the noise the penalty removes; layer columns are not
    penalized, so with them it drifts to the largest beta. The beta at
    which the chosen model's BIC is smallest is used instead.
    """
    if near is not None and near.model != "plain" and choice.beta_rule == "balance" and np.isfinite(near.beta):
        return pr.ParameterChoice("beta", "bic", near.beta, noise_method="BIC of the chosen near-wall model")
    return choose_beta(vp, raw, lumen, venc, choice, vopt, n_phi, where, viscosity_pa_s)


def choose_beta(
    vp: vel.VelocityProblem,
    raw,
    lumen,
    venc,
    choice: ChoiceOptions,
    vopt: vel.VelocityOptions,
    n_phi: int,
    where: str,
    viscosity_pa_s: float,
):
    """beta fixed, from the discrepancy principle (eq. (disc2), with the residual), GCV, the L-curve or balancing.

    The searches use direct Cholesky solves of the (linear) velocity problem;
    the chosen beta is then solved with the configured solver.
    """
    rule = choice.beta_rule
    if rule == "fixed":
        return pr.ParameterChoice("beta", "fixed", vopt.beta)
    if rule == "gcv":
        return gcv_beta(vp, choice)
    betas = pr.geometric_grid(choice.beta_start, BETA_STOP)
    if rule == "lcurve":
        _, res, pen = pr.gcv_curve(vp.tikhonov, betas)
        i, k = pr.lcurve_corner(res, pen)
        return pr.ParameterChoice("beta", "lcurve", float(betas[i]), betas, res, criterion=k)
    noise = nl.given_or_velocity_noise(vp, raw, lumen, venc, choice.noise_velocity, where)
    if not noise.value > 0:
        return pr.noise_free_choice("beta", rule, vopt.beta, noise)
    if rule == "balance":
        smat, _ = wss_mod.wss_matrix(vp.basis, vp.disk_map, viscosity_pa_s, n_phi)
        correlate = None if vp.noise_correlation is None else vp.noise_correlation.apply
        i, ratio, res = pr.wss_balance(
            vp.tikhonov,
            betas,
            smat,
            noise.details["per_voxel"],
            choice.kappa_beta,
            correlate,
        )
        return pr.ParameterChoice(
            "beta",
            "balance",
            float(betas[i]),
            betas,
            res,
            noise.value,
            noise.method,
            choice.kappa_beta,
            # the last betas agree with "every smaller one" (few or none) almost trivially: reaching them means
            # nothing balanced
            satisfied=bool(i < betas.size - BALANCE_TAIL),
            criterion=ratio,
        )

    def solve(beta, prev):
        c = vel.solve_cholesky(vp, beta)
        return c, vp.residual_norm(c)

    _, picked = pr.discrepancy_search(solve, choice.beta_start, noise.value, choice.tau_beta, smallest=BETA_STOP)
    picked.name, picked.noise_method = "beta", noise.method
    return picked


def gcv_beta(vp: vel.VelocityProblem, choice: ChoiceOptions) -> pr.ParameterChoice:
    """beta minimizing GCV on the grid ``beta_start 2^-n`` down to ``BETA_STOP``."""
    betas = pr.geometric_grid(choice.beta_start, BETA_STOP)
    gcv, res, _ = pr.gcv_curve(vp.tikhonov, betas)
    i = int(np.argmin(gcv))
    return pr.ParameterChoice("beta", "gcv", float(betas[i]), betas, res, criterion=gcv)


def segment_beta(choices) -> float:
    """One beta for a z-coupled segment of a stack from its slices' choices: their geometric median.

    The z-penalty pools neighbouring slices, so they need a common beta; the
    median keeps one slice with an outlying choice (a noisier image, a
    fallback) from setting it, and the log scale matches the 2^-n grids.
    """
    return geometric_median([c.chosen for c in choices])


def geometric_median(values) -> float:
    """``exp(median(log values))``: the median on a log scale, for positive parameters pooled over slices."""
    return float(np.exp(np.median(np.log(values))))
