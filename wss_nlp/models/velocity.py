"""Velocity approximation on the reference disk (Sec. 3, Remark 3.5, Sec. 7.2).

Given the lumen ``Omega_R = phi_R(B)``, find ``v = sum_j c_j v_j`` in a basis
vanishing on the wall minimizing

    (1/|Omega|) sum_i |V_i cap Omega| (T_i c - u_i)^2 + (beta/pi) ||Delta v||^2_{L^2(B)},

where ``T_i c`` is the mean of ``v o phi_R^{-1}`` over ``V_i cap Omega``
(the operator ``T~_h`` of Sec. 7.2) and ``i`` runs over the voxels that meet
the lumen. The residual is measured in the physical domain (Remark 3.5).
Dividing the misfit by the lumen area and the penalty by ``|B| = pi`` makes
``beta`` dimensionless and independent of vessel size and voxel size; the
paper's parameter is ``beta_paper = beta |Omega| / pi`` for a misfit in mm^2.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any
from functools import cached_property

import numpy as np

import casadi as ca

from . import acquisition as acq_model
from .acquisition import MIN_KSPACE_SIGNAL  # noqa: F401 (its home before the measurement models)
from . import kspace
from . import measurement as meas
from . import near_wall as nw
from ..core import radius as rad
from ..errors import InputError, SolverError
from ..core.mapping import DiskMap
from ..core.schema import option
from ..core.solver import SolverStats, ipopt_options, run_nlpsol
from ..core.tikhonov import LinearTikhonov
from ..core.velocity_basis import BASES, make_basis


@dataclass(frozen=True)
class VelocityOptions:
    """Options of the velocity step.

    Attributes
    ----------
    basis : {"zernike", "eigen"}
        ``(1 - |xi|^2)`` times Zernike polynomials up to ``degree`` (default),
        or the paper's Dirichlet eigenfunctions with eigenvalue <= ``max_eigenvalue``.
    degree : int
        Zernike degree: highest polynomial degree in the reference disk.
    angular_order : int or None
        Highest angular order |m| of the Zernike functions (None: ``degree``);
        a high degree with a low angular order resolves thin wall layers
        without the quadratic growth of the full set.
    max_eigenvalue : float
        Eigenvalue cut-off M of the eigenfunction basis.
    beta : float
        Regularization parameter (dimensionless, see module notes).
    laplacian_power : {1, 2}
        ``t`` in the penalty ``beta ||Delta^t v||^2``: 1 is eq. (tik2); 2 is
        Remark 3.5's stronger norm, which does not penalize a Poiseuille
        profile (``Delta^2 (1 - |xi|^2) = 0``) and so does not pull the wall
        gradient down the way ``||Delta v||^2`` does.
    eta : float
        Exponent of the map phi_R (>= 2).
    inner_radius : float or None
        ``r_in`` of phi_R in mm; None means ``inner_fraction * min R``.
    inner_fraction : float
        Used when ``inner_radius`` is None. 1 makes phi_R a pure scaling for
        a circular lumen; smaller values make the map closer to the radial
        stretch ``R(t) rho^eta`` near the wall, under which Poiseuille flow in
        an elliptic or star-shaped pipe becomes nearly polynomial.

    Notes
    -----
    Defaults come from a sweep over bases, penalties, ``r_in`` and beta on
    four laminar-type phantoms (ellipse, circle, Fourier lumen, three-lobed
    polynomial flow) and the turbulent one at h = 0.3-1.5 mm, SNR 25
    (docs, "How the defaults were chosen"): the Zernike basis with
    ``||Delta^2 v||^2`` had the smallest worst-case laminar WSS error; the
    eigenfunction basis with ``||Delta v||^2`` was 3-10x worse (Remark 3.4).
    quad_order : int or None
        Sub-voxel points per axis for ``T~_h`` and ``|V_i cap Omega|``; None
        chooses from h and the vessel size (:func:`wss_nlp.models.measurement.auto_quad_order`).
    solver : {"cholesky", "ipopt"}
        A direct Cholesky solve of the normal equations (default), or the
        CasADi/IPOPT solve of the symbolic functional (:func:`build_tikhonov`).
    """

    schema_group = "velocity (Sec. 3, 7.2)"

    basis: str = option(
        "zernike",
        "(1-|xi|^2) x Zernike polynomials, or the paper's Dirichlet eigenfunctions",
        cli="--basis",
        toml=("basis",),
        choices=BASES,
    )
    degree: int = option(20, "Zernike degree", cli="--degree", toml=("degree",))
    angular_order: int | None = option(
        6, "highest angular order |m| of the Zernike functions", cli="--angular-order", toml=("angular_order",)
    )
    max_eigenvalue: float = option(
        400.0, "eigenvalue cut-off M of the eigenfunction basis", cli="--max-eigenvalue", toml=("max_eigenvalue",)
    )
    beta: float = 5e-8  # on the command line and in studies through --beta (ReconstructionOptions.choice.beta_rule)
    laplacian_power: int = option(
        2,
        "t in ||Delta^t v||^2: 1 = eq. (tik2), 2 = Remark 3.5",
        cli="--laplacian-power",
        toml=("laplacian_power",),
        choices=(1, 2),
    )
    eta: float = option(2.0, "exponent of the map phi_R, >= 2", cli="--eta", toml=("eta",))
    inner_radius: float | None = None
    inner_fraction: float = option(
        0.5, "inner radius of phi_R as a fraction of min R", cli="--inner-fraction", toml=("inner_fraction",)
    )
    quad_order: int | None = None  # set with the geometry's (--quad-order)
    # the functional is quadratic: a Cholesky factorization of its normal equations is its exact minimizer (the
    # same coefficients as IPOPT on the CasADi form to 1e-15, 10-25 % faster per slice); IPOPT stays as the
    # cross-check (tests/test_velocity.py)
    solver: str = option(
        "cholesky",
        "direct Cholesky solve of the normal equations, or CasADi/IPOPT on the symbolic functional",
        cli="--velocity-solver",
        choices=("ipopt", "cholesky"),
    )

    near_wall: str = option(
        "auto",
        "wall-layer columns for layers thinner than a voxel: off, auto (plain or a family, chosen by BIC), "
        "or one family (wall_law: Reichardt's law of the wall; low_re: the law of the wall with a Re_tau-dependent "
        "buffer layer, auto's turbulent family; exponential: laminar layers)",
        cli="--near-wall",
        toml=("near_wall",),
        choices=nw.MODES,
    )
    layer_scale_mm: float | None = option(
        None,
        "fix the layer scale l in mm (with a --near-wall family; default: chosen from the data)",
        cli="--layer-scale",
        toml=("layer_scale",),
    )

    def __post_init__(self):
        if self.near_wall not in nw.MODES:
            raise InputError(f"near-wall model must be one of {', '.join(nw.MODES)}, got {self.near_wall!r}")
        if self.layer_scale_mm is not None and not (self.layer_scale_mm > 0 and self.near_wall in nw.FAMILIES):
            raise InputError(
                f"--layer-scale {self.layer_scale_mm:g} needs a positive scale and a --near-wall family "
                f"({', '.join(nw.FAMILIES)})"
            )
        if self.basis not in BASES:
            raise InputError(f"velocity basis must be one of {BASES}, got {self.basis!r}")
        if not self.beta > 0:
            raise InputError(f"beta must be > 0, got {self.beta}")
        if self.laplacian_power not in (1, 2):
            raise InputError(f"laplacian_power must be 1 or 2, got {self.laplacian_power}")
        if self.solver not in ("ipopt", "cholesky"):
            raise InputError(f"velocity solver must be 'ipopt' or 'cholesky', got {self.solver!r}")
        if not 0 < self.inner_fraction <= 1:
            raise InputError(f"inner_fraction must lie in (0, 1], got {self.inner_fraction}")

    def make_basis(self):
        return make_basis(self.basis, self.degree, self.max_eigenvalue, self.angular_order)

    def make_map(self, coefficients, center) -> DiskMap:
        rmin = float(np.min(rad.evaluate(coefficients, rad.uniform_angles(720))))
        r_in = self.inner_radius if self.inner_radius is not None else self.inner_fraction * rmin
        return DiskMap(np.asarray(coefficients, dtype=float), tuple(center), float(r_in), self.eta)


@dataclass
class VelocityProblem:
    """The assembled linear least-squares problem."""

    operator: np.ndarray  # (n_vox, n_basis): T~_h
    weights: np.ndarray  # (n_vox,) |V_i cap Omega| in mm^2
    data: np.ndarray  # (n_vox,) measured velocity in m/s
    data_image: np.ndarray  # (ny, nx) the whole measured velocity image
    gram: np.ndarray  # (n_basis, n_basis) Laplacian Gram matrix on B
    voxels: meas.LumenVoxels
    disk_map: DiskMap
    basis: Any  # a basis of wss_nlp.core.velocity_basis (or wss_nlp.models.near_wall.EnrichedBasis)
    cell_mm: tuple | None = None  # (dx, dy) of one quadrature cell (the near-wall layer integrates across it)
    averager: Any = (
        None  # k-space acquisition: the PSF image of point values (wss_nlp.models.kspace.Averager); None: box
    )
    noise_correlation: Any = None  # k-space: the voxels' noise correlation (wss_nlp.models.kspace.NoiseCorrelation)

    @property
    def area(self) -> float:
        return float(np.sum(self.weights))

    def residual_norm(self, coefficients) -> float:
        """``sqrt(sum_i |V_i cap Omega| (T_i c - u_i)^2 / |Omega|)`` in m/s, the misfit compared with epsilon."""
        return float(np.sqrt(np.sum(self.weights * (self.operator @ coefficients - self.data) ** 2) / self.area))

    @cached_property
    def tikhonov(self) -> LinearTikhonov:
        """The problem's normal equations and parameter grids (:class:`wss_nlp.core.tikhonov.LinearTikhonov`)."""
        return LinearTikhonov(self.operator, self.weights, self.data, self.gram)

    @cached_property
    def ipopt(self) -> ca.Function:
        """The functional's IPOPT solver, beta its parameter (:func:`ipopt_solver`; built on first use)."""
        return ipopt_solver(self)

    def with_layer(self, basis, columns: np.ndarray, laplacian_power: int) -> VelocityProblem:
        """The problem in an enriched basis (:class:`~.near_wall.EnrichedBasis`) whose extra voxel means are
        ``columns``: the same voxels, data and map, no re-assembly."""
        operator = np.hstack([self.operator[:, : basis.base.size], columns])
        gram = basis.laplacian_gram(laplacian_power)
        enriched = replace(self, operator=operator, gram=gram, basis=basis)
        if "tikhonov" in self.__dict__ and self.operator.shape[1] == basis.base.size:
            # the plain normal matrix is formed: border it with the layer's columns instead of forming it again
            enriched.__dict__["tikhonov"] = self.tikhonov.bordered(operator, self.weights, gram)
        return enriched

    def normal_equations(self, beta: float) -> tuple[np.ndarray, np.ndarray]:
        """``H c = g`` with ``H = T^T W T / A + beta G / pi``, ``g = T^T W u / A``."""
        return self.tikhonov.hessian(beta), self.tikhonov.rhs


