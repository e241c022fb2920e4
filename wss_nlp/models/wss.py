"""Wall shear stress from the reconstructed geometry and velocity (Sec. 4, eq. (wss)).

    tau(phi) = -mu n_R(phi) . J_R(xi)^{-T} grad_xi v(xi),   xi = (cos phi, sin phi),

with ``J_R`` the Jacobian of phi_R and ``n_R`` the outward unit normal of
eq. (normal). All derivatives are CasADi's exact symbolic ones. (The paper
writes ``n . J^{-1} grad v``; by the chain rule ``grad_x u = J^{-T} grad_xi v``,
which is what is implemented -- the two agree only when J is symmetric.)
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from dataclasses import dataclass

from typing import Any

import numpy as np

import casadi as ca

from ..core import radius as rad
from ..core.mapping import symbolic_forward

#: mm -> m: gradients in (m/s)/mm times this are in 1/s, so tau is in Pa.
PER_MM = 1000.0


@dataclass
class WssResult:
    phi: np.ndarray  # angles about the centre, rad
    tau: np.ndarray  # Pa
    mean: float  # arc-length weighted mean, Pa
    wall_x: np.ndarray  # wall points, mm
    wall_y: np.ndarray
    viscosity_pa_s: float
    tau_std: np.ndarray | None = (
        None  # linearized standard deviation from the data noise, Pa (wss_nlp.uncertainty.sensitivity)
    )
    mean_std: float = float("nan")
    vector: WssVector | None = None  # the 3D WSS vector of a stack with three velocity components


def wss_expression(velocity_of_xi, n_fourier: int, r_in: float | None, eta: float):
    """CasADi ``Function`` ``(phi, c_R, center, p_v, mu) -> (tau, x_wall)``.

    Parameters
    ----------
    velocity_of_xi : callable
        ``(xi: 2-vector, p_v) -> scalar``, the velocity on the reference disk
        as a CasADi expression with parameters ``p_v`` (basis coefficients
        for a reconstruction, anything for an analytic field). Built in SX
        (fast) unless the callable sets ``sx_ok = False`` (e.g. it calls
        MX-only callbacks); ``n_params`` gives the length of ``p_v``.
    n_fourier, r_in, eta : geometry of phi_R. ``r_in = None`` makes the
        inner radius a last input ``r_in`` (for derivatives with respect to it).

    Notes
    -----
    ``tau = -mu * 1000 * n . (J^{-T} grad v)``: lengths in mm, velocity in
    m/s, ``mu`` in Pa s, so ``tau`` is in Pa.
    """
    sym: Any = ca.SX if getattr(velocity_of_xi, "sx_ok", True) else ca.MX
    phi = sym.sym("phi")
    c_r = sym.sym("c_R", rad.n_coefficients(n_fourier))
    center = sym.sym("center", 2)
    mu = sym.sym("mu")
    xi = sym.sym("xi", 2)
    p_v = sym.sym("p_v", getattr(velocity_of_xi, "n_params", 1))
    r_in_sym = sym.sym("r_in") if r_in is None else None
    r_in_arg: Any = r_in_sym if r_in is None else r_in  # a symbol (for derivatives) or a number
    x = symbolic_forward(xi, c_r, center, r_in_arg, eta)
    v = velocity_of_xi(xi, p_v)
    jac = ca.jacobian(x, xi)
    grad_v = ca.gradient(v, xi)
    extra = [] if r_in_sym is None else [r_in_sym]
    at_xi = ca.Function("at_xi", [xi, c_r, center, p_v] + extra, [jac, grad_v, x])
    jac_w, grad_w, x_w = at_xi(ca.vertcat(ca.cos(phi), ca.sin(phi)), c_r, center, p_v, *extra)
    grad_x = ca.solve(jac_w.T, grad_w)
    big_r = rad.symbolic(c_r, phi)
    dr = ca.jacobian(big_r, phi)
    normal = ca.vertcat(big_r * ca.cos(phi) + dr * ca.sin(phi), big_r * ca.sin(phi) - dr * ca.cos(phi))
    normal = normal / ca.sqrt(big_r**2 + dr**2)  # eq. (normal)
    tau = -mu * PER_MM * ca.dot(normal, grad_x)
    return ca.Function(
        "wss",
        [phi, c_r, center, p_v, mu] + extra,
        [tau, x_w],
        ["phi", "c_R", "center", "p_v", "mu"] + ["r_in"] * bool(extra),
        ["tau", "x_wall"],
    )


def velocity_template(basis) -> tuple[Any, Any]:
    """``(template, parameters)``: what a WSS graph of ``basis`` depends on, and ``c -> p_v`` for it.

    A basis with a near-wall layer (:class:`wss_nlp.models.near_wall.EnrichedBasis`)
    leaves its scale as a parameter, so one graph serves every scale and
    slice (graphs are cached on the template); any other basis is its own
    template with ``p_v = c``.
    """
    if hasattr(basis, "wss_template"):
        return basis.wss_template(), basis.wss_parameters
    return basis, lambda c: np.asarray(c, dtype=float)


class _BasisVelocity:
    """``v(xi) = sum_j p_j v_j(xi)`` for a velocity basis (or template), as a callable for :func:`wss_expression`.

    ``p`` holds :attr:`n_params` numbers: the template's ``size`` linear coefficients, then its shape
    parameters (``n_shape``, none for a plain basis).
    """

    def __init__(self, template):
        self.template = template
        self.n_params = template.size + getattr(template, "n_shape", 0)

    def __call__(self, xi, p):
        if hasattr(self.template, "symbolic_with"):
            return self.template.symbolic_with(xi, p)
        return ca.dot(self.template.symbolic(xi), p)


def evaluate(phi, c_r, center, velocity_of_xi, params, r_in, eta, viscosity_pa_s) -> WssResult:
    """Evaluate tau on the angles ``phi`` and its arc-length weighted mean."""
    phi = np.asarray(phi, dtype=float)
    c_r = np.asarray(c_r, dtype=float)
    fun = wss_expression(velocity_of_xi, rad.n_fourier_from_size(c_r.size), r_in, eta).map(phi.size)
    tau, xw = fun(
        phi[None, :], c_r, np.asarray(center, float), np.atleast_1d(np.asarray(params, float)), viscosity_pa_s
    )
    tau = np.asarray(tau).ravel()
    xw = np.asarray(xw)
    r, dr = rad.evaluate(c_r, phi), rad.evaluate(c_r, phi, 1)
    mean = rad.arc_length_mean(tau, r, dr) if _is_uniform(phi) else float("nan")
    return WssResult(phi=phi, tau=tau, mean=mean, wall_x=xw[0], wall_y=xw[1], viscosity_pa_s=viscosity_pa_s)


def _is_uniform(phi) -> bool:
    return phi.size > 2 and np.allclose(phi, rad.uniform_angles(phi.size))


#: The last few WSS matrices of plain bases (:func:`wss_matrix`) by basis, wall, viscosity and angle count:
#: :func:`from_reconstruction` on such a wall takes ``tau = A c`` from them (the beta choice formed the matrix
#: of the wall the velocity is then solved on; 12 ms of CasADi a slice or cine frame saved).
_MATRICES: OrderedDict = OrderedDict()
_MATRICES_KEPT = 8


def _matrix_key(basis, disk_map, viscosity_pa_s: float, n_phi: int) -> tuple | None:
    """The key of :data:`_MATRICES` (the values that define the matrix); None for a basis with a layer."""
    if hasattr(basis, "wss_template"):
        return None
    dm = disk_map
    c_r = np.asarray(dm.coefficients, dtype=float)
    return (basis, c_r.tobytes(), tuple(float(v) for v in dm.center), float(dm.r_in), float(dm.eta),
            float(viscosity_pa_s), int(n_phi))  # fmt: skip


def from_reconstruction(velocity_result, n_phi: int, viscosity_pa_s: float) -> WssResult:
    """WSS of a :class:`wss_nlp.models.velocity.VelocityResult` at ``n_phi`` uniform angles.

    Where :func:`wss_matrix` was formed for the same plain basis, wall, viscosity and angles (the beta
    choice's), ``tau = A c`` (tau is linear in the coefficients; the same numbers to rounding) instead of
    evaluating the expression again."""
    dm = velocity_result.disk_map
    phi = rad.uniform_angles(n_phi)
    c_r = np.asarray(dm.coefficients, dtype=float)
    kept = _MATRICES.get(_matrix_key(velocity_result.basis, dm, viscosity_pa_s, n_phi))
    if kept is not None:
        a, xw = kept
        tau = a @ np.asarray(velocity_result.coefficients, dtype=float)
        mean = rad.arc_length_mean(tau, rad.evaluate(c_r, phi), rad.evaluate(c_r, phi, 1))
        return WssResult(phi=phi, tau=tau, mean=mean, wall_x=xw[0].copy(), wall_y=xw[1].copy(),
                         viscosity_pa_s=viscosity_pa_s)  # fmt: skip
    template, parameters = velocity_template(velocity_result.basis)
    fun = _basis_wss_map(template, rad.n_fourier_from_size(c_r.size), float(dm.eta), n_phi)
    center = np.asarray(dm.center, float)
    tau, xw = fun(phi[None, :], c_r, center, parameters(velocity_result.coefficients), viscosity_pa_s, dm.r_in)
    tau, xw = np.asarray(tau).ravel(), np.asarray(xw)
    mean = rad.arc_length_mean(tau, rad.evaluate(c_r, phi), rad.evaluate(c_r, phi, 1))
    return WssResult(phi=phi, tau=tau, mean=mean, wall_x=xw[0], wall_y=xw[1], viscosity_pa_s=viscosity_pa_s)


@functools.lru_cache(maxsize=16)  # bases are cached objects (velocity_basis.make_basis): one build per setting
def _basis_wss_map(template, n_fourier: int, eta: float, n_phi: int) -> ca.Function:
    """:func:`wss_expression` of a basis expansion with ``r_in`` an input, mapped over ``n_phi`` angles.

    Built once per basis template (:func:`velocity_template`) and angle count and reused by every slice and
    frame (``r_in``, the geometry and a layer's scale are inputs, not constants of the graph).
    """
    return wss_expression(_BasisVelocity(template), n_fourier, None, eta).map(n_phi)


def wss_matrix(basis, disk_map, viscosity_pa_s: float, n_phi: int = 360) -> tuple[np.ndarray, np.ndarray]:
    """``A`` with ``tau = A c`` for velocity coefficients ``c``, and the wall points.

    tau is linear in the velocity coefficients for a fixed geometry, so one
    CasADi Jacobian per angle gives the whole map; used for fast parameter
    studies (one matrix serves every beta).
    """
    dm = disk_map
    c_r = np.asarray(dm.coefficients, dtype=float)
    template, parameters = velocity_template(basis)
    g = _basis_wss_jacobian_map(template, rad.n_fourier_from_size(c_r.size), float(dm.eta), n_phi)
    shape = parameters(np.zeros(basis.size))[template.size :]
    a, xw = g(rad.uniform_angles(n_phi)[None, :], c_r, np.array(dm.center, dtype=float), viscosity_pa_s, dm.r_in, shape)
    # d tau / d c = d tau / d p_linear times d p_linear / d c (diagonal: the layer's column scale)
    matrix, points = np.asarray(a).reshape(n_phi, template.size) * linear_scale(basis)[None, :], np.asarray(xw)
    key = _matrix_key(basis, dm, viscosity_pa_s, n_phi)
    if key is not None:  # kept for from_reconstruction (read-only copies: callers may scale their own)
        _MATRICES[key] = (matrix.copy(), points.copy())
        while len(_MATRICES) > _MATRICES_KEPT:
            _MATRICES.popitem(last=False)
    return matrix, points


def linear_scale(basis) -> np.ndarray:
    """``d p_v / d c`` of :func:`velocity_template`'s parameters (diagonal, the linear entries only)."""
    template, parameters = velocity_template(basis)
    return parameters(np.ones(basis.size))[: template.size] - parameters(np.zeros(basis.size))[: template.size]


@functools.lru_cache(maxsize=16)
def _basis_wss_jacobian_map(template, n_fourier: int, eta: float, n_phi: int) -> ca.Function:
    """``(phi, c_R, center, mu, r_in, shape) -> (d tau / d p, x_wall)`` over ``n_phi`` angles, once per template."""
    f = wss_expression(_BasisVelocity(template), n_fourier, None, eta)
    ph, cc, ce = ca.SX.sym("ph"), ca.SX.sym("cc", rad.n_coefficients(n_fourier)), ca.SX.sym("ce", 2)
    p, mu, r_in = ca.SX.sym("p", template.size), ca.SX.sym("mu"), ca.SX.sym("r_in")
    shape = ca.SX.sym("shape", getattr(template, "n_shape", 0))
    tau, xw = f(ph, cc, ce, ca.vertcat(p, shape), mu, r_in)
    return ca.Function("g", [ph, cc, ce, mu, r_in, shape], [ca.jacobian(tau, p), xw]).map(n_phi)


@dataclass
class WssVector:
    """The WSS vector ``tau = -mu (grad u + grad u^T) n`` on the wall of a stack (Sec. 5), at the slice's angles.

    Arrays of shape ``(n_phi, 3)`` (x, y, z of the image frame) or ``(n_phi,)``; Pa.
    """

    vector: np.ndarray
    normal: np.ndarray  # outward unit normal of the 3D wall
    axial: np.ndarray  # tau . e_a, e_a the wall tangent along the vessel (through-plane direction)
    circumferential: np.ndarray  # tau . e_c, e_c = e_a x n (counter-clockwise about the centre)
    normal_part: np.ndarray  # tau . n: 2 mu div(u) on the wall, zero for incompressible flow
    magnitude: np.ndarray


def wss_vector(phi, coefficients, dcoef_dz, dcenter_dz, tau_planar, viscosity_pa_s: float) -> WssVector:
    """WSS vector from the in-plane WSS of each velocity component and the wall's slope along the vessel.

    Parameters
    ----------
    phi : (n,) angles of the wall points about the slice's centre.
    coefficients, dcoef_dz : radius coefficients of the slice and their z-derivative (1/mm units per mm).
    dcenter_dz : (2,) z-derivative of the centre line.
    tau_planar : (n, 3) ``-mu nu . grad_xy u_i`` for the components i = x, y, z at the wall of the slice
        (``nu``: outward normal of the slice contour), each from its own 2D reconstruction
        (:func:`from_reconstruction`).

    Notes
    -----
    The wall is ``X(phi, z) = c(z) + R(phi, z)(cos phi, sin phi, 0) + z e_z``
    with outward normal ``n = X_phi x X_z / |...|``. No-slip makes every
    tangential derivative of ``u`` vanish on the wall, so ``grad u = g n^T``
    with ``g = du/dn``; the in-plane part gives ``nu . grad_xy u_i = g_i |n_xy|``,
    hence ``g = -tau_planar / (mu |n_xy|)`` and, exactly,
    ``tau = -mu (g + n (g . n))`` (eq. of Sec. 5). No derivative of the data
    along z is taken: the z-slope of the wall comes from the stack's radius
    and centre-line model.
    """
    phi = np.asarray(phi, dtype=float)
    r, dr = rad.evaluate(coefficients, phi), rad.evaluate(coefficients, phi, 1)
    rz = rad.evaluate(dcoef_dz, phi)
    c, s = np.cos(phi), np.sin(phi)
    x_phi = np.stack([dr * c - r * s, dr * s + r * c, np.zeros_like(phi)], axis=1)
    x_z = np.stack([dcenter_dz[0] + rz * c, dcenter_dz[1] + rz * s, np.ones_like(phi)], axis=1)
    n = np.cross(x_phi, x_z)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n_xy = np.linalg.norm(n[:, :2], axis=1)
    g = -np.asarray(tau_planar, dtype=float) / (viscosity_pa_s * n_xy[:, None])  # in (m/s)/m, i.e. 1/s
    tau = -viscosity_pa_s * (g + n * np.sum(g * n, axis=1, keepdims=True))
    e_a = x_z / np.linalg.norm(x_z, axis=1, keepdims=True)
    e_c = np.cross(e_a, n)
    return WssVector(
        vector=tau,
        normal=n,
        axial=np.sum(tau * e_a, axis=1),
        circumferential=np.sum(tau * e_c, axis=1),
        normal_part=np.sum(tau * n, axis=1),
        magnitude=np.linalg.norm(tau, axis=1),
    )
