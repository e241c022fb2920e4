r"""The wall of a vessel from a 4D flow magnitude: Tikhonov regularization on the volume's voxels (paper Sec. 5).

Functional
----------
With the forward model ``F`` of :mod:`wss_nlp.vessel.tube` (voxel means of the smoothed lumen indicator of the
wall ``R(s, phi) = sum C_kj B_k(s) F_j(phi)`` about the fixed centreline) and the normalized magnitude ``m``,

.. math::

    J(c) = \sum_i |V_i| (F_i(c) - m_i)^2
         + \alpha \int \|R(s, \cdot) - R_{ref}(s)\|^2_{H^2(0, 2\pi)} ds
         + \kappa \int \|\partial_s^2 R(s, \cdot)\|^2_{L^2(0, 2\pi)} ds,

minimized subject to ``r0(s, phi_j) <= R(s_i, phi_j) <= r1(s, phi_j)`` at sample points (IPOPT inequality
constraints). The first two terms are the 2D functional of eq. (tik1) (prior "area") integrated along the vessel:
both are mm^3, so ``alpha`` keeps its 2D meaning and default. ``kappa = l^4 R / h``: a wall displacement ``delta``
changes the misfit by about ``(R / h) int ||delta(s, .)||^2 ds`` (a band of wall voxels of width ``h``), so ``l``
(``smoothing_mm``) is the length along the vessel below which the penalty wins over the data, as the stack's
``z_smoothing_mm`` (:mod:`wss_nlp.models.stack`, whose ``kappa = (l / dz)^4 R / h`` is this with the second
difference for the second derivative). The B-spline knots are ``knot_spacing_mm`` apart (default ``h``).

Two solves. IPOPT with the Gauss-Newton Hessian ``2 (J^T J + P)`` (:func:`wss_nlp.core.solver.gauss_newton_ipopt`;
``J = sqrt|V| S diag(H_gamma') A`` assembled by the chain rule from the voxels' windows of B-splines, block-banded).
The first (``coarse_order`` points per axis, default 2, ``gamma = h / 2``) starts from the circular reference
``R_ref(s)`` in a wide box ``R_ref +- max(2 h, R_ref / 4)``; the second (``q`` points per axis, ``gamma = h / q``)
starts from the first's wall in a box ``+- refine_mm`` (default ``h / 2``) about it, so that only points within
``refine_mm + 4 gamma`` of that wall enter the model (a ``q^3`` rule on the whole wide band would cost 8-27 times
as many points). A box row active at the end is reported (``box_active``) and flagged by the reconstruction.

Magnitude levels (Appendix B along the vessel)
----------------------------------------------
``m = (M - m0(s)) / (m1(s) - m0(s))`` with ``M`` the time-mean magnitude, ``m1(s)`` its mean in the eroded lumen
(voxel centres at ``r < 0.6 R_est(s)``) and ``m0(s)`` its mean in a shell just outside the wall (voxel centres
at ``R_est + d + h/4 <= r <= R_est + d + 5h/4``, ``d`` the voxel's half-diagonal: fully outside even where the
radius estimate ``R_est`` from the mask is a quarter voxel short), each a Gaussian-kernel mean along ``s``
(standard deviation :data:`LEVEL_BANDWIDTH_VOXELS` voxels): smooth functions of ``s``. The values are not clipped
to [0, 1] (clipping the noise biases the voxels next to the wall). With tissue around the vessel ``m0`` is the
level of the tissue right outside the wall, what a wall voxel's outer part holds; tissue whose level changes within
a voxel of the wall (a thin bright or dark wall layer) is not modelled and biases the wall by up to the fraction of
a voxel that layer's contrast moves the voxel means (measured in ``scripts/results/vessel_accuracy.md``).

Also estimated: the complex noise ``sigma`` (frame-to-frame differences of the lumen's magnitude for a cine, else
its robust spread) and the static signal just outside the wall relative to the lumen's,
``sqrt(max(<M_t^2>_shell - 2 sigma^2, 0)) / m1`` (the Rician second moment ``E|S + n|^2 = S^2 + 2 sigma^2``): the
velocity model weights a wall voxel's static part with it (:mod:`wss_nlp.vessel.velocity3d`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Any

import numpy as np

import casadi as ca

from .._lazy import scipy
from ..core import radius as rad
from ..core.solver import SolverStats, gauss_newton_ipopt, run_nlpsol
from ..errors import InputError, NoVesselError
from ..models import measurement as meas
from ..models.geometry import WARM_START  # the 2D warm re-solve's IPOPT options serve the outside level's updates
from . import tube

log = logging.getLogger(__name__)

#: Kernel width (standard deviation, in voxels) of the magnitude levels along s.
LEVEL_BANDWIDTH_VOXELS = 3.0
#: The outside level's updates stop when it changes by less than this (relative to the lumen's level).
OUTSIDE_TOL = 0.01
#: Over-relaxation of the outside level's updates: the alternation with the wall fit converges linearly (the wall
#: and the outside level trade off in the wall voxels), plain steps slowly; each update's change is in the
#: geometry's statuses (``outside_change``), its effect in ``scripts/results/vessel_choices.md``.
OUTSIDE_RELAXATION = 1.5
#: Fewest voxels in a level's kernel window below which the global level is used instead.
MIN_LEVEL_VOXELS = 20


@dataclass(frozen=True)
class Geometry3DOptions:
    """Options of the wall fit (module notes).

    Attributes
    ----------
    n_fourier : int
        Highest harmonic N in ``phi``.
    alpha : float
        Weight of the H^s penalty in ``phi`` (dimensionless, the 2D meaning).
    sobolev_s : int
        Order of that penalty.
    smoothing_mm : float or None
        Smoothing length ``l`` along the vessel (``kappa = l^4 R / h``); None: one voxel ``h``.
    knot_spacing_mm : float or None
        B-spline knot spacing in ``s``; None: ``h``.
    quad_order : int or None
        Sub-voxel points per axis of the final fit; None: :func:`wss_nlp.vessel.tube.auto_quad_order`.
    coarse_order : int
        Points per axis of the first (wide-box) fit.
    box_mm : float or None
        Half-width of the first fit's box about ``R_ref``; None: ``max(2 h, R_ref / 4)``.
    refine_mm : float or None
        Half-width of the final fit's box about the first fit's wall; None: ``h / 2``.
    """

    n_fourier: int = 6
    alpha: float = 1e-3
    sobolev_s: int = 2
    smoothing_mm: float | None = None
    knot_spacing_mm: float | None = None
    quad_order: int | None = None
    coarse_order: int = 2
    box_mm: float | None = None
    refine_mm: float | None = None
    heaviside: str = "erf"
    n_box_phi: int = 0
    tol: float = 1e-8
    max_iter: int = 100
    coarse_tol: float = 1e-5
    outside_updates: int = 4
    newton: bool = True

    def __post_init__(self):
        if self.n_fourier < 0:
            raise InputError(f"n_fourier must be >= 0, got {self.n_fourier}")
        if not self.alpha > 0:
            raise InputError(f"alpha must be > 0, got {self.alpha}")
        if self.smoothing_mm is not None and not self.smoothing_mm >= 0:
            raise InputError(f"smoothing length must be >= 0 mm, got {self.smoothing_mm}")
        if self.knot_spacing_mm is not None and not self.knot_spacing_mm > 0:
            raise InputError(f"knot spacing must be > 0 mm, got {self.knot_spacing_mm}")
        if self.heaviside not in meas.HEAVISIDES:
            raise InputError(f"heaviside must be one of {meas.HEAVISIDES}, got {self.heaviside!r}")


# ------------------------------------------------------------------ magnitude levels
@dataclass
class MagnitudeLevels:
    """The lumen and outside levels of the magnitude along ``s`` and the noise (module notes)."""

    s_mm: np.ndarray
    lumen: np.ndarray  # m1(s)
    outside: np.ndarray  # m0(s)
    static: np.ndarray  # static signal right outside the wall over the lumen's (0 without tissue)
    noise_sigma: float  # complex noise per channel, magnitude units
    method: dict = field(default_factory=dict)

    def at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(m1, m0, static)`` at ``s`` (linear interpolation, held beyond the ends)."""
        s = np.asarray(s, float)
        m1, m0, b = (np.interp(s, self.s_mm, v) for v in (self.lumen, self.outside, self.static))
        return m1, m0, b

    def normalize(self, magnitude, s) -> np.ndarray:
        """``(M - m0(s)) / (m1(s) - m0(s))``."""
        m1, m0, _ = self.at(s)
        return (np.asarray(magnitude, float) - m0) / (m1 - m0)

    def as_dict(self) -> dict:
        return {"s_mm": self.s_mm.tolist(), "lumen": self.lumen.tolist(), "outside": self.outside.tolist(),
                "static": self.static.tolist(), "noise_sigma": self.noise_sigma, **self.method}  # fmt: skip