@dataclass
class VelocityResult:
    coefficients: np.ndarray
    beta: float
    residual_norm: float  # sqrt(sum_i |V_i cap Omega| (T_i c - u_i)^2 / |Omega|), m/s
    penalty: float  # ||Delta v||^2_{L^2(B)} / pi
    stats: SolverStats
    disk_map: DiskMap
    basis: Any  # a basis of wss_nlp.core.velocity_basis
    fitted: np.ndarray  # T~_h c on the lumen voxels
    voxel_index: np.ndarray
    voxel_fraction: np.ndarray
    options: dict = field(default_factory=dict)
    dof: float = float("nan")  # the fit's effective parameters tr(H_beta^-1 K) (the smoother's trace)

    def evaluate_physical(self, x, y) -> np.ndarray:
        """Reconstructed velocity ``u = v o phi_R^{-1}`` at physical points (0 outside)."""
        rho, t = self.disk_map.inverse(x, y)
        inside = np.ravel(rho < 1)
        out = np.zeros(np.size(rho))
        if inside.any():
            xi, yi = (
                np.ravel(rho)[inside] * np.cos(np.ravel(t)[inside]),
                np.ravel(rho)[inside] * np.sin(np.ravel(t)[inside]),
            )
            # the coefficients through the small transform first: one matrix-vector product at the points
            out[inside] = self.basis.evaluate_raw(xi, yi) @ (self.basis.transform @ self.coefficients)
        return out.reshape(np.shape(rho))


