r"""The momentum balance across the frames of a cine slice: Womersley's model of pulsatile flow.

Fully developed flow in a rigid straight vessel obeys :math:`\rho\,\partial_t u = G(t) + \mu\,\Delta u`,
:math:`u = 0` on the wall, with one unknown pressure gradient :math:`G(t)` per instant. With
:math:`G(t) = \sum_n \mathrm{Re}[G_n e^{i n\omega t}]` every harmonic solves
:math:`(\Delta - i n\omega/\nu)\,\hat u_n = -G_n/\mu`; in a circular lumen of radius :math:`R`
(Womersley 1955, J. Physiol. 127, 553-563; :mod:`wss_nlp.synthetic.pulsatile`)

.. math::

    u(\sigma, t) = a_0 S_0(\sigma) + \sum_{n=1}^{K} \mathrm{Re}\big[a_n S_n(\sigma) e^{i n\omega t}\big],
    \qquad S_0 = 1 - \sigma^2, \quad
    S_n = 1 - \frac{J_0(\Lambda_n\sigma)}{J_0(\Lambda_n)}, \quad
    \Lambda_n = i^{3/2} R\sqrt{n\omega\rho/\mu},

:math:`\sigma = r/R`. The whole cycle is :math:`2K + 1` real numbers (:math:`a_0` and the complex
:math:`a_n`, in m/s), the unknowns of this model; the data of every frame decide them together, and the
near-wall Stokes layer (thickness :math:`\sqrt{2}R/|\Lambda_n|`, often thinner than a voxel) comes with
the model instead of from a polynomial that cannot bend that fast.

Each frame ``k`` keeps its own wall (its own geometry reconstruction): :math:`\sigma = |x - c_k| /
R_k(\theta)` along the rays of that wall and :math:`R = c_{k,0}` (its mean radius) in :math:`\Lambda_n`.
For a circle this is Womersley's solution; for other star-shaped lumens it is the circle's profile along
each ray (an approximation, which the model choice below judges), and a gently distending wall is
followed frame by frame (quasi-statically).

Notes
-----
Fit (Gauss-Markov): :math:`\min_a \sum_k \sum_i (\Phi_k a - u_k)_i^2/\sigma_{k,i}^2` with
:math:`\Phi_k` the voxel values of the columns at the frame's time :math:`t_k` (the box means or the k-space
PSF model, as the frame's own fit) and :math:`\sigma_{k,i}` the per-voxel velocity noise.

Wall shear stress, eq. (wss): :math:`\tau_k(\phi) = -\mu\,\partial_n u = -\mu\,(n\cdot\nabla\sigma)(\phi)
\sum_j a_j S_j'(1)\,e_j(t_k)` with :math:`S_0'(1) = -2`,
:math:`S_n'(1) = \Lambda_n J_1(\Lambda_n)/J_0(\Lambda_n)` and :math:`n\cdot\nabla\sigma` CasADi's exact
derivative of :math:`\sigma(x)` at the wall (1/mm; :math:`1/R` on a circle). Pa, with :math:`\mu` in Pa s.

Model choice (:func:`wss_nlp.parameters.cycle.choose`): Schwarz's criterion
:math:`\mathrm{BIC} = \nu\chi^2 + \ln(\nu N)\,\mathrm{dof}`
over all :math:`N` voxel values of the cycle, for the frames' own plain fits (each at its best beta,
dof the smoother's trace; :class:`~wss_nlp.parameters.layer.PlainCriterion`) and for this model with
:math:`K = 0, \dots, K_{\max}` harmonics (dof :math:`2K + 1`); :math:`\nu = 1` for white noise.
The frames' own fits stay the null hypothesis: the model must win by
:data:`~wss_nlp.parameters.cycle.EVIDENCE` over them and over
the temporal prior (:mod:`wss_nlp.models.temporal`), which in turn must win by that evidence over the frames' own
fits to be taken.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

import casadi as ca

from .._lazy import scipy
from ..core import radius as rad
from . import velocity as vel
from ..errors import InputError
from ..core.schema import option

#: What the cine velocity model may be: chosen by the BIC, the frames' own fits, the frames tied by a periodic
#: temporal prior (:mod:`wss_nlp.models.temporal`), or the momentum balance.
MODELS = ("auto", "independent", "temporal", "momentum")

#: How the momentum model takes the frames' walls (:func:`smooth_walls`).
WALLS = ("auto", "frames", "shared")

#: Where the momentum model's kinematic viscosity comes from (:mod:`wss_nlp.parameters.viscosity`).
VISCOSITIES = ("fit", "stated")

#: Most harmonics the model tries (fewer when the frames cannot carry them: ``K <= n_frames / 2``).
MAX_HARMONICS = 12


@dataclass(frozen=True)
class CineModelOptions:
    """How the frames of a cine slice are tied together.

    Attributes
    ----------
    model : {"auto", "independent", "temporal", "momentum"}
        "momentum": the velocity of all frames from the momentum balance (module notes); "temporal": the
        frames' plain fits tied by a periodic temporal prior (:mod:`wss_nlp.models.temporal`); "independent":
        each frame's own fit; "auto": the momentum model where the BIC prefers it by :data:`EVIDENCE` over
        both plain candidates, else the prior where it beats the frames' own fits by :data:`EVIDENCE`,
        else each frame's own fit.
    max_harmonics : int
        Most temporal harmonics of the momentum model (the BIC chooses how many).
    walls : {"auto", "frames", "shared"}
        The walls the momentum model and the temporal prior are fitted on (:func:`smooth_walls`).
    viscosity : {"fit", "stated"}
        The momentum model's kinematic viscosity (the Stokes layer's thickness): fitted to the frames with
        its interval (:mod:`wss_nlp.parameters.viscosity`), or the stated viscosity over the density. The
        stress takes the stated viscosity either way.
    """

    schema_group = "time-resolved (cine) data"

    model: str = option(
        "auto",
        "velocity over the cycle: momentum = the momentum balance of fully developed pulsatile flow "
        "(Womersley) fitted to all frames at once, temporal = the frames' own fits tied by a periodic "
        "temporal prior (equally spaced frames), independent = each frame on its own, auto = the BIC's "
        "choice (momentum must beat both others, temporal the frames' own fits)",
        cli="--cine-model",
        choices=MODELS,
    )
    max_harmonics: int = option(
        MAX_HARMONICS,
        "most temporal harmonics of the momentum model (the BIC chooses how many)",
        cli="--max-harmonics",
    )
    walls: str = option(
        "auto",
        "the walls the momentum model and the temporal prior use: frames = each frame's own reconstruction, "
        "shared = their mean (a rigid vessel), auto = the frames' radius coefficients as trigonometric "
        "polynomials in time, degree by the BIC (degree 0 is the shared wall)",
        cli="--cine-walls",
        choices=WALLS,
    )
    viscosity: str = option(
        "fit",
        "the momentum model's Stokes layer: fit = its kinematic viscosity fitted to the frames (reported with "
        "its interval; the stress keeps the stated viscosity), stated = from the stated viscosity and density",
        cli="--cine-viscosity",
        choices=VISCOSITIES,
    )

    def __post_init__(self):
        if self.model not in MODELS:
            raise InputError(f"cine model must be one of {MODELS}, got {self.model!r}")
        if self.walls not in WALLS:
            raise InputError(f"cine walls must be one of {WALLS}, got {self.walls!r}")
        if self.viscosity not in VISCOSITIES:
            raise InputError(f"cine viscosity must be one of {VISCOSITIES}, got {self.viscosity!r}")
        if not 0 <= self.max_harmonics <= 64:
            raise InputError(f"max_harmonics must lie in 0..64, got {self.max_harmonics}")


def womersley_parameter(n: int, radius_mm: float, omega: float, nu_m2_s: float) -> complex:
    r""":math:`\Lambda_n = i^{3/2} R\sqrt{n\omega/\nu}` (dimensionless; :math:`R` in mm, :math:`\omega` in rad/s)."""
    return complex(1j**1.5 * radius_mm * 1e-3 * np.sqrt(n * omega / nu_m2_s))


def shape(sigma, lam: complex) -> np.ndarray:
    r""":math:`S_n(\sigma)`: Poiseuille's :math:`1 - \sigma^2` for :math:`\Lambda = 0`, else Womersley's (complex)."""
    sigma = np.asarray(sigma, dtype=float)
    if lam == 0:
        return 1.0 - sigma**2
    return 1.0 - scipy.special.jv(0, lam * sigma) / scipy.special.jv(0, lam)


def wall_slope(lam: complex) -> complex:
    r""":math:`S_n'(1)`: :math:`-2` for :math:`\Lambda = 0`, else :math:`\Lambda J_1(\Lambda)/J_0(\Lambda)`."""
    if lam == 0:
        return -2.0
    return complex(lam * scipy.special.jv(1, lam) / scipy.special.jv(0, lam))


def ray_coordinate(coefficients, center, x, y) -> np.ndarray:
    r""":math:`\sigma = |x - c| / R(\theta)` at points ``(x, y)`` (mm): 0 at the centre, 1 on the wall."""
    dx, dy = np.asarray(x, float) - center[0], np.asarray(y, float) - center[1]
    return np.hypot(dx, dy) / rad.evaluate(np.asarray(coefficients, float), np.arctan2(dy, dx))


@functools.lru_cache(maxsize=8)
def normal_gradient_function(n_fourier: int) -> ca.Function:
    r"""``(phi, c_R) -> n . grad sigma`` at the wall point of angle ``phi`` (1/mm), CasADi's exact derivative."""
    phi, c = ca.SX.sym("phi"), ca.SX.sym("c_R", rad.n_coefficients(n_fourier))
    x = ca.SX.sym("x", 2)  # relative to the centre
    sigma = ca.norm_2(x) / rad.symbolic(c, ca.atan2(x[1], x[0]))
    grad = ca.Function("grad", [x, c], [ca.gradient(sigma, x)])
    big_r = rad.symbolic(c, phi)
    d_r = ca.jacobian(big_r, phi)
    normal = ca.vertcat(big_r * ca.cos(phi) + d_r * ca.sin(phi), big_r * ca.sin(phi) - d_r * ca.cos(phi))
    normal = normal / ca.sqrt(big_r**2 + d_r**2)  # eq. (normal), as in wss_nlp.models.wss
    wall = big_r * ca.vertcat(ca.cos(phi), ca.sin(phi))
    return ca.Function("n_grad_sigma", [phi, c], [ca.dot(normal, grad(wall, c))])


