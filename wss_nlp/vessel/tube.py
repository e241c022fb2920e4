r"""The 3D measurement model of a tube on the volume's own voxels (issue 38, item 3; paper Sec. 5).

Wall
----
About a FIXED centreline ``c(s)`` with its rotation-minimizing frame ``(t, n1, n2)``
(:class:`wss_nlp.vessel.centerline.Centerline`) the wall is

.. math:: x(s, \phi) = c(s) + R(s, \phi) (\cos\phi\, n_1(s) + \sin\phi\, n_2(s)), \qquad
          R(s, \phi) = \sum_k \sum_j C_{kj} B_k(s) F_j(\phi),

``B_k`` uniform cubic B-splines in ``s`` (:class:`SplineBasis`, knots about ``h`` apart over the fitted part of
the centreline), ``F_j`` the truncated Fourier basis of the 2D method (:func:`wss_nlp.core.radius.design_matrix`:
``1, cos phi, .., cos N phi, sin phi, .., sin N phi``). ``R`` is linear in ``c = vec(C)`` (knot-major:
``c[k (2N+1) + j] = C_kj``), :class:`WallBasis`.

Forward model
-------------
Voxel ``V_i`` of the volume (as it lies: oblique, anisotropic; its points come from the affine) gets ``q^3``
midpoint-rule points ``x_p`` (``q`` per index axis) with weights ``w_p = 1/q^3`` and local coordinates
``(s_p, r_p, phi_p)`` (the closest centreline point, the distance and the angle about ``t`` from ``n1``),
computed once (:class:`FrameTable`). The model of the normalized magnitude is the voxel mean of the smoothed
indicator (paper eq. (discForw) in 3D),

.. math:: F_i(c) = \sum_{p \in V_i} w_p\, H_\gamma\big(R(s_p, \phi_p) - r_p\big),
          \qquad H_\gamma(x) = (1 + \operatorname{erf}(x/\gamma))/2,

``gamma = h / q`` (the spacing of the points, so that the objective is smooth). In matrix form
``F(c) = S H_gamma(A c - r)`` with the design matrix ``A`` (points x coefficients, rows
``kron(B(s_p), F(phi_p))``) and the averaging matrix ``S`` (voxels x points, entries ``w_p``).

Only points that can see the wall are kept: with the admissible band ``lo(s, phi) <= R <= hi(s, phi)`` (the box of
the fit), a point with ``r_p < lo - reach`` has ``H = 1`` and one with ``r_p > hi + reach`` has ``H = 0`` for
every admissible ``R`` (to ``erfc(reach / gamma) / 2``; ``reach = 4 gamma``: 8e-9), so its weight goes to the
voxel's constant part and the point is dropped; voxels without a remaining point are dropped. ``A`` is never
formed (:meth:`TubeModel.design_matrix` builds it for tests): points are sorted by their first B-spline index, and
``A c``, ``A^T y`` and the Gauss-Newton Jacobian ``S diag(z) A`` are products of the points' Fourier rows with
four coefficient rows at a time (BLAS), so memory and time grow with the points times ``2N + 1``, not times
``4 (2N + 1)``.

Coordinates
-----------
:meth:`Centerline.project` costs about 12 s per million points (a KD-tree and eight Newton steps on quintic
splines). :class:`FrameTable` resamples the same centreline every ``ds`` mm (0.25 by default) and interpolates
``c``, ``t``, ``n1``, ``n2`` by cubic Hermite polynomials with the centreline's exact derivatives
(:meth:`Centerline.position`, :meth:`Centerline.frame_derivative`); a point's ``s`` is the root of
``(c(s) - x) . t(s)`` by Newton's method from its voxel centre's ``s`` (exactly projected by
:meth:`Centerline.project`). The coordinates agree with :meth:`Centerline.project` within 1e-5 mm on a smooth
centreline (tested); next to a jump of the curvature (a spline through a line joined to an arc) the Hermite
interpolation of the frame's derivative is worse there, and ``s`` differed by up to 1e-3 mm (``r`` and ``phi`` by
1e-5), far below the points' spacing.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

import casadi as ca

from .._lazy import scipy
from ..core import operators
from ..core import radius as rad
from ..errors import InputError
from ..models import measurement as meas

log = logging.getLogger(__name__)

#: Points farther than this many widths gamma outside the admissible band take the smoothed indicator's limit
#: (``erfc(4) / 2 = 7.7e-9``).
REACH_WIDTHS = 4.0
#: Newton steps of :meth:`FrameTable.project` from the voxel centre's arclength (quadratic convergence).
PROJECTION_STEPS = 3


# ------------------------------------------------------------------ B-splines in s
class SplineBasis:
    r"""Uniform cubic B-splines ``B_0 .. B_{n+2}`` on ``[lo, hi]`` cut into ``n`` equal intervals.

    ``B_i(s) = N_3((s - lo)/\Delta - i + 3)`` with the cardinal cubic B-spline ``N_3`` on ``[0, 4]``; on interval
    ``j`` (local ``t = (s - lo)/\Delta - j``) the nonzero ones are ``B_j .. B_{j+3}``,
    ``((1-t)^3, 3t^3 - 6t^2 + 4, -3t^3 + 3t^2 + 3t + 1, t^3) / 6``. Outside ``[lo, hi]`` the end intervals'
    polynomials continue (points a little beyond the ends).
    """

    def __init__(self, lo: float, hi: float, spacing: float):
        if not hi > lo or not spacing > 0:
            raise InputError(f"B-spline range [{lo:g}, {hi:g}] mm with spacing {spacing:g} mm is empty")
        self.lo, self.hi = float(lo), float(hi)
        self.intervals = max(1, int(np.ceil((self.hi - self.lo) / spacing - 1e-9)))
        self.delta = (self.hi - self.lo) / self.intervals

    @property
    def size(self) -> int:
        return self.intervals + 3

    def knots(self) -> np.ndarray:
        """The interval ends ``lo + j Delta``, ``j = 0 .. n``."""
        return self.lo + self.delta * np.arange(self.intervals + 1)

    def local(self, s, nu: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``(j, values)``: the first nonzero index ``j (m,)`` and ``d^nu B_{j+a} / ds^nu``, ``a = 0..3`` (m, 4)."""
        s = np.asarray(s, float).ravel()
        u = (s - self.lo) / self.delta
        j = np.clip(np.floor(u), 0, self.intervals - 1).astype(np.int64)
        t = u - j
        t2, t3 = t * t, t * t * t
        if nu == 0:
            b = np.stack([(1 - t) ** 3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], axis=1) / 6
        elif nu == 1:
            b = np.stack([-((1 - t) ** 2), 3 * t2 - 4 * t, -3 * t2 + 2 * t + 1, t2], axis=1) / (2 * self.delta)
        elif nu == 2:
            b = np.stack([1 - t, 3 * t - 2, 1 - 3 * t, t], axis=1) / self.delta**2
        elif nu == 3:
            b = np.broadcast_to(np.array([-1.0, 3.0, -3.0, 1.0]), (s.size, 4)) / self.delta**3
        else:
            raise ValueError(f"B-spline derivative order must be 0..3, got {nu}")
        return j, np.ascontiguousarray(b)

    def matrix(self, s, nu: int = 0):
        """``(m, size)`` CSR matrix of ``d^nu B_k / ds^nu`` at ``s``."""
        j, b = self.local(s, nu)
        m = j.size
        cols = j[:, None] + np.arange(4)[None, :]
        return scipy.sparse.csr_matrix((b.ravel(), cols.ravel(), np.arange(0, 4 * m + 1, 4)), shape=(m, self.size))

    def gram(self, nu: int = 0) -> np.ndarray:
        """``G_kl = int_lo^hi B_k^(nu) B_l^(nu) ds`` (dense, banded), exact (4-point Gauss-Legendre per interval)."""
        g, w = np.polynomial.legendre.leggauss(4)
        out = np.zeros((self.size, self.size))
        for j in range(self.intervals):
            s = self.lo + self.delta * (j + 0.5 * (g + 1))
            _, b = self.local(s, nu)
            out[j : j + 4, j : j + 4] += (b.T * (0.5 * self.delta * w)) @ b
        return out

    def fit(self, s, values, smoothing: float = 0.0) -> np.ndarray:
        """Least-squares coefficients of values at ``s`` (``(m,)`` or ``(m, k)``), with ``smoothing``
        ``int |f''|^2`` (an intercept-free ridge that keeps a sparse sampling well-posed)."""
        b = self.matrix(s).toarray()
        lhs = b.T @ b + smoothing * self.gram(2) + 1e-12 * np.eye(self.size)
        return np.linalg.solve(lhs, b.T @ np.asarray(values, float))

    def evaluate(self, coefficients, s, nu: int = 0) -> np.ndarray:
        """``sum_k c_k B_k^(nu)(s)`` for coefficients ``(size,)`` or ``(size, ...)``: per interval one product of the
        points' four B-spline values with four coefficient rows."""
        j, b = self.local(s, nu)
        c = np.asarray(coefficients, float)
        flat = c.reshape(self.size, -1)
        out = np.empty((j.size, flat.shape[1]))
        order = np.argsort(j, kind="stable")
        js = j[order]
        cut = np.concatenate([[0], np.flatnonzero(np.diff(js)) + 1, [js.size]])
        for lo, hi in zip(cut[:-1], cut[1:]):
            k = int(js[lo])
            sel = order[lo:hi]
            out[sel] = b[sel] @ flat[k : k + 4]
        return out.reshape((j.size,) + c.shape[1:])


