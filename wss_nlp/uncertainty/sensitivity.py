"""Derivatives of the reconstruction and a linearized uncertainty band.

:func:`coupled` handles the coupled NLP (see its notes). The decoupled
reconstruction is a chain of two solves, each differentiated exactly with
CasADi:

1. geometry: ``c_R(p_g)`` minimizes the Tikhonov functional of Sec. 2 with
   parameters ``p_g = (m, alpha, gamma, centre)``; its derivative comes from
   the implicit function theorem on the KKT system, with the exact Hessian
   assembled by the chain rule from CasADi's pointwise derivatives (of
   ``H_gamma`` and of the polar coordinates) and the active set read from IPOPT's
   multipliers (run with ``clip_inactive_lam``, so that the tiny multipliers
   IPOPT returns for inactive box constraints are not mistaken for active ones);
2. velocity: ``c_v = H(c_R, beta)^{-1} T(c_R)^T W u / A``; its normal
   equations are differentiated along every geometry direction, with CasADi
   derivatives of the sub-voxel points' reference coordinates and the voxel
   membership held at the solution (it is piecewise constant, so this is the
   derivative almost everywhere);
3. WSS: ``tau(phi_j; c_R, c_v, r_in(c_R))`` of eq. (wss) with
   ``r_in = f min R`` differentiated as well.

The chain rule is assembled from these Jacobians. The band is
``sigma_tau^2 = sum_i (d tau / d m_i)^2 sigma_m^2 + sum_i (d tau / d u_i)^2 sigma_u,i^2``
with independent per-voxel noise: ``sigma_m = sigma / (m1 - m0)`` for the
normalized magnitude and ``sigma_u,i = venc sigma / (pi |d_i|)`` (capped at
``venc / sqrt 3``) for the velocity, ``sigma`` the complex noise level
(Appendix B); magnitude and phase noise are independent to first order.

Held fixed (documented in the docs): the preprocessing outputs other
than the centre (normalization levels, the box, the reference radius) and
the dephasing factors of the second pass.
"""

from __future__ import annotations

import functools
import time
from typing import Any
from dataclasses import dataclass, field

import numpy as np

import casadi as ca

from .._lazy import scipy
from ..models import coupled as cpl
from ..models import geometry as geo
from ..models import acquisition as acq_model
from ..models import kspace
from ..core import mapping
from ..models import measurement as meas
from ..models import near_wall as nw
from ..core import radius as rad
from ..models import velocity as vel
from ..models import wss as wss_mod
from ..core.solver import DenseCall
from ..core.tikhonov import LinearTikhonov
from ..errors import InputError, SolverError

SCALARS = ("alpha", "beta", "gamma", "center_x", "center_y")


@dataclass
class Sensitivity:
    """Derivatives of tau and mean tau, and the uncertainty band they imply.

    ``d_tau`` has one column per name in :data:`SCALARS`; ``d_tau_d_m`` and
    ``d_tau_d_u`` have one column per voxel of ``m_index`` / ``u_index``
    (flat row-major indices). Units: Pa per unit of the parameter (alpha,
    beta: dimensionless; gamma, centre: mm; m: dimensionless; u: m/s).
    The per-voxel matrices are products ``(d tau / d c) (d c / d p)`` of
    the stored ``d_tau_d_coef`` and ``d_coef_r``, ``d_coef_v``, formed only
    when asked for: the band needs only Gram matrices of ``d c / d p``
    (:meth:`band`).
    """

    phi: np.ndarray
    d_tau: np.ndarray  # (n_phi, 5)
    d_mean: np.ndarray  # (5,)
    d_tau_d_coef: np.ndarray  # (n_phi, 2N+1 + n_basis): d tau / d [c_R; c_v]
    d_mean_d_m: np.ndarray
    d_mean_d_u: np.ndarray
    m_index: np.ndarray
    u_index: np.ndarray
    d_coef_r: np.ndarray  # (2N+1, n_m + n_u + 5): d c_R / d [m, u, scalars]
    d_coef_v: np.ndarray  # (n_basis, n_m + n_u + 5)
    tau_std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    mean_std: float = float("nan")
    mean_std_magnitude: float = float("nan")  # part of mean_std from the magnitude noise
    mean_std_velocity: float = float("nan")
    noise: dict = field(default_factory=dict)
    seconds: float = 0.0
    correlation: tuple | None = None  # (R_y, R_x, image shape): correlated (k-space) noise; None: independent

    @property
    def names(self) -> tuple[str, ...]:
        return SCALARS

    def _d_coef(self, start: int, stop: int) -> np.ndarray:
        """``d [c_R; c_v] / d p`` for the parameter columns ``start:stop``."""
        return np.vstack([self.d_coef_r[:, start:stop], self.d_coef_v[:, start:stop]])

    @property
    def d_tau_d_m(self) -> np.ndarray:
        """``d tau / d m`` at the voxels ``m_index`` (n_phi, n_m), Pa."""
        return self.d_tau_d_coef @ self._d_coef(0, self.m_index.size)

    @property
    def d_tau_d_u(self) -> np.ndarray:
        """``d tau / d u`` at the voxels ``u_index`` (n_phi, n_u), Pa per m/s."""
        n_m = self.m_index.size
        return self.d_tau_d_coef @ self._d_coef(n_m, n_m + self.u_index.size)

    def band(self, sigma_m: float, sigma_u: np.ndarray) -> tuple[np.ndarray, float, float, float]:
        """``(tau_std, mean_std, mean_std from m, mean_std from u)`` for per-voxel noise levels.

        Notes
        -----
        Independent voxels (box model): ``var tau_k = sum_i g_ki^2 sigma_i^2``
        with ``g_k = (d tau_k / d c) X``, ``X = d c / d p``. With
        :attr:`correlation` (a k-space acquisition: filtered, zero-filled
        noise) ``g_k^T D R D g_k``, ``R = R_y (x) R_x`` the separable noise
        correlation of :func:`wss_nlp.models.kspace.noise_correlation` and ``D`` the
        per-voxel standard deviations. Both are evaluated as
        ``(d tau_k / d c) (X D R D X^T) (d tau_k / d c)^T``: a Gram matrix of
        the few coefficient rows of ``X`` instead of the (n_phi x voxels)
        products ``g`` (4-8x fewer flops at h = 0.3 mm).
        """
        sigma_u = np.broadcast_to(np.asarray(sigma_u, float), self.u_index.shape)
        n_m, n_u, corr = self.m_index.size, self.u_index.size, self.correlation
        gram_m = weighted_gram(self._d_coef(0, n_m), self.m_index, sigma_m, corr)
        gram_u = weighted_gram(self._d_coef(n_m, n_m + n_u), self.u_index, sigma_u, corr)
        var_m, var_u = row_quadratic(self.d_tau_d_coef, gram_m), row_quadratic(self.d_tau_d_coef, gram_u)
        mean_m = float(weighted_gram(self.d_mean_d_m[None, :], self.m_index, sigma_m, corr)[0, 0])
        mean_u = float(weighted_gram(self.d_mean_d_u[None, :], self.u_index, sigma_u, corr)[0, 0])
        tau_std = np.sqrt(np.maximum(var_m, 0.0) + np.maximum(var_u, 0.0))  # >= 0 up to rounding
        return tau_std, float(np.sqrt(mean_m + mean_u)), float(np.sqrt(mean_m)), float(np.sqrt(mean_u))


