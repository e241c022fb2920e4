"""Geometry identification: Tikhonov regularization of F_{gamma,h}(R) = m (Sec. 2, 7.1).

The functional (paper eq. (tik1), discretized as in Sec. 7.1)

    J(c) = ||F_{gamma,h}(R_c) - m||^2_{L^2(D)} + alpha ||R_c - R_ref||^2_{H^s}

is written symbolically in CasADi and minimized over V_N subject to the box
``r0 <= R(phi_j) <= r1`` at ``n_box`` uniform angles, either by IPOPT
(:func:`solve_ipopt`) or by the paper's projected Gauss-Newton iteration
(:func:`solve_projected_gauss_newton`), which serves as an independent
cross-check.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

import casadi as ca

from .._lazy import scipy
from . import acquisition as acq_model
from . import kspace
from . import measurement as meas
from ..core import operators
from ..core import radius as rad
from ..errors import InputError, SolverError
from ..core.schema import option
from ..core.solver import SolverStats, gauss_newton_ipopt, ipopt_options, run_nlpsol


#: The geometry solver's Hessians (:attr:`GeometryOptions.hessian`).
HESSIANS = ("newton", "gauss-newton", "exact", "limited-memory")


@dataclass(frozen=True)
class GeometryOptions:
    """Options of the geometry step.

    Attributes
    ----------
    n_fourier : int
        Highest harmonic N of the radius space V_N.
    alpha : float
        Regularization parameter (dimensionless: misfit and penalty are both
        in mm^2).
    sobolev_s : int
        Order s of the H^s penalty (the paper uses s = 2).
    prior : {"area", "zero"}
        Reference radius in the penalty. "zero" is eq. (tik1) literally,
        ``alpha ||R||^2``, which shrinks the mean radius by about
        ``alpha h``; "area" penalizes ``R - R_ref`` with ``R_ref`` the
        equal-area radius of the normalized magnitude (a constant), the
        standard Tikhonov form with an initial guess, and removes that bias.
    gamma : float or None
        Width of the smoothed Heaviside in mm; None means ``h / q`` (the
        spacing of the sub-voxel points, so the objective is smooth).
    heaviside : {"erf", "arctan"}
        Shape of the smoothed Heaviside; "arctan" is the paper's, "erf" has
        Gaussian tails and far less bias (see
        :func:`wss_nlp.models.measurement.smoothed_heaviside`).
    quad_order : int or None
        Sub-voxel midpoint points per axis (q x q per voxel); None chooses
        q from h and the vessel size (:func:`wss_nlp.models.measurement.auto_quad_order`).
    solver : {"ipopt", "gauss-newton"}
        IPOPT with the box as linear inequalities, or projected Gauss-Newton.
    hessian : {"newton", "gauss-newton", "exact", "limited-memory"}
        Hessian used by IPOPT. "newton": the exact Hessian assembled by the
        chain rule, ``2 (J^T J + sum_i r_i Hess r_i + alpha W)`` with the
        second-order term from Fourier moments
        (:func:`wss_nlp.models.measurement.magnitude_model`,
        :func:`wss_nlp.models.kspace.magnitude_model`); it converges quadratically
        where the Gauss-Newton Hessian (without that term) converges linearly
        (this non-zero-residual problem: 4 iterations instead of 11-25,
        ``scripts/results/bench_geometry.md``). "exact": CasADi's algorithmic
        Hessian (the cross-check; slower to evaluate).
    n_box : int
        Angles at which the box constraint is imposed (0: ``max(64, 8N)``).
    tol, max_iter : float, int
        Stopping rules.
    """

    schema_group = "geometry (Sec. 2, 7.1)"

    n_fourier: int = option(8, "highest harmonic N of the radius R(phi)", cli="--n-fourier", toml=("N", "n_fourier"))
    alpha: float = 1e-3  # on the command line and in studies through --alpha (ReconstructionOptions.choice.alpha_rule)
    sobolev_s: int = option(2, "order s of the H^s penalty", cli="--sobolev", toml=("sobolev",))
    prior: str = option(
        "area",
        "penalize R - R_area (unbiased) or R itself as in eq. (tik1)",
        cli="--prior",
        toml=("prior",),
        choices=("area", "zero"),
    )
    gamma: float | None = option(
        None, "width of the smoothed Heaviside in mm (default: h / q)", cli="--gamma", toml=("gamma",)
    )
    heaviside: str = option(
        "erf",
        "smoothed Heaviside: erf (Gaussian tails) or the paper's arctan",
        cli="--heaviside",
        toml=("heaviside",),
        choices=meas.HEAVISIDES,
    )
    quad_order: int | None = option(
        None,
        "sub-voxel quadrature points per axis, q x q per voxel (default: clip(ceil(60 h / R), 2, 6))",
        cli="--quad-order",
        toml=("quad_order",),
        also=("velocity.quad_order",),
    )
    solver: str = option(
        "ipopt",
        "IPOPT or the paper's projected Gauss-Newton",
        cli="--geometry-solver",
        choices=("ipopt", "gauss-newton"),
    )
    hessian: str = option(
        "newton",
        "Hessian used by IPOPT (newton: exact, by the chain rule; gauss-newton drops the second-order term)",
        cli="--hessian",
        choices=HESSIANS,
    )
    n_box: int = 0
    tol: float = 1e-9
    max_iter: int = 200

    def __post_init__(self):
        if self.n_fourier < 0:
            raise InputError(f"n_fourier must be >= 0, got {self.n_fourier}")
        if not self.alpha > 0:
            raise InputError(f"alpha must be > 0, got {self.alpha}")
        if self.prior not in ("area", "zero"):
            raise InputError(f"geometry prior must be 'area' or 'zero', got {self.prior!r}")
        if self.solver not in ("ipopt", "gauss-newton"):
            raise InputError(f"geometry solver must be 'ipopt' or 'gauss-newton', got {self.solver!r}")
        if self.hessian not in HESSIANS:
            raise InputError(f"hessian must be one of {', '.join(HESSIANS)}, got {self.hessian!r}")
        if self.heaviside not in meas.HEAVISIDES:
            raise InputError(f"heaviside must be one of {meas.HEAVISIDES}, got {self.heaviside!r}")
        if self.gamma is not None and not self.gamma > 0:
            raise InputError(f"gamma must be > 0 mm, got {self.gamma}")

    def box_angles(self) -> np.ndarray:
        return rad.uniform_angles(self.n_box or max(64, 8 * self.n_fourier))


@dataclass
class GeometryProblem:
    """Data of one geometry identification: normalized magnitude on a grid."""

    grid: meas.VoxelGrid
    magnitude: np.ndarray  # normalized, (ny, nx), values in [0, 1]
    center: tuple[float, float]  # mm
    r0: float  # box lower bound, mm
    r1: float  # box upper bound, mm
    r_ref: float  # reference (equal-area) radius, mm
    psf: kspace.PSF | None = None  # None: voxel means (box model); else the k-space point-spread function

    @property
    def measurement(self) -> acq_model.MeasurementModel:
        """The measurement model of the magnitude (:mod:`wss_nlp.models.acquisition`)."""
        return acq_model.of(self.psf)

    def __post_init__(self):
        if not 0 < self.r0 < self.r1:
            raise InputError(f"geometry box must satisfy 0 < r0 < r1, got r0 = {self.r0} mm, r1 = {self.r1} mm")


@dataclass
class GeometryResult:
    coefficients: np.ndarray
    center: tuple[float, float]
    alpha: float
    gamma: float
    residual_norm: float  # ||F(R) - m||_{L^2(D)} in mm
    annulus_residual_norm: float  # the same on the annulus voxels only (what the discrepancy principle uses)
    penalty: float  # ||R - R_ref||_{H^s}^2 in mm^2
    stats: SolverStats
    box: tuple[float, float] = (0.0, 0.0)
    box_active: bool = False
    options: dict = field(default_factory=dict)
    box_multipliers: np.ndarray = field(default_factory=lambda: np.zeros(0))  # IPOPT lam_g (0 where inactive)

    def radius(self, phi, derivative: int = 0) -> np.ndarray:
        return rad.evaluate(self.coefficients, phi, derivative)


@dataclass
class TikhonovNLP:
    """CasADi pieces of the geometry functional (returned by :func:`build_tikhonov`)."""

    c: ca.MX  # decision variables
    alpha: ca.MX  # regularization parameter (an NLP parameter)
    f: ca.MX  # objective J(c; alpha)
    g: ca.MX  # box-constraint expression R(phi_j)
    residual: ca.MX  # weighted residual on the annulus, J = |residual|^2 + penalty
    penalty: ca.MX  # ||R - R_ref||^2_{H^s}
    reference: np.ndarray  # R_ref coefficients
    weights: np.ndarray  # H^s weights
    model: meas.AnnulusModel | kspace.KSpaceMagnitudeModel
    gamma: float
    data: ca.MX | None = None  # the annulus magnitude as a symbol (solvers reused across data), or None: constants
    jacobian: ca.MX | None = None  # d residual / d c by the chain rule (the Gauss-Newton solvers' form), or None
    # sum_i residual_i d^2 residual_i / dc^2 by the chain rule (with the Jacobian: the exact Hessian), or None
    curvature: ca.MX | None = None


def quad_order(problem: GeometryProblem, options: GeometryOptions) -> int:
    return meas.auto_quad_order(options.quad_order, problem.grid, problem.r_ref)


def effective_gamma(problem: GeometryProblem, options: GeometryOptions) -> float:
    return options.gamma if options.gamma is not None else problem.grid.h / quad_order(problem, options)


def build_tikhonov(
    problem: GeometryProblem,
    options: GeometryOptions,
    gamma_symbol=None,
    data_symbol: bool = False,
    separable_jacobian: bool = False,
    second_order: bool = False,
) -> TikhonovNLP:
    """Build the CasADi expression of the Tikhonov functional (eq. (tik1)).

    Notes
    -----
    ``J(c) = sum_i |V_i| (F_i(c) - m_i)^2 + alpha sum_k w_k (c_k - c_ref,k)^2``
    with the H^s weights ``w`` of :func:`wss_nlp.core.radius.sobolev_weights`;
    ``|V_i|`` in mm^2 makes the first term the L^2(D) norm of the
    piecewise-constant residual. Voxels outside the annulus of
    :class:`wss_nlp.models.measurement.AnnulusModel` contribute a constant.
    With ``problem.psf`` (a k-space acquisition) ``F_i`` is the magnitude of
    the PSF-filtered lumen indicator on a window about the wall annulus
    (:func:`wss_nlp.models.kspace.magnitude_model`), the rest again a constant.
    ``data_symbol`` makes the fitted magnitude values a symbol
    (``TikhonovNLP.data``) instead of constants, so one solver serves every
    magnitude image of the same grid, centre and box (:func:`solver_for`).
    ``separable_jacobian`` sets ``TikhonovNLP.jacobian``, the residual's
    Jacobian assembled by the chain rule with BLAS
    (:func:`wss_nlp.models.measurement.magnitude_model` or
    :func:`wss_nlp.models.kspace.magnitude_model` with ``jacobian=True``): the
    Gauss-Newton solvers' form, 2-4x cheaper than CasADi's forward sweeps.
    ``second_order`` (with ``separable_jacobian``) also sets
    ``TikhonovNLP.curvature``, ``sum_i r_i Hess r_i``, so that
    ``2 (J^T J + sum_i r_i Hess r_i + alpha W)`` is the exact Hessian of
    ``J`` (:func:`wss_nlp.models.measurement.magnitude_model`,
    :func:`wss_nlp.models.kspace.magnitude_model`).
    """
    n = options.n_fourier
    q = quad_order(problem, options)
    gamma = effective_gamma(problem, options)
    c = ca.MX.sym("c", rad.n_coefficients(n))
    alpha = ca.MX.sym("alpha")  # a parameter, so one solver serves a whole alpha sequence
    width = gamma if gamma_symbol is None else gamma_symbol  # a symbol lets callers differentiate in gamma
    measurement = problem.measurement
    model = measurement.magnitude_setup(problem.grid, problem.center, problem.r0, problem.r1, q, gamma)
    second = None
    if separable_jacobian and second_order:
        predicted, d_predicted, second = measurement.magnitude_model(
            model, c, width, options.heaviside, jacobian=True, second_order=True
        )
    elif separable_jacobian:
        predicted, d_predicted = measurement.magnitude_model(model, c, width, options.heaviside, jacobian=True)
    else:
        predicted = measurement.magnitude_model(model, c, width, options.heaviside)
    m = problem.magnitude.ravel()
    area = problem.grid.voxel_area
    data = ca.MX.sym("m", model.annulus.size) if data_symbol else None
    residual = np.sqrt(area) * (predicted - (ca.DM(m[model.annulus]) if data is None else data))
    ref = np.zeros(rad.n_coefficients(n))
    if options.prior == "area":
        ref[0] = problem.r_ref
    w = rad.sobolev_weights(n, options.sobolev_s)
    dc = c - ca.DM(ref)
    penalty = ca.dot(ca.DM(w) * dc, dc)
    f = ca.sumsqr(residual) + alpha * penalty
    g = ca.mtimes(ca.DM(rad.design_matrix(options.box_angles(), n)), c)
    jac = np.sqrt(area) * d_predicted if separable_jacobian else None
    # r_i = sqrt|V| (F_i - m_i): sum_i r_i Hess r_i = sum_i (sqrt|V| r_i) Hess F_i
    curvature = None if second is None else second(np.sqrt(area) * residual)
    return TikhonovNLP(c, alpha, f, g, residual, penalty, ref, w, model, gamma, data, jac, curvature)


def _constant_misfit(m: np.ndarray, model, area: float) -> float:
    """``|V| sum (F_i - m_i)^2`` of the voxels the functional does not fit (``F = 1`` inside, 0 outside)."""
    outside = np.setdiff1d(np.arange(m.size), np.concatenate([model.annulus, model.inside]))
    return float(area * (np.sum((1 - m[model.inside]) ** 2) + np.sum(m[outside] ** 2)))


def fitted_voxels(problem: GeometryProblem, options: GeometryOptions) -> np.ndarray:
    """Flat indices of the voxels whose magnitude the functional fits (the annulus, or the k-space window)."""
    q, gamma = quad_order(problem, options), effective_gamma(problem, options)
    return problem.measurement.magnitude_setup(problem.grid, problem.center, problem.r0, problem.r1, q, gamma).annulus


def model_image(problem: GeometryProblem, options: GeometryOptions, result: GeometryResult) -> np.ndarray:
    """The forward model's normalized magnitude of ``result`` as an image (0 outside the fitted voxels)."""
    q = quad_order(problem, options)
    out = np.zeros(problem.magnitude.size)
    measurement = problem.measurement
    model = measurement.magnitude_setup(problem.grid, problem.center, problem.r0, problem.r1, q, result.gamma)
    out[model.inside] = 1.0
    out[model.annulus] = measurement.magnitude_model(model, result.coefficients, result.gamma, options.heaviside)
    return out.reshape(problem.magnitude.shape)


