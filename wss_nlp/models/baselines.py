"""Classical WSS estimators, implemented honestly, to compare the paper's method against.

Both start from the same threshold segmentation of the magnitude image and
report WSS at the same angles and in the same result format as the
reconstruction, so a study can put them side by side.

* ``oyre``: cubic polynomial fit of the velocity along inward wall normals
  (the near-wall profile method of Oyre et al. 1998, in the 2D form used by
  most later work).
* ``stalder``: smoothing tensor-product cubic B-spline fit of the velocity
  over the cross-section with zero-velocity points on the segmented contour,
  WSS from the spline gradient (Stalder et al. 2008).

Assumptions shared by both (docs, "Classical baselines")
-----------------------------------------------------------
* The wall is the 50 % iso-line of the normalized magnitude (bilinear
  interpolation between voxel centres, marching squares via ``contourpy``):
  the full-width-at-half-maximum segmentation of clinical tools. It is
  smoothed by a least-squares Fourier series ``R(phi)`` of ``n_fourier``
  harmonics about the lumen centre, which gives the wall normals.
* No-slip: the velocity is zero on that contour.
* Nothing models the voxel averaging; that is exactly what the paper's
  method adds, and why these estimators are biased at coarse resolution.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .._lazy import scipy
from . import preprocess as pp
from ..core import radius as rad
from ..errors import NoVesselError, SolverError
from .measurement import VoxelGrid
from .wss import WssResult

#: Methods provided here (``--method``).
METHODS = ("oyre", "stalder")


@dataclass(frozen=True)
class BaselineOptions:
    """Options of the classical estimators (stored in the result file).

    Attributes
    ----------
    n_fourier : int
        Harmonics of the Fourier series that smooths the segmented contour.
    oyre_range_fraction : float
        Oyre: the profile is sampled on ``(0, L]`` along the inward normal,
        ``L = oyre_range_fraction R_area`` (the outer half of the radius by
        default). A range of a few voxels instead leaves a bias that does
        not vanish as h -> 0: the partial-volume voxel at the wall then
        always carries the same weight in the fit (+8.8 % mean WSS on
        noise-free Poiseuille flow at h = 0.25 mm with ``L = 3h``; docs,
        "Classical baselines").
    oyre_spacing_voxels : float
        Oyre: spacing of the samples in voxels (at least ``oyre_degree + 3`` samples).
    oyre_degree : int
        Oyre: degree of the polynomial ``u(d) = sum_{k=1}^{deg} a_k d^k``
        (no constant term: no-slip at the contour).
    stalder_knot_voxels : float
        Stalder: knot spacing of the cubic B-splines in voxels.
    stalder_wall_spacing_voxels : float
        Stalder: spacing of the zero-velocity points on the contour in voxels.
    """

    n_fourier: int = 8
    oyre_range_fraction: float = 0.5
    oyre_spacing_voxels: float = 0.5
    oyre_degree: int = 3
    stalder_knot_voxels: float = 2.0
    stalder_wall_spacing_voxels: float = 0.5

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class SolveStats:
    """Enough of :class:`wss_nlp.core.solver.SolveStats`'s interface for reports (baselines solve in closed form)."""

    solver: str
    status: str = "closed form"
    converged: bool = True


