r"""A periodic temporal prior on the velocity of a cine slice's frames.

Every frame :math:`k` keeps its own wall, voxel operator :math:`T_k`, data :math:`u_k` and Tikhonov weight
:math:`\beta_k` (the one its own fit chose, :mod:`wss_nlp.choice`); the prior ties the frames' coefficients
by their periodic second difference over equally spaced frames:

.. math::

    \min_{v_0, \dots, v_{n-1}} \sum_k \Big[\|T_k v_k - u_k\|_{W_k}^2 + \frac{\beta_k}{\pi} v_k^\top G v_k\Big]
    + \frac{\gamma}{\pi}\sum_k \|(D_2 v)_k\|^2_{L^2(B)},
    \qquad (D_2 v)_k = v_{k+1} - 2 v_k + v_{k-1} \text{ (periodic)},

the plain Tikhonov functional of every frame (eq. (tik2), :mod:`wss_nlp.velocity`; the coefficients live on
the reference disk, so frames on different walls are compared there). Its normal equations

.. math::

    \Big(\operatorname{blockdiag}_k\big(K_k + \tfrac{\beta_k}{\pi} G\big)
    + \tfrac{\gamma}{\pi} D_2^\top D_2 \otimes G_0\Big) v = \big(T_k^\top W_k u_k\big)_k,
    \qquad K_k = T_k^\top W_k T_k,

with :math:`G` the penalty's Gram matrix and :math:`G_0` the :math:`L^2(B)` one, are solved by one Cholesky
factorization per :math:`\gamma` (``n_frames`` blocks of the basis size: 2380 unknowns for 20 frames of 119
functions, about 0.1 s). :math:`\gamma \to 0` gives the frames' own fits back.

Notes
-----
Choice of :math:`\gamma` (:func:`fit`): Schwarz's criterion :math:`\nu\chi^2 + \ln(\nu N)\,\mathrm{dof}` over
:data:`GAMMAS`, :math:`\chi^2 = \sum_k \|T_k v_k - u_k\|^2_{\Sigma_k^{-1}}` with the per-voxel noise and
:math:`\mathrm{dof} = \operatorname{tr}(H^{-1}\operatorname{blockdiag}_k K_k)` (the smoother's trace): the
criterion of the frames' own fits and of the momentum model (:mod:`wss_nlp.womersley`) it competes with.
Per-frame :math:`\beta_k` matter: one :math:`\beta` for all frames (which would let a temporal DFT decouple
the system) over-smoothed systole's steep profile (worst frame 34 % of the peak instead of the frames' own
21 %, rigid Womersley flow at h = 1 mm; session notes of issue 15).

The band (:attr:`PriorFit.covariance`) is the velocity noise's:
:math:`\operatorname{Cov}(v) = H^{-1}\operatorname{blockdiag}_k(T_k^\top W_k \Sigma_k W_k T_k) H^{-1}/\nu`,
its diagonal blocks kept (one per frame); the walls are taken as given.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from .errors import SolverError
from .velocity import VelocityProblem

#: Where the search for gamma starts, its bounds and its steps (log10; gamma -> 0 is the frames' own fits,
#: whose criterion is computed apart).
LOG_GAMMA_START, LOG_GAMMA_BOUNDS, LOG_GAMMA_STEPS = -2.0, (-5.0, 5.0), (1.0, 0.5)


@dataclass
class PriorFit:
    """The temporal prior's best fit: its weight, coefficients per frame, their covariance, the criterion."""

    gamma: float
    betas: np.ndarray  # the frames' own Tikhonov weights, kept
    coefficients: np.ndarray  # (n_frames, n_basis)
    covariance: np.ndarray  # (n_frames, n_basis, n_basis): each frame's block, (m/s)^2
    bic: float
    chi2: float
    dof: float
    curve: dict = field(default_factory=dict)  # gamma -> criterion

    def as_dict(self) -> dict:
        return {
            "gamma": self.gamma,
            "betas": [float(b) for b in self.betas],
            "dof": self.dof,
            "bic": {f"{g:g}": v for g, v in self.curve.items()},
        }


def second_difference(n: int) -> np.ndarray:
    """The periodic second difference ``(D_2 v)_k = v_{k+1} - 2 v_k + v_{k-1}`` as an ``(n, n)`` matrix."""
    eye = np.eye(n)
    return np.roll(eye, 1, axis=1) - 2 * eye + np.roll(eye, -1, axis=1)


class _System:
    """The normal equations of the prior (module docstring), assembled once for every gamma."""

    def __init__(self, problems: list[VelocityProblem], betas):
        if len(problems) < 3:
            raise SolverError(f"the temporal prior needs at least 3 frames, got {len(problems)}")
        self.problems = problems
        self.betas = np.asarray(betas, dtype=float)
        self.m = problems[0].operator.shape[1]
        self.tw = [p.tikhonov.weighted_operator for p in problems]  # W_k T_k
        self.normal = [p.tikhonov.normal for p in problems]  # K_k
        self.rhs = np.concatenate([p.tikhonov.rhs for p in problems])
        self.diag = scipy.linalg.block_diag(*[p.tikhonov.hessian(b) for p, b in zip(problems, self.betas)])
        d2 = second_difference(len(problems))
        self.coupling = np.kron(d2.T @ d2, problems[0].basis.laplacian_gram(0) / np.pi)

    def factor(self, gamma: float):
        try:
            hessian = gamma * self.coupling
            hessian += self.diag
            return scipy.linalg.cho_factor(hessian, lower=True, overwrite_a=True, check_finite=False)
        except np.linalg.LinAlgError as exc:
            raise SolverError(f"temporal prior: the normal matrix is not positive definite at gamma {gamma:g}") from exc

    def blocks(self, x: np.ndarray) -> np.ndarray:
        return x.reshape(len(self.problems), self.m)


