"""Choosing alpha and beta from the data (Theorems 2.1, 3.4; eqs. (disc), (disc2)).

* Noise levels: :func:`magnitude_noise` (delta, for the normalized
  magnitude) and :func:`velocity_noise` (epsilon, for the velocity), each
  returned with how it was obtained.
* :func:`discrepancy_search`: ``p = max{p0 2^-n : residual(p) <= tau * noise}``,
  each solve warm-started from the previous one.
* For the linear velocity problem: :func:`gcv_curve` (generalized
  cross-validation, closed form) and :func:`lcurve_corner`.
* :func:`oracle` picks the error-minimizing value when the truth is known
  (phantoms only; used to judge the rules, never as a rule).

Residuals and noise levels are measured on the voxels where the model
depends on the unknown: the annulus of the geometry model (voxels that no
admissible R can change contribute pure noise, equally for every alpha) and
the voxels that meet the lumen for the velocity. This keeps the discrepancy
independent of the size of the field of view.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage

from .errors import InputError
from .preprocess import robust_std, where_prefix

#: Fewest plateau voxels on which a noise level is estimated.
MIN_PLATEAU_VOXELS = 20


class NoiseEstimationError(InputError):
    """The data do not allow a noise estimate; the message names the option that supplies one."""


@dataclass
class NoiseEstimate:
    value: float
    method: str
    details: dict = field(default_factory=dict)


def _plateaus(mask: np.ndarray, width: int = 2):
    inner = scipy.ndimage.binary_erosion(mask, iterations=width)
    outer = ~scipy.ndimage.binary_dilation(mask, iterations=width)
    return inner, outer


def magnitude_noise(m: np.ndarray, raw: np.ndarray, mask: np.ndarray, m0: float, m1: float, voxel_area: float,
                    region: np.ndarray, source: str = "") -> NoiseEstimate:
    """Noise level ``delta`` of the normalized magnitude on the voxels ``region``.

    Notes
    -----
    ``delta^2 = |V| sum_{i in region} E[(m_i - f_i)^2]`` with ``f_i`` the
    noise-free volume fraction. On the lumen plateau (two voxels inside the
    bright region) ``f = 1`` and on the background plateau ``f = 0``, so
    their mean squares are measured directly (they include the truncation
    ``T``); wall voxels are not truncated, so they get the variance of the
    raw lumen signal, ``(1.4826 MAD(raw on the lumen plateau) / (m1 - m0))^2``.
    Units: mm (an L^2(D) norm of a dimensionless image).
    """
    inner, outer = _plateaus(mask)
    where = where_prefix(source)
    if outer.sum() < MIN_PLATEAU_VOXELS:
        raise NoiseEstimationError(f"{where}cannot estimate the magnitude noise: no background in the field of view; "
                                   "pass --noise-magnitude (delta, mm) or a fixed --alpha")
    if inner.sum() < MIN_PLATEAU_VOXELS:
        raise NoiseEstimationError(f"{where}cannot estimate the magnitude noise: the lumen is too small for a plateau; "
                                   "pass --noise-magnitude (delta, mm) or a fixed --alpha")
    msq_in = float(np.mean((1 - m[inner]) ** 2))
    msq_out = float(np.mean(m[outer] ** 2))
    var_wall = (robust_std(raw[inner]) / (m1 - m0)) ** 2
    flat_in, flat_out = inner.ravel()[region], outer.ravel()[region]
    flat_wall = ~(flat_in | flat_out)
    total = msq_in * flat_in.sum() + msq_out * flat_out.sum() + var_wall * flat_wall.sum()
    return NoiseEstimate(
        value=float(np.sqrt(voxel_area * total)),
        method="plateaus: mean squares on lumen and background plateaus, raw lumen spread on wall voxels",
        details={"msq_lumen": msq_in, "msq_background": msq_out, "var_wall": var_wall,
                 "n_lumen": int(flat_in.sum()), "n_background": int(flat_out.sum()), "n_wall": int(flat_wall.sum())},
    )


def complex_noise_sigma(raw: np.ndarray, mask: np.ndarray) -> float:
    """Per-channel standard deviation of complex Gaussian noise from the background.

    The background magnitude is Rayleigh distributed, ``E[|d|^2] = 2 sigma^2``.
    """
    _, outer = _plateaus(mask)
    if outer.sum() < MIN_PLATEAU_VOXELS:
        return float("nan")
    return float(np.sqrt(np.mean(raw[outer] ** 2) / 2))


def velocity_noise(velocity: np.ndarray, raw: np.ndarray, mask: np.ndarray, voxel_index: np.ndarray,
                   weights: np.ndarray, venc: float | None, source: str = "") -> NoiseEstimate:
    """Noise level ``epsilon`` of the velocity, in the units of the velocity misfit.

    Notes
    -----
    With ``venc`` (phase data) the phase noise of voxel i is about
    ``sigma / |d_i|`` for complex noise of standard deviation ``sigma`` per
    channel (from the Rayleigh background), so
    ``sigma_u,i = venc sigma / (pi |d_i|)``, capped at the standard deviation
    of a uniform phase, ``venc / sqrt(3)``; it grows as the magnitude falls
    towards the wall (Appendix B). Then
    ``epsilon^2 = sum_i w_i sigma_u,i^2 / sum_i w_i`` with the partial-volume
    weights of the misfit. Without ``venc`` (velocity data only) a
    homoscedastic ``sigma_u`` is taken from the high frequencies on the
    lumen plateau: ``r = u - (mean of the 4 neighbours)`` has variance
    ``1.25 sigma_u^2`` for white noise.
    """
    where = where_prefix(source)
    sigma = complex_noise_sigma(raw, mask)
    if venc is not None and np.isfinite(sigma):
        mag = np.maximum(raw.ravel()[voxel_index], 1e-300)
        su = np.minimum(venc * sigma / (np.pi * mag), venc / np.sqrt(3))
        eps = float(np.sqrt(np.sum(weights * su**2) / np.sum(weights)))
        return NoiseEstimate(eps, "phase noise: venc sigma / (pi |d_i|), sigma from the Rayleigh background",
                             {"sigma_complex": sigma, "venc_m_s": venc})
    inner, _ = _plateaus(mask)
    inner &= scipy.ndimage.binary_erosion(np.ones_like(mask), iterations=1)
    if inner.sum() < MIN_PLATEAU_VOXELS:
        raise NoiseEstimationError(f"{where}cannot estimate the velocity noise: no venc and the lumen is too small "
                                   "for a plateau; pass --noise-velocity (epsilon, m/s) or a fixed --beta")
    u = velocity
    nb = 0.25 * (np.roll(u, 1, 0) + np.roll(u, -1, 0) + np.roll(u, 1, 1) + np.roll(u, -1, 1))
    r = (u - nb)[inner]
    s = robust_std(r) / np.sqrt(1.25)
    return NoiseEstimate(s, "high-pass: MAD of u minus its 4-neighbour mean on the lumen plateau", {})


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


def discrepancy_search(solve, start: float, noise: float, tau: float, factor: float = 0.5, max_steps: int = 60,
                       stagnation: float = 1e-3, floor_slack: float = 0.02, smallest: float = 0.0):
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
            return prev, ParameterChoice("", "discrepancy", p, np.array(params), np.array(residuals), noise, "", tau,
                                         True)
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


def gcv_curve(operator, weights, data, gram, betas):
    """Generalized cross-validation of the linear velocity problem for each beta.

    Notes
    -----
    With ``W = diag(w)/A``, ``H = T^T W T + (beta/pi) G`` and the influence
    matrix ``A_beta = W^{1/2} T H^{-1} T^T W^{1/2}``,
    ``GCV(beta) = n |W^{1/2}(T c_beta - u)|^2 / (n - tr A_beta)^2``,
    ``tr A_beta = tr(H^{-1} T^T W T)``; everything is ``n_basis``-sized.
    Returns ``(gcv, residual_norms, penalties)`` arrays.
    """
    w = weights / np.sum(weights)
    tw = operator * w[:, None]
    ktk = tw.T @ operator
    rhs = tw.T @ data
    n = data.size
    out_g, out_r, out_p = [], [], []
    for beta in betas:
        h = ktk + beta / np.pi * gram
        c = np.linalg.solve(h, rhs)
        r2 = float(np.sum(w * (operator @ c - data) ** 2))
        tr = float(np.trace(np.linalg.solve(h, ktk)))
        out_g.append(n * r2 / (n - tr) ** 2)
        out_r.append(np.sqrt(r2))
        out_p.append(float(c @ gram @ c / np.pi))
    return np.array(out_g), np.array(out_r), np.array(out_p)


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
