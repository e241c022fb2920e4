r"""The wall shear stress vector on the reconstructed vessel wall from exact derivatives (paper Sec. 4, 5).

.. math:: \tau = (I - n n^\top) \big(-\mu (\nabla u + \nabla u^\top) n\big)

at wall points ``(s_i, phi_j)`` of the wall ``x(s, phi) = c(s) + R(s, phi)(cos phi n1(s) + sin phi n2(s))``
(:mod:`wss_nlp.vessel.geometry3d`), ``n`` its outward unit normal ``x_phi x x_s / |x_phi x x_s|``, ``u`` the
reconstructed velocity (:mod:`wss_nlp.vessel.velocity3d`, world components). ``grad u`` comes from CasADi's exact
derivatives through the coordinate map ``(s, rho, theta) -> x``,

.. math:: x = c(s) + \big(r_{in}(s) \rho + (R(s, \theta) - r_{in}(s)) \rho^2\big)
          (\cos\theta\, n_1(s) + \sin\theta\, n_2(s)),

as ``grad u = (d u / d(s, rho, theta)) (d x / d(s, rho, theta))^{-1}``. Around each wall point ``s_i`` the graph
takes ``s = s_i + sigma`` with everything to first order in ``sigma``: ``c = c_i + sigma t_i``,
``n_k = n_{k,i} + sigma n_k'(s_i)`` (the rotation-minimizing frame's exact derivatives,
:meth:`wss_nlp.vessel.centerline.Centerline.frame_derivative`), ``R = F(theta) . (R_i + sigma R_{s,i})`` and the
velocity coefficients ``A_i + sigma A'_i`` (the B-splines' values and slopes at ``s_i``): first derivatives at
``sigma = 0``, all this needs, are exact. Units: lengths in mm, velocity in m/s, so ``grad u`` is in (m/s)/mm and
``tau = -mu 1000 (...)`` in Pa.

Parts: the axial WSS ``tau . t`` (signed, positive along the centreline's direction), the circumferential part
``tau . e_c`` with ``e_c = e_a x n`` (``e_a`` the unit wall tangent along ``t``: counter-clockwise about ``t``), and
``tau . n`` before the projection (``2 mu`` times the wall's ``div u`` part, zero for a divergence-free field).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

import casadi as ca

from ..core import radius as rad

#: mm -> m: gradients in (m/s)/mm times this are in 1/s, so tau is in Pa.
PER_MM = 1000.0


@dataclass(frozen=True)
class _WallGeometry:
    """The wall's symbolic map ``x(sigma, rho, theta)`` about the centreline (``sigma`` the arc-length offset from
    the point, substituted by 0 once differentiated), its Jacobian, normal, area element and circumferential unit
    vector; ``inputs``/``names`` the geometry's inputs shared by :func:`point_function` and
    :func:`wall_function`."""

    sigma: ca.SX
    rho: ca.SX
    theta: ca.SX
    t: ca.SX
    q: ca.SX
    x: ca.SX
    jac_x: ca.SX
    normal: ca.SX
    area: ca.SX
    e_c: ca.SX
    inputs: list
    names: list


def _wall_geometry(n_fourier: int) -> _WallGeometry:
    sx = ca.SX
    rho, theta, sigma = sx.sym("rho"), sx.sym("theta"), sx.sym("sigma")
    c, t, n1, n2, dn1, dn2 = (sx.sym(k, 3) for k in ("c", "t", "n1", "n2", "dn1", "dn2"))
    nf = rad.n_coefficients(n_fourier)
    r_i, r_s = sx.sym("R_i", nf), sx.sym("R_s", nf)
    rin, rin_s = sx.sym("r_in"), sx.sym("r_in_s")
    big_r = rad.symbolic(r_i + sigma * r_s, theta)
    r_in = rin + sigma * rin_s
    radius = r_in * rho + (big_r - r_in) * rho**2
    e_r = ca.cos(theta) * (n1 + sigma * dn1) + ca.sin(theta) * (n2 + sigma * dn2)
    x = c + sigma * t + radius * e_r
    q = ca.vertcat(sigma, rho, theta)
    jac_x = ca.jacobian(x, q)  # (3, 3): columns d/dsigma, d/drho, d/dtheta
    x_s, x_th = jac_x[:, 0], jac_x[:, 2]
    cross = ca.cross(x_th, x_s)
    area = ca.norm_2(cross)
    normal = cross / area
    e_a = t - ca.dot(t, normal) * normal
    e_c = ca.cross(e_a / ca.norm_2(e_a), normal)
    inputs = [rho, theta, c, t, n1, n2, dn1, dn2, r_i, r_s, rin, rin_s]
    names = ["rho", "theta", "c", "t", "n1", "n2", "dn1", "dn2", "R_i", "R_s", "r_in", "r_in_s"]
    return _WallGeometry(sigma, rho, theta, t, q, x, jac_x, normal, area, e_c, inputs, names)


@functools.lru_cache(maxsize=8)
def point_function(disk, n_fourier: int) -> ca.Function:
    """CasADi ``Function`` of one point ``(rho, theta)`` near the wall point ``s_i`` (module notes).

    Inputs: ``rho, theta, c, t, n1, n2, dn1, dn2`` (3-vectors), ``R_i, R_s`` (``2N + 1`` Fourier coefficients and
    their s-derivatives), ``r_in, r_in_s``, ``A, A_s`` (``(n_z, 3)`` velocity coefficients per world component and
    their s-derivatives), ``mu`` (Pa s). Outputs: ``u`` (3, m/s), ``grad`` (3 x 3, ``d u_a / d x_b`` in 1/s),
    ``x`` (3, mm), ``normal`` (3, outward unit normal of the ``rho``-level surface: the wall's at ``rho = 1``),
    ``tau`` (3, Pa, tangential), ``axial``, ``circumferential``, ``normal_part`` (Pa), ``area`` (``|x_theta x
    x_s|``, mm^2 per mm and rad), ``e_c`` (the circumferential unit vector).
    """
    g = _wall_geometry(n_fourier)
    sigma, rho, theta, t, normal = g.sigma, g.rho, g.theta, g.t, g.normal
    nz = disk.size
    a, a_s = ca.SX.sym("A", nz, 3), ca.SX.sym("A_s", nz, 3)
    mu = ca.SX.sym("mu")
    w = disk.symbolic(ca.vertcat(rho * ca.cos(theta), rho * ca.sin(theta)))
    u = ca.mtimes((a + sigma * a_s).T, w)  # (3,)
    jac_u = ca.jacobian(u, g.q)
    grad = ca.mtimes(jac_u, ca.inv(g.jac_x)) * PER_MM  # d u_a / d x_b, 1/s
    traction = -mu * ca.mtimes(grad + grad.T, normal)
    normal_part = ca.dot(traction, normal)
    tau = traction - normal_part * normal
    inputs = [*g.inputs, a, a_s, mu]
    names = [*g.names, "A", "A_s", "mu"]
    outputs = [u, grad, g.x, normal, tau, ca.dot(tau, t), ca.dot(tau, g.e_c), normal_part, g.area, g.e_c]
    outputs = [ca.substitute(o, sigma, 0) for o in outputs]
    out_names = ["u", "grad", "x", "normal", "tau", "axial", "circumferential", "normal_part", "area", "e_c"]
    return ca.Function("vessel_wss_point", inputs, outputs, names, out_names)


@functools.lru_cache(maxsize=8)
def wall_function(disk, n_fourier: int) -> ca.Function:
    """The velocity-independent part of :func:`point_function` at a point ``(rho, theta)``: ``x``, ``normal``,
    ``area``, ``e_c``, ``minv`` (``(d x / d(s, rho, theta))^{-1}``, 3 x 3), the basis ``w`` (``n_z``) and its
    derivatives ``w_rho``, ``w_theta`` (CasADi's exact ones).

    ``grad u`` is linear in the velocity coefficients: with ``A``, ``A_s`` as in :func:`point_function`,
    ``d u_c / d(s, rho, theta) = (w . A_s[:, c], w_rho . A[:, c], w_theta . A[:, c])`` and
    ``grad u = 1000 (d u / d(s, rho, theta)) minv`` (:func:`traction`), so every frame costs a few products.
    Inputs: :func:`point_function`'s without ``A``, ``A_s``, ``mu``.
    """
    g = _wall_geometry(n_fourier)
    rho, theta = g.rho, g.theta
    w = disk.symbolic(ca.vertcat(rho * ca.cos(theta), rho * ca.sin(theta)))
    outputs = [g.x, g.normal, g.area, g.e_c, ca.inv(g.jac_x), w, ca.jacobian(w, rho), ca.jacobian(w, theta)]
    outputs = [ca.substitute(o, g.sigma, 0) for o in outputs]
    inputs, names = g.inputs, g.names
    return ca.Function("vessel_wall_point", inputs, outputs, names,
                       ["x", "normal", "area", "e_c", "minv", "w", "w_rho", "w_theta"])  # fmt: skip


def traction(d_u: np.ndarray, minv: np.ndarray, normal: np.ndarray, mu: float) -> tuple[np.ndarray, np.ndarray]:
    """``(tau, grad u)``: ``grad u = 1000 d_u minv`` (1/s) from ``d u / d(s, rho, theta)`` ``(m, 3, 3)``, and
    ``tau = (I - n n^T)(-mu (grad u + grad u^T) n)`` (Pa), for points along the first axis."""
    grad = np.einsum("mcq,mqb->mcb", d_u, minv) * PER_MM
    trac = -mu * np.einsum("mcb,mb->mc", grad + np.swapaxes(grad, 1, 2), normal)
    return trac - np.sum(trac * normal, axis=1, keepdims=True) * normal, grad


@dataclass
class PointInputs:
    """Per-point geometry inputs of :func:`point_function` (arrays with points along the last axis)."""

    c: np.ndarray
    t: np.ndarray
    n1: np.ndarray
    n2: np.ndarray
    dn1: np.ndarray
    dn2: np.ndarray
    r_i: np.ndarray
    r_s: np.ndarray
    r_in: np.ndarray
    r_in_s: np.ndarray
    s: np.ndarray


def point_inputs(centerline, geometry, basis, s) -> PointInputs:
    """The centreline, frame, wall and inner radius at arclengths ``s (m,)``."""
    s = np.asarray(s, float).ravel()
    t, n1, n2 = centerline.frame(s)
    _, dn1, dn2 = centerline.frame_derivative(s)
    return PointInputs(
        c=centerline.position(s).T,
        t=t.T,
        n1=n1.T,
        n2=n2.T,
        dn1=dn1.T,
        dn2=dn2.T,
        r_i=geometry.basis.fourier_at(geometry.coefficients, s, 0).T,
        r_s=geometry.basis.fourier_at(geometry.coefficients, s, 1).T,
        r_in=basis.r_in(s),
        r_in_s=basis.r_in(s, 1),
        s=s,
    )


@dataclass
class WallEvaluation:
    """Outputs of :func:`evaluate` at ``m`` points (arrays ``(m, ...)``; per frame a leading axis)."""

    x: np.ndarray  # (m, 3) mm
    normal: np.ndarray  # (m, 3)
    area: np.ndarray  # (m,) |x_theta x x_s|
    u: np.ndarray  # (nt, m, 3) m/s
    grad: np.ndarray  # (nt, m, 3, 3) 1/s
    tau: np.ndarray  # (nt, m, 3) Pa
    axial: np.ndarray  # (nt, m)
    circumferential: np.ndarray  # (nt, m)
    normal_part: np.ndarray  # (nt, m)


def evaluate(centerline, geometry, velocity, s, theta, rho=None, mu: float = 3.5e-3, frames=None) -> WallEvaluation:
    """``tau`` and the rest of :func:`point_function` at points ``(s, rho, theta)`` (``rho = 1``: the wall) for
    every frame of ``velocity`` (:class:`wss_nlp.vessel.velocity3d.Velocity3DResult`)."""
    basis = velocity.basis
    s = np.asarray(s, float).ravel()
    theta = np.asarray(theta, float).ravel()
    rho = np.ones_like(s) if rho is None else np.broadcast_to(np.asarray(rho, float).ravel(), s.shape)
    m = s.size
    fun = point_function(basis.disk, geometry.basis.n_fourier).map(m)
    p = point_inputs(centerline, geometry, basis, s)
    coef = velocity.coefficients if frames is None else velocity.coefficients[list(frames)]
    nt = coef.shape[0]
    outs = []
    for k in range(nt):
        a, a_s = _velocity_blocks(basis, coef[k], s)  # per point an (n_z, 3) block
        res = fun(rho[None], theta[None], p.c, p.t, p.n1, p.n2, p.dn1, p.dn2, p.r_i, p.r_s, p.r_in[None],
                  p.r_in_s[None], a, a_s, mu)  # fmt: skip
        outs.append([np.asarray(v) for v in res])
    u = np.stack([o[0].T for o in outs])
    grad = np.stack([o[1].reshape(3, 3, m, order="F").transpose(2, 0, 1) for o in outs])
    first = outs[0]
    return WallEvaluation(
        x=first[2].T,
        normal=first[3].T,
        area=first[8].ravel(),
        u=u,
        grad=grad,
        tau=np.stack([o[4].T for o in outs]),
        axial=np.stack([o[5].ravel() for o in outs]),
        circumferential=np.stack([o[6].ravel() for o in outs]),
        normal_part=np.stack([o[7].ravel() for o in outs]),
    )


def _velocity_blocks(basis, coefficients, s):
    """Per point the ``(n_z, 3)`` blocks ``A = sum_k B_k(s) a_k`` and ``A_s = sum_k B_k'(s) a_k`` side by side
    (CasADi's mapped layout), for coefficients ``(size, 3)``."""
    nz, m = basis.disk.size, s.size
    j, b = basis.spline.local(s, 0)
    _, db = basis.spline.local(s, 1)
    rows = np.asarray(coefficients, float).reshape(basis.spline.size, nz, 3)[j[:, None] + np.arange(4)[None, :]]
    a = np.einsum("ma,majc->jcm", b, rows).reshape(nz, 3 * m, order="F")
    a_s = np.einsum("ma,majc->jcm", db, rows).reshape(nz, 3 * m, order="F")
    return a, a_s


@dataclass
class WallPieces:
    """The velocity-independent pieces of :func:`wall_function` at ``m`` wall points (arrays ``(m, ...)``), the
    centreline's tangent ``t`` and the points' B-spline window: ``knot`` (the first of the four B-splines of the
    velocity's spline basis that are non-zero at ``s``), ``b``/``db`` their values and slopes ``(m, 4)``."""

    x: np.ndarray  # (m, 3) mm
    normal: np.ndarray  # (m, 3)
    area: np.ndarray  # (m,)
    e_c: np.ndarray  # (m, 3)
    t: np.ndarray  # (m, 3)
    minv: np.ndarray  # (m, 3, 3)
    w: np.ndarray  # (m, n_z)
    w_rho: np.ndarray  # (m, n_z)
    w_theta: np.ndarray  # (m, n_z)
    knot: np.ndarray  # (m,) int
    b: np.ndarray  # (m, 4)
    db: np.ndarray  # (m, 4)


def wall_pieces(centerline, geometry, basis, s, theta) -> WallPieces:
    """:func:`wall_function` at wall points ``(s, theta)`` (``rho = 1``) for the velocity basis ``basis``
    (:class:`wss_nlp.vessel.velocity3d.VelocityBasis3D`), with the B-spline windows of the points."""
    s = np.asarray(s, float).ravel()
    theta = np.asarray(theta, float).ravel()
    m = s.size
    fun = wall_function(basis.disk, geometry.basis.n_fourier).map(m)
    p = point_inputs(centerline, geometry, basis, s)
    out = [np.asarray(v) for v in fun(np.ones((1, m)), theta[None], p.c, p.t, p.n1, p.n2, p.dn1, p.dn2, p.r_i, p.r_s,
                                       p.r_in[None], p.r_in_s[None])]  # fmt: skip
    j, b = basis.spline.local(s, 0)
    _, db = basis.spline.local(s, 1)
    return WallPieces(
        x=out[0].T, normal=out[1].T, area=out[2].ravel(), e_c=out[3].T, t=p.t.T,
        minv=out[4].reshape(3, 3, m, order="F").transpose(2, 0, 1), w=out[5].T, w_rho=out[6].T, w_theta=out[7].T,
        knot=np.asarray(j), b=np.asarray(b), db=np.asarray(db),
    )  # fmt: skip


def wall_wss(centerline, geometry, velocity, s, theta, mu: float = 3.5e-3, progress=None,
             pieces: WallPieces | None = None) -> WallEvaluation:  # fmt: skip
    """``tau`` at wall points ``(s, theta)`` for every frame: the points' velocity-independent pieces once
    (:func:`wall_pieces`, or ``pieces`` computed for these points before), then per frame the velocity's
    derivatives ``(w . A_s, w_rho . A, w_theta . A)`` and :func:`traction` (``u`` is zero on the wall; ``grad`` is
    returned)."""
    basis = velocity.basis
    nz = basis.disk.size
    pc = wall_pieces(centerline, geometry, basis, s, theta) if pieces is None else pieces
    m = pc.x.shape[0]
    w, w_rho, w_theta, normal, minv = pc.w, pc.w_rho, pc.w_theta, pc.normal, pc.minv
    nt = velocity.coefficients.shape[0]
    taus, grads = np.empty((nt, m, 3)), np.empty((nt, m, 3, 3))
    j, b, db = pc.knot, pc.b, pc.db
    for k in range(nt):
        rows = np.asarray(velocity.coefficients[k], float).reshape(basis.spline.size, nz, 3)[j[:, None] + np.arange(4)]
        a = np.einsum("ma,majc->mjc", b, rows)  # (m, n_z, 3): the coefficients at s
        a_s = np.einsum("ma,majc->mjc", db, rows)
        d_u = np.stack([np.einsum("mj,mjc->mc", w, a_s), np.einsum("mj,mjc->mc", w_rho, a),
                        np.einsum("mj,mjc->mc", w_theta, a)], axis=2)  # (m, 3 components, 3 coordinates)  # fmt: skip
        taus[k], grads[k] = traction(d_u, minv, normal, mu)
        if progress is not None:
            progress.update()
    return WallEvaluation(
        x=pc.x, normal=normal, area=pc.area, u=np.zeros((nt, m, 3)), grad=grads, tau=taus,
        axial=np.einsum("tmc,mc->tm", taus, pc.t), circumferential=np.einsum("tmc,mc->tm", taus, pc.e_c),
        normal_part=np.zeros((nt, m)),
    )  # fmt: skip


def wall_grid(s_range: tuple[float, float], h: float, n_phi: int = 64, spacing: float | None = None):
    """Arclengths (every ``spacing`` mm, default ``h / 2``) over ``s_range`` and ``n_phi`` uniform angles."""
    lo, hi = s_range
    ds = 0.5 * h if spacing is None else float(spacing)
    n = max(2, int(np.round((hi - lo) / ds)) + 1)
    return np.linspace(lo, hi, n), rad.uniform_angles(n_phi)