def _kernel_mean(s_sample, s_grid, values, width) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-kernel means of ``values`` at ``s_grid`` and the kernels' effective counts."""
    w = np.exp(-0.5 * ((s_grid[:, None] - s_sample[None, :]) / width) ** 2)
    total = w.sum(axis=1)
    return (w @ values) / np.maximum(total, 1e-300), total


def magnitude_levels(vol, coords: tube.VoxelCoordinates, radius_of_s, s_grid: np.ndarray) -> MagnitudeLevels:
    """Lumen and outside levels along ``s`` (module notes) from voxels with centreline coordinates ``coords``.

    ``radius_of_s``: callable, the radius estimate ``R_est(s)`` (mm).
    """
    a = np.asarray(vol.affine_mm, float)
    spacing = np.linalg.norm(a[:3, :3], axis=0)
    h = float(spacing.max())
    half_diag = 0.5 * float(np.linalg.norm(spacing))
    mags = np.asarray(vol.magnitude, float)[:, coords.index[:, 0], coords.index[:, 1], coords.index[:, 2]]  # (nt, V)
    mean = mags.mean(axis=0)
    r_est = radius_of_s(coords.s)
    ok = coords.beyond == 0
    core = ok & (coords.r < 0.6 * r_est)
    shell = ok & (coords.r >= r_est + half_diag + 0.25 * h) & (coords.r <= r_est + half_diag + 1.25 * h)
    if core.sum() < MIN_LEVEL_VOXELS or shell.sum() < MIN_LEVEL_VOXELS:
        raise NoVesselError(
            f"{vol.source}: too few voxels inside ({int(core.sum())}) or just outside ({int(shell.sum())}) the "
            "vessel to normalize the magnitude; check the mask or centreline"
        )
    width = LEVEL_BANDWIDTH_VOXELS * h
    lumen, n_in = _kernel_mean(coords.s[core], s_grid, mean[core], width)
    outside, n_out = _kernel_mean(coords.s[shell], s_grid, mean[shell], width)
    second, _ = _kernel_mean(coords.s[shell], s_grid, np.mean(mags[:, shell] ** 2, axis=0), width)
    # where a kernel holds too few voxels (the ends, gaps) use the global levels
    lumen = np.where(n_in >= MIN_LEVEL_VOXELS, lumen, float(np.mean(mean[core])))
    outside = np.where(n_out >= MIN_LEVEL_VOXELS, outside, float(np.mean(mean[shell])))
    second = np.where(n_out >= MIN_LEVEL_VOXELS, second, float(np.mean(mags[:, shell] ** 2)))
    nt = mags.shape[0]
    if nt > 1:  # frame-to-frame: the lumen's own brightness cancels
        dev = mags[:, core] - mean[core][None]
        sigma = float(np.sqrt(np.sum(dev**2) / (dev.size - core.sum())))
        how = "frame-to-frame spread of the lumen's magnitude"
    else:
        from ..models.preprocess import robust_std

        sigma = robust_std(mean[core] - np.interp(coords.s[core], s_grid, lumen))
        how = "robust spread of the lumen's magnitude"
    if not np.all(lumen > outside):
        raise NoVesselError(f"{vol.source}: the lumen is not brighter than its surroundings; no wall to fit")
    # the static signal right outside, without the noise floor (Rician: E|S + n|^2 = S^2 + 2 sigma^2): where it is
    # far above the noise it equals the mean magnitude there; without tissue it is ~0 where the mean is the
    # Rayleigh floor sigma sqrt(pi / 2), which a partial-volume voxel's magnitude does not carry
    static_level = np.sqrt(np.maximum(second - 2 * sigma**2, 0.0))
    method = {"noise_from": how, "frames": nt, "outside_mean": outside.tolist()}
    return MagnitudeLevels(s_grid, lumen, static_level, static_level / lumen, sigma, method)