#: Rays along which :func:`initial_guess` finds the half-maximum contour.
START_RAYS = 64


def initial_guess(problem: GeometryProblem, n_fourier: int) -> np.ndarray:
    """Coefficients to start the geometry solve from: the half-maximum contour of the normalized magnitude.

    Notes
    -----
    Along :data:`START_RAYS` rays from the centre the normalized magnitude
    (bilinear interpolation, steps of a quarter voxel) falls through 1/2;
    of the crossings inside the box the one nearest the equal-area radius
    ``r_ref`` is kept (a ray without one keeps ``r_ref``), and ``R`` is their
    least-squares fit in V_N. Where that fit leaves the box the start is the
    circle of radius ``r_ref``. The start does not choose the minimizer
    (the same to 1e-11 mm from either start on the phantoms of
    ``scripts/bench_geometry.py``): the contour lies within about 0.07 mm of
    it where the circle may be 1.5 mm away, which spares IPOPT the steps of
    a fraction of a voxel each that the smoothed Heaviside allows far from
    the wall.
    """
    circle = np.zeros(rad.n_coefficients(n_fourier))
    circle[0] = problem.r_ref
    grid = problem.grid
    phi = rad.uniform_angles(START_RAYS)
    step = 0.25 * min(grid.dx, grid.dy)
    r = np.arange(0.0, problem.r1 + step, step)
    x = problem.center[0] + np.outer(np.cos(phi), r)
    y = problem.center[1] + np.outer(np.sin(phi), r)
    rows, cols = (y - grid.origin_mm[1]) / grid.dy, (x - grid.origin_mm[0]) / grid.dx
    m = scipy.ndimage.map_coordinates(problem.magnitude, [rows.ravel(), cols.ravel()], order=1, mode="nearest")
    m = m.reshape(x.shape)
    radius = np.full(START_RAYS, float(problem.r_ref))
    for k in range(START_RAYS):
        above = m[k] >= 0.5
        falls = np.flatnonzero(above[:-1] & ~above[1:])
        falls = falls[(r[falls] >= problem.r0) & (r[falls + 1] <= problem.r1)]
        if falls.size:
            i = falls[np.argmin(np.abs(r[falls] - problem.r_ref))]
            radius[k] = r[i] + step * (m[k, i] - 0.5) / (m[k, i] - m[k, i + 1])
    c0 = np.linalg.lstsq(rad.design_matrix(phi, n_fourier), radius, rcond=None)[0]
    check = rad.evaluate(c0, rad.uniform_angles(4 * START_RAYS))
    if not np.all((check > problem.r0) & (check < problem.r1)):  # also where a non-finite value got in
        return circle
    return c0