# ------------------------------------------------------------------ the wall R(s, phi)
@dataclass(frozen=True)
class WallBasis:
    """``R(s, phi) = sum_kj C_kj B_k(s) F_j(phi)`` (module notes), coefficients knot-major."""

    spline: SplineBasis
    n_fourier: int

    @property
    def n_phi_terms(self) -> int:
        return rad.n_coefficients(self.n_fourier)

    @property
    def size(self) -> int:
        return self.spline.size * self.n_phi_terms

    def matrix(self, c) -> np.ndarray:
        """The coefficients as ``C (n_s, 2N + 1)``."""
        return np.asarray(c, float).reshape(self.spline.size, self.n_phi_terms)

    def evaluate(self, c, s, phi, ds: int = 0, dphi: int = 0) -> np.ndarray:
        """``d^ds d^dphi R / ds^ds dphi^dphi`` at the points ``(s, phi)`` (broadcast, flattened)."""
        s, phi = (np.ravel(v) for v in np.broadcast_arrays(np.asarray(s, float), np.asarray(phi, float)))
        per_s = self.spline.evaluate(self.matrix(c), s, ds)  # (m, 2N+1): the Fourier coefficients at each s
        return np.sum(per_s * rad.design_matrix(phi, self.n_fourier, dphi), axis=1)

    def fourier_at(self, c, s, ds: int = 0) -> np.ndarray:
        """The cross-sections' Fourier coefficients (and their s-derivatives) at ``s``: ``(m, 2N + 1)``."""
        return self.spline.evaluate(self.matrix(c), s, ds)

    def design(self, s, phi, ds: int = 0, dphi: int = 0):
        """``(m, size)`` CSR matrix ``D`` with ``D c = d^ds d^dphi R(s, phi)``: rows ``kron(B(s), F(phi))``."""
        s, phi = (np.ravel(v) for v in np.broadcast_arrays(np.asarray(s, float), np.asarray(phi, float)))
        j, b = self.spline.local(s, ds)
        f = rad.design_matrix(phi, self.n_fourier, dphi)
        nf = self.n_phi_terms
        vals = (b[:, :, None] * f[:, None, :]).reshape(s.size, 4 * nf)
        cols = ((j[:, None] + np.arange(4))[:, :, None] * nf + np.arange(nf)).reshape(s.size, 4 * nf)
        ptr = np.arange(0, 4 * nf * s.size + 1, 4 * nf)
        return scipy.sparse.csr_matrix((vals.ravel(), cols.ravel(), ptr), shape=(s.size, self.size))

    def constant(self, radius_of_s) -> np.ndarray:
        """Coefficients of a circular wall whose radius (per knot) is ``radius_of_s`` (``(n_s,)`` spline
        coefficients of ``R_0(s)``)."""
        c = np.zeros((self.spline.size, self.n_phi_terms))
        c[:, 0] = radius_of_s
        return c.ravel()

    def fit(self, s, phi, radius, smoothing: float = 1e-6) -> np.ndarray:
        """Least-squares coefficients of sampled radii (a small ``int |R_ss|^2`` ridge keeps it well-posed)."""
        d = self.design(s, phi)
        w0 = rad.sobolev_weights(self.n_fourier, 0)
        lhs = (d.T @ d).toarray() + smoothing * np.kron(self.spline.gram(2), np.diag(w0))
        return np.linalg.solve(lhs + 1e-12 * np.eye(self.size), d.T @ np.asarray(radius, float).ravel())

    def penalty(self, alpha: float, kappa: float, sobolev_s: int = 2) -> np.ndarray:
        r"""The quadratic form ``P`` of ``alpha int ||R(s, .)||^2_{H^s} ds + kappa int ||R_ss(s, .)||^2_{L^2} ds``.

        ``P = alpha (M_0 (x) W_s) + kappa (M_2 (x) W_0)`` with the spline Gram matrices ``M_nu`` of
        :meth:`SplineBasis.gram` and the Fourier weights ``W_s`` of :func:`wss_nlp.core.radius.sobolev_weights`.
        """
        ws, w0 = rad.sobolev_weights(self.n_fourier, sobolev_s), rad.sobolev_weights(self.n_fourier, 0)
        return alpha * np.kron(self.spline.gram(0), np.diag(ws)) + kappa * np.kron(self.spline.gram(2), np.diag(w0))