@functools.lru_cache(maxsize=8)
def normal_gradient_offset_function(n_fourier: int) -> ca.Function:
    r"""``(phi, c_R) -> (n . grad sigma, its derivative in c_R[0])``: the wall moved outward by ``epsilon`` (mm) is
    ``c_R[0] + epsilon`` (CasADi's exact derivative of :func:`normal_gradient_function`)."""
    phi, c = ca.SX.sym("phi"), ca.SX.sym("c_R", rad.n_coefficients(n_fourier))
    value = normal_gradient_function(n_fourier)(phi, c)
    return ca.Function("n_grad_sigma_offset", [phi, c], [value, ca.jacobian(value, c)[0]])


#: Node spacing of a shape's table times :math:`|\Lambda|` (cubic Hermite interpolation from exact values and
#: sigma-derivatives at the nodes: error about :math:`(h|\Lambda|)^4/384` of the shape's scale, 2e-9 here;
#: the layer of harmonic n is about :math:`1/|\Lambda_n|` wide in sigma), and the fewest and most nodes.
TABLE_STEP, TABLE_MIN, TABLE_MAX = 0.03, 256, 16384


def _nodes(lam: complex) -> int:
    """Intervals of the table of the shape of parameter ``lam`` on sigma in [0, 1] (:data:`TABLE_STEP`)."""
    return int(np.clip(np.ceil(abs(lam) / TABLE_STEP), TABLE_MIN, TABLE_MAX))