#: A box row within this fraction of ``r1`` of its bound counts as on it (active).
BOX_SLACK = 1e-6


def on_bound(problem, options, coef) -> np.ndarray:
    """Per box row (angle of ``options.box_angles()``): whether ``R`` sits on ``r0`` or ``r1`` (within
    :data:`BOX_SLACK` ``r1``)."""
    r = rad.evaluate(coef, options.box_angles())
    return np.minimum(r - problem.r0, problem.r1 - r) <= BOX_SLACK * problem.r1


def finish(problem, options, nlp, coef, stats, alpha) -> GeometryResult:
    """GeometryResult of coefficients ``coef`` of the functional ``nlp`` (misfits, penalty, box activity)."""
    m = problem.magnitude.ravel()
    inputs, values = [nlp.c], [coef]
    if nlp.data is not None:
        inputs.append(nlp.data)
        values.append(m[nlp.model.annulus])
    fun = ca.Function("parts", inputs, [ca.sumsqr(nlp.residual), nlp.penalty])
    mis, pen = (float(v) for v in fun(*values))
    active = bool(np.any(on_bound(problem, options, coef)))
    return GeometryResult(
        coefficients=np.asarray(coef, dtype=float).ravel(),
        center=tuple(problem.center),
        alpha=float(alpha),
        gamma=nlp.gamma,
        residual_norm=float(np.sqrt(mis + _constant_misfit(m, nlp.model, problem.grid.voxel_area))),
        annulus_residual_norm=float(np.sqrt(mis)),
        penalty=pen,
        stats=stats,
        box=(problem.r0, problem.r1),
        box_active=active,
        # the acquisition model as resolved for this slice (zero-filling may come from the file)
        options={**vars(options), "acquisition": problem.psf.describe() if problem.psf else {"model": "box"}},
    )