# ------------------------------------------------------------------ fast coordinates
class FrameTable:
    """A centreline resampled for fast coordinates (module notes, "Coordinates"): cubic Hermite interpolation of
    ``c, t, n1, n2`` between samples ``ds`` mm apart, with the centreline's exact derivatives at the samples."""

    def __init__(self, centerline, ds: float = 0.25):
        self.centerline = centerline
        length = centerline.length_mm
        n = max(8, int(np.ceil(length / ds)) + 1)
        self.s = np.linspace(0.0, length, n)
        self.ds = float(self.s[1] - self.s[0])
        s = self.s
        t, n1, n2 = centerline.frame(s)
        dt, dn1, dn2 = centerline.frame_derivative(s)
        speed = np.linalg.norm(centerline.position(s, 1), axis=1, keepdims=True)
        # P' = |P'| t; the arclength spline has |P'| = 1 to interpolation error, kept as it is
        self._tables = {
            "point": (centerline.position(s), centerline.position(s, 1)),
            "tangent": (t, dt),
            "n1": (n1, dn1),
            "n2": (n2, dn2),
        }
        self._speed = speed

    @property
    def length_mm(self) -> float:
        return float(self.s[-1])

    def _locate(self, s):
        u = np.clip(np.asarray(s, float) / self.ds, 0.0, self.s.size - 1 - 1e-12)
        i = np.minimum(np.floor(u).astype(np.int64), self.s.size - 2)
        return i, u - i

    def value(self, name: str, s, derivative: bool = False):
        """Hermite-interpolated ``name`` (``point``, ``tangent``, ``n1``, ``n2``) at ``s (m,)``; with ``derivative``
        also its s-derivative. Outside ``[0, length]`` the end value is held (``s`` clamped)."""
        i, t = self._locate(s)
        y, dy = self._tables[name]
        h = self.ds
        t2, t3 = t * t, t * t * t
        h00, h10, h01, h11 = 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + t, -2 * t3 + 3 * t2, t3 - t2
        out = (
            h00[:, None] * y[i] + (h * h10)[:, None] * dy[i] + h01[:, None] * y[i + 1] + (h * h11)[:, None] * dy[i + 1]
        )
        if not derivative:
            return out
        d00, d10, d01, d11 = 6 * t2 - 6 * t, 3 * t2 - 4 * t + 1, -6 * t2 + 6 * t, 3 * t2 - 2 * t
        dout = (
            d00[:, None] * y[i] + h * d10[:, None] * dy[i] + d01[:, None] * y[i + 1] + h * d11[:, None] * dy[i + 1]
        ) / h
        return out, dout

    def project(self, points, s_start) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(s, r, phi)`` of world points ``(m, 3)`` by Newton's method on ``(c(s) - x) . t(s) = 0`` from ``s_start``
        (clamped to ``[0, length]``), then ``r = |x - c(s)|`` and ``phi`` the angle of ``x - c(s)`` from ``n1``
        towards ``n2``."""
        x = np.asarray(points, float).reshape(-1, 3)
        s = np.clip(np.asarray(s_start, float).ravel(), 0.0, self.length_mm)
        for _ in range(PROJECTION_STEPS):
            p = self.value("point", s)
            t, dt = self.value("tangent", s, derivative=True)
            d = p - x
            f = np.sum(d * t, axis=1)
            fp = np.sum(t * t, axis=1) + np.sum(d * dt, axis=1)
            step = np.where(fp > 1e-6, f / np.where(fp > 1e-6, fp, 1.0), f)
            s = np.clip(s - step, 0.0, self.length_mm)
        d = x - self.value("point", s)
        n1, n2 = self.value("n1", s), self.value("n2", s)
        return s, np.linalg.norm(d, axis=1), np.arctan2(np.sum(d * n2, axis=1), np.sum(d * n1, axis=1))


# ------------------------------------------------------------------ sub-voxel points
def subvoxel_offsets(q: int) -> np.ndarray:
    """Midpoints of the ``q^3`` sub-cells of a voxel about its centre, in index units, ``(q^3, 3)``."""
    if q < 1:
        raise InputError(f"sub-voxel points per axis must be >= 1, got {q}")
    t = (np.arange(q) + 0.5) / q - 0.5
    return np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)


@dataclass
class VoxelCoordinates:
    """Voxels (integer indices ``(V, 3)``), their centres' world points and centreline coordinates."""

    index: np.ndarray
    world: np.ndarray
    s: np.ndarray
    r: np.ndarray
    phi: np.ndarray
    beyond: np.ndarray  # -1 / +1: the centre lies past an end of the centreline