@functools.lru_cache(maxsize=128)
def _table(lam: complex) -> tuple:
    r"""Exact values at the table's nodes: :math:`S`, :math:`\partial_\sigma S`, :math:`\partial_\theta S` and
    :math:`\partial_\sigma\partial_\theta S` with :math:`\theta = \ln\nu` (:func:`shape_derivative`)."""
    n = _nodes(lam)
    x = np.linspace(0.0, 1.0, n + 1)
    j0, j1 = scipy.special.jv(0, lam * x), scipy.special.jv(1, lam * x)
    big0, big1 = scipy.special.jv(0, lam), scipy.special.jv(1, lam)
    value, slope = 1.0 - j0 / big0, lam * j1 / big0
    d_lam = x * j1 / big0 - j0 * big1 / big0**2  # dS / dLambda
    d_lam_slope = lam * x * j0 / big0 + lam * j1 * big1 / big0**2  # d^2 S / dsigma dLambda
    to_theta = -0.5 * lam  # dLambda / d ln(nu): Lambda is proportional to nu^(-1/2)
    return n, value, slope, to_theta * d_lam, to_theta * d_lam_slope


def _hermite(n: int, values: np.ndarray, slopes: np.ndarray, sigma: np.ndarray, derivative: bool = False):
    """Cubic Hermite interpolation of a table on ``n`` equal intervals of [0, 1] at ``sigma`` (in [0, 1]); with
    ``derivative`` also the interpolant's sigma-derivative."""
    u = sigma * n
    j = np.minimum(u.astype(int), n - 1)
    t = u - j
    t2 = t * t
    t3 = t2 * t
    h = 1.0 / n
    f0, f1, d0, d1 = values[j], values[j + 1], h * slopes[j], h * slopes[j + 1]
    value = (2 * t3 - 3 * t2 + 1) * f0 + (t3 - 2 * t2 + t) * d0 + (3 * t2 - 2 * t3) * f1 + (t3 - t2) * d1
    if not derivative:
        return value
    slope = ((6 * t2 - 6 * t) * (f0 - f1) + (3 * t2 - 4 * t + 1) * d0 + (3 * t2 - 2 * t) * d1) / h
    return value, slope


def shape_derivative(sigma, lam: complex) -> np.ndarray:
    r""":math:`\partial S_n/\partial\theta` with :math:`\theta = \ln\nu` (:math:`\Lambda_n \propto \nu^{-1/2}`):

    .. math::

        \frac{\partial S}{\partial\theta} = -\frac{\Lambda}{2}\Big(\frac{\sigma J_1(\Lambda\sigma)}{J_0(\Lambda)}
        - \frac{J_0(\Lambda\sigma) J_1(\Lambda)}{J_0(\Lambda)^2}\Big),

    from :math:`J_0' = -J_1` (exact; 0 for Poiseuille's :math:`\Lambda = 0`).
    """
    sigma = np.asarray(sigma, dtype=float)
    if lam == 0:
        return np.zeros_like(sigma, dtype=complex)
    j0, j1 = scipy.special.jv(0, lam * sigma), scipy.special.jv(1, lam * sigma)
    big0, big1 = scipy.special.jv(0, lam), scipy.special.jv(1, lam)
    return -0.5 * lam * (sigma * j1 / big0 - j0 * big1 / big0**2)


def wall_slope_derivative(lam: complex) -> complex:
    r""":math:`\partial S_n'(1)/\partial\theta = -\tfrac{\Lambda^2}{2}\big(1 + J_1(\Lambda)^2/J_0(\Lambda)^2\big)`
    (:math:`\theta = \ln\nu`; from :math:`J_1' = J_0 - J_1/z`), 0 for :math:`\Lambda = 0`."""
    if lam == 0:
        return 0.0
    ratio = scipy.special.jv(1, lam) / scipy.special.jv(0, lam)
    return complex(-0.5 * lam**2 * (1.0 + ratio**2))