class IpoptGeometrySolver:
    """IPOPT for the geometry functional, built once and reused for any alpha and any magnitude image.

    ``options.hessian = "newton"`` passes the exact Hessian of the
    Lagrangian assembled by the chain rule, ``2 (J^T J + sum_i r_i Hess r_i +
    alpha W)`` (the constraints are linear); "gauss-newton" drops the
    second-order term, following CasADi's ``sysid.py`` example; "exact"
    uses CasADi's algorithmic Hessian.
    alpha and the fitted magnitude values are the NLP's parameters, so
    :meth:`solve` takes a ``problem`` with another magnitude on the same
    grid, centre and box (the dephasing passes, cine frames) without a
    rebuild; :func:`solver_for` keeps recent solvers.
    """

    def __init__(self, problem: GeometryProblem, options: GeometryOptions, warm: bool = False):
        self.problem, self.options = problem, options
        self.hessian = options.hessian
        chain_rule = self.hessian in ("newton", "gauss-newton")
        nlp = self.nlp = build_tikhonov(
            problem, options, data_symbol=True, separable_jacobian=chain_rule, second_order=self.hessian == "newton"
        )
        assert nlp.data is not None  # data_symbol=True
        params = ca.vertcat(nlp.alpha, nlp.data)
        # clip_inactive_lam: IPOPT leaves ~1e-12 multipliers on inactive bounds, which sensitivity analysis
        # (wss_nlp.uncertainty.sensitivity) would read as active constraints
        extra: dict = {"clip_inactive_lam": True}
        self._response: ca.Function | None = None  # built on the first call of :meth:`response`
        if warm:  # re-solves from a solution: start the barrier where it ended instead of at mu = 0.1
            extra.update(WARM_START)
        elif self.hessian == "newton":
            extra.update(COLD_START)
        if chain_rule:
            assert nlp.jacobian is not None  # separable_jacobian=True
            self._gram = operators.Gram(*nlp.jacobian.shape)  # kept alive with the solver (a callback): J^T J by BLAS
            hess = 2 * self._gram(nlp.jacobian) + 2 * nlp.alpha * ca.diag(ca.DM(nlp.weights))
            if nlp.curvature is not None:
                hess = hess + 2 * nlp.curvature
            self.solver = gauss_newton_ipopt(
                "geometry", nlp.c, nlp.f, nlp.g, hess, params, options.tol, options.max_iter, extra
            )
            return
        opts = ipopt_options(options.tol, options.max_iter, extra)
        if options.hessian == "limited-memory":
            opts["ipopt.hessian_approximation"] = "limited-memory"
        self.solver = ca.nlpsol("geometry", "ipopt", {"x": nlp.c, "p": params, "f": nlp.f, "g": nlp.g}, opts)

    def solve(
        self, alpha: float | None = None, x0=None, problem: GeometryProblem | None = None, lam_g0=None
    ) -> GeometryResult:
        """Solve at ``alpha`` from ``x0`` for ``problem`` (default: the one built with; same grid, centre, box).

        ``lam_g0``: the box multipliers to start from (a warm solver's re-solve from a solution).
        """
        problem = self.problem if problem is None else problem
        alpha = self.options.alpha if alpha is None else float(alpha)
        x0 = initial_guess(problem, self.options.n_fourier) if x0 is None else np.asarray(x0, dtype=float)
        data = problem.magnitude.ravel()[self.nlp.model.annulus]
        sol, stats = run_nlpsol(
            self.solver,
            "geometry (IPOPT)",
            x0=x0,
            p=np.concatenate([[alpha], data]),
            lbg=problem.r0,
            ubg=problem.r1,
            **({} if lam_g0 is None else {"lam_g0": lam_g0}),
        )
        stats.extra["hessian"] = self.hessian
        out = finish(problem, self.options, self.nlp, np.asarray(sol["x"]).ravel(), stats, alpha)
        out.box_multipliers = np.asarray(sol["lam_g"]).ravel()
        return out

    def response(self, result: GeometryResult, problem: GeometryProblem, magnitude) -> np.ndarray | None:
        r"""First-order change of the minimizer ``result`` of ``problem`` when its magnitude becomes ``magnitude``.

        Returns ``dc`` (radius coefficients, mm), or None where the linearization does not hold: a box row
        active at ``result``, or a solver built without the exact Hessian (``hessian`` other than "newton").

        Notes
        -----
        The implicit function theorem on the stationarity of eq. (tik1) in the fitted values ``d``,
        ``J^T r + \alpha W (c - c_{ref}) = 0`` with ``r = \sqrt{|V|} (F(c) - d)``:

        .. math::

            \delta c = \left(J^\top J + \sum_i r_i \nabla^2 r_i + \alpha W\right)^{-1} J^\top \sqrt{|V|}\,\delta d,

        with the solver's own exact Hessian at the solution (one Jacobian and one 17 x 17 solve, about a
        tenth of a re-solve). :func:`wss_nlp.uncertainty.sensitivity.geometry_kkt` gives the same derivative (and those
        in every other parameter) from a graph built for the purpose, 8-40x slower (tested equal); this form
        reuses the solver's graph, so the dephasing passes can afford it to see that a further pass would
        not move the wall (:mod:`wss_nlp.pipeline.driver`).
        """
        nlp = self.nlp
        if nlp.curvature is None or np.any(result.box_multipliers != 0):
            return None
        if self._response is None:
            assert nlp.data is not None and nlp.jacobian is not None  # the solver's build (data_symbol, chain rule)
            inputs: list = [nlp.c, ca.vertcat(nlp.alpha, nlp.data)]
            outputs: list = [nlp.jacobian, self._gram(nlp.jacobian) + nlp.curvature]
            self._response = ca.Function("geometry_response", inputs, outputs)
        annulus = nlp.model.annulus
        data = problem.magnitude.ravel()[annulus]
        jac, hmat = (np.asarray(v) for v in self._response(result.coefficients, np.concatenate([[result.alpha], data])))
        hmat = hmat + result.alpha * np.diag(nlp.weights)
        change = np.asarray(magnitude, dtype=float).ravel()[annulus] - data
        try:
            return np.linalg.solve(hmat, jac.T @ (np.sqrt(problem.grid.voxel_area) * change))
        except np.linalg.LinAlgError:
            return None


