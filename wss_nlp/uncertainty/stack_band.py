r"""The uncertainty band of a z-regularized stack (paper Sec. 5 with Appendix B's noise model).

In a stack the slices are solved together, so the noise of one slice moves
the wall and the velocity of its neighbours. The band linearizes the whole
segment at its solution.

Geometry: the segment's coefficients :math:`C = (c_1, \dots, c_n)` minimize
:math:`\sum_k J_k(c_k; m_k) + \kappa\, C^\top (L \otimes W_0) C` under the
box (:mod:`wss_nlp.models.stack`). With the exact per-slice Hessians :math:`H_k`
and data derivatives :math:`D_k = \partial \nabla J_k / \partial m_k`
(:func:`wss_nlp.uncertainty.sensitivity.geometry_parameter_derivatives`), the implicit
function theorem on the segment's KKT system

.. math::

    \begin{pmatrix} \operatorname{diag}(H_k) + 2\kappa\, L \otimes W_0 & G_A^\top \\ G_A & 0 \end{pmatrix}
    \begin{pmatrix} \delta C \\ \delta\lambda \end{pmatrix}
    = \begin{pmatrix} -\operatorname{diag}(D_k)\, \delta m \\ 0 \end{pmatrix}

(``G_A`` the active box rows) gives
:math:`\operatorname{Cov}(C) = K^{-1}\operatorname{diag}(D_k \Sigma_{m,k} D_k^\top) K^{-1}`
with :math:`K^{-1}` the primal block of the inverse.

Velocity: the coupled normal equations :math:`M V = g` with
:math:`M = \operatorname{diag}(H_k(\beta_k)) + \kappa_v L \otimes G_0/\pi`
are differentiated along the data and the walls,
:math:`M\,\delta V = \operatorname{diag}(T_k^\top W_k)\,\delta u + \operatorname{diag}(Q_k)\,\delta C`,
:math:`Q_k = -(\partial T_k^\top W_k r_k + T_k^\top W_k\, \partial T_k\, v_k)` (as for one slice,
:func:`wss_nlp.uncertainty.sensitivity.decoupled`), so

.. math::

    \operatorname{Cov}(V) = M^{-1}\left[\operatorname{diag}(T_k^\top W_k \Sigma_{u,k} W_k T_k)
        + Q \operatorname{Cov}(C) Q^\top\right] M^{-1},\quad
    \operatorname{Cov}(V, C) = M^{-1} Q \operatorname{Cov}(C).

WSS: :math:`\delta\tau_k = A_k\,\delta c_k + B_k\,\delta v_k` (:func:`wss_nlp.uncertainty.sensitivity.wss_jacobians`),
so :math:`\sigma_{\tau,k}^2 = \operatorname{diag}([A_k\ B_k]\operatorname{Cov}_{kk}[A_k\ B_k]^\top)`
from the diagonal blocks alone. Both solves form one joint system in the
walls, the active box multipliers and the velocities of every slice,
block tridiagonal in groups of ``order`` slices, whose covariance's diagonal
blocks :func:`block_covariances` finds in two sweeps (cost linear in the
number of slices; see :func:`covariances`). The coupled method's segments
(:func:`coupled_segment_band`) use the same sweeps on the coupled NLP's KKT
systems. A law-of-the-wall slice adds its scale's response to its
own layer amplitude (as :func:`wss_nlp.pipeline.reconstruct.uncertainty`; the
amplitude's z-coupled covariance is used, its scale derivative is the
slice's own).

Held fixed, as for one slice: the preprocessing outputs (normalization,
box, centres, reference radii), the betas and the near-wall choices, the
dephasing factors. The linearization point is the segment's solution to
the stack tolerance, not re-solved tighter.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .._lazy import scipy
from ..models import geometry as geo
from ..models import near_wall as nw
from ..core import radius as rad
from . import sensitivity as sens
from ..models import velocity as vel
from ..models import wss as wss_mod
from ..errors import SolverError


@dataclass
class BandSlice:
    """What the band needs of one slice of a solved segment."""

    problem: geo.GeometryProblem  # the geometry problem of the final pass
    geometry: geo.GeometryResult
    box_multipliers: np.ndarray  # of the box rows (zero: inactive)
    velocity_problem: vel.VelocityProblem
    velocity: np.ndarray  # coefficients
    beta: float
    near: Any = None  # wss_nlp.models.near_wall.NearWallChoice or None
    sigma_m: float = float("nan")  # normalized magnitude noise (1 std)
    sigma_u: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per lumen voxel, m/s


@dataclass
class SliceBand:
    """The band of one slice: tau std per angle and the mean's std with its two parts (Pa)."""

    tau_std: np.ndarray
    mean_std: float
    mean_std_magnitude: float
    mean_std_velocity: float
    scale_std_log: float = float("nan")