def _kernel_density(s_grid, s_values, weights, width, lo, hi) -> np.ndarray:
    """``sum_i K(s - s_i) w_i`` per unit length with a Gaussian kernel of standard deviation ``width`` (``int K = 1``),
    divided by the kernel's mass on ``[lo, hi]`` where the data are (no loss at the data's ends)."""
    from scipy.special import ndtr

    k = np.exp(-0.5 * ((s_grid[:, None] - s_values[None, :]) / width) ** 2) / (np.sqrt(2 * np.pi) * width)
    mass = ndtr((hi - s_grid) / width) - ndtr((lo - s_grid) / width)
    return (k @ weights) / np.maximum(mass, 0.2)


def radius_from_mask(mask, vol, coords: tube.VoxelCoordinates, s_grid: np.ndarray) -> np.ndarray:
    """Equal-area radius of a mask along ``s``: ``sqrt(A(s) / pi)`` with ``A(s)`` the kernel-weighted volume of
    the mask's voxels per unit length (``sum_i K(s - s_i) |V|``, ``int K ds = 1``, corrected at the mask's ends)."""
    a = np.asarray(vol.affine_mm, float)
    voxel = abs(float(np.linalg.det(a[:3, :3])))
    h = float(np.linalg.norm(a[:3, :3], axis=0).max())
    inside = np.asarray(mask, bool)[tuple(coords.index.T)] & (coords.beyond == 0)
    if not inside.any():
        raise NoVesselError(f"{vol.source}: the mask holds no voxel along the centreline")
    s_in = coords.s[inside]
    density = _kernel_density(s_grid, s_in, np.full(s_in.size, voxel), 1.5 * h, s_in.min() - 0.5 * h,
                              s_in.max() + 0.5 * h)  # fmt: skip
    return np.sqrt(density / np.pi)