def assemble(
    grid: meas.VoxelGrid,
    velocity_image: np.ndarray,
    coefficients,
    center,
    options: VelocityOptions,
    basis=None,
    psf: kspace.PSF | None = None,
) -> VelocityProblem:
    """Assemble ``T~_h``, the partial volumes and the data on the voxels meeting the lumen.

    Notes
    -----
    ``T~_h(v)_i = (1/|V_i cap Omega|) int_{V_i cap Omega} v(phi_R^{-1}(x)) dx``
    by the midpoint rule on the sub-voxel points inside the lumen.

    With a k-space ``psf`` the voxel phase is, to first order in the phase
    variation, the signal-weighted mean ``T_i v = (K * chi v)_i / (K * chi)_i``
    (:class:`wss_nlp.models.kspace.Averager`; ``K`` the PSF, ``chi`` the lumen) and
    the weight ``|V_i| (K * chi)_i`` replaces ``|V_i cap Omega|`` (the same
    formulas with the box PSF). Voxels whose modeled signal
    ``(K * chi)_i`` is below :data:`MIN_KSPACE_SIGNAL` carry no reliable
    phase and are left out.
    """
    basis = options.make_basis() if basis is None else basis
    disk_map = options.make_map(coefficients, center)
    q = meas.auto_quad_order(options.quad_order, grid, float(np.asarray(coefficients)[0]))
    vox = meas.lumen_voxels(grid, center, coefficients, q)
    if vox.index.size == 0:  # more functions than voxels is fine: beta > 0 keeps the problem well-posed
        raise InputError("no voxel meets the reconstructed lumen; the geometry step failed to find a vessel")
    px, py = vox.px[vox.inside], vox.py[vox.inside]
    rho, t = disk_map.inverse(px, py)
    rho = np.minimum(rho, 1.0)
    model = acq_model.of(psf)
    operator, weights, averager = model.velocity_operator(grid, vox, basis, rho, t, q)
    return VelocityProblem(
        operator=operator,
        weights=weights,
        data=np.asarray(velocity_image, dtype=float).ravel()[vox.index],
        data_image=np.asarray(velocity_image, dtype=float),
        gram=basis.laplacian_gram(options.laplacian_power),
        voxels=vox,
        disk_map=disk_map,
        basis=basis,
        cell_mm=(grid.dx / q, grid.dy / q),
        averager=averager,
        noise_correlation=model.noise_correlation(grid.shape, vox.index),
    )