#: IPOPT options of a warm re-solve (:class:`IpoptGeometrySolver` with ``warm=True``): the iterate and the
#: multipliers are taken as given and the barrier starts small, so a re-solve from a solution to a tighter
#: tolerance takes a few iterations instead of the 10-14 of a cold start.
WARM_START = {
    "ipopt.warm_start_init_point": "yes",
    "ipopt.mu_init": 1e-9,
    "ipopt.warm_start_bound_push": 1e-9,
    "ipopt.warm_start_mult_bound_push": 1e-9,
    "ipopt.warm_start_slack_bound_push": 1e-9,
}

#: IPOPT options of a first solve with the Newton Hessian: the adaptive barrier (Mehrotra's probing) lets the
#: barrier follow Newton's quadratic convergence instead of the monotone schedule's fixed decrease from
#: mu = 0.1 (4 iterations instead of 6 on the phantoms of ``scripts/bench_geometry.py``, same minimizer).
COLD_START = {"ipopt.mu_strategy": "adaptive"}

#: How many built geometry solvers :func:`solver_for` keeps (a slice needs two or three; the filter choice four).
SOLVER_CACHE_SIZE = 8
_solvers: dict = {}


def solver_for(problem: GeometryProblem, options: GeometryOptions, warm: bool = False) -> IpoptGeometrySolver:
    """A built :class:`IpoptGeometrySolver` for ``problem``'s grid, centre, box and model and ``options``.

    Reused when only the magnitude or alpha differ (both are solver
    parameters); the least recently used of :data:`SOLVER_CACHE_SIZE` is
    dropped. Pass the problem to :meth:`IpoptGeometrySolver.solve`.
    ``warm`` gives a solver for re-solves from a solution (:data:`WARM_START`).
    """
    key = (
        problem.grid,
        problem.magnitude.shape,
        tuple(float(v) for v in problem.center),
        float(problem.r0),
        float(problem.r1),
        float(problem.r_ref),
        problem.psf,
        replace(options, alpha=1.0),  # alpha is a parameter
        warm,
    )
    solver = _solvers.pop(key, None)
    if solver is None:
        solver = IpoptGeometrySolver(problem, options, warm)
        while len(_solvers) >= SOLVER_CACHE_SIZE:
            _solvers.pop(next(iter(_solvers)))
    _solvers[key] = solver  # most recently used last
    return solver


