"""Rules that choose alpha and beta (eqs. (disc), (disc2)), on problem objects.

* :func:`discrepancy_search`: ``p = max{p0 2^-n : residual(p) <= tau * noise}``,
  each solve warm-started from the previous one (any problem: a ``solve``
  callable);
* for the linear velocity problem (a :class:`wss_nlp.core.tikhonov.LinearTikhonov`):
  :func:`gcv_curve` (generalized cross-validation, closed form),
  :func:`lcurve_corner` and :func:`balancing_principle` (Lepskii: compare
  the WSS estimates of neighbouring betas with their exact noise
  propagation, :func:`wss_balance`);
* :func:`oracle` picks the error-minimizing value when the truth is known
  (phantoms only; used to judge the rules, never as a rule).

:mod:`wss_nlp.parameters.choice` applies them to a slice's geometry and
velocity problems with the noise levels of :mod:`wss_nlp.parameters.noise`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..core.tikhonov import LinearTikhonov


@dataclass
class ParameterChoice:
    """How a regularization parameter was chosen, with the whole search."""

    name: str  # "alpha" or "beta"
    rule: str  # "fixed", "discrepancy", "gcv", "lcurve", "oracle"
    chosen: float
    parameters: np.ndarray = field(default_factory=lambda: np.zeros(0))
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))
    noise: float = float("nan")
    noise_method: str = ""
    tau: float = float("nan")
    satisfied: bool = True
    criterion: np.ndarray = field(default_factory=lambda: np.zeros(0))  # GCV values / curvature, if any

    @property
    def threshold(self) -> float:
        return self.tau * self.noise


def discrepancy_search(
    solve,
    start: float,
    noise: float,
    tau: float,
    factor: float = 0.5,
    max_steps: int = 60,
    stagnation: float = 1e-3,
    floor_slack: float = 0.02,
    smallest: float = 0.0,
):
    """``p = max{start factor^n : residual(p) <= tau * noise}``, eq. (disc) / (disc2).

    Parameters
    ----------
    solve : callable
        ``solve(p, previous) -> (result, residual)``; ``previous`` is the
        result of the preceding parameter (for warm starts) or None.
    stagnation, floor_slack : float
        If the residual, after falling by ``20 stagnation`` from its first
        value, stops falling (relative change below ``stagnation`` twice in
        a row) while still above ``tau * noise``, model error, not
        noise, limits the fit; the search stops and returns the largest
        parameter whose residual is within ``1 + floor_slack`` of the
        smallest one, with ``satisfied = False``. The same fallback applies
        after ``max_steps`` or below ``smallest``.
    smallest : float
        No parameter below this is tried (a slowly falling residual would
        otherwise lead the search to values where the solve is meaningless:
        measured, beta = 4e-18 gave a 530 % WSS error).

    Returns
    -------
    (result, ParameterChoice)
    """
    if not noise > 0:
        raise InputError(f"the discrepancy principle needs a positive noise level, got {noise}")
    if not start >= smallest:
        raise InputError(f"the discrepancy search starts at {start:g}, below its smallest allowed value {smallest:g}")
    params, residuals, results = [], [], []
    prev = None
    p = float(start)
    flat = 0
    for _ in range(max_steps):
        if p < smallest:
            break
        prev, res = solve(p, prev)
        params.append(p)
        residuals.append(float(res))
        results.append(prev)
        if res <= tau * noise:
            return prev, ParameterChoice(
                "", "discrepancy", p, np.array(params), np.array(residuals), noise, "", tau, True
            )
        dropped = res < (1 - 20 * stagnation) * residuals[0]  # flat before the fall is not stagnation
        if dropped and residuals[-2] - res <= stagnation * residuals[-2]:
            flat += 1
            if flat >= 2:
                break
        else:
            flat = 0
        p *= factor
    r = np.array(residuals)
    i = int(np.flatnonzero(r <= (1 + floor_slack) * r.min())[0])
    return results[i], ParameterChoice("", "discrepancy", params[i], np.array(params), r, noise, "", tau, False)


def gcv_curve(problem: LinearTikhonov, betas):
    """Generalized cross-validation of the linear velocity problem for each beta.

    Notes
    -----
    With ``W = diag(w)/A``, ``H = T^T W T + (beta/pi) G`` and the influence
    matrix ``A_beta = W^{1/2} T H^{-1} T^T W^{1/2}``,
    ``GCV(beta) = n |W^{1/2}(T c_beta - u)|^2 / (n - tr A_beta)^2``,
    ``tr A_beta = tr(H^{-1} T^T W T)``; the whole grid from one generalized
    eigendecomposition (:meth:`wss_nlp.core.tikhonov.LinearTikhonov.gcv`).
    Returns ``(gcv, residual_norms, penalties)`` arrays.
    """
    return problem.gcv(betas)


def balancing_principle(gram_estimates: np.ndarray, gram_noise: np.ndarray, kappa: float) -> tuple[int, np.ndarray]:
    """Lepskii's balancing principle from the Gram matrices of the estimates and of their noise parts.

    Parameters
    ----------
    gram_estimates : (n, n) array
        ``<x_j, x_k>`` of the estimates, ordered from the most to the least
        regularized parameter.
    gram_noise : (n, n) array
        ``E<e_j, e_k>`` of their noise parts (``x_j = E x_j + e_j``).
    kappa : float
        How many noise standard deviations a difference may reach.

    Returns
    -------
    (j, ratio)
        ``j`` is the first (most regularized) index with
        ``|x_j - x_k| <= kappa s_jk`` for every ``k > j``, where
        ``s_jk^2 = E|e_j - e_k|^2``; ``ratio[j] = max_k |x_j - x_k| / s_jk``
        (0 for the last index).

    Notes
    -----
    Less regularized estimates have less bias and more noise; a difference
    larger than the noise can explain is bias of the more regularized one,
    so the choice is the largest parameter whose estimate agrees with every
    less regularized one within their noise (Mathé & Pereverzev 2003; Mathé,
    "The Lepskii principle revisited", 2006). Only differences of estimates
    enter, so model error that is common to all parameters does not bias
    the choice the way it biases a residual (discrepancy principle).
    """
    if not kappa > 0:
        raise InputError(f"the balancing principle needs kappa > 0, got {kappa}")
    d_est = np.diag(gram_estimates)
    d_noise = np.diag(gram_noise)
    diff = np.sqrt(np.maximum(d_est[:, None] + d_est[None, :] - 2 * gram_estimates, 0.0))
    sd = np.sqrt(np.maximum(d_noise[:, None] + d_noise[None, :] - 2 * gram_noise, 0.0))
    n = d_est.size
    ratio = np.zeros(n)
    for j in range(n - 1):
        s = sd[j, j + 1 :]
        ratio[j] = float(np.max(np.where(s > 0, diff[j, j + 1 :] / np.where(s > 0, s, 1.0), np.inf)))
    return int(np.flatnonzero(ratio <= kappa)[0]), ratio


def balance_grams(problem: LinearTikhonov, betas, functional, sigma_u, correlate=None):
    """Gram matrices of ``S c_beta`` and of their noise parts for the linear velocity problem, and the residuals.

    Notes
    -----
    ``c_beta = H_beta^{-1} T^T W u`` with ``H_beta = T^T W T + (beta/pi) G``
    and ``W = diag(w)/A`` (:func:`gcv_curve`). With independent voxel noise
    of standard deviations ``sigma_u``, the noise part of ``S c_j`` is
    ``M_j n`` with ``M_j = S H_j^{-1} T^T W diag(sigma_u)`` and ``n`` standard
    normal, so ``E<e_j, e_k> = tr(M_j M_k^T)``; the whole beta grid from one
    generalized eigendecomposition (:meth:`wss_nlp.core.tikhonov.LinearTikhonov.balance_grams`).
    Returns ``(gram_estimates, gram_noise, residual_norms)``.
    """
    return problem.balance_grams(betas, functional, sigma_u, correlate)


def wss_balance(problem: LinearTikhonov, betas, wss_matrix, sigma_u, kappa: float, correlate=None):
    """The balancing principle for beta on the WSS ``tau = S c`` (``wss_matrix``, Pa, at the wall points).

    ``betas`` must decrease; ``sigma_u`` (m/s) per voxel. Returns
    ``(index, ratio, residual_norms)``: see :func:`balancing_principle`
    and :func:`balance_grams` (``correlate``: correlated noise, ``x -> C x``).
    """
    g_est, g_noise, res = balance_grams(problem, betas, wss_matrix, sigma_u, correlate)
    j, ratio = balancing_principle(g_est, g_noise, kappa)
    return j, ratio, res


def curvature(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Menger curvature of consecutive point triples (ends get -inf)."""
    k = np.full(x.size, -np.inf)
    for i in range(1, x.size - 1):
        a = np.array([x[i - 1], y[i - 1]])
        b = np.array([x[i], y[i]])
        c = np.array([x[i + 1], y[i + 1]])
        area2 = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        denom = np.linalg.norm(b - a) * np.linalg.norm(c - b) * np.linalg.norm(c - a)
        k[i] = 2 * abs(area2) / denom if denom > 0 else -np.inf
    return k