def reference_radius(m_norm, coords: tube.VoxelCoordinates, r_est, s_grid, voxel: float, h: float) -> np.ndarray:
    """Equal-area radius of the normalized magnitude along ``s`` (the 2D "area" prior per cross-section):
    ``A(s) = sum_i K(s - s_i) m_i |V|`` over voxels within ``R_est + 1.5 h`` of the centreline."""
    near = (coords.r < r_est + 1.5 * h) & (coords.beyond == 0)
    s_in = coords.s[near]
    density = _kernel_density(s_grid, s_in, m_norm[near] * voxel, 1.5 * h, s_in.min() - 0.5 * h, s_in.max() + 0.5 * h)
    return np.sqrt(np.maximum(density, 0.0) / np.pi)


def update_outside(problem: GeometryProblem3D, stage, c: np.ndarray) -> float:
    r"""Re-estimate the outside level ``b(s) = m0(s) / m1(s)`` from the voxels the fitted wall cuts.

    Notes
    -----
    A wall voxel with lumen fraction ``f_i`` (the model's, at the fitted wall) holds
    ``M_i / m1 = f_i + (1 - f_i) b``: ``b`` is the level of what lies right outside the wall, within a voxel of
    it, which a shell farther out need not share (a thin wall layer darker or brighter than the tissue beyond).
    Its least-squares estimate over the voxels with ``0.02 < f_i < 0.98``, a Gaussian-kernel mean along ``s``
    as for the other levels: ``b(s) = sum K (1 - f_i)(M_i / m1 - f_i) / sum K (1 - f_i)^2``. Alternated with the
    wall fit (at most ``outside_updates`` times, until ``b`` changes by less than :data:`OUTSIDE_TOL`), each step
    over-relaxed by :data:`OUTSIDE_RELAXATION`. Returns the largest change of ``b``.
    """
    lev = problem.levels
    f = stage.model.predict(c)
    pos = stage.position
    s = problem.coords.s[pos]
    m1, _, _ = lev.at(s)
    y = problem.raw[pos] / m1 - f
    x = 1.0 - f
    cut = (f > 0.02) & (f < 0.98)
    if cut.sum() < MIN_LEVEL_VOXELS:
        return 0.0
    width = LEVEL_BANDWIDTH_VOXELS * problem.h
    k = np.exp(-0.5 * ((lev.s_mm[:, None] - s[cut][None, :]) / width) ** 2)
    num, den = k @ (x[cut] * y[cut]), k @ (x[cut] ** 2)
    enough = k.sum(axis=1) >= MIN_LEVEL_VOXELS
    b = np.where(enough, num / np.maximum(den, 1e-300), float(np.sum(x[cut] * y[cut]) / np.sum(x[cut] ** 2)))
    b = np.clip(lev.static + OUTSIDE_RELAXATION * (b - lev.static), 0.0, 0.9)
    change = float(np.max(np.abs(b - lev.static)))
    lev.static = b
    lev.outside = b * lev.lumen
    lev.method["outside_from"] = "least squares on the voxels the fitted wall cuts"
    return change