def clear_solvers() -> None:
    """Forget the solvers :func:`solver_for` keeps (benchmarks time a slice as a user's first one)."""
    _solvers.clear()


def predicted_change(problem: GeometryProblem, options: GeometryOptions, result: GeometryResult, magnitude):
    """``dc`` of :meth:`IpoptGeometrySolver.response` for a solution of :func:`solve` (None: not predictable)."""
    if options.solver != "ipopt":
        return None
    return solver_for(problem, options).response(result, problem, magnitude)


def solve_ipopt(problem: GeometryProblem, options: GeometryOptions, x0=None) -> GeometryResult:
    """Minimize the geometry functional with IPOPT; the box goes to IPOPT."""
    return solver_for(problem, options).solve(options.alpha, x0, problem)


def _project_box(y, hmat, box_matrix, r0, r1):
    """Projection of ``y`` onto ``{r0 <= S c <= r1}`` in the metric of ``hmat``."""
    s = box_matrix @ y
    if np.all(s >= r0) and np.all(s <= r1):
        return y
    cons = [
        {"type": "ineq", "fun": lambda z: box_matrix @ z - r0, "jac": lambda z: box_matrix},
        {"type": "ineq", "fun": lambda z: r1 - box_matrix @ z, "jac": lambda z: -box_matrix},
    ]
    start = np.clip(s, r0, r1)
    z0 = np.linalg.lstsq(box_matrix, start, rcond=None)[0]
    import scipy.optimize  # here: only the projected Gauss-Newton path needs it, and it is slow to import

    res = scipy.optimize.minimize(
        lambda z: 0.5 * (z - y) @ hmat @ (z - y),
        z0,
        jac=lambda z: hmat @ (z - y),
        constraints=cons,
        method="SLSQP",
        options={"ftol": 1e-14, "maxiter": 200},
    )
    return res.x


