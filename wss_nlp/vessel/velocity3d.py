r"""The blood velocity in a vessel from 4D flow: three components in one basis that vanishes on the wall (Sec. 3, 5).

Basis
-----
Each cross-section ``s`` of the fitted lumen is the image of the unit disk ``B`` under the 2D map of eq. (trafo)
about the centreline point, ``x = c(s) + (r_in(s) rho + (R(s, theta) - r_in(s)) rho^2) (cos theta n1 +
sin theta n2)`` (``eta = 2``; :func:`wss_nlp.core.mapping.inverse_radius` inverts it). A velocity component is

.. math:: u(x) = \sum_k \sum_j a_{kj} B_k(s) w_j(\xi), \qquad \xi = \rho (\cos\theta, \sin\theta),

``B_k`` cubic B-splines in ``s`` (knots ``knot_spacing_mm`` apart, default ``2 h``), ``w_j`` the 2D Zernike wall
basis ``(1 - |xi|^2) Z_n^m`` (:class:`wss_nlp.core.velocity_basis.ZernikeWallBasis`): zero on the wall for every
``s``. The three world components x, y, z (the volume's, along the affine's world axes) use the SAME basis, so
the fit is one operator with three right-hand sides. The inner radius ``r_in(s)`` of the map (``inner``):

* ``"mean"`` (default): ``f R_0(s)``, ``R_0`` the wall's mean radius (its constant Fourier term, a spline in
  ``s`` with an exact derivative). For a circular section and ``f = 1`` the map is the scaling ``x = R rho``, under
  which Poiseuille flow is the first basis function and skewed and swirling parabolic flows are low-degree
  polynomials, whatever ``R(s)`` does along the vessel. The map stays one-to-one while ``r_in < 2 min R`` (its
  radial derivative ``2 R - r_in`` at the wall); capped otherwise (below). Against "min" on the tapering and the
  elliptic phantoms: ``scripts/results/vessel_choices.md`` (on the taper the smallest radius over a B-spline's
  support lies well below the local radius and the map departs from a scaling);
  where a fitted wall is far from round (its smallest radius over a B-spline's support below
  ``R_0 / MAX_INNER_RATIO``: a loose end of the fit, a vessel of one or two voxels' radius) the spline coefficient
  of ``r_in`` is capped at :data:`MAX_INNER_RATIO` times that smallest radius (sampled 8 times per knot
  interval), which keeps the map one-to-one (a convex combination: ``r_in(s) <= 1.5 min_theta R(s, theta)`` up to
  the radius' dip between samples, so the radial derivative at the wall ``2 R - r_in`` stays near ``R / 2``), and
  the wall points over the capped B-splines' supports are reported (:attr:`VelocityBasis3D.capped`) and flagged
  unresolved by the reconstruction; where nothing is capped the basis is the plain "mean" rule's;
* ``"min"``: the 2D rule, ``f`` times the smallest radius: ``f sum_k B_k(s) rho_k`` with ``rho_k`` the smallest
  ``R`` over the support of ``B_k`` (a convex combination, so ``r_in <= f min_theta R(s, theta)``, the condition of
  Lemma A.4, with an exact s-derivative).

Functional
----------
On the voxels that meet the fitted lumen (``q^3`` points each, those with ``r < R(s, phi)`` inside):

.. math::

    Q(a) = \frac{1}{|\Omega|} \sum_i |V_i \cap \Omega| (T_i a - u_i)^2
         + \frac{\beta}{\pi L} \int \|\Delta^t_\xi v(s, \cdot)\|^2_{L^2(B)} ds
         + \frac{\kappa_v}{\pi L} \int \|\partial_s^2 v(s, \cdot)\|^2_{L^2(B)} ds,

``|Omega|`` the lumen volume, ``L`` the fitted length: per unit length this is the 2D functional of
:mod:`wss_nlp.models.velocity` (misfit over the lumen area, penalty over ``|B| = pi``), so ``beta`` keeps its
dimensionless meaning; ``kappa_v = l^4`` with ``l = smoothing_mm`` the length below which the s-penalty wins over
the data (as the stack's ``kappa_v = (l / dz)^4``, :mod:`wss_nlp.models.stack`). ``T_i a`` is the signal-weighted
mean of the model over the voxel: a voxel's phase is that of its summed signal, lumen (level 1, velocity ``u``)
plus static outside signal (level ``b``, :class:`wss_nlp.vessel.geometry3d.MagnitudeLevels`, velocity 0), to first
order in the phase spread ``T_i a = sum_{p in} v(x_p) / (n_in + b n_out)`` over the voxel's inside and outside
points: the 2D mean over ``V_i cap Omega`` when nothing static surrounds the vessel.

The normal matrix is block-banded in ``s`` (unknowns knot-major, half-bandwidth ``(W - 1)`` knots of
``n_z`` functions) and is solved by a banded Cholesky factorization (:func:`scipy.linalg.cholesky_banded`) for the
three components at once; a cine reuses it for every frame (the geometry is rigid).

``beta``: GCV (generalized cross-validation) on the three components' joint residual, minimized over a grid of
``beta`` with the trace ``tr(H^{-1} T^T W T / |Omega|)`` from the banded factor and Hutchinson's estimator
(:data:`GCV_PROBES` Rademacher vectors, the same for every beta, so the curve is smooth); or fixed.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._lazy import scipy
from ..core.mapping import inverse_radius
from ..core.velocity_basis import make_basis
from ..errors import InputError
from . import tube

log = logging.getLogger(__name__)

#: beta for noise-free data (the magnitude's noise estimate zero), where GCV has no noise to balance and takes the
#: grid's smallest value (a fit of the model's own discretization error); against GCV there:
#: ``scripts/results/vessel_choices.md``.
NOISE_FREE_BETA = 1e-5
#: The data-driven rules for beta.
BETA_RULES = ("gcv", "discrepancy")
#: Rademacher probe vectors of the GCV trace estimate.
GCV_PROBES = 12
#: The beta grid of GCV (dimensionless, as in 2D): decades, the best refined by half a decade either side.
GCV_BETAS = 10.0 ** -np.arange(2.0, 10.01, 1.0)
#: Largest ratio of the "mean" rule's inner radius to the smallest wall radius over a B-spline's support (module
#: notes): the map's radial derivative at the wall ``2 R - r_in`` stays above ``R / 2``. A round wall has ratio 1;
#: the phantoms' 12 x 9 mm ellipse 1.15, the taper's stenosis over a wall B-spline's support (4 h) 1.14 at h = 2 mm
#: and 1.17 at 2.5 mm, so the cap binds only on walls far from round (before it, those beyond 2: a refusal).
MAX_INNER_RATIO = 1.5


@dataclass(frozen=True)
class Velocity3DOptions:
    """Options of the velocity fit (module notes).

    Attributes
    ----------
    degree, angular_order : int
        Zernike degree and highest angular order of the wall basis in each cross-section.
    knot_spacing_mm : float or None
        B-spline knot spacing along ``s``; None: ``2 h``.
    smoothing_mm : float or None
        Smoothing length ``l`` along the vessel (``kappa_v = l^4``); None: ``h``.
    beta : float or str
        The Laplacian prior's weight (dimensionless), or a rule: "gcv" (default), "discrepancy" (needs the venc
        and the magnitude's noise: :func:`discrepancy_beta`).
    tau_discrepancy : float
        The discrepancy principle's factor.
    noise_free_beta : float or None
        The beta a rule gives way to on noise-free data (:data:`NOISE_FREE_BETA`; None: the rule anyway).
    laplacian_power : int
        ``t`` of ``||Delta^t v||^2`` (2: Remark 3.5's norm, the 2D default).
    inner, inner_fraction : str, float
        The map's inner radius ``r_in``: ``f`` times the mean radius ("mean") or the smallest ("min", the 2D rule).
    quad_order : int
        Points per voxel axis for the voxel means (``q^3`` per voxel).
    """

    degree: int = 10
    angular_order: int | None = 4
    knot_spacing_mm: float | None = None
    smoothing_mm: float | None = None
    beta: float | str = "gcv"
    tau_discrepancy: float = 1.1
    noise_free_beta: float | None = NOISE_FREE_BETA
    laplacian_power: int = 2
    inner: str = "mean"
    inner_fraction: float = 1.0
    quad_order: int = 3

    def __post_init__(self):
        if isinstance(self.beta, str):
            if self.beta not in BETA_RULES:
                raise InputError(f"beta must be a number > 0 or one of {', '.join(BETA_RULES)}, got {self.beta!r}")
        elif not self.beta > 0:
            raise InputError(f"beta must be > 0, got {self.beta}")
        if self.inner not in ("mean", "min"):
            raise InputError(f"inner radius rule must be 'mean' or 'min', got {self.inner!r}")
        if not 0 < self.inner_fraction <= 1:
            raise InputError(f"inner_fraction must lie in (0, 1], got {self.inner_fraction}")
        if self.laplacian_power not in (1, 2):
            raise InputError(f"laplacian_power must be 1 or 2, got {self.laplacian_power}")
        if self.quad_order < 1:
            raise InputError(f"quad_order must be >= 1, got {self.quad_order}")

    def make_basis(self):
        return make_basis("zernike", self.degree, 400.0, self.angular_order)


@dataclass
class VelocityBasis3D:
    """``v(s, xi) = sum a_kj B_k(s) w_j(xi)`` with the reference disk of each cross-section (module notes)."""

    spline: tube.SplineBasis
    disk: Any  # ZernikeWallBasis
    wall: tube.WallBasis
    wall_coefficients: np.ndarray
    inner: np.ndarray  # spline coefficients of r_in(s)
    inner_spline: tube.SplineBasis  # their B-splines (the velocity's for "min", the wall's for "mean")
    capped: list = field(default_factory=list)  # (s0, s1) supports of the capped r_in coefficients ("mean" rule)

    @property
    def size(self) -> int:
        return self.spline.size * self.disk.size

    def r_in(self, s, nu: int = 0) -> np.ndarray:
        return self.inner_spline.evaluate(self.inner, s, nu)

    def reference(self, s, r, phi) -> tuple[np.ndarray, np.ndarray]:
        """``(rho, theta)`` of points with centreline coordinates ``(s, r, phi)`` (``theta = phi``)."""
        big_r = self.wall.evaluate(self.wall_coefficients, s, phi)
        return inverse_radius(big_r, r, self.r_in(s)), np.asarray(phi, float)

    def evaluate(self, coefficients, s, r, phi) -> np.ndarray:
        """The fitted velocity ``(m, k)`` at points ``(s, r, phi)`` for coefficients ``(size, k)`` (0 outside)."""
        rho, theta = self.reference(s, r, phi)
        out = np.zeros((np.size(s),) + np.shape(coefficients)[1:])
        inside = rho < 1
        if inside.any():
            z = self.disk.evaluate(rho[inside] * np.cos(theta[inside]), rho[inside] * np.sin(theta[inside]))
            per_s = self.spline.evaluate(np.asarray(coefficients, float).reshape(self.spline.size, self.disk.size, -1),
                                         np.asarray(s, float)[inside])  # (m, nz, k)  # fmt: skip
            out[inside] = np.einsum("mj,mjk->mk", z, per_s).reshape(out[inside].shape)
        return out


def velocity_basis(geometry, options: Velocity3DOptions, h: float) -> VelocityBasis3D:
    """The velocity basis about a fitted wall (``geometry``: :class:`wss_nlp.vessel.geometry3d.Geometry3DResult`)."""
    lo, hi = geometry.s_range
    spline = tube.SplineBasis(lo, hi, options.knot_spacing_mm or 2 * h)
    phi = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    capped: list = []
    if options.inner == "mean":
        inner_spline = geometry.basis.spline
        inner = options.inner_fraction * geometry.basis.matrix(geometry.coefficients)[:, 0]
        # 8 samples per knot interval: the cap's bound holds on them; between them a fitted wall's radius dips
        # by O(delta^2 R_ss / 128), far inside the 2 min R the map needs
        cap = MAX_INNER_RATIO * _support_minima(geometry, inner_spline, phi, points=33)
        over = inner > cap
        if over.any():
            capped = [_support(inner_spline, int(k)) for k in np.flatnonzero(over)]
            where = ", ".join(f"[{a:.1f}, {b:.1f}]" for a, b in capped)
            log.info("velocity map: inner radius capped at %g x the smallest wall radius on %d B-spline(s), s in %s mm",
                     MAX_INNER_RATIO, int(over.sum()), where)  # fmt: skip
            inner = np.minimum(inner, cap)
    else:
        inner_spline = spline
        inner = options.inner_fraction * _support_minima(geometry, spline, phi)
    s = np.linspace(lo, hi, 4 * spline.intervals + 1)
    grid_s, grid_phi = np.meshgrid(s, phi, indexing="ij")
    r_min = geometry.radius(grid_s.ravel(), grid_phi.ravel()).reshape(s.size, phi.size).min(axis=1)
    r_in = inner_spline.evaluate(inner, s)
    if not np.all(r_min > 0) or not np.all((r_in > 0) & (r_in < 2 * r_min)):
        raise InputError(
            "the fitted wall is too far from round about the centreline for the velocity's map (its inner radius "
            "must lie between 0 and twice the smallest radius); use --inner min or a centreline through the lumen"
        )
    return VelocityBasis3D(spline, options.make_basis(), geometry.basis, geometry.coefficients, inner, inner_spline,
                           capped)  # fmt: skip


def _support(spline: tube.SplineBasis, k: int) -> tuple[float, float]:
    """``B_k``'s support clipped to the spline's range (mm)."""
    return max(spline.lo, spline.lo + (k - 3) * spline.delta), min(spline.hi, spline.lo + (k + 1) * spline.delta)


def _support_minima(geometry, spline: tube.SplineBasis, phi: np.ndarray, points: int = 9) -> np.ndarray:
    """The smallest wall radius over each B-spline's support (clipped to the fitted range), sampled at ``points``
    arclengths and the angles ``phi``."""
    out = np.empty(spline.size)
    for k in range(spline.size):
        a, b = _support(spline, k)
        ss, pp = np.meshgrid(np.linspace(a, b, points), phi, indexing="ij")
        out[k] = float(np.min(geometry.radius(ss.ravel(), pp.ravel())))
    return out


@dataclass
class VelocityProblem3D:
    """The assembled linear least-squares problem of the velocity (module notes)."""

    basis: VelocityBasis3D
    voxel_index: np.ndarray  # (V, 3)
    voxel_s: np.ndarray  # (V,) arclength of the voxel centres
    fraction: np.ndarray  # (V,) |V_i cap Omega| / |V_i|
    windows: np.ndarray  # (V, W, n_z): T's rows in each voxel's window of W knots
    window_start: np.ndarray  # (V,)
    window: int
    voxel_volume: float
    length_mm: float
    gram_laplace: np.ndarray  # (n, n) int ||Delta^t v||^2 ds (banded, dense storage)
    gram_smooth: np.ndarray  # (n, n) int ||v_ss||^2 ds
    kappa: float
    seconds: float = 0.0
    _normal: np.ndarray | None = field(default=None, repr=False)

    @property
    def n_voxels(self) -> int:
        return int(self.voxel_index.shape[0])

    @property
    def size(self) -> int:
        return self.basis.size

    @property
    def weights(self) -> np.ndarray:
        """``|V_i cap Omega| / |Omega|``."""
        return self.fraction / np.sum(self.fraction)

    def operator(self):
        """``T`` as a CSR matrix (voxels x coefficients)."""
        nz = self.basis.disk.size
        cols = self.window_start[:, None] * nz + np.arange(self.window * nz)[None, :]
        ptr = np.arange(0, self.n_voxels * self.window * nz + 1, self.window * nz)
        return scipy.sparse.csr_matrix((self.windows.reshape(self.n_voxels, -1).ravel(), cols.ravel(), ptr),
                                       shape=(self.n_voxels, self.size))  # fmt: skip

    def normal(self) -> np.ndarray:
        """``T^T W T`` (dense storage of a block-banded matrix), ``W = diag(weights)``."""
        if self._normal is None:
            self._normal = self.weighted_normal(self.weights)
        return self._normal

    def weighted_normal(self, d: np.ndarray) -> np.ndarray:
        """``T^T diag(d) T`` for voxel weights ``d (V,) >= 0`` (dense storage, the band of :meth:`normal`)."""
        nz = self.basis.disk.size
        wn = self.window * nz
        flat = self.windows.reshape(self.n_voxels, wn) * np.sqrt(np.asarray(d, float))[:, None]
        out = np.zeros((self.size, self.size))
        order = np.argsort(self.window_start, kind="stable")
        starts = self.window_start[order]
        cut = np.concatenate([[0], np.flatnonzero(np.diff(starts)) + 1, [order.size]])
        for a, b in zip(cut[:-1], cut[1:]):
            x = flat[order[a:b]]
            k = int(starts[a]) * nz
            out[k : k + wn, k : k + wn] += x.T @ x
        return out

    def hessian(self, beta: float) -> np.ndarray:
        return self.normal() + beta / (np.pi * self.length_mm) * self.gram_laplace + \
            self.kappa / (np.pi * self.length_mm) * self.gram_smooth  # fmt: skip

    def bandwidth(self) -> int:
        return (max(self.window, 4)) * self.basis.disk.size - 1

    def factor(self, beta: float) -> np.ndarray:
        """The banded Cholesky factor (upper form) of :meth:`hessian`."""
        return scipy.linalg.cholesky_banded(to_banded(self.hessian(beta), self.bandwidth()), lower=False)

    def rhs(self, data: np.ndarray) -> np.ndarray:
        """``T^T W u`` for data ``(V, k)``."""
        return np.asarray(
            self.operator().T @ (self.weights[:, None] * np.asarray(data, float).reshape(self.n_voxels, -1))
        )

    def solve(self, beta: float, data: np.ndarray, factor=None) -> np.ndarray:
        cb = self.factor(beta) if factor is None else factor
        return scipy.linalg.cho_solve_banded((cb, False), self.rhs(data))

    def residual_norm(self, coefficients, data) -> np.ndarray:
        """``sqrt(sum_i w_i (T_i a - u_i)^2)`` per component (m/s)."""
        fit = self.operator() @ coefficients
        return np.sqrt(np.sum(self.weights[:, None] * (fit - np.asarray(data).reshape(fit.shape)) ** 2, axis=0))


def to_banded(m: np.ndarray, u: int) -> np.ndarray:
    """Upper banded storage ``ab[u + i - j, j] = m[i, j]`` of a symmetric matrix with half-bandwidth ``u``."""
    n = m.shape[0]
    ab = np.zeros((u + 1, n))
    for d in range(u + 1):
        ab[u - d, d:] = np.diagonal(m, d)
    return ab


def assemble(vol, geometry, frame: tube.FrameTable, coords: tube.VoxelCoordinates, options: Velocity3DOptions,
             static_level=None, exclude=None) -> VelocityProblem3D:  # fmt: skip
    """Voxels meeting the fitted lumen, their partial volumes and the operator ``T`` (module notes).

    ``coords``: voxels near the vessel with their centres' centreline coordinates; ``static_level(s)``: the
    static signal outside the wall relative to the lumen's (None: 0); ``exclude(s, phi)``: wall regions whose
    voxels are left out (branches).
    """
    t0 = time.perf_counter()
    h = float(np.asarray(vol.voxel_size_mm).max())
    half_diag = 0.5 * float(np.linalg.norm(vol.voxel_size_mm))
    basis = velocity_basis(geometry, options, h)
    lo, hi = geometry.s_range
    big_r = geometry.radius(coords.s, coords.phi)
    sel = (coords.beyond == 0) & (coords.s >= lo) & (coords.s <= hi) & (coords.r < big_r + half_diag)
    sub = tube.VoxelCoordinates(coords.index[sel], coords.world[sel], coords.s[sel], coords.r[sel], coords.phi[sel],
                                coords.beyond[sel])  # fmt: skip
    q = options.quad_order
    s, r, phi = tube.point_coordinates(vol, sub, frame, q)
    inside = r < geometry.radius(s.ravel(), phi.ravel()).reshape(s.shape)
    keep = inside.any(axis=1)
    if exclude is not None:
        keep &= ~exclude(s, phi).any(axis=1)
    if not keep.any():
        raise InputError(f"{vol.source}: no voxel meets the fitted lumen; the wall fit failed to find the vessel")
    s, r, phi, inside = s[keep], r[keep], phi[keep], inside[keep]
    nv, nq = s.shape
    n_in = inside.sum(axis=1)
    b = np.zeros(nv) if static_level is None else np.asarray(static_level(sub.s[keep]), float)
    denom = n_in + b * (nq - n_in)
    pv = np.repeat(np.arange(nv), n_in)
    ps, pr, pp = s[inside], r[inside], phi[inside]
    rho, theta = basis.reference(ps, pr, pp)
    rho = np.minimum(rho, 1.0)
    k0, bs = basis.spline.local(ps)
    lo_k = np.full(nv, np.iinfo(np.int64).max)
    np.minimum.at(lo_k, pv, k0)
    hi_k = np.full(nv, -1)
    np.maximum.at(hi_k, pv, k0)
    n_s = basis.spline.size
    window = min(int(np.max(hi_k - lo_k)) + 4, n_s)
    start = np.minimum(lo_k, n_s - window)
    rows = (pv * window + (k0 - start[pv]))[:, None] + np.arange(4)[None, :]
    data = bs / denom[pv][:, None]
    m = scipy.sparse.csc_matrix((data.ravel(), rows.ravel(), np.arange(0, 4 * pv.size + 1, 4)),
                                shape=(nv * window, pv.size))  # fmt: skip
    raw = basis.disk.evaluate_raw(rho * np.cos(theta), rho * np.sin(theta))  # (P, n_z)
    windows = np.asarray(m @ raw) @ basis.disk.transform
    disk = basis.disk
    g_lap = disk.laplacian_gram(options.laplacian_power)
    g0 = disk.laplacian_gram(0)
    gram_laplace = np.kron(basis.spline.gram(0), g_lap)
    gram_smooth = np.kron(basis.spline.gram(2), g0)
    smoothing = h if options.smoothing_mm is None else float(options.smoothing_mm)
    a = np.asarray(vol.affine_mm, float)
    return VelocityProblem3D(
        basis=basis,
        voxel_index=sub.index[keep],
        voxel_s=sub.s[keep],
        fraction=n_in / nq,
        windows=windows.reshape(nv, window, disk.size),
        window_start=start,
        window=window,
        voxel_volume=abs(float(np.linalg.det(a[:3, :3]))),
        length_mm=hi - lo,
        gram_laplace=gram_laplace,
        gram_smooth=gram_smooth,
        kappa=smoothing**4,
        seconds=time.perf_counter() - t0,
    )


@dataclass
class BetaChoice:
    rule: str
    beta: float
    betas: np.ndarray = field(default_factory=lambda: np.zeros(0))
    criterion: np.ndarray = field(default_factory=lambda: np.zeros(0))


def gcv_beta(problem: VelocityProblem3D, data: np.ndarray, betas=GCV_BETAS, seed: int = 0,
             refine: bool = True) -> BetaChoice:  # fmt: skip
    r"""``beta`` minimizing ``GCV(beta) = n |W^{1/2}(T a_beta - u)|^2 / (n - tr A_beta)^2`` (three components'
    residuals summed, ``n`` three times the voxels, ``tr A_beta = 3 tr(H_beta^{-1} T^T W T)`` by Hutchinson's
    estimator with :data:`GCV_PROBES` fixed Rademacher vectors and the banded factor of ``H_beta``) on ``betas``,
    then (``refine``) at half a step either side of the best."""
    if refine:
        first = gcv_beta(problem, data, betas, seed, refine=False)
        extra = [b for b in (first.beta * np.sqrt(10.0), first.beta / np.sqrt(10.0)) if min(betas) <= b <= max(betas)]
        second = gcv_beta(problem, data, np.array(extra), seed, refine=False) if extra else None
        grid = np.concatenate([first.betas, [] if second is None else second.betas])
        crit = np.concatenate([first.criterion, [] if second is None else second.criterion])
        order = np.argsort(grid)[::-1]
        grid, crit = grid[order], crit[order]
        return BetaChoice("gcv", float(grid[int(np.argmin(crit))]), grid, crit)
    rng = np.random.default_rng(seed)
    probes = rng.choice([-1.0, 1.0], size=(problem.size, GCV_PROBES))
    k_probes = problem.normal() @ probes
    rhs = problem.rhs(data)
    op = problem.operator()
    u = np.asarray(data, float).reshape(problem.n_voxels, -1)
    w = problem.weights
    n = u.size
    scores = []
    for beta in betas:
        cb = problem.factor(beta)
        a = scipy.linalg.cho_solve_banded((cb, False), np.hstack([rhs, k_probes]))
        coef, hk = a[:, : rhs.shape[1]], a[:, rhs.shape[1] :]
        trace = u.shape[1] * float(np.mean(np.sum(probes * hk, axis=0)))
        res = float(np.sum(w[:, None] * (op @ coef - u) ** 2))
        # the weights sum to one: n_eff = n times the residual per datum
        scores.append(n * res / max(n - trace, 1e-12) ** 2)
    scores_a = np.array(scores)
    return BetaChoice("gcv", float(betas[int(np.argmin(scores_a))]), np.asarray(betas), scores_a)


def velocity_noise(vol, problem: VelocityProblem3D, levels) -> np.ndarray:
    """Standard deviation ``(V, 3)`` (m/s) of each voxel's measured velocity components: the phase noise of a
    voxel whose summed signal is ``S_i = m1 (f_i + b (1 - f_i))`` (lumen fraction ``f_i``, static level ``b``) is
    ``sigma / S_i`` for complex noise ``sigma`` per channel, so ``venc_c sigma / (pi S_i)``."""
    if vol.venc_m_s is None:
        raise InputError(
            f"{vol.source}: the velocity's noise needs the velocity encoding: the file has no 'venc_m_s'; pass "
            "--venc (m/s, one value or one per component), or choose beta by GCV or a number"
        )
    m1, _, b = levels.at(problem.voxel_s)
    signal = m1 * (problem.fraction + b * (1 - problem.fraction))
    return np.asarray(vol.venc_m_s, float)[None, :] * levels.noise_sigma / (np.pi * signal[:, None])


def discrepancy_beta(problem: VelocityProblem3D, data: np.ndarray, sigma: np.ndarray, tau: float,
                     betas=GCV_BETAS) -> BetaChoice:  # fmt: skip
    """The largest ``beta`` whose weighted residual ``sum_i w_i |T_i a - u_i|^2`` is at most ``tau^2`` times the
    noise's ``sum_i w_i |sigma_i|^2`` (the discrepancy principle, eq. (disc2) in 3D), from large to small."""
    noise = float(np.sum(problem.weights[:, None] * sigma**2))
    rhs = problem.rhs(data)
    op = problem.operator()
    u = np.asarray(data, float).reshape(problem.n_voxels, -1)
    res = []
    for beta in sorted(betas, reverse=True):
        coef = scipy.linalg.cho_solve_banded((problem.factor(beta), False), rhs)
        res.append(float(np.sum(problem.weights[:, None] * (op @ coef - u) ** 2)))
        if res[-1] <= tau**2 * noise:
            break
    grid = np.array(sorted(betas, reverse=True)[: len(res)])
    ok = np.flatnonzero(np.array(res) <= tau**2 * noise)
    chosen = float(grid[ok[0]] if ok.size else grid[int(np.argmin(res))])
    return BetaChoice("discrepancy", chosen, grid, np.sqrt(np.array(res) / noise))


@dataclass
class Velocity3DResult:
    """Coefficients ``(size, 3)`` (world x, y, z components) for each frame and how they were found."""

    problem: VelocityProblem3D
    coefficients: np.ndarray  # (nt, size, 3)
    beta: float
    beta_choice: BetaChoice
    residual_norm: np.ndarray  # (nt, 3) m/s
    seconds: float

    @property
    def basis(self) -> VelocityBasis3D:
        return self.problem.basis


def voxel_velocities(vol, problem: VelocityProblem3D, frames=None) -> np.ndarray:
    """The measured velocity ``(nt, V, 3)`` (m/s, world components) on the problem's voxels."""
    idx = problem.voxel_index
    frames = range(vol.nt) if frames is None else frames
    v = np.asarray(vol.velocity, float)
    return np.stack([v[t][:, idx[:, 0], idx[:, 1], idx[:, 2]].T for t in frames])


def fit_velocity(vol, problem: VelocityProblem3D, options: Velocity3DOptions, frames=None,
                 beta_frame: int | None = None, levels=None) -> Velocity3DResult:  # fmt: skip
    """Solve for the three components of every frame (one factorization serves all: rigid walls).

    ``beta``: fixed, or a rule on ``beta_frame`` (default: the frame with the largest mean speed, where the signal
    is strongest; one beta for the cycle); "discrepancy" needs ``levels`` (the magnitude's noise) and the venc.
    """
    t0 = time.perf_counter()
    u = voxel_velocities(vol, problem, frames)
    k = int(np.argmax(np.mean(np.linalg.norm(u, axis=2), axis=1))) if beta_frame is None else beta_frame
    noise_free = levels is not None and not levels.noise_sigma > 1e-9 * float(np.mean(levels.lumen))
    if options.beta in BETA_RULES and noise_free and options.noise_free_beta is not None:
        choice = BetaChoice(f"{options.beta} (noise-free data: fixed)", float(options.noise_free_beta))
    elif options.beta == "gcv":
        choice = gcv_beta(problem, u[k])
    elif options.beta == "discrepancy":
        if levels is None:
            raise InputError("beta rule 'discrepancy' needs the magnitude's noise level (levels)")
        choice = discrepancy_beta(problem, u[k], velocity_noise(vol, problem, levels), options.tau_discrepancy)
    else:
        choice = BetaChoice("fixed", float(options.beta))
    cb = problem.factor(choice.beta)
    nt = u.shape[0]
    rhs = np.concatenate([problem.rhs(u[t]) for t in range(nt)], axis=1)
    coef = scipy.linalg.cho_solve_banded((cb, False), rhs).reshape(problem.size, nt, 3).transpose(1, 0, 2)
    res = np.stack([problem.residual_norm(coef[t], u[t]) for t in range(nt)])
    log.info("velocity: %d voxels, %d unknowns x 3 components x %d frames, beta %.3g (%s)", problem.n_voxels,
             problem.size, nt, choice.beta, choice.rule)  # fmt: skip
    return Velocity3DResult(problem, coef, choice.beta, choice, res, time.perf_counter() - t0)