@dataclass
class FrameTerms:
    """What one frame of a slice contributes to the model choice: normal equations and the plain BIC curve.

    Formed right after the frame's reconstruction (:func:`frame_terms`), so the frames' voxel problems need
    not be kept for the whole series.
    """

    index: int  # frame number
    time_s: float
    coefficients: np.ndarray  # the frame's radius coefficients, mm
    center: tuple[float, float]
    normal: np.ndarray  # Phi^T Sigma^-1 Phi of the 2 K_max + 1 columns
    rhs: np.ndarray  # Phi^T Sigma^-1 u
    usu: float  # u^T Sigma^-1 u
    n_data: int
    plain_chi2: np.ndarray  # chi^2 of the frame's own plain fit on wss_nlp.parameters.layer.CRITERION_BETAS
    plain_dof: np.ndarray  # and its effective parameter count
    nu: float  # effective fraction of independent voxels (1 for white noise)
    radius_mm: float  # the radius in Lambda_n (the cycle's, shared by the frames)


def time_factors(harmonics: int, omega: float, time_s: float) -> np.ndarray:
    """``e^{i n omega t}`` for ``n = 1..K``."""
    return np.exp(1j * np.arange(1, harmonics + 1) * omega * time_s)


def lambdas(harmonics: int, radius_mm: float, omega: float, nu_m2_s: float) -> list[complex]:
    """``Lambda_n`` for ``n = 1..K`` at a mean radius (mm)."""
    return [womersley_parameter(n, radius_mm, omega, nu_m2_s) for n in range(1, harmonics + 1)]


def columns_at(sigma: np.ndarray, lams: list[complex], phase: np.ndarray) -> np.ndarray:
    """The ``2K + 1`` real columns ``S_0, Re(S_n e_n), -Im(S_n e_n)`` at ``sigma``, shape ``(n, 2K + 1)``."""
    return _columns(shapes_at(sigma, lams), phase)


def shapes_at(sigma: np.ndarray, lams: list[complex], derivative: bool = False):
    r"""``S_0, S_1, ..., S_K`` at ``sigma`` (complex, shape ``(n, K + 1)``); with ``derivative`` also their
    derivatives in :math:`\theta = \ln\nu` (column 0, Poiseuille's, is 0).

    Each complex shape is tabulated with its sigma-derivative at :func:`_nodes` equal intervals of [0, 1]
    (exact values, :func:`_table`, built once per ``Lambda``) and interpolated by cubic Hermite polynomials:
    the Bessel functions of complex argument cost about a microsecond each and a frame has ten thousand
    sub-voxel points.
    """
    value, _, d_theta = shape_parts(sigma, lams, slopes=False, theta=derivative)
    return (value, d_theta) if derivative else value


def shape_parts(sigma: np.ndarray, lams: list[complex], slopes: bool = True, theta: bool = True):
    r"""``(S, dS/dsigma, dS/dtheta)`` of ``S_0 .. S_K`` at ``sigma`` (complex ``(n, K + 1)`` each; None where
    not asked for), :math:`\theta = \ln\nu`, from the tables (:func:`shapes_at`)."""
    sigma = np.clip(np.asarray(sigma, dtype=float).ravel(), 0.0, 1.0)
    value = np.empty((sigma.size, len(lams) + 1), dtype=complex)
    value[:, 0] = 1.0 - sigma**2
    slope = np.zeros_like(value) if slopes else None
    d_theta = np.zeros_like(value) if theta else None
    if slope is not None:
        slope[:, 0] = -2.0 * sigma
    for i, lam in enumerate(lams, start=1):
        n, v, s, dv, ds = _table(complex(lam))
        if slope is not None:
            value[:, i], slope[:, i] = _hermite(n, v, s, sigma, derivative=True)
        else:
            value[:, i] = _hermite(n, v, s, sigma)
        if d_theta is not None:
            d_theta[:, i] = _hermite(n, dv, ds, sigma)
    return value, slope, d_theta