def voxel_values(problem: VelocityProblem, point_values: np.ndarray) -> np.ndarray:
    """Voxel values of functions given at the problem's inside sub-voxel points, as its operator forms them.

    ``point_values`` has shape ``(n_inside_points, m)`` (the points ``voxels.px[voxels.inside]``); the
    result ``(n_vox, m)`` holds the box means, or with a k-space acquisition ``(K chi f)_i / (K chi)_i``
    on the voxels the fit keeps (0 elsewhere), exactly as :func:`assemble` forms ``T~_h``.
    """
    vox = problem.voxels
    values = np.asarray(point_values, dtype=float)
    if problem.averager is None:
        return np.asarray(vox.mean_matrix() @ values)
    full = np.zeros(vox.inside.shape + (values.shape[1],))
    full[vox.inside] = values
    signal = problem.averager(vox.inside.astype(float))
    keep = problem.weights > 0
    return np.where(keep[:, None], problem.averager(full) / np.where(keep, signal, 1.0)[:, None], 0.0)


def build_tikhonov(problem: VelocityProblem):
    """CasADi expression of the velocity functional; returns ``(c, beta, f)``, beta a symbol.

    Notes
    -----
    The misfit ``|W^{1/2}(T c - u)|^2 / A`` is expanded exactly as
    ``c^T (T^T W T) c / A - 2 c^T T^T W u / A + u^T W u / A`` so the graph
    holds ``n_basis^2`` numbers instead of the ``n_voxels x n_basis``
    operator; the value is the same functional, eq. (tik2):
    ``f = c^T K c - 2 g^T c + u^T W u / A + (beta / pi) c^T G c``.
    beta is a parameter of the graph, as alpha is of the geometry's, so one
    built solver serves every beta (:attr:`VelocityProblem.ipopt`).
    """
    c = ca.MX.sym("c", problem.operator.shape[1])  # MX: matrix products stay single nodes
    beta = ca.MX.sym("beta")
    tk = problem.tikhonov
    const = float(problem.data @ (problem.weights * problem.data) / problem.area)
    f = ca.dot(c, ca.mtimes(ca.DM(tk.normal), c)) - 2 * ca.dot(ca.DM(tk.rhs), c) + const
    f = f + beta / np.pi * ca.dot(c, ca.mtimes(ca.DM(problem.gram), c))
    return c, beta, f