def _active_multipliers(lam, problem: geo.GeometryProblem, gopt: geo.GeometryOptions, coef) -> np.ndarray:
    """The box multipliers of rows that are active: IPOPT's ``clip_inactive_lam`` leaves ~1e-12 on rows far
    from their bound in the joint stack NLP, so a row counts only where it also sits on its bound
    (:func:`wss_nlp.models.geometry.on_bound`)."""
    lam = np.asarray(lam, float)
    if lam.size != len(gopt.box_angles()):
        return np.zeros(len(gopt.box_angles()))
    return np.where(geo.on_bound(problem, gopt, coef), lam, 0.0)


def _row_space(rows: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the span of the active box rows: ``G_A dc = 0`` unchanged, but adjacent
    active angles (nearly parallel rows, possibly more than there are coefficients) no longer make the
    KKT matrix singular."""
    if rows.shape[0] == 0:
        return rows
    _, sv, vt = np.linalg.svd(rows, full_matrices=False)
    return vt[sv > 1e-10 * sv[0]]


def joint_blocks(lin: Linearization, kappa: float, kappa_v: float, zop: np.ndarray, w0: np.ndarray, gram0):
    """The blocks ``A_kj`` of the segment's joint linear system in ``[c_k; lambda_k; v_k]`` per slice (see
    :func:`covariances`); returns ``(block(k, j) -> ndarray, sizes [(n_r, n_active, n_v)] per slice)``."""
    n_r = lin.hessians[0].shape[0]
    sizes = [(n_r, a.shape[0], h.shape[0]) for a, h in zip(lin.active, lin.normal)]
    m = gram0.shape[0]

    def block(k: int, j: int) -> np.ndarray:
        (nr, na, nv), (_, ma, mv) = sizes[k], sizes[j]
        out = np.zeros((nr + na + nv, nr + ma + mv))
        if zop[k, j] != 0:
            out[:nr, :nr] = 2 * kappa * zop[k, j] * np.diag(w0)
            out[nr + na : nr + na + m, nr + ma : nr + ma + m] = kappa_v * zop[k, j] * gram0 / np.pi
        if k == j:
            out[:nr, :nr] += lin.hessians[k]
            out[:nr, nr : nr + na] = lin.active[k].T
            out[nr : nr + na, :nr] = lin.active[k]
            out[nr + na :, :nr] = -lin.q[k]
            out[nr + na :, nr + na :] += lin.normal[k]
        return out

    return block, sizes


def covariances(
    lin: Linearization,
    info_m: list,
    info_u: list,
    kappa: float,
    kappa_v: float,
    zop: np.ndarray,
    w0: np.ndarray,
    gram0: np.ndarray,
) -> list[tuple[np.ndarray, np.ndarray]]:
    r"""Per slice, the covariance of ``[c_k; v_k]`` from the magnitude noise and from the velocity noise.

    Parameters
    ----------
    lin : the segment's :class:`Linearization`.
    info_m, info_u : per slice ``D_k Sigma_m,k D_k^T`` and ``P_k Sigma_u,k P_k^T``: the noise seen by the
        geometry gradient and by the velocity normal equations.
    kappa, kappa_v, zop, w0, gram0 : the z-coupling (:mod:`wss_nlp.models.stack`).

    Returns
    -------
    list of ``(cov_m, cov_u)``, each ``(n_r + n_v)`` square.

    Notes
    -----
    The perturbations solve one joint system :math:`A\,\delta x = \delta b`, per slice
    :math:`x_k = (c_k, \lambda_k, v_k)` (walls, active box multipliers, velocity),

    .. math::

        A_{kk} = egin{pmatrix} H_k + 2\kappa L_{kk} W_0 & G_{A,k}^	op & 0 \ G_{A,k} & 0 & 0 \
            -Q_k & 0 & H_k(eta_k) + \kappa_v L_{kk} G_0/\pi \end{pmatrix},\quad
        A_{kj} = \operatorname{diag}(2\kappa L_{kj} W_0,\ 0,\ \kappa_v L_{kj} G_0/\pi),

    with independent right-hand sides :math:`\operatorname{Cov}(\delta b_k) = S_k =
    \operatorname{diag}(D_k\Sigma_{m,k}D_k^	op, 0, P_k\Sigma_{u,k}P_k^	op)`. ``L`` couples slices up to
    ``order`` apart, so groups of ``order`` consecutive slices make ``A`` block tridiagonal, and the
    diagonal blocks of :math:`A^{-1} S A^{-	op}` follow from two sweeps (recursive Green's functions):
    left- and right-connected inverses
    :math:`g^L_i = (A_{ii} - A_{i,i-1} g^L_{i-1} A_{i-1,i})^{-1}`,
    :math:`g^R_i = (A_{ii} - A_{i,i+1} g^R_{i+1} A_{i+1,i})^{-1}`, the noise they carry
    :math:`\Lambda^L_i = g^L_i (S_i + A_{i,i-1}\Lambda^L_{i-1}A_{i,i-1}^	op) g^{L	op}_i` (and
    :math:`\Lambda^R_i` alike), and with
    :math:`G_{ii} = (A_{ii} - A_{i,i-1} g^L_{i-1} A_{i-1,i} - A_{i,i+1} g^R_{i+1} A_{i+1,i})^{-1}`

    .. math::

        [A^{-1} S A^{-	op}]_{ii} = G_{ii}\left(A_{i,i-1}\Lambda^L_{i-1}A_{i,i-1}^	op + S_i
            + A_{i,i+1}\Lambda^R_{i+1}A_{i,i+1}^	op
ight) G_{ii}^	op,

    since :math:`G_{ij} = \mp G_{ii} A_{i,i-1} g^L_{i-1} \cdots A_{j+1,j} g^L_j` for ``j < i`` (and alike
    for ``j > i``). Cost linear in the number of slices (dense ``A^{-1}`` would be quadratic in memory).
    """
    block, sizes = joint_blocks(lin, kappa, kappa_v, zop, w0, gram0)

    def noise(k: int, which: int) -> np.ndarray:
        nr, na, nv = sizes[k]
        out = np.zeros((nr + na + nv,) * 2)
        if which == 0:
            out[:nr, :nr] = info_m[k]
        else:
            out[nr + na :, nr + na :] = info_u[k]
        return out

    def keep(k: int) -> np.ndarray:
        nr, na, nv = sizes[k]
        return np.r_[0:nr, nr + na : nr + na + nv]

    return block_covariances(block, [sum(sz) for sz in sizes], noise, keep, zop)


def block_covariances(block, dims: list[int], noise, keep, zop: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Diagonal blocks of ``A^-1 S A^-T`` for a joint system coupled as ``zop`` (see :func:`covariances`).

    ``block(k, j)``: the ``dims[k] x dims[j]`` block of ``A``; ``noise(k, which)``: ``S_k`` of the magnitude
    (``which = 0``) or the velocity noise (1); ``keep(k)``: the indices of slice k's reported unknowns.
    Returns ``(cov from the magnitude noise, cov from the velocity noise)`` on ``keep(k)`` per slice.
    """
    ns = len(dims)
    rows, cols = np.nonzero(zop)
    width = max(int(np.max(np.abs(cols - rows), initial=0)), 1)
    groups = [list(range(i, min(i + width, ns))) for i in range(0, ns, width)]

    def big(gi: int, gj: int) -> np.ndarray:
        return np.block([[block(k, j) for j in groups[gj]] for k in groups[gi]])

    n = len(groups)
    diag = [big(i, i) for i in range(n)]
    lower = [big(i + 1, i) for i in range(n - 1)]  # A_{i+1,i}
    upper = [big(i, i + 1) for i in range(n - 1)]  # A_{i,i+1}

    def from_left(i: int):
        return lower[i - 1] @ g_left[i - 1] @ upper[i - 1] if i else 0

    def from_right(i: int):
        return upper[i] @ g_right[i + 1] @ lower[i] if i < n - 1 else 0

    try:
        g_left: list = [None] * n
        g_right: list = [None] * n
        for i in range(n):
            g_left[i] = np.linalg.inv(diag[i] - from_left(i))
        for i in reversed(range(n)):
            g_right[i] = np.linalg.inv(diag[i] - from_right(i))
        g_diag = [np.linalg.inv(diag[i] - from_left(i) - from_right(i)) for i in range(n)]
    except np.linalg.LinAlgError as exc:
        raise SolverError(f"stack band: the segment's linearized system is singular ({exc})") from exc
    out: list = [[None, None] for _ in range(ns)]
    for which in (0, 1):
        s = [scipy.linalg.block_diag(*[noise(k, which) for k in groups[i]]) for i in range(n)]
        lam_left: list = [None] * n
        lam_right: list = [None] * n
        for i in range(n):
            inner = s[i] + (lower[i - 1] @ lam_left[i - 1] @ lower[i - 1].T if i else 0)
            lam_left[i] = g_left[i] @ inner @ g_left[i].T
        for i in reversed(range(n)):
            inner = s[i] + (upper[i] @ lam_right[i + 1] @ upper[i].T if i < n - 1 else 0)
            lam_right[i] = g_right[i] @ inner @ g_right[i].T
        for i in range(n):
            inner = s[i] + (lower[i - 1] @ lam_left[i - 1] @ lower[i - 1].T if i else 0)
            inner = inner + (upper[i] @ lam_right[i + 1] @ upper[i].T if i < n - 1 else 0)
            cov = g_diag[i] @ inner @ g_diag[i].T
            start = 0
            for k in groups[i]:
                idx = start + keep(k)
                c = cov[np.ix_(idx, idx)]
                out[k][which] = 0.5 * (c + c.T)
                start += dims[k]
    return [(a, b) for a, b in out]


@dataclass
class Linearization:
    """The pieces of one solved segment's linearization (see the module notes); per slice ``k``:

    ``hessians[k]`` (exact Hessian of ``J_k``), ``active[k]`` (active box rows), ``d_grad_m[k]``
    (``dgrad J_k / dm`` on the annulus voxels ``m_index[k]``), ``normal[k]`` (``H_k(beta_k)``), ``q[k]``
    (``n_v x n_r``), ``p[k] = T_k^T W_k`` on the lumen voxels ``u_index[k]``, ``jac_tau[k]``
    (``d tau / d [c_k; v_k]``, ``n_phi x (n_r + n_v)``), ``jac_mean[k]``, ``scale_factor[k]`` (``d log l / d a_0``
    of a law-of-the-wall layer, else NaN), ``correlation[k]`` (k-space noise, else None).
    """

    hessians: list = field(default_factory=list)
    active: list = field(default_factory=list)
    d_grad_m: list = field(default_factory=list)
    m_index: list = field(default_factory=list)
    normal: list = field(default_factory=list)
    q: list = field(default_factory=list)
    p: list = field(default_factory=list)
    u_index: list = field(default_factory=list)
    jac_tau: list = field(default_factory=list)
    jac_mean: list = field(default_factory=list)
    scale_factor: list = field(default_factory=list)
    correlation: list = field(default_factory=list)

    def covariances(self, info_m: list, info_u: list, kappa: float, kappa_v: float, zop, w0, gram0) -> list:
        """:func:`covariances` with the noise the gradients and the normal equations see (``info_m``, ``info_u``)."""
        return covariances(self, info_m, info_u, kappa, kappa_v, zop, w0, gram0)


def linearize(
    slices: list[BandSlice], gopt: geo.GeometryOptions, vopt: vel.VelocityOptions, viscosity_pa_s: float, n_phi: int
) -> Linearization:
    """The per-slice derivatives of a solved segment (the z-coupling enters in :func:`covariances`)."""
    box = rad.design_matrix(gopt.box_angles(), gopt.n_fourier)
    out = Linearization()
    for s in slices:
        g, vp, c_r = s.geometry, s.velocity_problem, s.geometry.coefficients
        derivatives = sens.parameter_derivatives(s.problem)
        hmat, dgrad, annulus = derivatives(s.problem, geo.with_options(gopt, alpha=g.alpha), c_r, g.alpha, g.gamma)
        lam = _active_multipliers(s.box_multipliers, s.problem, gopt, c_r)
        out.hessians.append(hmat)
        out.active.append(_row_space(box[lam != 0]))
        out.d_grad_m.append(dgrad[:, : annulus.size])
        out.m_index.append(annulus)
        out.correlation.append(sens.noise_correlation_of(s.problem))

        center = np.asarray(s.problem.center, float)
        od, r_in, dr_in = sens.operator_derivatives(vp, vopt, c_r, center)
        t_op = od.op
        wt = vp.weights / np.sum(vp.weights)
        resid = t_op @ s.velocity - vp.data
        q = -(od.transpose_times(wt * resid) + t_op.T @ (wt[:, None] * od.times(s.velocity)))
        out.normal.append(vp.normal_equations(s.beta)[0])
        out.q.append(q[:, : c_r.size])
        out.p.append(t_op.T * wt[None, :])
        out.u_index.append(vp.voxels.index)

        _, _, _, dt_dr, dt_dv, dm_dr, dm_dv = sens.wss_jacobians(
            vp.basis, vopt.eta, viscosity_pa_s, n_phi, c_r, center, s.velocity, r_in, dr_in
        )
        factor = float("nan")
        near = s.near
        if near is not None and near.consistent:
            # the scale follows the layer amplitude a_0 (u_tau l = nu): d log l = -(dg/da_0)/(dg/d log l) d a_0
            smat, _ = wss_mod.wss_matrix(vp.basis, vp.disk_map, viscosity_pa_s, n_phi)
            nu = viscosity_pa_s / near.density_kg_m3
            dg_da0, dg_dlog, dtau_dlog = nw.scale_sensitivity(vp, s.velocity, s.beta, smat, nu)
            nb, factor = vp.basis.base.size, -dg_da0 / dg_dlog
            phi = rad.uniform_angles(n_phi)
            ds = np.hypot(rad.evaluate(c_r, phi), rad.evaluate(c_r, phi, 1))
            dt_dv, dm_dv = dt_dv.copy(), dm_dv.copy()
            dt_dv[:, nb] += dtau_dlog * factor
            dm_dv[nb] += float(np.sum(dtau_dlog * ds) / np.sum(ds)) * factor
        out.jac_tau.append(np.hstack([dt_dr, dt_dv]))
        out.jac_mean.append(np.concatenate([dm_dr, dm_dv]))
        out.scale_factor.append(factor)
    return out


def segment_band(
    slices: list[BandSlice],
    gopt: geo.GeometryOptions,
    vopt: vel.VelocityOptions,
    kappa: float,
    kappa_v: float,
    zop: np.ndarray,
    viscosity_pa_s: float,
    n_phi: int,
) -> list[SliceBand]:
    """The band of every slice of a solved z-regularized segment (see the module notes).

    ``zop`` is the segment's z-operator ``L`` (:func:`wss_nlp.models.stack.z_operator`). Each slice's ``sigma_m``
    and ``sigma_u`` are its noise levels (:func:`wss_nlp.parameters.noise.band_noise_levels`).
    """
    lin = linearize(slices, gopt, vopt, viscosity_pa_s, n_phi)
    info_m = [
        sens.weighted_gram(d, idx, s.sigma_m, corr)
        for d, idx, s, corr in zip(lin.d_grad_m, lin.m_index, slices, lin.correlation)
    ]
    info_u = [
        sens.weighted_gram(p, idx, s.sigma_u, corr)
        for p, idx, s, corr in zip(lin.p, lin.u_index, slices, lin.correlation)
    ]
    w0 = rad.sobolev_weights(gopt.n_fourier, 0)
    basis = slices[0].velocity_problem.basis
    gram0 = getattr(basis, "base", basis).laplacian_gram(0)
    covs = lin.covariances(info_m, info_u, kappa, kappa_v, zop, w0, gram0)
    out = []
    for k, (cov_m, cov_u) in enumerate(covs):
        scale_std = float("nan")
        if np.isfinite(lin.scale_factor[k]):
            a0 = slices[k].geometry.coefficients.size + slices[k].velocity_problem.basis.base.size
            scale_std = float(abs(lin.scale_factor[k]) * np.sqrt(cov_m[a0, a0] + cov_u[a0, a0]))
        out.append(slice_band(cov_m, cov_u, lin.jac_tau[k], lin.jac_mean[k], scale_std))
    return out


def slice_band(cov_m, cov_u, jac_tau, jac_mean, scale_std: float = float("nan")) -> SliceBand:
    """A slice's band from the covariances of its coefficients (magnitude and velocity noise) and the
    Jacobians of tau and of its mean with respect to them."""
    var_tau = sens.row_quadratic(jac_tau, cov_m + cov_u)
    mean_m, mean_u = float(jac_mean @ cov_m @ jac_mean), float(jac_mean @ cov_u @ jac_mean)
    return SliceBand(
        np.sqrt(np.maximum(var_tau, 0.0)),
        float(np.sqrt(max(mean_m + mean_u, 0.0))),
        float(np.sqrt(max(mean_m, 0.0))),
        float(np.sqrt(max(mean_u, 0.0))),
        scale_std,
    )


def coupled_segment_band(
    results: list,
    problems: list,
    levels,
    gopt: geo.GeometryOptions,
    vopt: vel.VelocityOptions,
    kappa: float,
    kappa_v: float,
    zop: np.ndarray,
    viscosity_pa_s: float,
    n_phi: int,
) -> list[SliceBand]:
    r"""The band of a segment solved by the coupled method (:func:`wss_nlp.models.stack.coupled_segment`).

    Notes
    -----
    Per slice the unknowns are :math:`x_k = (c_k, v_k)` and the active box multipliers; the diagonal block is
    the coupled NLP's KKT matrix with the exact Hessian (:func:`wss_nlp.uncertainty.sensitivity.coupled_kkt`, at the
    segment's solution: no per-slice polishing, which would leave the joint optimum), plus the z-penalties'
    Hessians :math:`2\kappa L_{kk} W_0` on :math:`c_k` and :math:`2\lambda\kappa_v L_{kk} G_0/\pi` on the
    plain velocity coefficients (:math:`\lambda` the segment's velocity weight); off-diagonal blocks hold
    those z-terms alone. The noise enters through :math:`\partial\nabla f_k/\partial(m, u)` (the magnitude
    also through the velocity misfit's precision weights). ``levels(k, m_index, u_index)`` returns slice k's
    noise levels ``(sigma_m, sigma_u)`` (each a scalar or one value per voxel of its index). The centre and the
    inner radius of the map are held, as for one slice.
    """
    w0 = rad.sobolev_weights(gopt.n_fourier, 0)
    pieces, info, jacs = [], [], []
    for k, (cres, pb) in enumerate(zip(results, problems)):
        c_r = cres.geometry.coefficients
        lam = _active_multipliers(cres.geometry.box_multipliers, pb, gopt, c_r)
        held = replace(cres, geometry=replace(cres.geometry, box_multipliers=lam))
        kkt = sens.coupled_kkt(held, pb, gopt, polish_steps=0)
        n_m, n_u = kkt.m_index.size, kkt.u_index.size
        sigma_m, sigma_u = levels(k, kkt.m_index, kkt.u_index)
        corr = sens.noise_correlation_of(pb)
        info.append(
            (
                sens.weighted_gram(kkt.dgrad[:, :n_m], kkt.m_index, sigma_m, corr),
                sens.weighted_gram(kkt.dgrad[:, n_m : n_m + n_u], kkt.u_index, sigma_u, corr),
            )
        )
        pieces.append((kkt.hessian, _row_space(kkt.active), c_r.size))
        _, _, _, dt_dr, dt_dv, dm_dr, dm_dv = sens.wss_jacobians(
            cres.velocity.basis, vopt.eta, viscosity_pa_s, n_phi, c_r, pb.center, cres.velocity.coefficients,
            cres.velocity.disk_map.r_in, np.zeros(c_r.size),
        )  # fmt: skip
        jacs.append((np.hstack([dt_dr, dt_dv]), np.concatenate([dm_dr, dm_dv])))
    basis = results[0].velocity.basis
    gram0 = getattr(basis, "base", basis).laplacian_gram(0)
    m = gram0.shape[0]
    weight = float(results[0].weight)

    def block(k: int, j: int) -> np.ndarray:
        (hk, ak, nr), (hj, aj, _) = pieces[k], pieces[j]
        nk, nj = hk.shape[0], hj.shape[0]
        out = np.zeros((nk + ak.shape[0], nj + aj.shape[0]))
        if zop[k, j] != 0:
            out[:nr, :nr] = 2 * kappa * zop[k, j] * np.diag(w0)
            out[nr : nr + m, nr : nr + m] = 2 * weight * kappa_v * zop[k, j] * gram0 / np.pi
        if k == j:
            out[:nk, :nk] += hk
            out[:nk, nk:] = ak.T
            out[nk:, :nk] = ak
        return out

    dims = [h.shape[0] + a.shape[0] for h, a, _ in pieces]

    def noise(k: int, which: int) -> np.ndarray:
        out = np.zeros((dims[k], dims[k]))
        n = pieces[k][0].shape[0]
        out[:n, :n] = info[k][which]
        return out

    covs = block_covariances(block, dims, noise, lambda k: np.arange(pieces[k][0].shape[0]), zop)
    return [slice_band(cov_m, cov_u, jac, jm) for (cov_m, cov_u), (jac, jm) in zip(covs, jacs)]