def _columns(shapes: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """The real columns ``S_0, Re(S_n e_n), -Im(S_n e_n)`` of complex ``shapes`` (any linear image of them)."""
    value = shapes[:, 1:] * np.asarray(phase)[None, :]
    cols = np.empty((shapes.shape[0], 2 * value.shape[1] + 1))
    cols[:, 0] = shapes[:, 0].real
    cols[:, 1::2], cols[:, 2::2] = value.real, -value.imag
    return cols


def wall_shapes(problem: vel.VelocityProblem, k_max: int, omega: float, nu_m2_s: float, radius_mm: float):
    """The voxel values of ``S_0 .. S_K`` on ``problem``'s wall (complex ``(n_vox, K + 1)``): frames on one wall
    share them, each frame's columns are these times its phases (the voxel values are linear). Each point's
    cell integrated along its ray (:func:`offset_columns` with no offset)."""
    return offset_columns(WallPoints.of(problem), k_max, omega, nu_m2_s, radius_mm, 0.0, derivative=False)


#: The model's nonlinear parameters where they are fitted (:mod:`wss_nlp.parameters.viscosity`): the log of the
#: kinematic viscosity over the stated one, and the walls' outward offset (mm).
NONLINEAR = ("ln_nu", "wall_offset_mm")


@dataclass
class MomentumFit:
    """The momentum model of one cine slice fitted with ``harmonics`` harmonics.

    Where the viscosity and the walls' offset were fitted too (:mod:`wss_nlp.parameters.viscosity`),
    ``offset_mm`` moves every wall outward (``c_R[0] + offset``, and the cycle's radius with it) and ``joint``
    is the covariance of the coefficients and of :data:`NONLINEAR`: the band then carries their uncertainty
    (:meth:`joint_covariance`).
    """

    harmonics: int
    coefficients: np.ndarray  # a_0, Re a_1, Im a_1, ... (m/s)
    covariance: np.ndarray  # of the coefficients from the velocity noise, (m/s)^2
    chi2: float
    n_data: int
    omega: float  # rad/s
    nu_m2_s: float
    offset_mm: float = 0.0
    joint: np.ndarray | None = None  # Cov(a, ln nu, offset) where fitted

    def joint_covariance(self) -> np.ndarray:
        """Covariance of ``(a, ln nu, offset)`` (the last two rows and columns 0 where they were not fitted)."""
        if self.joint is not None:
            return self.joint
        p = self.coefficients.size
        out = np.zeros((p + 2, p + 2))
        out[:p, :p] = self.covariance
        return out


#: Condition number of a (diagonally scaled) normal matrix beyond which more harmonics are not fitted: frames
#: that leave part of the cycle empty cannot carry them.
MAX_CONDITION = 1e10


def fit(terms: list[FrameTerms], omega: float, nu_m2_s: float) -> list[MomentumFit]:
    """Weighted least squares over all frames (module notes) with ``K = 0 .. K_max`` harmonics.

    The columns of ``K`` harmonics are the first ``2K + 1`` of ``K_max``'s, so each fit solves the leading
    block of the summed normal matrix; its inverse is the coefficients' covariance.
    """
    normal = np.sum([t.normal for t in terms], axis=0)
    rhs = np.sum([t.rhs for t in terms], axis=0)
    usu, n_data = sum(t.usu for t in terms), sum(t.n_data for t in terms)
    return fits_from_normal(normal, rhs, usu, n_data, omega, nu_m2_s)


def fits_from_normal(
    normal, rhs, usu: float, n_data: int, omega: float, nu_m2_s: float, offset_mm: float = 0.0
) -> list[MomentumFit]:
    """The fits with ``K = 0, 1, ...`` harmonics from the summed normal equations of ``K_max``'s columns; stops
    before a ``K`` whose normal matrix is ill-conditioned (:data:`MAX_CONDITION`: e.g. frames with a gap)."""
    out = []
    for k in range((normal.shape[0] - 1) // 2 + 1):
        j = 2 * k + 1
        block = normal[:j, :j]
        scale = np.sqrt(np.abs(np.diag(block)))
        if np.any(scale == 0) or np.linalg.cond(block / np.outer(scale, scale)) > MAX_CONDITION:
            break
        covariance = np.linalg.inv(block)
        coef = covariance @ rhs[:j]
        chi2 = float(coef @ block @ coef - 2 * coef @ rhs[:j] + usu)
        out.append(MomentumFit(k, coef, covariance, chi2, n_data, omega, nu_m2_s, offset_mm))
    if not out:
        raise InputError("the momentum model's normal matrix is singular; too few frames or no flow")
    return out


@dataclass
class WallPoints:
    """A wall's quadrature points for the model's columns on the wall moved outward by an offset.

    ``r`` is each point's distance from the centre and ``wall`` the wall's radius in its direction (mm, shape
    ``(n_vox, q^2)``: the problem's points), ``cell`` the side of a point's quadrature cell (mm).
    """

    problem: vel.VelocityProblem
    r: np.ndarray
    wall: np.ndarray
    cell: float

    @classmethod
    def of(cls, problem: vel.VelocityProblem) -> WallPoints:
        vox, dm = problem.voxels, problem.disk_map
        dx, dy = vox.px - dm.center[0], vox.py - dm.center[1]
        wall = rad.evaluate(np.asarray(dm.coefficients, float), np.arctan2(dy, dx).ravel()).reshape(dx.shape)
        q = int(round(np.sqrt(vox.px.shape[1])))
        cell = float(np.sqrt(problem.cell_mm[0] * problem.cell_mm[1])) if problem.cell_mm else _spacing(vox.px, q)
        return cls(problem, np.hypot(dx, dy), wall, cell)

    def aggregate(self, values: np.ndarray) -> np.ndarray:
        """Point values ``(n_vox, q^2, m)`` to voxel sums (box) or PSF-weighted sums (k-space)."""
        if self.problem.averager is None:
            return values.sum(axis=1)
        return self.problem.averager(values)


def _spacing(px: np.ndarray, q: int) -> float:
    """The spacing of a voxel's ``q x q`` points along x (mm)."""
    return float(abs(px[0, 1] - px[0, 0])) if q > 1 else float("nan")


def _integral(n: int, values: np.ndarray, slopes: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    r""":math:`\int_0^\sigma` of the cubic Hermite interpolant of a table (:func:`_hermite`), exactly."""
    h = 1.0 / n
    d = h * slopes
    cumulative = np.r_[0.0, np.cumsum(h * ((values[:-1] + values[1:]) / 2 + (d[:-1] - d[1:]) / 12))]
    u = sigma * n
    j = np.minimum(u.astype(int), n - 1)
    t = u - j
    t2 = t * t
    t3, t4 = t2 * t, t2 * t2
    part = (values[j] * (t4 / 2 - t3 + t) + d[j] * (t4 / 4 - 2 * t3 / 3 + t2 / 2)
            + values[j + 1] * (t3 - t4 / 2) + d[j + 1] * (t4 / 4 - t3 / 3))  # fmt: skip
    return cumulative[j] + h * part


def offset_columns(
    points: WallPoints, k: int, omega: float, nu_m2_s: float, radius_mm: float, offset_mm: float,
    derivative: bool = True,
):  # fmt: skip
    r"""Voxel values of ``S_0 .. S_K`` on the wall moved outward by ``offset_mm`` (complex ``(n_vox, K + 1)``),
    and with ``derivative`` their derivatives in :math:`\theta = \ln\nu` and in the offset.

    Notes
    -----
    Each quadrature point stands for its cell (side :math:`c`), whose integral of a radial profile is taken
    along the ray, over the radial segment :math:`[r - c/2, \min(r + c/2, R(\phi) + \epsilon)]`: exactly, from
    the antiderivative of the tabulated shape (:func:`_integral`). A square's second moment is the same in
    every direction, so this matches the cell's own integral to fourth order, where the midpoint value
    misses the Stokes layer by :math:`(c/\delta)^2/24` (one per cent at 1.5 mm voxels and 4 x 4 points); the
    segment's inside length is the cell's smooth partial volume :math:`w`. In :math:`\sigma = r/(R(\phi) +
    \epsilon)`,

    .. math::

        c\,v_p = (R_\epsilon)\big[I(\sigma_+) - I(\sigma_-)\big], \qquad
        c\,\partial_\epsilon v_p = I(\sigma_+) - I(\sigma_-) + R_\epsilon\big[S(\sigma_+)\sigma_+' -
        S(\sigma_-)\sigma_-'\big] - \frac{2R_\epsilon}{R + \epsilon}\big[I_\theta(\sigma_+) - I_\theta(\sigma_-)\big],

    :math:`R_\epsilon = R(\phi) + \epsilon`, :math:`\sigma_\pm' = -\sigma_\pm/R_\epsilon` (0 where the
    segment ends at the wall), :math:`I` and :math:`I_\theta` the antiderivatives of :math:`S` and
    :math:`\partial_\theta S`, the last term because :math:`\Lambda_n \propto R + \epsilon` (the cycle's
    radius). A voxel's value is :math:`\sum_p v_p / \sum_p w_p` over its points (box means), or the PSF's
    weighted sums of both (k-space). Cells at the centre (:math:`r < c/2`) take their midpoint value.
    """
    eff = points.wall + offset_mm
    c = points.cell
    lo_r = points.r - c / 2
    hi_r = np.minimum(points.r + c / 2, eff)
    w = np.clip((hi_r - lo_r) / c, 0.0, 1.0)
    centre = lo_r < 0
    lo = np.clip(lo_r / eff, 0.0, 1.0)
    hi = np.clip(hi_r / eff, 0.0, 1.0)
    mid = np.clip(points.r / eff, 0.0, 1.0)
    big_r = radius_mm + offset_mm
    lams = lambdas(k, big_r, omega, nu_m2_s)
    shape = points.r.shape + (k + 1,)
    value = np.zeros(shape, dtype=complex)
    d_theta = np.zeros(shape, dtype=complex)
    d_eps = np.zeros(shape, dtype=complex)
    at_wall = hi_r >= eff  # the segment ends at the wall: sigma_+ = 1 whatever the offset
    d_lo, d_hi = -lo / eff, np.where(at_wall, 0.0, -hi / eff)
    # Poiseuille's S_0 = 1 - sigma^2: I_0 = sigma - sigma^3 / 3
    i0 = (hi - hi**3 / 3) - (lo - lo**3 / 3)
    value[..., 0] = np.where(centre, w * (1 - mid**2), eff * i0 / c)
    d_eps[..., 0] = np.where(centre, w * 2 * mid**2 / eff, (i0 + eff * ((1 - hi**2) * d_hi - (1 - lo**2) * d_lo)) / c)
    for i, lam in enumerate(lams, start=1):
        n, v, sl, dv, dsl = _table(complex(lam))
        big_i = _integral(n, v, sl, hi) - _integral(n, v, sl, lo)
        s_hi, s_lo = _hermite(n, v, sl, hi), _hermite(n, v, sl, lo)
        s_mid, slope_mid = _hermite(n, v, sl, mid, derivative=True)
        value[..., i] = np.where(centre, w * s_mid, eff * big_i / c)
        if derivative:
            big_it = _integral(n, dv, dsl, hi) - _integral(n, dv, dsl, lo)
            t_mid = _hermite(n, dv, dsl, mid)
            d_theta[..., i] = np.where(centre, w * t_mid, eff * big_it / c)
            along = (big_i + eff * (s_hi * d_hi - s_lo * d_lo)) / c
            d_eps[..., i] = np.where(
                centre, w * (-mid / eff * slope_mid - 2 / big_r * t_mid), along - 2 / big_r * eff * big_it / c
            )
    den = points.aggregate(w[..., None].astype(complex))
    keep = np.abs(den) > 1e-12 * np.max(np.abs(den))
    den = np.where(keep, den, 1.0)
    columns = np.where(keep, points.aggregate(value) / den, 0.0)
    if not derivative:
        return columns
    dw = np.where(at_wall & (w > 0) & (w < 1), 1.0 / c, 0.0)[..., None]
    c_theta = np.where(keep, points.aggregate(d_theta) / den, 0.0)
    c_eps = np.where(keep, (points.aggregate(d_eps) - columns * points.aggregate(dw.astype(complex))) / den, 0.0)
    return columns, c_theta, c_eps


@dataclass
class NormalBlocks:
    r"""The normal equations of the model with ``2K + 1`` columns :math:`\Phi` and their derivatives
    :math:`\Phi_j` in the nonlinear parameters (:data:`NONLINEAR`), summed over the frames (weights
    :math:`W = \Sigma^{-1}`): ``A`` :math:`= \Phi^\top W\Phi`, ``B[j]`` :math:`= \Phi^\top W\Phi_j`,
    ``C[j][l]`` :math:`= \Phi_j^\top W\Phi_l`, ``b`` :math:`= \Phi^\top W u`, ``c[j]`` :math:`= \Phi_j^\top W u`,
    ``usu`` :math:`= u^\top W u`."""

    A: np.ndarray
    B: list
    C: list
    b: np.ndarray
    c: list
    usu: float
    n_data: int


@dataclass
class CycleData:
    r"""The voxel data of a cine slice's frames for the momentum model at any viscosity and wall offset.

    ``problems[k]`` is frame ``k``'s plain velocity problem on the wall the model uses, ``sigmas[k]`` its
    per-voxel velocity noise (m/s), ``times_s[k]`` its trigger time; ``radius_mm`` the cycle's radius in
    :math:`\Lambda_n`. Frames on one wall (the same voxels and map) share its columns.
    """

    problems: list
    sigmas: list
    times_s: np.ndarray
    omega: float
    radius_mm: float
    voxel_mm: float = 1.0  # the voxel size (bounds the walls' offset)
    groups: list = field(default_factory=list)  # per frame, the index of its wall among the distinct ones

    def __post_init__(self):
        self.times_s = np.asarray(self.times_s, dtype=float)
        walls: list = []
        self.groups = []
        for p in self.problems:
            same = [i for i, q in enumerate(walls) if _same_wall(p, q)]
            if same:
                self.groups.append(same[0])
            else:
                self.groups.append(len(walls))
                walls.append(p)
        self.points = [WallPoints.of(p) for p in walls]

    @property
    def n_data(self) -> int:
        return int(sum(p.data.size for p in self.problems))

    def blocks(self, nu_m2_s: float, harmonics: int, offset_mm: float = 0.0, derivative: bool = True):
        r"""The summed normal equations at viscosity ``nu_m2_s`` and wall offset ``offset_mm`` (:class:`NormalBlocks`;
        ``B``, ``C``, ``c`` empty without ``derivative``).

        Per frame one Gram matrix of :math:`[\Phi, \Phi_\theta, \Phi_\epsilon, u]`: the columns cost far more
        than these products.
        """
        k, p = harmonics, 2 * harmonics + 1
        parts = [offset_columns(w, k, self.omega, nu_m2_s, self.radius_mm, offset_mm, derivative) for w in self.points]
        n_nl = len(NONLINEAR) if derivative else 0
        size = p * (1 + n_nl) + 1
        total = np.zeros((size, size))
        for problem, sigma, t, g in zip(self.problems, self.sigmas, self.times_s, self.groups):
            phase = time_factors(k, self.omega, t)
            blocks = parts[g] if derivative else (parts[g],)
            cols = np.hstack([_columns(v, phase) for v in blocks] + [problem.data[:, None]])
            weighted = cols / np.asarray(sigma, dtype=float)[:, None]
            total += weighted.T @ weighted
        span = [slice(p * (1 + j), p * (2 + j)) for j in range(n_nl)]
        return NormalBlocks(
            total[:p, :p], [total[:p, sj] for sj in span], [[total[sj, sl] for sl in span] for sj in span],
            total[:p, -1], [total[sj, -1] for sj in span], float(total[-1, -1]), self.n_data,
        )  # fmt: skip

    def fits(self, nu_m2_s: float, k_max: int, offset_mm: float = 0.0) -> list[MomentumFit]:
        """The fits with ``K = 0 .. k_max`` harmonics at one viscosity and offset (:func:`fits_from_normal`)."""
        b = self.blocks(nu_m2_s, k_max, offset_mm, derivative=False)
        return fits_from_normal(b.A, b.b, b.usu, b.n_data, self.omega, nu_m2_s, offset_mm)


def _same_wall(p: vel.VelocityProblem, q: vel.VelocityProblem) -> bool:
    """Two frames' problems on one wall and voxel set (their model columns are the same)."""
    return (
        p.voxels is q.voxels
        and np.array_equal(p.disk_map.coefficients, q.disk_map.coefficients)
        and tuple(p.disk_map.center) == tuple(q.disk_map.center)
        and p.averager is q.averager
    )


def wall_rows(fitted: MomentumFit, frame: FrameTerms, phi: np.ndarray, viscosity_pa_s: float):
    """``D`` with ``tau(phi) = D a`` on a frame's wall at its time (Pa per m/s), shape ``(n_phi, 2K + 1)``."""
    return rows_at(fitted, frame.coefficients, frame.time_s, frame.radius_mm, phi, viscosity_pa_s)[0]


def rows_at(fitted: MomentumFit, wall, time_s: float, radius_mm: float, phi: np.ndarray, viscosity_pa_s: float):
    r"""``(D, d_tau)``: ``tau(phi) = D a`` on a wall (radius coefficients, mm; moved outward by the fit's
    ``offset_mm``) at any time of the cycle (Pa per m/s, ``(n_phi, 2K + 1)``), and the derivatives of ``tau`` in
    :data:`NONLINEAR` (Pa, ``(n_phi, 2)``).

    :math:`\tau = -\mu\,(n\cdot\nabla\sigma) \sum_j a_j S_j'(1) e_j(t)`; in the offset both factors move:
    :math:`n\cdot\nabla\sigma` (CasADi's exact derivative, :func:`normal_gradient_offset_function`) and
    :math:`\Lambda_n \propto R + \epsilon` (:math:`\partial_\epsilon S'(1) = -\tfrac{2}{R+\epsilon}
    \partial_\theta S'(1)`, :func:`wall_slope_derivative`)."""
    wall = np.array(wall, dtype=float)
    wall[0] += fitted.offset_mm
    radius = radius_mm + fitted.offset_mm
    grad, d_grad = normal_gradient(wall, phi, derivative=True)
    k = fitted.harmonics
    lams = lambdas(k, radius, fitted.omega, fitted.nu_m2_s)
    slopes, d_slopes = [wall_slope(0)], [0.0]
    for lam, e in zip(lams, time_factors(k, fitted.omega, time_s)):
        value, d_value = wall_slope(lam) * e, wall_slope_derivative(lam) * e
        slopes += [value.real, -value.imag]
        d_slopes += [d_value.real, -d_value.imag]
    s, ds = np.real(np.array(slopes)), np.real(np.array(d_slopes))
    # tau = -mu d_n u with u in m/s and grad sigma in 1/mm
    scale = -viscosity_pa_s * 1e3
    rows = scale * grad[:, None] * s[None, :]
    a = fitted.coefficients
    d_theta = scale * grad * (ds @ a)
    d_offset = scale * (d_grad * (s @ a) + grad * (-2.0 / radius) * (ds @ a))
    return rows, np.column_stack([d_theta, d_offset])


def normal_gradient(wall, phi: np.ndarray, derivative: bool = False):
    r""":math:`n\cdot\nabla\sigma` at the wall points of angles ``phi`` of the wall ``R(phi)`` (1/mm); with
    ``derivative`` also its derivative in an outward offset of the wall (1/mm^2)."""
    wall = np.asarray(wall, dtype=float)
    phi = np.asarray(phi, dtype=float)
    value, d_value = _normal_gradient(wall.tobytes(), phi.tobytes())
    return (value.copy(), d_value.copy()) if derivative else value.copy()


@functools.lru_cache(maxsize=64)
def _normal_gradient(wall: bytes, phi: bytes) -> tuple[np.ndarray, np.ndarray]:
    """:func:`normal_gradient` once per wall and angles (a rigid wall's at every instant of the cycle)."""
    c, angles = np.frombuffer(wall), np.frombuffer(phi)
    fun = normal_gradient_offset_function(rad.n_fourier_from_size(c.size)).map(angles.size)
    value, d_value = fun(angles[None, :], c)
    return np.asarray(value).ravel(), np.asarray(d_value).ravel()


def wall_shear(
    fitted: MomentumFit, frame: FrameTerms, phi: np.ndarray, viscosity_pa_s: float
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``(tau, tau_std, mean, mean_std)`` of the fitted model on a frame's wall (Pa; std: the velocity noise's,
    through the fitted viscosity and wall offset too where they were fitted)."""
    return shear_at(fitted, frame.coefficients, frame.time_s, frame.radius_mm, phi, viscosity_pa_s)


def shear_at(fitted: MomentumFit, wall, time_s: float, radius_mm: float, phi, viscosity_pa_s: float):
    """:func:`wall_shear` on any wall at any time of the cycle (:func:`rows_at`); the mean over the moved wall."""
    rows, d_tau = rows_at(fitted, wall, time_s, radius_mm, phi, viscosity_pa_s)
    full = np.hstack([rows, d_tau])  # tau is linear in a; the nonlinear parameters enter to first order
    coefficients = np.r_[fitted.coefficients, 0.0, 0.0]
    moved = np.array(wall, dtype=float)
    moved[0] += fitted.offset_mm
    return linear_wall_shear(full, coefficients, fitted.joint_covariance(), moved, phi)


def linear_wall_shear(rows: np.ndarray, coefficients, covariance, wall, phi: np.ndarray):
    """``(tau, tau_std, mean, mean_std)`` of a WSS linear in the model's coefficients, ``tau = rows @ c``, with
    ``c``'s covariance; the mean is the arc-length mean over uniform angles ``phi`` of the wall ``R(phi)``
    (radius coefficients ``wall``; :func:`wss_nlp.core.radius.arc_length_mean`)."""
    tau = rows @ coefficients
    tau_std = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", rows, covariance, rows), 0.0))
    ds = np.hypot(rad.evaluate(wall, phi), rad.evaluate(wall, phi, 1))
    mean_row = (ds / np.sum(ds)) @ rows
    return tau, tau_std, float(mean_row @ coefficients), float(np.sqrt(max(mean_row @ covariance @ mean_row, 0.0)))


def max_harmonics(n_frames: int, limit: int) -> int:
    """Harmonics the frames can carry: up to the Nyquist harmonic ``n_frames // 2``, at most ``limit``.

    At the Nyquist harmonic the frames see ``e^{i n omega t_k} = (-1)^k`` only, but its two columns still
    differ in space (the real and imaginary parts of ``S_n``), so its complex amplitude stays identifiable.
    """
    return int(max(0, min(limit, n_frames // 2)))