# ------------------------------------------------------------------ the NLP
@dataclass
class GeometryNLP:
    """CasADi pieces of one wall fit (:func:`build_nlp`)."""

    model: tube.TubeModel
    c: ca.MX
    f: ca.MX  # objective J(c)
    g: ca.MX  # R at the box samples
    residual: ca.MX  # sqrt|V| (F(c) - m)
    hessian: ca.MX  # 2 (J^T J + P), the Gauss-Newton Hessian
    jacobian: ca.MX  # J = d residual / dc by the chain rule (sparse)
    penalty: np.ndarray  # P (dense)
    reference: np.ndarray  # c_ref
    data: np.ndarray  # m on the fitted voxels
    kept: tuple  # callbacks (CasADi's rule: alive while the functions are)


def build_nlp(model: tube.TubeModel, data, penalty: np.ndarray, reference: np.ndarray,
              alpha_part: np.ndarray, box_matrix, newton: bool = True) -> GeometryNLP:  # fmt: skip
    """``J(c) = |sqrt|V| (F(c) - m)|^2 + (c - c_ref)^T P_a (c - c_ref) + c^T (P - P_a) c`` (module notes), its
    box rows and its Hessian: ``2 (J^T J + P)`` (Gauss-Newton) plus, with ``newton``, the second-order term
    ``2 sum_i r_i Hess r_i = 2 A^T diag(d) A``, ``d_p = |V| (F_i - m_i) w_p H_gamma''(gap_p)`` (the exact Hessian,
    quadratic convergence where Gauss-Newton converges linearly on residuals that do not vanish: noise, tissue).
    ``data``: the normalized magnitude of the model's voxels, or a CasADi symbol for it (one solver for several
    data: the outside level's updates)."""
    sym = tube.symbolic(model)
    c = sym.c
    scale = np.sqrt(model.voxel_volume)
    data_expr = data if isinstance(data, ca.MX) else ca.DM(data)
    residual = scale * (sym.predicted - data_expr)
    dc = c - ca.DM(reference)
    p_alpha = _sparse_dm(alpha_part)
    p_rest = _sparse_dm(penalty - alpha_part)
    f = ca.sumsqr(residual) + ca.dot(dc, ca.mtimes(p_alpha, dc)) + ca.dot(c, ca.mtimes(p_rest, c))
    slope = meas.heaviside_slope(sym.gap, model.gamma, model.heaviside)
    gn = tube._GaussNewton(model, scale)
    jac = tube._Jacobian(model, scale)
    hess = 2 * gn(slope) + 2 * _sparse_dm(penalty)
    kept: tuple = (sym.callbacks, gn, jac)
    if newton:
        curv = tube._Curvature(model)
        per_point = model.voxel_volume * sym.callbacks[2](sym.predicted - data_expr)
        d = per_point * ca.DM(model.weight) * meas.heaviside_curvature(sym.gap, model.gamma, model.heaviside)
        hess = hess + 2 * curv(d)
        kept = kept + (curv,)
    g = ca.mtimes(_sparse_dm(box_matrix), c)
    return GeometryNLP(model, c, f, g, residual, hess, jac(slope), penalty, reference, data, kept)


def _sparse_dm(m) -> ca.DM:
    csc = scipy.sparse.csc_matrix(m)
    csc.eliminate_zeros()
    csc.sort_indices()
    sp = ca.Sparsity(csc.shape[0], csc.shape[1], csc.indptr.tolist(), csc.indices.tolist())
    return ca.DM(sp, csc.data)