def row_quadratic(jac: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``diag(J C J^T)``: the variance of each row's linear form under the covariance ``C`` (a product, then a
    row sum; a three-operand ``einsum`` loops over every index triple, about 10x slower at 360 x 140)."""
    return np.sum((jac @ cov) * jac, axis=1)


def weighted_gram(g: np.ndarray, index: np.ndarray, sigma, correlation=None) -> np.ndarray:
    r"""``G diag(s) R diag(s) G^T`` for the voxels ``index`` (``R = I`` without a correlation).

    ``g`` has one column per voxel of ``index`` (flat row-major), ``sigma``
    their noise levels; ``correlation = (R_y, R_x, shape)`` the separable
    noise correlation :math:`R = R_y \otimes R_x` of a k-space acquisition.
    """
    gs = np.asarray(g, float) * np.broadcast_to(np.asarray(sigma, float), (np.size(index),))[None, :]
    if correlation is None:
        return gs @ gs.T
    image, smoothed = correlated_images(gs, index, correlation)
    return np.einsum("nad,kad->nk", image, smoothed)


def correlated_images(g: np.ndarray, index, correlation) -> tuple[np.ndarray, np.ndarray]:
    r"""Rows of ``g`` (values at the voxels ``index``) as images ``G_n`` on the bounding rows and columns of the
    voxels, and :math:`R_y G_n R_x^\top`: ``g R h^T = sum(G_n * (R_y H_k R_x^T))`` for the separable noise
    correlation ``correlation = (R_y, R_x, shape)`` of a k-space acquisition."""
    ry, rx, (_, nx) = correlation
    iy, ix = np.divmod(np.asarray(index), nx)
    rows, cols = np.unique(iy), np.unique(ix)
    image = np.zeros((g.shape[0], rows.size, cols.size))
    image[:, np.searchsorted(rows, iy), np.searchsorted(cols, ix)] = g
    return image, np.einsum("ab,nbc,dc->nad", ry[np.ix_(rows, rows)], image, rx[np.ix_(cols, cols)])


# --------------------------------------------------------------------------- symbolic pieces
@functools.lru_cache(maxsize=4)
def heaviside_pieces(heaviside: str) -> ca.Function:
    r"""Per point: ``H_gamma(g)`` and its derivatives ``H'``, ``H''``, ``dH/dgamma``, ``dH'/dgamma`` (SX).

    Inputs ``(g, gamma)``, rows of points (CasADi maps the scalar function
    over them); the derivatives are CasADi's exact ones of
    :func:`wss_nlp.models.measurement.smoothed_heaviside`.
    """
    g, w = ca.SX.sym("g"), ca.SX.sym("gamma")
    h = meas.smoothed_heaviside(g, w, heaviside)
    d1 = ca.jacobian(h, g)
    return ca.Function("heaviside", [g, w], [h, d1, ca.jacobian(d1, g), ca.jacobian(h, w), ca.jacobian(d1, w)])


@functools.lru_cache(maxsize=1)
def polar_pieces() -> ca.Function:
    """Per point ``(x, y)`` about the centre ``(c_x, c_y)``: ``r``, ``t`` and their derivatives in the centre (SX).

    Outputs ``(r, t, dr/dc_x, dr/dc_y, dt/dc_x, dt/dc_y)`` with ``t = atan2(y - c_y, x - c_x)``.
    """
    x, y, cx, cy = (ca.SX.sym(v) for v in ("x", "y", "cx", "cy"))
    dx, dy = x - cx, y - cy
    r, t = ca.sqrt(dx * dx + dy * dy), ca.atan2(dy, dx)
    parts = [ca.jacobian(v, u) for v in (r, t) for u in (cx, cy)]
    return ca.Function("polar", [x, y, cx, cy], [r, t, *parts])


@functools.lru_cache(maxsize=1)
def inverse_map_pieces() -> ca.Function:
    """Per point: ``rho`` of the inverse map (eta = 2) from ``(r, R, r_in)`` and its three partial derivatives (SX)."""
    r, big_r, r_in = ca.SX.sym("r"), ca.SX.sym("R"), ca.SX.sym("r_in")
    rho = mapping.inverse_radius(big_r, r, r_in)
    return ca.Function(
        "rho", [r, big_r, r_in], [rho, ca.jacobian(rho, r), ca.jacobian(rho, big_r), ca.jacobian(rho, r_in)]
    )


#: Points per call of the mapped pointwise functions (:func:`_rows`): the map is built once per function.
ROW_CHUNK = 4096


@functools.lru_cache(maxsize=64)
def _mapped(fun: ca.Function, n: int) -> ca.Function:
    return fun.map(n)


def _rows(fun: ca.Function, *args) -> list[np.ndarray]:
    """``fun`` on every point (array arguments: one value per point; scalars shared), outputs as flat arrays.

    Evaluated in chunks of :data:`ROW_CHUNK` points (fewer points: their count rounded up to a power of
    two) by one cached ``map`` (building a map for each point count costs about twice its
    evaluation; calling ``fun`` on rows maps implicitly, 15x slower), reading and writing NumPy memory
    directly (:class:`wss_nlp.core.solver.DenseCall`: converting the outputs from ``DM`` took a fifth of a band).
    """
    n = max(np.size(a) for a in args)
    chunk = min(ROW_CHUNK, 1 << max(n - 1, 0).bit_length())
    mapped = _mapped(fun, chunk)
    outs = [np.empty(n) for _ in range(mapped.n_out())]
    dense = all(mapped.sparsity_out(i).is_dense() for i in range(mapped.n_out()))
    call = DenseCall(mapped) if dense else None
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        rows: list = []
        for a in args:
            if np.isscalar(a):  # the map takes a row for every input
                rows.append(np.full(chunk, a, dtype=float))
                continue
            part = np.ravel(a)[start:stop].astype(float)
            # the last chunk is padded with its last value (any finite input would do; the padding is dropped)
            rows.append(np.pad(part, (0, chunk - part.size), mode="edge"))
        if call is not None:
            res = [r.ravel() for r in call(*rows)]
        else:  # a structurally zero output: CasADi's own call fills the zeros
            res = [np.asarray(v).ravel() for v in mapped(*[r[None, :] for r in rows])]
        for out, r in zip(outs, res):
            out[start:stop] = r[: stop - start]
    return outs


@functools.lru_cache(maxsize=16)  # bases are cached objects (velocity_basis.make_basis): one build per setting
def wss_derivative_function(template, n_fourier: int, eta: float, viscosity_pa_s: float) -> ca.Function:
    """Per angle: ``tau`` of eq. (wss) and its gradient in ``[c_R; p_linear; r_in]`` (SX).

    ``template`` and ``p = [p_linear; shape]`` as :func:`wss_nlp.models.wss.velocity_template` gives them (a
    layer's scale is an input, held fixed: no derivative in it).
    """
    tau_f = wss_mod.wss_expression(wss_mod._BasisVelocity(template), n_fourier, None, eta)
    n_r = rad.n_coefficients(n_fourier)
    phi, c_r, center = ca.SX.sym("phi"), ca.SX.sym("c_R", n_r), ca.SX.sym("center", 2)
    p_lin, shape = ca.SX.sym("p", template.size), ca.SX.sym("shape", getattr(template, "n_shape", 0))
    r_in = ca.SX.sym("r_in")
    tau = tau_f(phi, c_r, center, ca.vertcat(p_lin, shape), viscosity_pa_s, r_in)[0]
    return ca.Function(
        "dtau", [phi, c_r, center, p_lin, shape, r_in], [tau, ca.gradient(tau, ca.vertcat(c_r, p_lin, r_in))]
    )


def geometry_parameter_derivatives(
    problem: geo.GeometryProblem,
    options: geo.GeometryOptions,
    coefficients: np.ndarray,
    alpha: float,
    gamma: float,
    gradient: bool = False,
):
    """Hessian of the geometry functional in ``c_R`` and ``d grad / d [m_annulus; alpha; gamma; c_x; c_y]``.

    Notes
    -----
    With ``r_i = F_i(z) - m_i`` and ``J(c) = |V| sum r_i^2 + alpha (c - c_ref)^T W (c - c_ref)``:
    ``H = 2 |V| sum (grad_c F_i grad_c F_i^T + r_i hess_cc F_i) + 2 alpha W``,
    ``dgrad/dm_i = -2 |V| grad_c F_i``, ``dgrad/dalpha = 2 W (c - c_ref)``,
    ``dgrad/dq = 2 |V| sum (d_q F_i grad_c F_i + r_i d_q grad_c F_i)`` for
    ``q`` in ``(gamma, c_x, c_y)``. ``F_i`` is the mean over the voxel's
    points of ``H_gamma(g_j)``, ``g_j = b(t_j)^T c - r_j`` with the polar
    coordinates ``(r_j, t_j)`` about the centre ``u``, so by the chain rule
    ``grad_c F_i = mean H' b``, ``d_gamma F_i = mean dH/dgamma``,
    ``d_u F_i = mean H' dg/du`` with ``dg/du = (b'^T c) dt/du - dr/du``, and
    ``sum_i r_i hess_cc F_i = B^T diag(w H'') B``,
    ``sum_i r_i d_gamma grad_c F_i = B^T (w dH'/dgamma)``,
    ``sum_i r_i d_u grad_c F_i = B^T diag(w H'') dg/du + B'^T diag(w H') dt/du``
    (``w_j = r_i / q^2`` for the points of voxel ``i``). The pointwise
    derivatives (of ``H_gamma`` and of the polar coordinates) are CasADi's
    exact ones (:func:`heaviside_pieces`, :func:`polar_pieces`); the
    products are BLAS. Returns ``(H, dgrad, annulus)``, and with ``gradient`` also
    ``grad J = 2 |V| sum r_i grad_c F_i + 2 alpha W (c - c_ref)``.
    """
    n = options.n_fourier
    n_r = rad.n_coefficients(n)
    q = geo.quad_order(problem, options)
    model = meas.annulus_model(problem.grid, problem.center, problem.r0, problem.r1, q)
    px, py = meas.subvoxel_points(problem.grid, model.annulus, q)
    n_a, nq = model.annulus.size, q * q
    # pointwise pieces from CasADi, assembled by the chain rule with BLAS (R is linear in c_R): see the notes
    _, th, dr_dx, dr_dy, dt_dx, dt_dy = _rows(polar_pieces(), px, py, *problem.center)
    b, b1 = rad.design_matrix(th, n), rad.design_matrix(th, n, 1)
    gap = b @ coefficients - model.rho.ravel()
    h0, h1, h2, hg, h1g = _rows(heaviside_pieces(options.heaviside), gap, gamma)
    dgap_du = np.stack([(b1 @ coefficients) * dt_dx - dr_dx, (b1 @ coefficients) * dt_dy - dr_dy], axis=1)

    def mean(v):  # voxel means of point values (points are stored voxel-major)
        return v.reshape(n_a, nq, *v.shape[1:]).mean(axis=1)

    resid = mean(h0) - problem.magnitude.ravel()[model.annulus]
    g_c = mean(h1[:, None] * b).T  # (n_r, n_a): grad_c F_i
    grad_g, grad_u = mean(hg), mean(h1[:, None] * dgap_du)  # d F_i / d gamma, d F_i / d centre
    wr = np.repeat(resid, nq) / nq  # sum_i r_i (second derivatives of F_i) = sum_j w_j (... at point j)
    area = problem.grid.voxel_area
    w = rad.sobolev_weights(n, options.sobolev_s)
    ref = np.zeros(n_r)
    if options.prior == "area":
        ref[0] = problem.r_ref
    hmat = 2 * area * (g_c @ g_c.T + rad.weighted_gram(b, wr * h2)) + 2 * alpha * np.diag(w)
    dgrad = np.zeros((n_r, n_a + 4))
    dgrad[:, :n_a] = -2 * area * g_c
    dgrad[:, n_a] = 2 * w * (coefficients - ref)
    dgrad[:, n_a + 1] = 2 * area * (g_c @ grad_g + b.T @ (wr * h1g))
    mixed_u = b.T @ ((wr * h2)[:, None] * dgap_du) + b1.T @ ((wr * h1)[:, None] * np.stack([dt_dx, dt_dy], axis=1))
    dgrad[:, n_a + 2 :] = 2 * area * (g_c @ grad_u + mixed_u)
    if gradient:
        return hmat, dgrad, model.annulus, 2 * area * g_c @ resid + 2 * alpha * w * (coefficients - ref)
    return hmat, dgrad, model.annulus


def kspace_parameter_derivatives(
    problem: geo.GeometryProblem, options: geo.GeometryOptions, coefficients: np.ndarray, alpha: float, gamma: float
):
    """:func:`geometry_parameter_derivatives` for the k-space magnitude model (:func:`~.kspace.magnitude_model`).

    Notes
    -----
    The same quantities, ``H`` and ``d grad / d [m_window; alpha; gamma; c_x; c_y]``, from one CasADi graph
    of the functional with ``gamma`` and a centre shift as symbols: ``H`` and the mixed derivatives by
    CasADi's exact (forward-over-reverse) differentiation, ``d grad / d m = -2 sqrt(|V|) J^T`` with ``J``
    the residual's Jacobian. Returns ``(H, dgrad, window voxel indices)``.
    """
    n = options.n_fourier
    q = geo.quad_order(problem, options)
    if not isinstance(problem.measurement, acq_model.KSpace):
        raise InputError("kspace_parameter_derivatives: the problem has no k-space PSF")
    model = problem.measurement.magnitude_setup(problem.grid, problem.center, problem.r0, problem.r1, q, gamma)
    c, g, shift = ca.MX.sym("c", rad.n_coefficients(n)), ca.MX.sym("gamma"), ca.MX.sym("shift", 2)
    root_area = np.sqrt(problem.grid.voxel_area)
    data = problem.magnitude.ravel()[model.annulus]
    res = root_area * (kspace.magnitude_model(model, c, g, options.heaviside, shift=shift) - ca.DM(data))
    w = rad.sobolev_weights(n, options.sobolev_s)
    ref = np.zeros(c.numel())
    if options.prior == "area":
        ref[0] = problem.r_ref
    dc = c - ca.DM(ref)
    grad = ca.gradient(ca.sumsqr(res) + alpha * ca.dot(ca.DM(w) * dc, dc), c)
    outputs = [ca.jacobian(grad, c), ca.jacobian(res, c), ca.jacobian(grad, ca.vertcat(g, shift))]
    fun = ca.Function("kspace_kkt", [c, g, shift], outputs)
    hmat, jac, mixed = (np.asarray(a) for a in fun(coefficients, gamma, np.zeros(2)))
    n_a = model.annulus.size
    dgrad = np.zeros((c.numel(), n_a + 4))
    dgrad[:, :n_a] = -2 * root_area * jac.T
    dgrad[:, n_a] = 2 * w * (coefficients - ref)
    dgrad[:, n_a + 1 :] = mixed
    return 0.5 * (hmat + hmat.T), dgrad, model.annulus


def bordered(hmat: np.ndarray, g_active: np.ndarray) -> np.ndarray:
    """The KKT matrix ``[[H, G_A^T], [G_A, 0]]`` of a problem with linear active constraints ``G_A x = const``."""
    n, k = hmat.shape[0], g_active.shape[0]
    out = np.zeros((n + k, n + k))
    out[:n, :n] = hmat
    out[:n, n:] = g_active.T
    out[n:, :n] = g_active
    return out


def solve_kkt(kkt: np.ndarray, dgrad: np.ndarray, what: str) -> np.ndarray:
    """``dx/dp`` from ``kkt [dx; dlam] = [-d grad/dp; 0]`` (implicit function theorem)."""
    n = dgrad.shape[0]
    rhs = np.zeros((kkt.shape[0], dgrad.shape[1]))
    rhs[:n] = -dgrad
    try:
        return np.linalg.solve(kkt, rhs)[:n]
    except np.linalg.LinAlgError as exc:
        raise SolverError(
            f"{what}: the KKT matrix is singular ({exc}); more box constraints are active "
            "than the radius has degrees of freedom"
        ) from exc


def geometry_kkt(
    problem: geo.GeometryProblem,
    options: geo.GeometryOptions,
    coefficients: np.ndarray,
    alpha: float,
    gamma: float,
    lam_box: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``d c_R / d [m_annulus; alpha; gamma; c_x; c_y]`` at a solution, by the implicit function theorem.

    Notes
    -----
    Stationarity plus the active box rows ``G_A c = r_0 | r_1`` give
    ``[[H, G_A^T], [G_A, 0]] [dc; dlam] = [-dgrad/dp; 0]`` with ``H`` and
    ``dgrad/dp`` from :func:`geometry_parameter_derivatives`. The active set
    is where IPOPT's multipliers are nonzero (run with ``clip_inactive_lam``,
    so inactive ones are exactly zero). Returns ``(dc/dp, annulus indices)``.
    """
    hmat, dgrad, annulus = parameter_derivatives(problem)(problem, options, coefficients, alpha, gamma)
    box = rad.design_matrix(options.box_angles(), options.n_fourier)
    return solve_kkt(bordered(hmat, box[lam_box != 0]), dgrad, "geometry sensitivity"), annulus