def voxel_coordinates(vol, index: np.ndarray, centerline) -> VoxelCoordinates:
    """Exact centreline coordinates (:meth:`Centerline.project`) of the centres of voxels ``index (V, 3)``."""
    index = np.asarray(index, np.int64).reshape(-1, 3)
    world = vol.world(index.astype(float))
    proj = centerline.project(world)
    return VoxelCoordinates(index, world, proj.s, proj.r, proj.phi, proj.beyond)


def point_coordinates(vol, voxels: VoxelCoordinates, frame: FrameTable, q: int, chunk: int = 200_000):
    """World points and ``(s, r, phi)`` of the ``q^3`` sub-voxel points of each voxel: arrays ``(V, q^3)``."""
    a = np.asarray(vol.affine_mm, float)
    off = subvoxel_offsets(q) @ a[:3, :3].T  # world offsets of the sub-points
    nv, nq = voxels.index.shape[0], off.shape[0]
    s, r, phi = (np.empty((nv, nq)) for _ in range(3))
    t_c = frame.value("tangent", voxels.s)
    step = max(1, chunk // nq)
    for v0 in range(0, nv, step):
        sl = slice(v0, v0 + step)
        pts = (voxels.world[sl, None, :] + off[None]).reshape(-1, 3)
        start = (voxels.s[sl, None] + np.einsum("qk,vk->vq", off, t_c[sl])).ravel()
        ss, rr, pp = frame.project(pts, start)
        s[sl], r[sl], phi[sl] = ss.reshape(-1, nq), rr.reshape(-1, nq), pp.reshape(-1, nq)
    return s, r, phi


# ------------------------------------------------------------------ the forward model
@dataclass
class TubeModel:
    """The voxels and points of the 3D forward model (module notes) and its linear maps.

    Points are sorted by their first B-spline index ``k0`` (``groups``: the start of each ``k0`` run), voxels keep
    the order of ``voxel_index``.
    """

    basis: WallBasis
    voxel_index: np.ndarray  # (V, 3) voxel indices of the fitted voxels
    constant: np.ndarray  # (V,) weight of the voxel's points that are inside for every admissible wall
    point_voxel: np.ndarray  # (P,) position of the point's voxel in voxel_index
    weight: np.ndarray  # (P,) w_p (fraction of the voxel)
    k0: np.ndarray  # (P,) first nonzero B-spline
    bs: np.ndarray  # (P, 4) B-spline values
    four: np.ndarray  # (P, 2N+1) Fourier rows
    r: np.ndarray  # (P,) distance to the centreline, mm
    s: np.ndarray  # (P,) arclength, mm
    phi: np.ndarray  # (P,) angle, rad
    gamma: float
    q: int
    voxel_volume: float  # mm^3
    heaviside: str = "erf"
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        order = np.argsort(self.k0, kind="stable")
        for name in ("point_voxel", "weight", "k0", "bs", "four", "r", "s", "phi"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[order]))
        edges = np.flatnonzero(np.diff(self.k0)) + 1
        self.groups = np.concatenate([[0], edges, [self.k0.size]]).astype(np.int64)
        nv = self.voxel_index.shape[0]
        self.averaging = scipy.sparse.csr_matrix(
            (self.weight, (self.point_voxel, np.arange(self.k0.size))), shape=(nv, self.k0.size)
        )
        # each voxel's window of W consecutive B-splines holding all its points' four
        lo = np.full(nv, np.iinfo(np.int64).max)
        np.minimum.at(lo, self.point_voxel, self.k0)
        hi = np.full(nv, -1)
        np.maximum.at(hi, self.point_voxel, self.k0)
        n_s = self.basis.spline.size
        width = int(np.max(hi - lo)) + 4 if nv else 4
        self.window = min(width, n_s)
        self.window_start = np.minimum(lo, n_s - self.window)
        offset = self.k0 - self.window_start[self.point_voxel]
        self._jac_rows = (self.point_voxel * self.window + offset)[:, None] + np.arange(4)[None, :]

    # --- sizes
    @property
    def n_voxels(self) -> int:
        return int(self.voxel_index.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.k0.size)

    @property
    def n_coefficients(self) -> int:
        return self.basis.size

    # --- linear maps
    def radius_at_points(self, c) -> np.ndarray:
        """``A c``: ``R(s_p, phi_p)`` at the points."""
        cm = self.basis.matrix(c)
        out = np.empty(self.n_points)
        g = self.groups
        for a, b in zip(g[:-1], g[1:]):
            k = int(self.k0[a])
            out[a:b] = np.einsum("pa,pa->p", self.bs[a:b], self.four[a:b] @ cm[k : k + 4].T)
        return out

    def radius_adjoint(self, y) -> np.ndarray:
        """``A^T y`` for point values ``y (P,)``."""
        out = np.zeros((self.basis.spline.size, self.basis.n_phi_terms))
        g = self.groups
        y = np.asarray(y, float).ravel()
        for a, b in zip(g[:-1], g[1:]):
            k = int(self.k0[a])
            out[k : k + 4] += (self.bs[a:b] * y[a:b, None]).T @ self.four[a:b]
        return out.ravel()

    def design_matrix(self):
        """``A`` as a CSR matrix (points x coefficients; for tests and small problems)."""
        return self.basis.design(self.s, self.phi)

    def predict(self, c) -> np.ndarray:
        """``F(c)``: the model's normalized magnitude of the fitted voxels."""
        gap = self.radius_at_points(c) - self.r
        return self.constant + self.averaging @ meas.smoothed_heaviside(gap, self.gamma, self.heaviside)

    def jacobian_windows(self, z) -> np.ndarray:
        """``S diag(z) A`` as each voxel's window ``(V, W, 2N+1)`` (columns ``window_start .. + W`` of the knots)."""
        z = np.asarray(z, float).ravel()
        data = (self.weight * z)[:, None] * self.bs
        m = scipy.sparse.csc_matrix(
            (data.ravel(), self._jac_rows.ravel(), np.arange(0, 4 * self.n_points + 1, 4)),
            shape=(self.n_voxels * self.window, self.n_points),
        )
        return np.asarray(m @ self.four).reshape(self.n_voxels, self.window, self.basis.n_phi_terms)

    def jacobian(self, c, scale: float = 1.0):
        """``dF/dc`` at ``c`` times ``scale`` as a CSR matrix (voxels x coefficients)."""
        gap = self.radius_at_points(c) - self.r
        win = scale * self.jacobian_windows(meas.heaviside_slope(gap, self.gamma, self.heaviside))
        return self.windows_to_csr(win)

    def windows_to_csr(self, win: np.ndarray):
        nf = self.basis.n_phi_terms
        cols = self.window_start[:, None] * nf + np.arange(self.window * nf)[None, :]
        ptr = np.arange(0, self.n_voxels * self.window * nf + 1, self.window * nf)
        return scipy.sparse.csr_matrix((win.reshape(self.n_voxels, -1).ravel(), cols.ravel(), ptr),
                                       shape=(self.n_voxels, self.basis.size))  # fmt: skip

    def gram_from_windows(self, win: np.ndarray) -> np.ndarray:
        """``J^T J`` (dense ``(n, n)``, block-banded) of the Jacobian windows."""
        nf = self.basis.n_phi_terms
        n = self.basis.size
        out = np.zeros((n, n))
        wn = self.window * nf
        flat = win.reshape(self.n_voxels, wn)
        if "by_start" not in self._cache:
            order = np.argsort(self.window_start, kind="stable")
            starts = self.window_start[order]
            cut = np.flatnonzero(np.diff(starts)) + 1
            self._cache["by_start"] = (order, np.concatenate([[0], cut, [order.size]]), starts)
        order, bounds, starts = self._cache["by_start"]
        for a, b in zip(bounds[:-1], bounds[1:]):
            x = flat[order[a:b]]
            k = int(starts[a]) * nf
            out[k : k + wn, k : k + wn] += x.T @ x
        return out

    def point_gram(self, d) -> np.ndarray:
        """``A^T diag(d) A`` (dense ``(n, n)``, block-banded) for point weights ``d (P,)``.

        Per run of points with the same first B-spline ``k`` the knot blocks ``(k + a, k + e)`` are the weighted
        Fourier Gram matrices ``F^T diag(d b_a b_e) F``, each from three Fourier moments
        (:func:`wss_nlp.core.radius.weighted_gram_map`): one product ``F^T [W, W cos N phi, W sin N phi]`` with
        the ten weight columns ``W = d b_a b_e`` (``a <= e``) per run instead of ten Gram matrices.
        """
        nf = self.basis.n_phi_terms
        n_s = self.basis.spline.size
        if "gram_map" not in self._cache:
            n = self.basis.n_fourier
            nth = self.four[:, [n, 2 * n]] if n else np.column_stack([np.ones(self.n_points), np.zeros(self.n_points)])
            pairs = [(a, e) for a in range(4) for e in range(a, 4)]
            self._cache["gram_map"] = (rad.weighted_gram_map(n), np.ascontiguousarray(nth), pairs)
        gmap, nth, pairs = self._cache["gram_map"]
        ia, ie = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
        out = np.zeros((n_s, nf, n_s, nf))
        d = np.asarray(d, float).ravel()
        g = self.groups
        for lo, hi in zip(g[:-1], g[1:]):
            k = int(self.k0[lo])
            b = self.bs[lo:hi]
            w = (d[lo:hi, None] * b[:, ia]) * b[:, ie]  # (m, 10)
            cols = np.concatenate([w, w * nth[lo:hi, :1], w * nth[lo:hi, 1:]], axis=1)  # (m, 30)
            mom = self.four[lo:hi].T @ cols  # (nf, 30): [u | v | w] per pair
            stacked = np.concatenate([mom[:, : len(pairs)], mom[:, len(pairs) : 2 * len(pairs)],
                                      mom[:, 2 * len(pairs) :]], axis=0)  # (3 nf, 10)  # fmt: skip
            blocks = (gmap @ stacked).reshape(nf, nf, len(pairs))
            for i, (a, e) in enumerate(pairs):
                out[k + a, :, k + e, :] += blocks[:, :, i]
                if e != a:
                    out[k + e, :, k + a, :] += blocks[:, :, i]
        n = self.basis.size
        return out.reshape(n, n)

    def hessian_pattern(self) -> ca.Sparsity:
        """Block-banded sparsity of ``J^T J`` and the penalties (half-bandwidth ``max(W, 4) - 1`` knots)."""
        if "pattern" not in self._cache:
            nf, n_s = self.basis.n_phi_terms, self.basis.spline.size
            band = max(self.window, 4) - 1
            knots = scipy.sparse.diags([np.ones(n_s - abs(d)) for d in range(-band, band + 1)],
                                       list(range(-band, band + 1)), shape=(n_s, n_s))  # fmt: skip
            full = scipy.sparse.kron(knots, np.ones((nf, nf))).tocsc()
            full.sort_indices()
            self._cache["pattern"] = ca.Sparsity(n_s * nf, n_s * nf, full.indptr.tolist(), full.indices.tolist())
        return self._cache["pattern"]