@dataclass
class Geometry3DResult:
    """The fitted wall and how it was found."""

    basis: tube.WallBasis
    coefficients: np.ndarray
    reference: np.ndarray  # c_ref (the equal-area circle along s)
    alpha: float
    kappa: float
    smoothing_mm: float
    gamma: float
    q: int
    levels: MagnitudeLevels
    stats: list  # SolverStats of the coarse and the final fit
    box_active: np.ndarray  # (n_s_box, n_phi_box) bool: a box row on its bound at the end
    box_s: np.ndarray
    box_phi: np.ndarray
    residual_norm: float  # sqrt(sum |V| (F - m)^2) over the fitted voxels, mm^1.5
    fitted_voxels: int
    points: int
    seconds: float
    options: dict = field(default_factory=dict)

    def radius(self, s, phi, ds: int = 0, dphi: int = 0) -> np.ndarray:
        return self.basis.evaluate(self.coefficients, s, phi, ds, dphi)

    @property
    def s_range(self) -> tuple[float, float]:
        return self.basis.spline.lo, self.basis.spline.hi


@dataclass
class GeometryProblem3D:
    """What the wall fit needs: the volume, the centreline (and its fast table), the fitted range, the voxels near
    the vessel with their coordinates, the normalized magnitude on them, the radius estimate and the levels."""

    vol: Any
    centerline: Any
    frame: tube.FrameTable
    s_range: tuple[float, float]
    coords: tube.VoxelCoordinates
    raw: np.ndarray  # time-mean magnitude on coords
    radius_estimate: Callable  # s -> R_est
    levels: MagnitudeLevels
    exclude: Callable | None = None  # (s, phi) -> bool: wall regions left out of the fit (branches)

    @property
    def magnitude(self) -> np.ndarray:
        """The normalized magnitude on ``coords`` with the current levels."""
        return self.levels.normalize(self.raw, self.coords.s)

    @property
    def h(self) -> float:
        return float(np.asarray(self.vol.voxel_size_mm).max())

    @property
    def half_diagonal(self) -> float:
        return 0.5 * float(np.linalg.norm(self.vol.voxel_size_mm))


def problem_from_mask(
    vol, centerline, mask, coords: tube.VoxelCoordinates, s_range, s_grid: np.ndarray, exclude=None
) -> GeometryProblem3D:
    """The wall fit's problem from a vessel mask: the mask's equal-area radius along ``s`` (:func:`radius_from_mask`
    on ``s_grid``, linearly interpolated) as the radius estimate, the magnitude levels along ``s``
    (:func:`magnitude_levels`) and the time-mean magnitude on ``coords``; ``s_range`` the part to fit,
    ``exclude(s, phi)`` wall regions left out (branches)."""
    r_mask = radius_from_mask(mask, vol, coords, s_grid)

    def radius_estimate(s):
        return np.interp(s, s_grid, r_mask)

    levels = magnitude_levels(vol, coords, radius_estimate, s_grid)
    raw = np.mean(np.asarray(vol.magnitude, float), axis=0)[tuple(coords.index.T)]
    frame = tube.FrameTable(centerline)
    return GeometryProblem3D(vol, centerline, frame, tuple(s_range), coords, raw, radius_estimate, levels, exclude)


def _box_samples(basis: tube.WallBasis, n_phi: int) -> tuple[np.ndarray, np.ndarray]:
    """Box rows at the knots and ``n_phi`` angles (between them ``R`` is a cubic in ``s`` and a trigonometric
    polynomial in ``phi`` whose excursions beyond the rows are far below the box's margin ``4 gamma``)."""
    return basis.spline.knots(), rad.uniform_angles(n_phi)


@dataclass
class _Stage:
    """The forward model of one stage (a box and a quadrature) and where its voxels sit in the problem's."""

    model: tube.TubeModel
    position: np.ndarray  # index into problem.coords of each model voxel
    lower: Callable
    upper: Callable
    q: int
    gamma: float
    solvers: dict = field(default_factory=dict)  # built IPOPT solvers (the data are a parameter), by tolerance


def _stage(problem: GeometryProblem3D, basis, options, q, gamma, lower, upper) -> _Stage:
    """The forward model with ``q`` points per axis on the voxels that can see walls in ``lower .. upper``."""
    reach = tube.REACH_WIDTHS * gamma + problem.half_diagonal
    co = problem.coords
    sel = (co.beyond == 0) & (co.s >= basis.spline.lo) & (co.s <= basis.spline.hi)
    sel &= (co.r >= lower(co.s, co.phi) - reach) & (co.r <= upper(co.s, co.phi) + reach)
    sub = tube.VoxelCoordinates(co.index[sel], co.world[sel], co.s[sel], co.r[sel], co.phi[sel], co.beyond[sel])
    keep = None
    if problem.exclude is not None:
        exclude = problem.exclude

        def keep(s, r, phi):
            return ~exclude(s, phi)

    model = tube.build_model(problem.vol, sub, problem.frame, basis, q, gamma, lower, upper, options.heaviside, keep)
    if model.n_voxels == 0:
        raise NoVesselError(f"{problem.vol.source}: no voxel sees the wall; nothing to fit")
    lookup = {tuple(v): i for i, v in enumerate(sub.index.tolist())}
    pos = np.flatnonzero(sel)[np.array([lookup[tuple(v)] for v in model.voxel_index.tolist()], dtype=np.int64)]
    return _Stage(model, pos, lower, upper, q, gamma)