def ipopt_solver(problem: VelocityProblem) -> ca.Function:
    """The IPOPT solver of :func:`build_tikhonov` with beta as its parameter ``p`` (built once per problem)."""
    c, beta, f = build_tikhonov(problem)
    opts = ipopt_options(1e-12, 50, {"ipopt.hessian_constant": "yes"})
    return ca.nlpsol("velocity", "ipopt", {"x": c, "p": beta, "f": f}, opts)


def solve_cholesky(problem: VelocityProblem, beta: float) -> np.ndarray:
    """Direct solve of the normal equations by Cholesky factorization."""
    return problem.tikhonov.solve(beta)


def solve(problem: VelocityProblem, options: VelocityOptions, beta: float | None = None) -> VelocityResult:
    """Solve the velocity Tikhonov problem (CasADi/IPOPT or Cholesky)."""
    import time

    beta = options.beta if beta is None else beta
    if options.solver == "ipopt":
        x0 = np.zeros(problem.operator.shape[1])
        sol, stats = run_nlpsol(problem.ipopt, "velocity (IPOPT)", x0=x0, p=float(beta))
        coef = np.asarray(sol["x"]).ravel()
    else:
        t0 = time.perf_counter()
        coef = solve_cholesky(problem, beta)
        obj = problem.residual_norm(coef) ** 2 + beta / np.pi * float(coef @ problem.gram @ coef)
        stats = SolverStats("cholesky", "Solve_Succeeded", True, 1, obj, time.perf_counter() - t0)
    return result(problem, options, coef, beta, stats)


def result(problem: VelocityProblem, options: VelocityOptions, coef, beta: float, stats: SolverStats) -> VelocityResult:
    """VelocityResult of coefficients ``coef`` on the assembled ``problem``."""
    return VelocityResult(
        coefficients=coef,
        beta=beta,
        residual_norm=problem.residual_norm(coef),
        penalty=float(coef @ problem.gram @ coef / np.pi),
        stats=stats,
        disk_map=problem.disk_map,
        basis=problem.basis,
        fitted=problem.operator @ coef,
        voxel_index=problem.voxels.index,
        voxel_fraction=problem.voxels.fraction,
        options=dict(vars(options)),
        dof=effective_parameters(problem, beta),
    )


def effective_parameters(problem: VelocityProblem, beta: float) -> float:
    """``tr(H_beta^-1 K)``: how many parameters the fit at ``beta`` spends on the data (NaN if H is singular).

    Near the number of voxels the fit interpolates the noise (:attr:`wss_nlp.pipeline.results.SliceResult.warnings`).
    """
    if not beta > 0:
        return float("nan")
    try:  # the beta rules have usually built the pencil this needs already
        return float(problem.tikhonov.traces([beta])[0])
    except SolverError:
        return float("nan")