def auto_quad_order(order: int | None, h_mm: float, radius_mm: float, cap: int = 4) -> int:
    """Sub-voxel points per axis: ``order`` if given, else the 2D rule
    (:func:`wss_nlp.models.measurement.auto_quad_order`,
    ``clip(ceil(60 h / R), 2, 6)``) capped at ``cap``: the points grow like ``q^3`` in 3D (see the geometry
    module's notes for the measured effect of the cap)."""
    grid = meas.VoxelGrid((1, 1), (h_mm, h_mm))
    return min(meas.auto_quad_order(order, grid, radius_mm), order if order is not None else cap)


def build_model(
    vol,
    voxels: VoxelCoordinates,
    frame: FrameTable,
    basis: WallBasis,
    q: int,
    gamma: float,
    lower,
    upper,
    heaviside: str = "erf",
    keep=None,
) -> TubeModel:
    """The forward model on ``voxels`` with ``q^3`` points each, for walls between ``lower(s, phi)`` and
    ``upper(s, phi)`` (callables of point arrays, mm): points beyond ``REACH_WIDTHS gamma`` of that band are
    constant (module notes); ``keep(s, r, phi) -> bool (V, q^3)`` may drop voxels (any point False drops it)."""
    s, r, phi = point_coordinates(vol, voxels, frame, q)
    reach = REACH_WIDTHS * gamma
    lo = lower(s.ravel(), phi.ravel()).reshape(s.shape) - reach
    hi = upper(s.ravel(), phi.ravel()).reshape(s.shape) + reach
    inside, active = r < lo, (r >= lo) & (r <= hi)
    usable = active.any(axis=1)
    if keep is not None:
        usable &= keep(s, r, phi).all(axis=1)
    vox = np.flatnonzero(usable)
    w = 1.0 / s.shape[1]
    act = active[vox]
    pv = np.repeat(np.arange(vox.size), act.sum(axis=1))
    ps, pr, pp = s[vox][act], r[vox][act], phi[vox][act]
    k0, bs = basis.spline.local(ps)
    a = np.asarray(vol.affine_mm, float)
    model = TubeModel(
        basis=basis,
        voxel_index=voxels.index[vox],
        constant=inside[vox].sum(axis=1) * w,
        point_voxel=pv,
        weight=np.full(pv.size, w),
        k0=k0,
        bs=bs,
        four=rad.design_matrix(pp, basis.n_fourier),
        r=pr,
        s=ps,
        phi=pp,
        gamma=float(gamma),
        q=int(q),
        voxel_volume=abs(float(np.linalg.det(a[:3, :3]))),
        heaviside=heaviside,
    )
    log.debug("tube model: %d voxels, %d points (q = %d, gamma = %.3g mm)", model.n_voxels, model.n_points, q, gamma)
    return model