def operator_derivatives(vp: vel.VelocityProblem, options: vel.VelocityOptions, c_r0: np.ndarray, center0):
    """The voxel-mean operator ``T~_h`` and its derivatives with respect to ``[c_R; c_x; c_y]``.

    Returns ``(OperatorDerivative, r_in, d r_in / d c_R)``.

    Notes
    -----
    Every raw basis function is ``radial(rho) angular(t)`` and a sub-voxel
    point moves in the reference disk only through ``rho_p`` (which depends
    on R(t_p), ``r_in = f min R`` and the centre) and ``t_p`` (centre only),
    so ``d raw = angular radial' d rho_p + angular' radial d t_p``. CasADi
    differentiates ``rho_p`` and ``t_p`` exactly; ``radial'`` comes from the
    Chebyshev form (exact for the Zernike basis; a near-wall layer's in
    closed form, its voxel means those of the fit) and ``angular'`` in closed
    form. Membership of the points and the partial volumes are those of
    ``vp`` (piecewise constant in R). ``min R`` is taken over 720 angles
    like :meth:`wss_nlp.models.velocity.VelocityOptions.make_map`; its derivative
    is the design row of the minimizing angle. Requires ``eta = 2``.
    """
    if options.eta != 2:
        raise InputError(f"sensitivities use the closed-form inverse of phi_R, which needs eta = 2 (got {options.eta})")
    basis, vox = vp.basis, vp.voxels
    n_r = c_r0.size
    n = rad.n_fourier_from_size(n_r)
    if options.inner_radius is not None:
        r_in, dr_in = float(options.inner_radius), np.zeros(n_r)
    else:
        design = rad.design_matrix(rad.uniform_angles(720), n)
        j = int(np.argmin(design @ c_r0))
        r_in, dr_in = options.inner_fraction * float(design[j] @ c_r0), options.inner_fraction * design[j]
    inside = vox.inside
    px, py = vox.px[inside], vox.py[inside]
    # rho(r, R(t), r_in) of the inverse map and the polar coordinates (r, t) about the centre: pointwise
    # derivatives from CasADi, the chain rule through R = b(t)^T c_R and r_in(c_R) with BLAS
    r0, th0, dr_dx, dr_dy, dt_dx, dt_dy = _rows(polar_pieces(), px, py, center0[0], center0[1])
    b = rad.design_matrix(th0, n)
    slope_t = rad.design_matrix(th0, n, 1) @ c_r0  # dR/dt
    rho0, rho_r, rho_big_r, rho_in = _rows(inverse_map_pieces(), r0, b @ c_r0, r_in)
    # columns [c_R, c_x, c_y]
    drho = np.hstack(
        [
            rho_big_r[:, None] * b + np.outer(rho_in, dr_in),
            (rho_big_r * slope_t * dt_dx + rho_r * dr_dx)[:, None],
            (rho_big_r * slope_t * dt_dy + rho_r * dr_dy)[:, None],
        ]
    )
    dth = np.hstack([np.zeros((px.size, n_r)), dt_dx[:, None], dt_dy[:, None]])
    clipped = rho0 > 1.0  # velocity.assemble clips rho to 1 (points on the wall within rounding)
    rho0 = np.minimum(rho0, 1.0)
    drho[clipped] = 0.0

    # a near-wall layer's radial factors are far too steep for a Chebyshev form: in closed form instead
    polynomial = getattr(basis, "base", basis)
    pb = cpl.polar_basis(polynomial, th0)
    tk = np.polynomial.chebyshev.chebvander(2 * rho0 / cpl.RHO_MAX - 1, pb.cheb.shape[1] - 1).T
    # distinct radial factors only (Zernike functions with +-m share one); raw function j uses row r_of[j]
    r_of = np.argmax(pb.select_radial, axis=1)
    radial, dradial = pb.cheb @ tk, pb.cheb_derivative @ tk
    if polynomial is not basis:  # cell means, as in the fit: a point rule would differentiate the steep layer badly
        stretch = nw.stretch(vp.disk_map)
        cells = None if vp.cell_mm is None else tuple(h / stretch for h in nw.cell_half_widths(vp.cell_mm, th0))
        layer, dlayer = basis.layer_radial(rho0, cells)
        r_of = np.concatenate([r_of, radial.shape[0] + np.arange(layer.shape[0])])
        radial, dradial = np.vstack([radial, layer]), np.vstack([dradial, dlayer])
    # the angular factors repeat across radial degrees: the trigonometry once per distinct (order, kind)
    terms = basis.angular_terms()
    distinct = sorted(set(terms))
    a_of = np.array([distinct.index(term) for term in terms])
    orders = np.array([m for m, _ in distinct], float)[:, None]
    is_cos = np.array([kind == "cos" for _, kind in distinct])[:, None]
    cos_t, sin_t = np.cos(orders * th0), np.sin(orders * th0)
    ang = np.where(is_cos, cos_t, sin_t)
    dang = np.where(is_cos, -orders * sin_t, orders * cos_t)
    # the operator itself is the fit's (the same points, map and averaging; a layer's columns exact across cells)
    factors = (radial, dradial, ang, dang, r_of, a_of)
    return OperatorDerivative(vp.operator, _averaging(vp), factors, drho, dth, basis.transform), r_in, dr_in


