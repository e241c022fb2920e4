r"""A periodic temporal prior on the velocity of a cine slice's frames.

Every frame :math:`k` keeps its own wall, voxel operator :math:`T_k`, data :math:`u_k` and Tikhonov weight
:math:`\beta_k` (the one its own fit chose, :mod:`wss_nlp.parameters.choice`); the prior ties the frames' coefficients
by their periodic second difference over equally spaced frames:

.. math::

    \min_{v_0, \dots, v_{n-1}} \sum_k \Big[\|T_k v_k - u_k\|_{W_k}^2 + \frac{\beta_k}{\pi} v_k^\top G v_k\Big]
    + \frac{\gamma}{\pi}\sum_k \|(D_2 v)_k\|^2_{L^2(B)},
    \qquad (D_2 v)_k = v_{k+1} - 2 v_k + v_{k-1} \text{ (periodic)},

the plain Tikhonov functional of every frame (eq. (tik2), :mod:`wss_nlp.models.velocity`; the coefficients live on
the reference disk, so frames on different walls are compared there). Its normal equations

.. math::

    \Big(\operatorname{blockdiag}_k\big(K_k + \tfrac{\beta_k}{\pi} G\big)
    + \tfrac{\gamma}{\pi} D_2^\top D_2 \otimes G_0\Big) v = \big(T_k^\top W_k u_k\big)_k,
    \qquad K_k = T_k^\top W_k T_k,

with :math:`G` the penalty's Gram matrix and :math:`G_0` the :math:`L^2(B)` one, are solved by a block
Cholesky factorization per :math:`\gamma` that keeps the coupling's block band (:class:`_BandedFactor`; 20
frames of 119 functions: 0.07 s per gamma where a dense factorization and triangular inverse of the 2380
unknowns took 0.3 s). :math:`\gamma \to 0` gives the frames' own fits back.

Notes
-----
Choice of :math:`\gamma` (:func:`fit`, decades downhill from :data:`LOG_GAMMA_START`, then half decades):
Schwarz's criterion :math:`\nu\chi^2 + \ln(\nu N)\,\mathrm{dof}`,
:math:`\chi^2 = \sum_k \|T_k v_k - u_k\|^2_{\Sigma_k^{-1}}` with the per-voxel noise and
:math:`\mathrm{dof} = \operatorname{tr}(H^{-1}\operatorname{blockdiag}_k K_k)` (the smoother's trace): the
criterion of the frames' own fits and of the momentum model (:mod:`wss_nlp.models.womersley`) it competes with.
Per-frame :math:`\beta_k` matter: one :math:`\beta` for all frames (which would let a temporal DFT decouple
the system) over-smoothed systole's steep profile (worst frame 34 % of the peak instead of the frames' own
21 %, rigid Womersley flow at h = 1 mm; session notes of issue 15).

The band (:attr:`PriorFit.covariance`) is the velocity noise's:
:math:`\operatorname{Cov}(v) = H^{-1}\operatorname{blockdiag}_k(T_k^\top W_k \Sigma_k W_k T_k) H^{-1}/\nu`,
its diagonal blocks kept (one per frame); the walls are taken as given.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .._lazy import scipy
from ..errors import SolverError
from .velocity import VelocityProblem

#: Where the search for gamma starts, its bounds and its steps (log10; gamma -> 0 is the frames' own fits,
#: whose criterion is computed apart).
LOG_GAMMA_START, LOG_GAMMA_BOUNDS, LOG_GAMMA_STEPS = -2.0, (-5.0, 5.0), (1.0, 0.5)


@dataclass
class PriorFit:
    """The temporal prior's best fit: its weight, coefficients per frame, the criterion; the band on demand."""

    gamma: float
    betas: np.ndarray  # the frames' own Tikhonov weights, kept
    coefficients: np.ndarray  # (n_frames, n_basis)
    band: Callable[[], np.ndarray]  # () -> each frame's covariance block (n_frames, n_basis, n_basis), (m/s)^2
    bic: float
    chi2: float
    dof: float
    curve: dict = field(default_factory=dict)  # gamma -> criterion
    bounds: dict = field(default_factory=dict)  # gamma -> a lower bound of the criterion (its trace not computed)

    @functools.cached_property
    def covariance(self) -> np.ndarray:
        """Each frame's covariance block of the coefficients (computed when first asked: only a chosen prior
        needs its band)."""
        return self.band()

    def as_dict(self) -> dict:
        return {
            "gamma": self.gamma,
            "betas": [float(b) for b in self.betas],
            "dof": self.dof,
            "bic": {f"{g:g}": v for g, v in self.curve.items()},
            "bic_at_least": {f"{g:g}": v for g, v in self.bounds.items()},
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
        self.own = [p.tikhonov.hessian(b) for p, b in zip(problems, self.betas)]  # K_k + beta_k G / pi
        d2 = second_difference(len(problems))
        self.d = d2.T @ d2  # couples frames at most two apart (periodically)
        self.g0 = problems[0].basis.laplacian_gram(0) / np.pi

    def blocks(self, x: np.ndarray) -> np.ndarray:
        return x.reshape(len(self.problems), self.m)


class _BandedFactor:
    r"""Block Cholesky factor of the prior's normal matrix in an interleaved frame order.

    Ordering the frames :math:`0, n-1, 1, n-2, 2, \dots` puts frames that are at most two apart (periodically)
    at most four block rows apart, so the factor keeps that block band: :math:`n b^2` products of
    :math:`m \times m` blocks instead of a dense factorization (:math:`(n m)^3 / 3`). The diagonal blocks of the
    inverse, which the trace :math:`\operatorname{tr}(H^{-1}\operatorname{blockdiag} K_k)` needs, come from
    the band of the factor alone (Takahashi's recurrence, :meth:`inverse_diagonal`).
    """

    BAND = 4

    def __init__(self, system: _System, gamma: float):
        n, b = len(system.problems), self.BAND
        self.order = [k for pair in zip(range(n), range(n - 1, -1, -1)) for k in pair][:n]
        self.order = list(dict.fromkeys(self.order))  # 0, n-1, 1, n-2, ... each frame once
        position = np.argsort(self.order)
        rows, cols = np.nonzero(system.d)
        if np.max(np.abs(position[rows] - position[cols])) > b:  # the band holds every coupling (n = 3..79 checked)
            raise SolverError(f"temporal prior: {n} frames do not fit the factor's block band")
        self.n, self.m = n, system.m
        o = self.order
        self.lower: dict = {}  # (r, c) -> block of L, r >= c, r - c <= BAND
        try:
            for i in range(n):
                s = system.own[o[i]] + gamma * system.d[o[i], o[i]] * system.g0
                for j in range(max(0, i - b), i):
                    s = s - self.lower[i, j] @ self.lower[i, j].T
                self.lower[i, i] = np.linalg.cholesky(s)
                for r in range(i + 1, min(n, i + b + 1)):
                    t = gamma * system.d[o[r], o[i]] * system.g0
                    for j in range(max(0, r - b), i):
                        t = t - self.lower[r, j] @ self.lower[i, j].T
                    self.lower[r, i] = scipy.linalg.solve_triangular(self.lower[i, i], t.T, lower=True).T
        except np.linalg.LinAlgError as exc:
            raise SolverError(f"temporal prior: the normal matrix is not positive definite at gamma {gamma:g}") from exc

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``H^-1 rhs`` for a vector or the columns of a matrix (frame order in, frame order out)."""
        n, m, b, o = self.n, self.m, self.BAND, self.order
        x = [np.array(rhs[k * m : (k + 1) * m], dtype=float) for k in o]
        for i in range(n):  # L y = x
            for j in range(max(0, i - b), i):
                x[i] -= self.lower[i, j] @ x[j]
            x[i] = scipy.linalg.solve_triangular(self.lower[i, i], x[i], lower=True)
        for i in range(n - 1, -1, -1):  # L^T z = y
            for r in range(i + 1, min(n, i + b + 1)):
                x[i] -= self.lower[r, i].T @ x[r]
            x[i] = scipy.linalg.solve_triangular(self.lower[i, i], x[i], lower=True, trans="T")
        out = np.empty(np.shape(rhs))
        for i, k in enumerate(o):
            out[k * m : (k + 1) * m] = x[i]
        return out

    def inverse_diagonal(self) -> list:
        """The diagonal blocks of ``H^-1`` in frame order, from the band of ``L`` (Takahashi's recurrence on
        ``H = M D M^T``, ``M`` unit block lower triangular): ``Z_ri = -sum_j Z_rj M_ji`` below the diagonal,
        ``Z_ii = D_i^-1 - sum_j M_ji^T Z_ji``, ``j`` over the band below ``i``."""
        n, b = self.n, self.BAND
        unit = {}  # M_ri = L_ri L_ii^-1
        inv_diag = []
        for i in range(n):
            li_inv = scipy.linalg.solve_triangular(self.lower[i, i], np.eye(self.m), lower=True)
            inv_diag.append(li_inv.T @ li_inv)  # D_i^-1 = L_ii^-T L_ii^-1
            for r in range(i + 1, min(n, i + b + 1)):
                unit[r, i] = self.lower[r, i] @ li_inv
        z: dict = {}  # (r, c), r >= c, within the band

        def zz(r, c):
            return z[r, c] if r >= c else z[c, r].T

        for i in range(n - 1, -1, -1):
            below = range(i + 1, min(n, i + b + 1))
            for r in below:
                z[r, i] = -sum(zz(r, j) @ unit[j, i] for j in below)
            z[i, i] = inv_diag[i] - sum((unit[j, i].T @ z[j, i] for j in below), np.zeros((self.m, self.m)))
        out: list = [None] * n
        for i, k in enumerate(self.order):
            out[k] = z[i, i]
        return out


def solve(problems: list[VelocityProblem], betas, gamma: float) -> np.ndarray:
    """The prior's coefficients ``(n_frames, n_basis)`` at one ``gamma`` (frames' weights ``betas``)."""
    system = _System(problems, betas)
    return system.blocks(_BandedFactor(system, gamma).solve(system.rhs))


def fit(problems: list[VelocityProblem], betas, sigmas, nu: float, log_n: float) -> PriorFit:
    """The prior over the frames' problems (one per frame, in time order), gamma by the criterion (notes).

    ``betas`` are the frames' own Tikhonov weights, ``sigmas`` their per-voxel noise (one array per frame),
    ``nu`` the effective fraction of independent voxels, ``log_n`` the criterion's ``ln(nu N)`` (shared with
    the models it competes with). gamma: decades from :data:`LOG_GAMMA_START` downhill until the criterion
    rises, then the half decades beside the best (each value one banded block factorization, and the trace
    from the inverse's diagonal blocks, :class:`_BandedFactor`).

    The trace (the inverse's diagonal blocks, the dearer half of a value) is skipped where a lower bound of
    the criterion already decides the comparison it is wanted for (:class:`_TraceFloor`): the search visits
    the same gammas and returns the same best gamma, coefficients and criterion; a value decided by its bound
    is recorded as that bound (:attr:`PriorFit.bounds`).
    """
    system = _System(problems, betas)
    inv_var = [1.0 / np.asarray(s, dtype=float) ** 2 for s in sigmas]
    curve: dict = {}  # log gamma -> criterion
    floors: dict = {}  # log gamma -> a lower bound of the criterion where its trace was not computed
    traces: dict = {}  # log gamma -> dof (exact)
    solutions: dict = {}  # log gamma -> (coefficients, chi2, dof)
    factors: dict = {}  # the best factor so far, which the band reuses
    trace_floor = _TraceFloor(system)

    def criterion(log_gamma: float, beat: float = np.inf) -> float:
        """The criterion at ``log_gamma``, or a lower bound of it where that bound is at least ``beat``
        (the value it is compared with: then it cannot be smaller)."""
        if log_gamma in curve:
            return curve[log_gamma]
        if log_gamma in floors and floors[log_gamma][0] >= beat:
            return floors[log_gamma][0]
        if log_gamma in floors:  # bounded before against a value it did not reach: solved already
            factor, v, chi2 = floors[log_gamma][1]
        else:
            factor, v, chi2 = _solved(system, problems, inv_var, 10.0**log_gamma)
        # the trace decreases with gamma (notes of _TraceFloor): any larger gamma's bounds it, and its limit
        larger = max([trace_floor.limit, *(traces[x] for x in traces if x > log_gamma)])
        for dof_floor in (lambda: larger, lambda: trace_floor(10.0**log_gamma)):  # the cheap bound first
            floor = nu * chi2 + log_n * dof_floor()
            # rounding: the traces carry relative errors near 1e-12; the margin keeps a bound from deciding a tie
            if floor - _FLOOR_MARGIN * (abs(floor) + 1.0) >= beat:
                floors[log_gamma] = (floor, (factor, v, chi2))
                return floor
        floors.pop(log_gamma, None)
        dof = sum(float(np.sum(z * kk)) for z, kk in zip(factor.inverse_diagonal(), system.normal))
        traces[log_gamma] = dof
        curve[log_gamma] = nu * chi2 + log_n * dof
        solutions[log_gamma] = (v, chi2, dof)
        if not factors or curve[log_gamma] < min(curve[x] for x in factors):
            factors.clear()
            factors[log_gamma] = factor
        return curve[log_gamma]

    coarse, fine = LOG_GAMMA_STEPS
    lo, hi = LOG_GAMMA_BOUNDS
    here = LOG_GAMMA_START
    first = criterion(here)
    step = coarse if criterion(here + coarse, beat=first) < first else -coarse
    here = here + coarse if step > 0 else here
    while lo <= here + step <= hi and criterion(here + step, beat=criterion(here)) < criterion(here):
        here += step
    for x in (here - fine, here + fine):
        if lo <= x <= hi:
            criterion(x, beat=min(curve.values()))
    best = min(curve, key=curve.__getitem__)
    v, chi2, dof = solutions[best]
    table = {10.0**x: float(curve[x]) for x in sorted(curve)}
    gamma = 10.0**best
    factor = factors[best]
    fitted = PriorFit(gamma, system.betas, v, lambda: _covariance(system, factor, sigmas) / nu, float(curve[best]),
                      chi2, dof, table)  # fmt: skip
    fitted.bounds = {10.0**x: float(floors[x][0]) for x in sorted(floors)}
    return fitted


#: Relative margin by which a criterion's lower bound must exceed the value it is compared with to decide.
_FLOOR_MARGIN = 1e-9


def _solved(system: _System, problems: list[VelocityProblem], inv_var: list, gamma: float):
    """``(factor, coefficients, chi2)`` at one gamma: the factorization and solve without the trace."""
    factor = _BandedFactor(system, gamma)
    v = system.blocks(factor.solve(system.rhs))
    chi2 = sum(float(np.sum((p.operator @ vk - p.data) ** 2 * iv)) for p, vk, iv in zip(problems, v, inv_var))
    return factor, v, chi2


class _TraceFloor:
    r"""Lower bounds of the smoother's trace :math:`\mathrm{dof}(\gamma) = \operatorname{tr}(H_\gamma^{-1}
    \operatorname{blockdiag} K_k)` at any gamma, without factorizing the coupled system.

    Notes
    -----
    :math:`H_\gamma = A + \gamma C`, :math:`A = \operatorname{blockdiag}_k(K_k + \beta_k G / \pi)`,
    :math:`C = D_2^\top D_2 \otimes G_0 / \pi \succeq 0`; :math:`\operatorname{tr}(Z K) =
    \operatorname{tr}(K^{1/2} Z K^{1/2})` grows with :math:`Z` (Loewner order), so (i) the trace decreases
    with gamma (the search bounds a value by the trace at any larger gamma it computed); (ii) a diagonal block
    of the inverse dominates the inverse of the diagonal block (it is the inverse of a Schur complement,
    :math:`H_{kk}` less a positive semi-definite term): :math:`(H^{-1})_{kk} \succeq H_{kk}^{-1}`, so
    :math:`\mathrm{dof}(\gamma) \ge \sum_k \operatorname{tr}((A_k + \gamma (D_2^\top D_2)_{kk} G_0 /
    \pi)^{-1} K_k)`, one small factorization per frame; (iii) as :math:`\gamma \to \infty` the frames are
    forced to one coefficient vector (the null space of :math:`C` is the constants in time, :math:`G_0` being
    definite), so :math:`\mathrm{dof} \ge \operatorname{tr}((\sum_k A_k)^{-1} \sum_k K_k)` at every gamma.
    """

    def __init__(self, system: _System):
        self.system = system
        #: (iii), at every gamma
        self.limit = float(np.trace(np.linalg.solve(sum(system.own), sum(system.normal))))

    def __call__(self, gamma: float) -> float:
        """The larger of (ii) and (iii) at ``gamma``."""
        system, per_frame = self.system, 0.0
        for k, (own, kk) in enumerate(zip(system.own, system.normal)):
            try:
                diagonal = scipy.linalg.cho_factor(own + gamma * system.d[k, k] * system.g0)  # H_kk
                per_frame += float(np.trace(scipy.linalg.cho_solve(diagonal, kk)))
            except np.linalg.LinAlgError:
                return self.limit
        return max(self.limit, per_frame)


def _covariance(system: _System, factor: _BandedFactor, sigmas) -> np.ndarray:
    """Each frame's block of ``H^-1 blockdiag(T_k^T W_k Sigma_k W_k T_k) H^-1`` (module notes), from the
    factor: frame k's block column of ``H^-1`` (= its block row transposed) by one solve with ``m`` columns."""
    n, m = len(system.problems), system.m
    middle = [tw.T @ (np.asarray(s, dtype=float)[:, None] ** 2 * tw) for tw, s in zip(system.tw, sigmas)]
    out = np.empty((n, m, m))
    unit = np.zeros((n * m, m))
    for k in range(n):
        unit[k * m : (k + 1) * m] = np.eye(m)
        columns = factor.solve(unit)  # (n m, m): H^-1 E_k
        unit[k * m : (k + 1) * m] = 0.0
        out[k] = sum(columns[j * m : (j + 1) * m].T @ middle[j] @ columns[j * m : (j + 1) * m] for j in range(n))
    return out