# ------------------------------------------------------------------ CasADi maps
class _Linear(operators._LinearCallback):
    """A linear map ``x (n_in,) -> y (n_out,)`` (``forward``; ``adjoint`` its transpose) on ``cols`` columns, one
    column at a time; its derivatives are the map itself (forward) and the adjoint (reverse), built once and kept
    by the root (:class:`wss_nlp.core.operators._LinearCallback`)."""

    def __init__(self, name: str, n_in: int, n_out: int, forward, adjoint, cols: int = 1, parent=None,
                 transposed: bool = False):  # fmt: skip
        self.fwd, self.adj, self.transposed = forward, adjoint, transposed
        self._root: _Linear = self if parent is None else parent._root
        super().__init__(name, n_in, n_out, cols)

    def apply(self, x: np.ndarray) -> np.ndarray:
        f = self.adj if self.transposed else self.fwd
        return np.stack([f(np.ascontiguousarray(x[:, k])) for k in range(self.cols)], axis=1)

    def derived(self, cols: int, flip: bool) -> _Linear:
        root, transposed = self._root, self.transposed != flip
        n_in, n_out = (root.n_out_, root.n_in_) if transposed else (root.n_in_, root.n_out_)
        name = f"{root.name()}_{'adj' if transposed else 'fwd'}_{cols}"
        return root._kept(
            (cols, transposed), lambda: _Linear(name, n_in, n_out, root.fwd, root.adj, cols, root, transposed)
        )