def solve_projected_gauss_newton(
    problem: GeometryProblem, options: GeometryOptions, x0=None, alpha: float | None = None
) -> GeometryResult:
    """The paper's projected Gauss-Newton method (Sec. 7.1) with a line search.

    Notes
    -----
    Step: ``(J^T J + alpha W) d = -(J^T r + alpha W (c - c_ref))``; the trial
    point ``P(c + t d)`` is projected onto the box in the metric of the
    Gauss-Newton matrix and ``t`` is halved until the Armijo condition
    holds. Stops when the relative step falls below ``sqrt(tol)``.
    Residuals and Jacobians come from the same CasADi expressions as the
    IPOPT path; the iteration itself is independent NumPy/SciPy code.
    """
    t_start = time.perf_counter()
    nlp = build_tikhonov(problem, options)
    alpha = options.alpha if alpha is None else float(alpha)
    fun = ca.Function("gn", [nlp.c], [nlp.residual, ca.jacobian(nlp.residual, nlp.c)])
    objective = ca.Function("J", [nlp.c], [ca.substitute(nlp.f, nlp.alpha, alpha)])
    w = nlp.weights
    box_matrix = rad.design_matrix(options.box_angles(), options.n_fourier)
    c = initial_guess(problem, options.n_fourier) if x0 is None else np.asarray(x0, dtype=float).copy()
    c = _project_box(c, np.eye(c.size), box_matrix, problem.r0, problem.r1)
    f_c = float(objective(c))
    status, converged, it = "Maximum_Iterations_Exceeded", False, 0
    for it in range(1, options.max_iter + 1):  # noqa: B007 (the count is reported after the loop)
        r, jac = (np.asarray(v) for v in fun(c))
        r = r.ravel()
        grad = jac.T @ r + alpha * w * (c - nlp.reference)
        hmat = jac.T @ jac + alpha * np.diag(w)
        step = -np.linalg.solve(hmat, grad)
        t = 1.0
        while True:
            trial = _project_box(c + t * step, hmat, box_matrix, problem.r0, problem.r1)
            f_t = float(objective(trial))
            if f_t <= f_c + 1e-4 * 2 * grad @ (trial - c) or t < 1e-8:
                break
            t *= 0.5
        if t < 1e-8 and f_t > f_c:
            status = "Line_Search_Failed"
            break
        change = np.linalg.norm(trial - c) / (1 + np.linalg.norm(c))
        c, f_c = trial, f_t
        if change < np.sqrt(options.tol):
            status, converged = "Solve_Succeeded", True
            break
    if not np.all(np.isfinite(c)):
        raise SolverError("geometry (projected Gauss-Newton): iterate became non-finite")
    stats = SolverStats(
        solver="projected-gauss-newton",
        status=status,
        converged=converged,
        iterations=it,
        objective=f_c,
        seconds=time.perf_counter() - t_start,
    )
    return finish(problem, options, nlp, c, stats, alpha)


def solve(problem: GeometryProblem, options: GeometryOptions, x0=None) -> GeometryResult:
    """Dispatch on ``options.solver``."""
    if options.solver == "ipopt":
        return solve_ipopt(problem, options, x0)
    return solve_projected_gauss_newton(problem, options, x0)


def with_options(options: GeometryOptions, **changes) -> GeometryOptions:
    """Copy of the options with some fields changed."""
    return replace(options, **changes)