def lcurve_corner(residuals: np.ndarray, penalties: np.ndarray) -> tuple[int, np.ndarray]:
    """Index of the L-curve corner: largest curvature of ``(log residual, log penalty)``."""
    k = curvature(np.log(residuals), np.log(penalties))
    return int(np.argmax(k)), k


def oracle(parameters, errors) -> tuple[float, float]:
    """The parameter with the smallest error, and that error (truth needed: phantoms only)."""
    errors = np.asarray(errors, dtype=float)
    i = int(np.nanargmin(errors))
    return float(np.asarray(parameters)[i]), float(errors[i])


def geometric_grid(start: float, stop: float, factor: float = 0.5) -> np.ndarray:
    """``start, start factor, ...`` down to ``stop`` (inclusive within rounding)."""
    n = int(np.floor(np.log(stop / start) / np.log(factor) + 1e-9)) + 1
    return start * factor ** np.arange(n)


def noise_free_choice(name: str, rule: str, fixed: float, noise) -> ParameterChoice:
    """The fixed value, recorded as such, when the estimated noise is zero (noise-free synthetic data).

    There is no noise to balance against or to match a residual to; the
    choice says so (``SliceResult.warnings`` reports it) instead of guessing.
    """
    return ParameterChoice(
        name,
        "fixed",
        fixed,
        noise=0.0,
        noise_method=f"{rule} needs noise, the estimate is zero ({noise.method}); the fixed value is used",
    )