@dataclass
class ContourGeometry:
    """The segmented wall as ``R(phi)`` about ``center`` (same coefficient layout as the reconstruction)."""

    center: tuple[float, float]
    coefficients: np.ndarray
    threshold: float = 0.5
    alpha: float = float("nan")
    box: tuple[float, float] = (float("nan"), float("nan"))
    box_active: bool = False
    gamma: float = float("nan")

    def radius(self, phi, derivative: int = 0) -> np.ndarray:
        return rad.evaluate(self.coefficients, phi, derivative)

    def inside(self, grid: VoxelGrid) -> np.ndarray:
        """Voxels whose centre lies inside the contour, ``(ny, nx)`` bool."""
        xc, yc = grid.centers()
        r = np.hypot(xc - self.center[0], yc - self.center[1])
        p = np.mod(np.arctan2(yc - self.center[1], xc - self.center[0]), 2 * np.pi)
        return r < self.radius(p.ravel()).reshape(p.shape)

    def wall(self, phi) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Wall points ``(x, y)`` and outward unit normals ``(nx, ny)`` at the angles ``phi``."""
        r, dr = self.radius(phi), self.radius(phi, 1)
        c, s = np.cos(phi), np.sin(phi)
        x, y = self.center[0] + r * c, self.center[1] + r * s
        tx, ty = dr * c - r * s, dr * s + r * c  # d(wall)/dphi, counter-clockwise
        norm = np.hypot(tx, ty)
        return x, y, ty / norm, -tx / norm


@dataclass
class BaselineResult:
    """Result of a classical estimator on one slice (written in the same format as a reconstruction)."""

    index: int
    method: str
    geometry: ContourGeometry
    wss: WssResult
    normalization: pp.Normalization
    lumen: pp.Lumen
    grid: VoxelGrid
    magnitude: np.ndarray
    velocity_image: np.ndarray
    seconds: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)  # fit details (ranges, knots, smoothing, GCV)
    notes: list = field(default_factory=list)
    screen: dict = field(default_factory=dict)  # what wss_nlp.pipeline.plausibility found (vessels, aliasing)

    converged = True  # closed-form fits; failures raise instead

    @property
    def warnings(self) -> list[str]:
        return [f"slice {self.index}: {n}" for n in self.notes]


def segment(m: np.ndarray, grid: VoxelGrid, lumen: pp.Lumen, n_fourier: int, source: str = "") -> ContourGeometry:
    """The 50 % iso-contour of the normalized magnitude around the lumen, as a Fourier radius.

    Raises :class:`NoVesselError` when no closed contour encloses the lumen centre.
    """
    import contourpy

    xc, yc = grid.centers()
    lines = contourpy.contour_generator(xc, yc, m, line_type="Separate").lines(0.5)
    cx, cy = lumen.center
    best: tuple[float, np.ndarray] | None = None
    for pts in map(np.asarray, lines):
        if len(pts) < 8 or not np.allclose(pts[0], pts[-1]):
            continue  # open lines end at the image border
        ang = np.unwrap(np.arctan2(pts[:, 1] - cy, pts[:, 0] - cx))
        if abs(abs(ang[-1] - ang[0]) - 2 * np.pi) > 1e-6:
            continue  # closed but not around the centre (a noise island)
        area = 0.5 * abs(np.dot(pts[:-1, 0], pts[1:, 1]) - np.dot(pts[1:, 0], pts[:-1, 1]))
        if best is None or area > best[0]:
            best = (area, pts)
    if best is None:
        raise NoVesselError(
            f"{pp.where_prefix(source)}no closed 50 % magnitude contour around the lumen centre "
            f"({cx:.3g}, {cy:.3g}) mm; the threshold segmentation of the baselines needs one"
        )
    pts = best[1][:-1]
    phi = np.mod(np.arctan2(pts[:, 1] - cy, pts[:, 0] - cx), 2 * np.pi)
    r = np.hypot(pts[:, 0] - cx, pts[:, 1] - cy)
    n = min(n_fourier, (len(pts) - 1) // 2)
    return ContourGeometry(center=(float(cx), float(cy)), coefficients=rad.fit(phi, r, n))


def _interpolate(image: np.ndarray, grid: VoxelGrid, x, y) -> np.ndarray:
    """Bilinear interpolation of an image at physical points (mm)."""
    ix = (np.asarray(x) - grid.origin_mm[0]) / grid.dx
    iy = (np.asarray(y) - grid.origin_mm[1]) / grid.dy
    return scipy.ndimage.map_coordinates(image, [iy.ravel(), ix.ravel()], order=1, mode="nearest").reshape(np.shape(x))


def oyre_wss(
    geom: ContourGeometry,
    velocity: np.ndarray,
    grid: VoxelGrid,
    r_area: float,
    phi: np.ndarray,
    viscosity_pa_s: float,
    options: BaselineOptions,
):
    """Wall shear stress from polynomial fits of the near-wall profile along inward normals.

    Notes
    -----
    At each wall point ``w`` with outward normal ``n`` the velocity image is
    interpolated bilinearly at ``w - d_j n``, ``d_j = j L / J``, and
    ``u(d) = sum_{k=1}^{K} a_k d^k`` is fitted by least squares; then
    ``tau = -mu du/dn = mu a_1`` (Pa, with ``d`` in mm and a factor 1000).
    """
    length = options.oyre_range_fraction * r_area
    n_samples = max(int(round(length / (options.oyre_spacing_voxels * grid.h))), options.oyre_degree + 3)
    d = length * np.arange(1, n_samples + 1) / n_samples
    x, y, nx, ny = geom.wall(phi)
    # outside the segmentation the phase is noise; no-slip says zero there (as clinical tools mask it)
    velocity = np.where(geom.inside(grid), velocity, 0.0)
    u = _interpolate(velocity, grid, x[:, None] - d[None, :] * nx[:, None], y[:, None] - d[None, :] * ny[:, None])
    design = d[:, None] ** np.arange(1, options.oyre_degree + 1)[None, :]
    coef, *_ = np.linalg.lstsq(design, u.T, rcond=None)
    tau = viscosity_pa_s * 1000.0 * coef[0]
    return tau, {"fit_range_mm": float(length), "samples": int(n_samples), "degree": int(options.oyre_degree)}


def _bspline_basis(t: np.ndarray, x: np.ndarray, nu: int = 0) -> np.ndarray:
    n = len(t) - 4
    import scipy.interpolate  # here: a slow import the command line should not pay at start-up

    return scipy.interpolate.BSpline(t, np.eye(n), 3, extrapolate=False)(x, nu=nu)


def _knots(lo: float, hi: float, spacing: float) -> np.ndarray:
    n = max(int(np.ceil((hi - lo) / spacing)), 1)
    inner = np.linspace(lo, hi, n + 1)
    return np.concatenate([[lo] * 3, inner, [hi] * 3])


def _second_difference(n: int) -> np.ndarray:
    return np.diff(np.eye(n), 2, axis=0)


def stalder_wss(
    geom: ContourGeometry,
    velocity: np.ndarray,
    grid: VoxelGrid,
    phi: np.ndarray,
    viscosity_pa_s: float,
    options: BaselineOptions,
):
    """Wall shear stress from a smoothing B-spline fit of the velocity over the cross-section.

    Notes
    -----
    Data: the velocity at every voxel centre inside the contour and ``u = 0``
    at contour points spaced ``stalder_wall_spacing_voxels h``. Model: cubic
    tensor B-splines ``s(x, y) = sum c_kl B_k(x) B_l(y)`` with knot spacing
    ``stalder_knot_voxels h``, fitted by
    ``min ||B c - u||^2 + lambda (||D_x c||^2 + ||D_y c||^2)`` (second
    differences of the coefficients along x and y: a P-spline), ``lambda``
    minimizing generalized cross-validation ``n RSS / (n - tr H)^2`` on a
    log grid. Then ``tau = -mu grad s . n`` at the contour.
    """
    xc, yc = grid.centers()
    inside = geom.inside(grid)
    rmax = float(np.max(geom.radius(rad.uniform_angles(720))))
    ox, oy, _, _ = geom.wall(np.linspace(0, 2 * np.pi, 721))
    perimeter = float(np.sum(np.hypot(np.diff(ox), np.diff(oy))))
    n_wall = max(int(np.ceil(perimeter / (options.stalder_wall_spacing_voxels * grid.h))), 16)
    wx, wy, _, _ = geom.wall(rad.uniform_angles(n_wall))
    px = np.concatenate([xc[inside], wx])
    py = np.concatenate([yc[inside], wy])
    u = np.concatenate([velocity[inside], np.zeros(n_wall)])
    spacing = options.stalder_knot_voxels * grid.h
    pad = 2 * grid.h
    tx = _knots(geom.center[0] - rmax - pad, geom.center[0] + rmax + pad, spacing)
    ty = _knots(geom.center[1] - rmax - pad, geom.center[1] + rmax + pad, spacing)
    bx, by = _bspline_basis(tx, px), _bspline_basis(ty, py)
    design = (by[:, :, None] * bx[:, None, :]).reshape(len(u), -1)  # row-wise Kronecker, x fastest
    nbx, nby = bx.shape[1], by.shape[1]
    dx, dy = _second_difference(nbx), _second_difference(nby)
    penalty = np.kron(np.eye(nby), dx.T @ dx) + np.kron(dy.T @ dy, np.eye(nbx))
    gram = design.T @ design
    # Demmler-Reinsch form: with M = G + s P = L L^T (well conditioned: the penalty's null space, bilinear
    # functions, is seen by the data) and L^-1 G L^-T = U diag(mu) U^T, every lambda costs one product:
    # G + lambda P = L U diag(mu + (lambda / s)(1 - mu)) U^T L^T.
    scale = np.trace(gram) / max(np.trace(penalty), 1e-300)
    chol = scipy.linalg.cholesky(gram + scale * penalty, lower=True)
    li = scipy.linalg.solve_triangular(chol, np.eye(len(gram)), lower=True)
    mu, q = np.linalg.eigh(li @ gram @ li.T)
    mu = np.clip(mu, 0.0, 1.0)
    proj = q.T @ (li @ (design.T @ u))
    back = li.T @ q
    ratios = np.logspace(-9, 3, 49)  # lambda / s
    n = len(u)
    gcv = []
    for t in ratios:
        d = mu + t * (1 - mu)
        c = back @ (proj / d)
        rss = float(np.sum((design @ c - u) ** 2))
        dof = float(np.sum(mu / d))
        gcv.append(n * rss / max(n - dof, 1e-9) ** 2)
    i = int(np.argmin(gcv))
    coef = (back @ (proj / (mu + ratios[i] * (1 - mu)))).reshape(nby, nbx)
    x, y, nxx, nyy = geom.wall(phi)
    bxw, byw = _bspline_basis(tx, x), _bspline_basis(ty, y)
    dsdx = np.einsum("il,lk,ik->i", byw, coef, _bspline_basis(tx, x, 1))
    dsdy = np.einsum("il,lk,ik->i", _bspline_basis(ty, y, 1), coef, bxw)
    tau = -viscosity_pa_s * 1000.0 * (dsdx * nxx + dsdy * nyy)
    info = {
        "knot_spacing_mm": float(spacing),
        "n_coefficients": int(nbx * nby),
        "n_voxels": int(inside.sum()),
        "n_wall_points": int(n_wall),
        "lambda": float(ratios[i] * scale),
        "lambda_relative": float(ratios[i]),
        "gcv_at_grid_edge": bool(i in (0, len(ratios) - 1)),
    }
    return tau, info


def reconstruct_slice(
    magnitude: np.ndarray,
    velocity_image: np.ndarray,
    grid: VoxelGrid,
    viscosity_pa_s: float,
    method: str,
    options: BaselineOptions,
    n_phi: int = 360,
    source: str = "<memory>",
    index: int = 0,
    vessel=None,
) -> BaselineResult:
    """Segment the wall and estimate WSS with a classical method (``"oyre"`` or ``"stalder"``)."""
    where = f"{source} slice {index}"
    t = {}
    t0 = time.perf_counter()
    norm, m, lumen = pp.preprocess(magnitude, grid, where, vessel)
    geom = segment(m, grid, lumen, options.n_fourier, where)
    t["segmentation"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    phi = rad.uniform_angles(n_phi)
    velocity_image = np.asarray(velocity_image, dtype=float)
    if method == "oyre":
        tau, info = oyre_wss(geom, velocity_image, grid, lumen.r_area, phi, viscosity_pa_s, options)
    elif method == "stalder":
        tau, info = stalder_wss(geom, velocity_image, grid, phi, viscosity_pa_s, options)
    else:
        raise ValueError(f"unknown baseline {method!r}; choose from {METHODS}")
    t["wss"] = time.perf_counter() - t0
    if not np.all(np.isfinite(tau)):
        raise SolverError(f"{where}: {method} baseline gave non-finite wall shear stress")
    x, y, _, _ = geom.wall(phi)
    mean = rad.arc_length_mean(tau, geom.radius(phi), geom.radius(phi, 1))
    w = WssResult(phi=phi, tau=tau, mean=mean, wall_x=x, wall_y=y, viscosity_pa_s=viscosity_pa_s)
    notes = []
    if info.get("gcv_at_grid_edge"):
        notes.append(f"{method}: the GCV smoothing parameter is at the edge of its grid ({info['lambda']:.3g})")
    return BaselineResult(index, method, geom, w, norm, lumen, grid, m, velocity_image, t, info, notes)