def _averaging(vp: vel.VelocityProblem):
    """Voxel values from inside-point values: the box model's means, or the k-space PSF weights."""
    if vp.averager is None:
        return vp.voxels.mean_matrix()
    signal = vp.averager(vp.voxels.inside.astype(float))
    return kspace.AveragingOperator(vp.averager, vp.voxels.inside, signal, vp.weights > 0)


@dataclass
class OperatorDerivative:
    r"""``T~_h`` and the pieces of its derivative: ``dT_k = avg (diag(drho_k) A_rho + diag(dt_k) A_t) B``.

    Raw basis function ``j`` is ``radial_{r(j)}(rho) angular_{a(j)}(t)``, so
    ``A_rho[:, j] = angular_{a(j)} radial'_{r(j)}`` and
    ``A_t[:, j] = angular'_{a(j)} radial_{r(j)}``; they are kept as their
    distinct factors (``factors``: ``radial``, ``radial'`` (n_R, n_points),
    ``angular``, ``angular'`` (n_A, n_points), ``r(j)``, ``a(j)``) and never
    formed: ``A_rho x = sum_a angular_a (Q_x radial')_a`` with
    ``Q_x[a(j), r(j)] += x_j``, and ``A_rho^T Y`` one product per angular
    factor. ``B`` is the basis's orthonormalizing transform, applied on the
    small side of every product.
    """

    op: np.ndarray  # (n_vox, n_basis)
    avg: Any  # (n_vox, n_points): voxel means over the inside points (sparse), or kspace.AveragingOperator
    factors: tuple  # (radial, dradial, ang, dang, r_of, a_of), see the class notes
    drho: np.ndarray  # (n_points, n_dir)
    dtheta: np.ndarray  # (n_points, n_dir)
    transform: np.ndarray  # (n_raw, n_basis)

    def _raw_times(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(A_rho raw, A_t raw)`` at the points."""
        radial, dradial, ang, dang, r_of, a_of = self.factors
        q = np.zeros((ang.shape[0], radial.shape[0]))
        np.add.at(q, (a_of, r_of), raw)
        return np.sum(ang * (q @ dradial), axis=0), np.sum(dang * (q @ radial), axis=0)

    def _raw_transpose_times(self, y_rho: np.ndarray, y_t: np.ndarray) -> np.ndarray:
        """``A_rho^T y_rho + A_t^T y_t`` (point arrays of shape (n_points, k)), shape (n_raw, k)."""
        radial, dradial, ang, dang, r_of, a_of = self.factors
        out = np.empty((r_of.size, y_rho.shape[1]))
        for a in range(ang.shape[0]):
            j = np.flatnonzero(a_of == a)
            rows = r_of[j]
            out[j] = dradial[rows] @ (ang[a][:, None] * y_rho) + radial[rows] @ (dang[a][:, None] * y_t)
        return out

    def times(self, c: np.ndarray) -> np.ndarray:
        """``[dT_k c]_k``, shape (n_vox, n_dir)."""
        s_rho, s_t = self._raw_times(self.transform @ c)
        return np.asarray(self.avg @ (self.drho * s_rho[:, None] + self.dtheta * s_t[:, None]))

    def transpose_times(self, y: np.ndarray) -> np.ndarray:
        """``[dT_k^T y]_k``, shape (n_basis, n_dir)."""
        z = np.asarray(self.avg.T @ y).ravel()
        return self.transform.T @ self._raw_transpose_times(self.drho * z[:, None], self.dtheta * z[:, None])


@functools.lru_cache(maxsize=16)
def _wss_derivative_map(template, n_fourier: int, eta: float, viscosity_pa_s: float, n_phi: int) -> ca.Function:
    return wss_derivative_function(template, n_fourier, eta, viscosity_pa_s).map(n_phi)


def _mean_weight_jacobian(c_r: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc-length weights ``w_j = ds_j / sum ds`` on uniform angles and ``dw/dc_R`` (CasADi)."""
    out = _mean_weight_function(c_r.size, np.asarray(phi, dtype=float).tobytes())(c_r)
    return np.asarray(out[0]).ravel(), np.asarray(out[1])


@functools.lru_cache(maxsize=16)
def _mean_weight_function(n_coefficients: int, phi_bytes: bytes) -> ca.Function:
    """``c_R -> (w, dw/dc_R)``, built once per radius space and angle set (the same for every slice)."""
    phi = np.frombuffer(phi_bytes, dtype=float)
    n = rad.n_fourier_from_size(n_coefficients)
    c = ca.SX.sym("c", n_coefficients)
    big_r = ca.mtimes(ca.DM(rad.design_matrix(phi, n)), c)
    d_r = ca.mtimes(ca.DM(rad.design_matrix(phi, n, 1)), c)
    ds = ca.sqrt(big_r * big_r + d_r * d_r)
    w = ds / ca.sum1(ds)
    return ca.Function("w", [c], [w, ca.jacobian(w, c)])


def wss_jacobians(basis, eta: float, viscosity_pa_s: float, n_phi: int, c_r0, center, c_v0, r_in: float, dr_in):
    """tau at ``n_phi`` angles and the derivatives of tau and of its mean with respect to ``c_R`` and ``c_v``.

    Returns ``(phi, tau, mean tau, d tau/d c_R, d tau/d c_v, d mean/d c_R, d mean/d c_v)``; ``r_in`` depends on
    ``c_R`` through ``dr_in`` (zero where it is fixed). tau does not depend on the centre directly
    (translation invariance).
    """
    n_r = np.size(c_r0)
    phi = rad.uniform_angles(n_phi)
    template, parameters = wss_mod.velocity_template(basis)
    fun = _wss_derivative_map(template, rad.n_fourier_from_size(n_r), eta, viscosity_pa_s, n_phi)
    p = parameters(c_v0)
    nb = np.size(c_v0)
    tau0, grad = (np.asarray(a) for a in fun(phi[None, :], c_r0, np.asarray(center, float), p[:nb], p[nb:], r_in))
    tau0 = tau0.ravel()
    dt_dr = grad[:n_r].T + np.outer(grad[n_r + nb], dr_in)
    dt_dv = grad[n_r : n_r + nb].T * wss_mod.linear_scale(basis)[None, :]
    w_mean, dw = _mean_weight_jacobian(c_r0, phi)
    return phi, tau0, float(w_mean @ tau0), dt_dr, dt_dv, w_mean @ dt_dr + tau0 @ dw, w_mean @ dt_dv


def _wss_sensitivity(
    basis,
    eta: float,
    viscosity_pa_s: float,
    n_phi: int,
    c_r0,
    center,
    c_v0,
    r_in: float,
    dr_in: np.ndarray,
    dcr: np.ndarray,
    dcv: np.ndarray,
    m_index,
    u_index,
) -> Sensitivity:
    """tau and its mean at ``n_phi`` angles and their derivatives, given ``d c_R / dp`` and ``d c_v / dp``.

    ``p = [magnitude voxels (m_index); velocity voxels (u_index); SCALARS]`` (:func:`wss_jacobians`).
    """
    n_m, n_u = m_index.size, u_index.size
    phi, tau0, mean0, dt_dr, dt_dv, dm_dr, dm_dv = wss_jacobians(
        basis, eta, viscosity_pa_s, n_phi, c_r0, center, c_v0, r_in, dr_in
    )
    scalars = slice(n_m + n_u, None)
    dmean = dm_dr @ dcr + dm_dv @ dcv
    out = Sensitivity(
        phi=phi,
        d_tau=dt_dr @ dcr[:, scalars] + dt_dv @ dcv[:, scalars],
        d_mean=dmean[n_m + n_u :],
        d_tau_d_coef=np.hstack([dt_dr, dt_dv]),
        d_mean_d_m=dmean[:n_m],
        d_mean_d_u=dmean[n_m : n_m + n_u],
        m_index=np.asarray(m_index),
        u_index=np.asarray(u_index),
        d_coef_r=dcr,
        d_coef_v=dcv,
    )
    out.noise.update({"tau_reference": tau0, "mean_reference": mean0})
    return out


# --------------------------------------------------------------------------- driver
def decoupled(
    problem: geo.GeometryProblem,
    gopt: geo.GeometryOptions,
    geometry: geo.GeometryResult,
    vp: vel.VelocityProblem,
    vopt: vel.VelocityOptions,
    velocity: vel.VelocityResult,
    viscosity_pa_s: float,
    n_phi: int = 360,
    tol: float = 1e-12,
) -> Sensitivity:
    """Sensitivities of the decoupled reconstruction at its solution (see the module notes).

    Parameters
    ----------
    problem, gopt, geometry : the geometry solve (``geometry.alpha`` and ``geometry.gamma`` are used).
    vp, vopt, velocity : the velocity problem assembled on ``geometry`` and its solution (``velocity.beta``).
    tol : float
        IPOPT tolerance of the re-solve that anchors the sensitivities when the
        Newton step does not (:func:`_newton_anchor`: a box row on its bound, a
        large step, k-space data); the solution derivatives are only as good as
        the KKT point.
    """
    t_start = time.perf_counter()
    gopt_t = geo.with_options(gopt, alpha=geometry.alpha, tol=tol)
    # the closed-form Newton anchor exists for voxel means; other models re-solve to a tight tolerance
    voxel_means = isinstance(problem.measurement, acq_model.VoxelMeans)
    newton = _newton_anchor(problem, gopt_t, geometry) if voxel_means else None
    if newton is not None:
        c_r0, dcr_dpg, annulus, active_rows = newton
    else:
        # anchor: re-solve from the solution to a tight tolerance (the reconstruction's tolerance leaves the
        # stationarity residual at ~1e-9, which would show in the derivatives)
        solver = geo.solver_for(problem, gopt_t, warm=True)
        lam = geometry.box_multipliers  # empty after the projected Gauss-Newton solver: start from none active
        lam = lam if lam.size == solver.nlp.g.numel() else np.zeros(solver.nlp.g.numel())
        anchor = solver.solve(geometry.alpha, geometry.coefficients, problem, lam)
        if not anchor.stats.converged:
            raise SolverError(
                f"geometry sensitivity re-solve did not converge ({anchor.stats.status}); "
                "the derivatives would not be those of a solution"
            )
        c_r0 = anchor.coefficients
        dcr_dpg, annulus = geometry_kkt(problem, gopt_t, c_r0, geometry.alpha, geometry.gamma, anchor.box_multipliers)
        active_rows = int(np.count_nonzero(anchor.box_multipliers))

    # velocity: c_v = H^{-1} T^T W u with H = T^T W T + beta G / pi (W includes 1/A); differentiate the
    # normal equations along each geometry direction
    ctr = np.asarray(problem.center, float)
    n_r, n_u = c_r0.size, vp.data.size
    od, r_in, dr_in = operator_derivatives(vp, vopt, c_r0, ctr)
    t_op = od.op
    wt = vp.weights / vp.area
    tik = LinearTikhonov(t_op, vp.weights, vp.data, vp.gram)
    cho = scipy.linalg.cho_factor(tik.hessian(velocity.beta))
    cv0 = scipy.linalg.cho_solve(cho, tik.rhs)
    resid = t_op @ cv0 - vp.data
    dcv_du = scipy.linalg.cho_solve(cho, t_op.T * wt[None, :])
    dcv_db = -scipy.linalg.cho_solve(cho, vp.gram @ cv0 / np.pi)
    # H dc = -(dT^T W r + T^T W dT c) along each of the n_r + 2 geometry directions at once
    dcv_dgeo = -scipy.linalg.cho_solve(cho, od.transpose_times(wt * resid) + t_op.T @ (wt[:, None] * od.times(cv0)))

    # chain rule on [m_annulus, u, alpha, beta, gamma, c_x, c_y]
    n_m = annulus.size
    n_all = n_m + n_u + len(SCALARS)
    dcr = np.zeros((n_r, n_all))
    dcr[:, :n_m] = dcr_dpg[:, :n_m]
    dcr[:, n_m + n_u + 0] = dcr_dpg[:, n_m]  # alpha
    dcr[:, n_m + n_u + 2] = dcr_dpg[:, n_m + 1]  # gamma
    dcr[:, n_m + n_u + 3 :] = dcr_dpg[:, n_m + 2 :]  # centre
    dcv = dcv_dgeo[:, :n_r] @ dcr
    dcv[:, n_m : n_m + n_u] += dcv_du
    dcv[:, n_m + n_u + 1] += dcv_db
    dcv[:, n_m + n_u + 3 :] += dcv_dgeo[:, n_r:]
    out = _wss_sensitivity(
        vp.basis, vopt.eta, viscosity_pa_s, n_phi, c_r0, ctr, cv0, r_in, dr_in, dcr, dcv, annulus, vp.voxels.index
    )
    _attach_correlation(out, problem)
    out.seconds = time.perf_counter() - t_start
    out.noise["active_box_constraints"] = active_rows
    out.noise["anchor"] = "newton step" if newton is not None else "ipopt re-solve"
    return out


#: Relative size (W0 norm) of the Newton step above which the anchor falls back to an IPOPT re-solve.
NEWTON_ANCHOR_STEP = 1e-4


def _newton_anchor(problem: geo.GeometryProblem, gopt: geo.GeometryOptions, geometry: geo.GeometryResult):
    """``(c, dc/dp, annulus, 0)`` from one Newton step on the geometry's stationarity, or None.

    The reconstruction stops at a tolerance (its stationarity residual ~1e-9, or the projected Gauss-Newton
    solver's 1e-5 mm), at which the exact Hessian it computes anyway for the KKT system gives the Newton step
    to the optimum: ``c* = c - H^-1 grad J``. The derivatives are taken with ``H`` and ``dgrad/dp`` at ``c``,
    which differ from those at ``c*`` by the step's relative size (``<=`` :data:`NEWTON_ANCHOR_STEP`). Box
    rows on their bound (or a larger step) send the anchor back to an IPOPT re-solve (None): the active set
    is IPOPT's business.
    """
    c = np.asarray(geometry.coefficients, float)
    if np.any(geo.on_bound(problem, gopt, c)):
        return None
    hmat, dgrad, annulus, grad = geometry_parameter_derivatives(
        problem, gopt, c, geometry.alpha, geometry.gamma, gradient=True
    )
    try:
        factor = scipy.linalg.cho_factor(hmat)
    except np.linalg.LinAlgError:
        return None  # not positive definite here: leave it to IPOPT
    step = scipy.linalg.cho_solve(factor, grad)
    w0 = rad.sobolev_weights(gopt.n_fourier, 0)
    if np.sqrt(np.sum(w0 * step**2) / np.sum(w0 * c**2)) > NEWTON_ANCHOR_STEP:
        return None
    new = c - step
    r = rad.evaluate(new, gopt.box_angles())
    if np.any(r < problem.r0) or np.any(r > problem.r1):
        return None
    return new, -scipy.linalg.cho_solve(factor, dgrad), annulus, 0


def noise_correlation_of(problem: geo.GeometryProblem):
    """``(R_y, R_x, shape)`` of a k-space acquisition's image noise (None for the box model: independent voxels)."""
    return problem.measurement.correlation_factors(problem.grid.shape)


def _attach_correlation(out: Sensitivity, problem: geo.GeometryProblem) -> None:
    """Give the band the noise correlation of a k-space acquisition (none for the box model)."""
    correlation = noise_correlation_of(problem)
    if correlation is None:
        return
    out.correlation = correlation
    psf = problem.psf
    assert psf is not None  # a correlated model is a PSF's
    out.noise["correlation"] = f"k-space noise: {psf.filter} filter, zero-filling {list(psf.zero_fill)}"


@dataclass
class CoupledKKT:
    """The coupled NLP's KKT pieces at a solution (:func:`coupled_kkt`): ``x = [c_R; c_v]``, the exact Hessian of
    the objective, the active box rows (in ``x``), ``d grad f / d p`` for ``p = [magnitude voxels (m_index);
    velocity voxels (u_index); SCALARS]`` and the stationarity residual after polishing."""

    x: np.ndarray
    hessian: np.ndarray
    active: np.ndarray
    dgrad: np.ndarray
    m_index: np.ndarray
    u_index: np.ndarray
    polished: float

    @property
    def kkt(self) -> np.ndarray:
        return bordered(self.hessian, self.active)


def coupled_kkt(cres, problem: geo.GeometryProblem, gopt: geo.GeometryOptions, polish_steps: int = 2) -> CoupledKKT:
    """The KKT system of the coupled NLP at ``cres`` (see :func:`coupled`); ``polish_steps`` Newton steps first."""
    nlp = cres.nlp
    if nlp is None:
        raise InputError("coupled sensitivities need the solved NLP (CoupledResult.nlp)")
    n_r = nlp.n_r
    x = np.concatenate([cres.geometry.coefficients, cres.velocity.coefficients])
    n_x = x.size
    gam = float(nlp.geometry.gamma)
    # columns of hess(w^T r) along c_R and the mixed column along gamma, one forward-over-reverse sweep each
    second = cpl.residual_curvature(nlp, with_gamma=True)
    directions = np.eye(n_x + 1)[:, list(range(n_r)) + [n_x]]
    # f = |r|^2 + penalty: its gradient 2 J^T r + grad(penalty) from the chain-rule Jacobian (a reverse sweep
    # through the misfit costs 10x an evaluation of J); d grad / d gamma = 2 (sum_i r_i dr_i/dx dgamma + J^T dr/dgamma)
    blocks = nlp.jacobian_blocks()
    outputs = [
        *blocks,
        nlp.residual,
        ca.gradient(nlp.penalty, nlp.x),
        nlp.velocity_error,
        ca.jtimes(nlp.residual, nlp.gamma, ca.DM(1.0)),
    ]
    fun = DenseCall(ca.Function("kkt", [nlp.x, nlp.gamma], [ca.densify(o) for o in outputs]))
    reg = 2 * nlp.penalty_hessian()
    box = rad.design_matrix(gopt.box_angles(), gopt.n_fourier)
    active = np.flatnonzero(cres.geometry.box_multipliers != 0)
    g_act = np.hstack([box[active], np.zeros((active.size, n_x - n_r))])

    def hessian(jac, sec):
        return 2 * jac.T @ jac + 2 * cpl.curvature_matrix(sec, n_r) + reg

    lam, sec = np.zeros(active.size), None
    for it in range(polish_steps + 1):
        values = fun(x, gam)
        jac = nlp.stack_jacobian(values[: len(blocks)])
        res0, grad_penalty, err_v, d_res = (v.ravel() for v in values[len(blocks) :])
        grad = 2 * jac.T @ res0 + grad_penalty
        if sec is None:
            # the second-order terms once, at IPOPT's solution (n_r + 1 forward-over-reverse sweeps, the costly
            # part): the polish moves x by about IPOPT's tolerance, which changes them by as little relative
            sec, mixed = np.split(DenseCall(second)(x, gam, res0, directions)[0], [n_r], axis=1)
        hess = hessian(jac, sec)
        kkt = bordered(hess, g_act)
        stationarity = grad + g_act.T @ lam
        if it == polish_steps or np.linalg.norm(stationarity) <= 1e-13 * max(1.0, float(np.linalg.norm(grad))):
            break
        step = np.linalg.solve(kkt, -np.concatenate([stationarity, np.zeros(active.size)]))
        x, lam = x + step[:n_x], lam + step[n_x:]
    polished = float(np.linalg.norm(grad + g_act.T @ lam))

    # d grad f / d p for p = [magnitude voxels; velocity voxels; alpha, beta, gamma, centre x, centre y]
    model = nlp.velocity_model
    annulus = nlp.geometry.model.annulus
    n_a = annulus.size
    m_index = np.union1d(annulus, model.index)
    u_index = model.index
    n_m, n_u = m_index.size, u_index.size
    dgrad = np.zeros((n_x, n_m + n_u + len(SCALARS)))
    area = problem.grid.voxel_area
    pos_a = np.searchsorted(m_index, annulus)
    dgrad[:, pos_a] += -2 * np.sqrt(area) * jac[:n_a].T
    # precision weights s_k = sqrt(|V|) m_k / sqrt(W), W = |V| sum m_k^2: d s_k / d m_j
    m_v = np.clip(problem.magnitude.ravel()[model.index], 0.0, 1.0)
    free = (m_v > 0) & (m_v < 1)
    big_w = area * np.sum(m_v**2)
    jac_v = jac[n_a:]  # rows of sqrt(lambda) s_k (T_k - u_k)
    e_v = np.sqrt(nlp.weight) * err_v
    # 4 sum_k (d s_k / d m_j) e_k J_k: diagonal part and the rank-one part through W
    diag_part = 4 * np.sqrt(area / big_w) * (free * e_v)[:, None] * jac_v  # (n_u, n_x), k = j
    coupling = 4 * np.sqrt(area) * area * big_w**-1.5 * ((m_v * e_v) @ jac_v)  # sum_k m_k e_k J_k
    pos_v = np.searchsorted(m_index, model.index)
    dgrad[:, pos_v] += diag_part.T - np.outer(coupling, free * m_v)
    scale = np.sqrt(model.weights / np.sum(model.weights))
    dgrad[:, n_m : n_m + n_u] = -2 * np.sqrt(nlp.weight) * scale[None, :] * jac_v.T
    ref = nlp.geometry.reference
    dgrad[:n_r, n_m + n_u + 0] = 2 * nlp.geometry.weights * (x[:n_r] - ref)
    dgrad[n_r:, n_m + n_u + 1] = 2 * nlp.weight * nlp.gram @ x[n_r:] / np.pi
    dgrad[:, n_m + n_u + 2] = 2 * (mixed.ravel() + jac.T @ d_res)
    dgrad[:, n_m + n_u + 3 :] = _coupled_centre_derivative(nlp, problem, gopt, x, gam, cres.velocity)
    return CoupledKKT(x, hess, g_act, dgrad, m_index, u_index, polished)


def coupled(
    cres,
    problem: geo.GeometryProblem,
    gopt: geo.GeometryOptions,
    vopt: vel.VelocityOptions,
    viscosity_pa_s: float,
    n_phi: int = 360,
    polish_steps: int = 2,
) -> Sensitivity:
    """Sensitivities of the coupled reconstruction (:mod:`wss_nlp.models.coupled`) at its solution.

    Notes
    -----
    Implicit function theorem on the KKT system of the coupled NLP with the
    exact Hessian ``2 J^T J + 2 sum_i r_i hess r_i + penalty Hessian``: ``J``
    is the chain-rule Jacobian of the residuals, and the second-order term
    comes from forward-over-reverse sweeps of ``w^T r`` (``w = r`` held fixed) along the ``c_R`` directions
    and gamma (:func:`wss_nlp.models.coupled.residual_curvature`, one direction at a time, at
    IPOPT's solution; the residuals are linear in ``c_v``). Parameters: the normalized
    magnitude (annulus voxels through the geometry misfit and the velocity
    voxels through the precision weights ``|V| m_i^2``), the velocity image,
    alpha, beta, gamma and the centre (geometry part from the per-voxel
    derivatives of :func:`geometry_parameter_derivatives`, velocity part by
    forward AD of the gradient through the polar coordinates of the
    sub-voxel points). The IPOPT solution (tolerance limited by rounding in the
    objective) is first polished by Newton steps on the KKT system, which
    need only gradients.
    """
    t_start = time.perf_counter()
    k = coupled_kkt(cres, problem, gopt, polish_steps)
    x, dgrad, m_index, u_index, polished = k.x, k.dgrad, k.m_index, k.u_index, k.polished
    n_r = cres.nlp.n_r
    dx = solve_kkt(k.kkt, dgrad, "coupled sensitivity")

    # r_in is fixed in the coupled model
    out = _wss_sensitivity(
        cres.velocity.basis,
        vopt.eta,
        viscosity_pa_s,
        n_phi,
        x[:n_r],
        problem.center,
        x[n_r:],
        cres.velocity.disk_map.r_in,
        np.zeros(n_r),
        dx[:n_r],
        dx[n_r:],
        m_index,
        u_index,
    )
    _attach_correlation(out, problem)
    out.seconds = time.perf_counter() - t_start
    out.noise.update({"active_box_constraints": int(k.active.shape[0]), "kkt_residual_after_polish": polished})
    return out


def _coupled_centre_derivative(nlp, problem, gopt, x: np.ndarray, gamma: float, velocity) -> np.ndarray:
    """``d grad_x J / d [c_x, c_y]`` of the coupled functional at ``x`` (n_x, 2).

    The geometry part (rows of c_R) comes from the per-voxel CasADi
    derivatives; the velocity part by forward AD of the gradient of the
    velocity misfit written with a symbolic centre. ``r_in`` is fixed in the
    coupled model; the box does not depend on the centre.
    """
    n_r = nlp.n_r
    derivatives = parameter_derivatives(problem)
    _, dgrad_geo, _ = derivatives(problem, geo.with_options(gopt, alpha=nlp.alpha), x[:n_r], nlp.alpha, gamma)
    center = ca.MX.sym("center", 2)
    res_v = cpl.velocity_residual(
        nlp.velocity_model,
        nlp.x[:n_r],
        nlp.x[n_r:],
        velocity.basis,
        velocity.disk_map.r_in,
        gamma,
        gopt.heaviside,
        center=center,
        stretch=nlp.stretch,
    )
    grad_v = ca.gradient(nlp.weight * ca.sumsqr(res_v), nlp.x)
    # one direction's graph mapped over the two (both in one graph took twice as long to build)
    direction = ca.MX.sym("direction", 2)
    one = ca.Function("dcentre", [nlp.x, center, direction], [ca.densify(ca.jtimes(grad_v, center, direction))])
    fun = one.map("dcentre_columns", "serial", 2, [0, 1], [])
    out = DenseCall(fun)(x, np.asarray(problem.center, float), np.eye(2))[0]
    out[:n_r] += dgrad_geo[:, -2:]
    return out


def parameter_derivatives(problem: geo.GeometryProblem):
    """The function giving the geometry functional's Hessian and ``d grad / d p`` for the problem's measurement model
    (:func:`geometry_parameter_derivatives` for voxel means, :func:`kspace_parameter_derivatives` for a PSF)."""
    return {acq_model.VoxelMeans: geometry_parameter_derivatives, acq_model.KSpace: kspace_parameter_derivatives}[
        type(problem.measurement)
    ]