class _SparseOfPoints(ca.Callback):
    """A map of the points' values ``z (P,)`` to a sparse matrix of a fixed ``pattern``, evaluation only (IPOPT's
    Hessian and the Gauss-Newton Jacobian are never differentiated); subclasses give :meth:`values`."""

    def __init__(self, name: str, model: TubeModel, pattern: ca.Sparsity):
        ca.Callback.__init__(self)
        self.model, self.pattern = model, pattern
        self.construct(name, {})

    def values(self, z: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """The pattern's nonzeros, column-major (CasADi's order)."""
        raise NotImplementedError

    def get_n_in(self):
        return 1

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(self.model.n_points, 1)

    def get_sparsity_out(self, i):
        return self.pattern

    def has_eval_buffer(self):
        return True

    def eval_buffer(self, arg, res):
        np.frombuffer(res[0], dtype=np.float64)[:] = self.values(np.frombuffer(arg[0], dtype=np.float64))
        return 0


class _OnHessianPattern(_SparseOfPoints):
    """A symmetric ``(n, n)`` matrix on the pattern of :meth:`TubeModel.hessian_pattern`, from its dense form."""

    def __init__(self, name: str, model: TubeModel):
        pattern = model.hessian_pattern()
        rows, cols = pattern.get_triplet()
        self._rows, self._cols = np.asarray(rows), np.asarray(cols)
        super().__init__(name, model, pattern)

    def dense(self, z: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def values(self, z):
        return self.dense(z)[self._rows, self._cols]


class _GaussNewton(_OnHessianPattern):
    """``z (P,) -> scale^2 J^T J`` with ``J = S diag(z) A`` (sparse, block-banded)."""

    def __init__(self, model: TubeModel, scale: float):
        self.scale = float(scale)
        super().__init__("tube_gauss_newton", model)

    def dense(self, z):
        return self.model.gram_from_windows(self.scale * self.model.jacobian_windows(z))


class _Curvature(_OnHessianPattern):
    """``d (P,) -> A^T diag(d) A`` (sparse, the pattern of :meth:`TubeModel.hessian_pattern`): the second-order
    term ``sum_i r_i Hess r_i`` of the least-squares Hessian for ``d_p = scale r_i(p) w_p H_gamma''(gap_p)``."""

    def __init__(self, model: TubeModel):
        super().__init__("tube_curvature", model)

    def dense(self, z):
        return self.model.point_gram(z)


class _Jacobian(_SparseOfPoints):
    """``z (P,) -> scale S diag(z) A`` as a sparse ``(V, n)`` matrix (the Gauss-Newton Jacobian)."""

    def __init__(self, model: TubeModel, scale: float):
        self.scale = float(scale)
        probe = model.windows_to_csr(np.ones((model.n_voxels, model.window, model.basis.n_phi_terms))).tocsc()
        probe.sort_indices()
        pattern = ca.Sparsity(probe.shape[0], probe.shape[1], probe.indptr.tolist(), probe.indices.tolist())
        super().__init__("tube_jacobian", model, pattern)

    def values(self, z):
        jac = self.model.windows_to_csr(self.scale * self.model.jacobian_windows(z)).tocsc()
        jac.sort_indices()
        return jac.data


@dataclass
class SymbolicModel:
    """The forward model as CasADi expressions of the coefficients ``c`` (kept: its callbacks)."""

    c: ca.MX
    predicted: ca.MX  # F(c) on the fitted voxels
    gap: ca.MX  # R(s_p, phi_p) - r_p at the points
    callbacks: tuple


def symbolic(model: TubeModel) -> SymbolicModel:
    """``F(c) = constant + S H_gamma(A c - r)`` in CasADi (``A`` and ``S`` as linear callbacks with their exact
    adjoints, so that CasADi's derivatives of any order are exact)."""
    c = ca.MX.sym("c", model.n_coefficients)
    at = _Linear("tube_radius", model.n_coefficients, model.n_points, model.radius_at_points, model.radius_adjoint)
    avg = model.averaging
    avg_t = avg.T.tocsr()
    mean = _Linear("tube_mean", model.n_points, model.n_voxels, lambda y: avg @ y, lambda v: avg_t @ v)
    gap = at(c) - ca.DM(model.r)
    predicted = ca.DM(model.constant) + mean(meas.smoothed_heaviside(gap, model.gamma, model.heaviside))
    # each point's voxel value (the residual of its voxel, for the Newton Hessian): a 0/1 matrix, as a callback
    # (indexing an MX by 10^5 positions builds a slow node)
    pv = model.point_voxel
    n_v = model.n_voxels
    expand = _Linear("tube_expand", n_v, model.n_points, lambda v: v[pv],
                     lambda y: np.bincount(pv, weights=y, minlength=n_v))  # fmt: skip
    return SymbolicModel(c, predicted, gap, (at, mean, expand))