def solve(problems: list[VelocityProblem], betas, gamma: float) -> np.ndarray:
    """The prior's coefficients ``(n_frames, n_basis)`` at one ``gamma`` (frames' weights ``betas``)."""
    system = _System(problems, betas)
    return system.blocks(scipy.linalg.cho_solve(system.factor(gamma), system.rhs))


def fit(problems: list[VelocityProblem], betas, sigmas, nu: float, log_n: float) -> PriorFit:
    """The prior over the frames' problems (one per frame, in time order), gamma by the criterion (notes).

    ``betas`` are the frames' own Tikhonov weights, ``sigmas`` their per-voxel noise (one array per frame),
    ``nu`` the effective fraction of independent voxels, ``log_n`` the criterion's ``ln(nu N)`` (shared with
    the models it competes with). gamma: decades from :data:`LOG_GAMMA_START` downhill until the criterion
    rises, then the half decades beside the best (each value one Cholesky factorization and one triangular
    inverse for the trace).
    """
    system = _System(problems, betas)
    m = system.m
    inv_var = [1.0 / np.asarray(s, dtype=float) ** 2 for s in sigmas]
    curve: dict = {}
    solutions: dict = {}  # log gamma -> (coefficients, chi2, dof)
    kept: dict = {}  # the best value so far: its L^-1 gives the band at the end without a new factorization

    def criterion(log_gamma: float) -> float:
        if log_gamma not in curve:
            lower = system.factor(10.0**log_gamma)
            v = system.blocks(scipy.linalg.cho_solve(lower, system.rhs))
            chi2 = sum(float(np.sum((p.operator @ vk - p.data) ** 2 * iv)) for p, vk, iv in zip(problems, v, inv_var))
            # tr(H^-1 blockdiag K_k) = sum_k tr(M_k K_k M_k^T), H^-1 = M^T M, M = L^-1 (lower triangular: its k-th
            # block column vanishes above block row k)
            inverse, info = scipy.linalg.lapack.dtrtri(lower[0], lower=1, overwrite_c=1)
            if info != 0:
                raise SolverError(f"temporal prior: triangular inverse failed (LAPACK info {info})")
            dof = 0.0
            for k, kk in enumerate(system.normal):
                block = slice(k * m, (k + 1) * m)
                diagonal = np.tril(inverse[block, block])  # LAPACK leaves the other triangle as it found it
                below = inverse[(k + 1) * m :, block]
                dof += float(np.sum((diagonal @ kk) * diagonal) + np.sum((below @ kk) * below))
            curve[log_gamma] = nu * chi2 + log_n * dof
            solutions[log_gamma] = (v, chi2, dof)
            if not kept or curve[log_gamma] < curve[kept["at"]]:
                kept.update(at=log_gamma, inverse=inverse)
        return curve[log_gamma]

    coarse, fine = LOG_GAMMA_STEPS
    lo, hi = LOG_GAMMA_BOUNDS
    here = LOG_GAMMA_START
    step = coarse if criterion(here + coarse) < criterion(here) else -coarse
    here = here + coarse if step > 0 else here
    while lo <= here + step <= hi and criterion(here + step) < criterion(here):
        here += step
    for x in (here - fine, here + fine):
        if lo <= x <= hi:
            criterion(x)
    best = kept["at"]
    v, chi2, dof = solutions[best]
    # H^-1 = M^T M from the kept M = L^-1 (LAPACK's lauum: the lower triangle of M^T M)
    inverse, info = scipy.linalg.lapack.dlauum(kept["inverse"], lower=1)
    if info != 0:
        raise SolverError(f"temporal prior: inverse failed (LAPACK info {info})")
    inverse = np.tril(inverse) + np.tril(inverse, -1).T
    cov = _covariance(system, inverse, sigmas) / nu
    table = {10.0**x: float(curve[x]) for x in sorted(curve)}
    return PriorFit(10.0**best, system.betas, v, cov, float(curve[best]), chi2, dof, table)


def _covariance(system: _System, inverse: np.ndarray, sigmas) -> np.ndarray:
    """Each frame's block of ``H^-1 blockdiag(T_k^T W_k Sigma_k W_k T_k) H^-1`` (module notes)."""
    n, m = len(system.problems), system.m
    middle = [tw.T @ (np.asarray(s, dtype=float)[:, None] ** 2 * tw) for tw, s in zip(system.tw, sigmas)]
    out = np.empty((n, m, m))
    for k in range(n):
        rows = inverse[k * m : (k + 1) * m]  # (m, n m)
        left = np.concatenate([rows[:, j * m : (j + 1) * m] @ middle[j] for j in range(n)], axis=1)
        out[k] = left @ rows.T
    return out