def _solve(problem: GeometryProblem3D, stage: _Stage, options, x0, reference, alpha_part, penalty, box, what, tol):
    """One IPOPT solve of the wall fit on ``stage``'s model with its box."""
    basis, model = stage.model.basis, stage.model
    s_box, phi_box = box
    ss, pp = (v.ravel() for v in np.meshgrid(s_box, phi_box, indexing="ij"))
    lo, hi = stage.lower(ss, pp), stage.upper(ss, pp)
    data = problem.magnitude[stage.position]
    box_matrix = basis.design(ss, pp)
    warm = "lam_g" in stage.solvers  # a re-solve from the previous solution: the outside level's updates
    key = (tol, warm)
    if key not in stage.solvers:
        symbol = ca.MX.sym("m", model.n_voxels)
        nlp = build_nlp(model, symbol, penalty, reference, alpha_part, box_matrix, options.newton)
        extra = {"clip_inactive_lam": True, "ipopt.mu_strategy": "adaptive"}
        if warm:
            extra = {"clip_inactive_lam": True, **WARM_START}
        solver = gauss_newton_ipopt("vessel_geometry", nlp.c, nlp.f, nlp.g, nlp.hessian, symbol, tol,
                                    options.max_iter, extra)  # fmt: skip
        stage.solvers[key] = (solver, nlp)
    solver, _ = stage.solvers[key]
    start = {"lam_g0": stage.solvers["lam_g"]} if warm else {}
    sol, stats = run_nlpsol(solver, f"vessel geometry ({what}, IPOPT)", x0=x0, p=data, lbg=lo, ubg=hi, **start)
    stage.solvers["lam_g"] = np.asarray(sol["lam_g"]).ravel()
    c = np.asarray(sol["x"]).ravel()
    r = box_matrix @ c
    slack = 1e-6 * float(np.max(hi))
    active = (np.minimum(r - lo, hi - r) <= slack).reshape(s_box.size, phi_box.size)
    misfit = float(np.sqrt(np.sum(model.voxel_volume * (model.predict(c) - data) ** 2)))
    stats.extra.update({"voxels": model.n_voxels, "points": model.n_points, "q": stage.q, "gamma_mm": stage.gamma})
    log.info("%s: %d voxels, %d points, %s in %d iterations (%.1f s)", what, model.n_voxels, model.n_points,
             stats.status, stats.iterations, stats.seconds)  # fmt: skip
    return c, stats, active, misfit


def fit_wall(problem: GeometryProblem3D, options: Geometry3DOptions | None = None) -> Geometry3DResult:
    """Fit ``R(s, phi)`` to the normalized magnitude (module notes): the coarse fit in the wide box, then the
    final fit about it."""
    options = options or Geometry3DOptions()
    t0 = time.perf_counter()
    h = problem.h
    lo_s, hi_s = problem.s_range
    spline = tube.SplineBasis(lo_s, hi_s, options.knot_spacing_mm or h)
    basis = tube.WallBasis(spline, options.n_fourier)
    # reference radius: the normalized magnitude's equal-area circle along s
    s_grid = np.linspace(lo_s, hi_s, max(2 * spline.intervals + 1, 8))
    co = problem.coords
    r_est = problem.radius_estimate(co.s)
    voxel = abs(float(np.linalg.det(np.asarray(problem.vol.affine_mm, dtype=float)[:3, :3])))
    r_ref = reference_radius(problem.magnitude, co, r_est, s_grid, voxel, h)
    ref_spline = spline.fit(s_grid, r_ref, smoothing=h**3)
    reference = basis.constant(ref_spline)
    r_mean = float(np.mean(r_ref))
    smoothing = h if options.smoothing_mm is None else float(options.smoothing_mm)
    kappa = smoothing**4 * r_mean / h
    n_phi = options.n_box_phi or max(32, 4 * options.n_fourier)
    box = _box_samples(basis, n_phi)
    p_alpha = basis.penalty(options.alpha, 0.0, options.sobolev_s)
    penalty = basis.penalty(options.alpha, kappa, options.sobolev_s)

    def ref_radius(s, phi):
        return spline.evaluate(ref_spline, s)

    width = options.box_mm if options.box_mm is not None else max(2 * h, 0.25 * r_mean)

    def lower1(s, phi):
        r = ref_radius(s, phi)
        return np.maximum(r - width, 0.3 * r)

    def upper1(s, phi):
        return ref_radius(s, phi) + width

    q1 = int(options.coarse_order)
    coarse = _stage(problem, basis, options, q1, h / q1, lower1, upper1)
    c1, st1, _, _ = _solve(problem, coarse, options, reference, reference, p_alpha, penalty, box, "coarse",
                           options.coarse_tol)  # fmt: skip
    q = tube.auto_quad_order(options.quad_order, h, r_mean)
    gamma = h / q
    half = options.refine_mm if options.refine_mm is not None else 0.5 * h

    def lower2(s, phi):
        return np.maximum(basis.evaluate(c1, s, phi) - half, 0.3 * ref_radius(s, phi))

    def upper2(s, phi):
        return basis.evaluate(c1, s, phi) + half

    final = _stage(problem, basis, options, q, gamma, lower2, upper2)
    model = final.model
    c2, st2, active, misfit = _solve(problem, final, options, c1, reference, p_alpha, penalty, box, "final",
                                     options.tol)  # fmt: skip
    stats = [st1, st2]
    for k in range(options.outside_updates):
        change = update_outside(problem, final, c2)
        if change < OUTSIDE_TOL:
            break
        c2, st, active, misfit = _solve(problem, final, options, c2, reference, p_alpha, penalty, box,
                                        f"outside level {k + 1}", options.tol)  # fmt: skip
        st.extra["outside_change"] = change
        stats.append(st)
    return Geometry3DResult(
        basis=basis,
        coefficients=c2,
        reference=reference,
        alpha=options.alpha,
        kappa=kappa,
        smoothing_mm=smoothing,
        gamma=gamma,
        q=q,
        levels=problem.levels,
        stats=stats,
        box_active=active,
        box_s=box[0],
        box_phi=box[1],
        residual_norm=misfit,
        fitted_voxels=model.n_voxels,
        points=model.n_points,
        seconds=time.perf_counter() - t0,
        options=dict(vars(options)),
    )


def functional(problem: GeometryProblem3D, basis: tube.WallBasis, options: Geometry3DOptions, q: int, lower, upper,
               reference=None, kappa: float | None = None) -> tuple[ca.Function, ca.Function, GeometryNLP]:  # fmt: skip
    """For derivative tests: ``f(c) -> (J, grad J)`` (CasADi's reverse mode through the graph) and
    ``r(c) -> (residual, chain-rule Jacobian)`` of the wall fit's functional with ``q`` points per axis and the box
    ``lower .. upper``."""
    h = problem.h
    reference = np.zeros(basis.size) if reference is None else reference
    kappa = h**3 if kappa is None else kappa
    penalty = basis.penalty(options.alpha, kappa, options.sobolev_s)
    p_alpha = basis.penalty(options.alpha, 0.0, options.sobolev_s)
    stage = _stage(problem, basis, options, q, h / q, lower, upper)
    s_box, phi_box = _box_samples(basis, 16)
    ss, pp = (v.ravel() for v in np.meshgrid(s_box, phi_box, indexing="ij"))
    data = problem.magnitude[stage.position]
    nlp = build_nlp(stage.model, data, penalty, reference, p_alpha, basis.design(ss, pp), options.newton)
    f = ca.Function("J", [nlp.c], [nlp.f, ca.gradient(nlp.f, nlp.c)])
    r = ca.Function("r", [nlp.c], [nlp.residual, nlp.jacobian])
    return f, r, nlp


def stats_dicts(stats: list[SolverStats]) -> list[dict]:
    return [{"solver": s.solver, "status": s.status, "converged": s.converged, "iterations": s.iterations,
             "objective": s.objective, "seconds": s.seconds, **s.extra} for s in stats]  # fmt: skip
