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
from dataclasses import dataclass

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

    def __post_init__(self):
        if self.model not in MODELS:
            raise InputError(f"cine model must be one of {MODELS}, got {self.model!r}")
        if self.walls not in WALLS:
            raise InputError(f"cine walls must be one of {WALLS}, got {self.walls!r}")
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


#: Points of the per-frame table of each shape function on sigma in [0, 1] (cubic spline; the layer of
#: harmonic n is about 1/|Lambda_n| wide in sigma, >= 0.01 for any harmonic a 20-frame series carries at
#: Womersley numbers below 30, so the spline's error is below 1e-8 of the shape's scale: tests).
TABLE_POINTS = 4097


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


def shapes_at(sigma: np.ndarray, lams: list[complex]) -> np.ndarray:
    """``S_0, S_1, ..., S_K`` at ``sigma`` (complex, shape ``(n, K + 1)``).

    Each complex shape is tabulated on :data:`TABLE_POINTS` values of sigma and interpolated by a cubic
    spline (built once per ``Lambda``): the Bessel functions of complex argument cost about a microsecond
    each and a frame has ten thousand sub-voxel points.
    """
    sigma = np.clip(np.asarray(sigma, dtype=float), 0.0, 1.0)
    return np.column_stack([shape(sigma, 0).astype(complex)] + [_spline(complex(lam))(sigma) for lam in lams])


@functools.lru_cache(maxsize=64)
def _spline(lam: complex):
    import scipy.interpolate  # here: a slow import (0.1 s) the command line should not pay at start-up

    table = np.linspace(0.0, 1.0, TABLE_POINTS)
    return scipy.interpolate.CubicSpline(table, shape(table, lam))


def _columns(shapes: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """The real columns ``S_0, Re(S_n e_n), -Im(S_n e_n)`` of complex ``shapes`` (any linear image of them)."""
    value = shapes[:, 1:] * np.asarray(phase)[None, :]
    cols = np.empty((shapes.shape[0], 2 * value.shape[1] + 1))
    cols[:, 0] = shapes[:, 0].real
    cols[:, 1::2], cols[:, 2::2] = value.real, -value.imag
    return cols


def wall_shapes(problem: vel.VelocityProblem, k_max: int, omega: float, nu_m2_s: float, radius_mm: float):
    """The voxel values of ``S_0 .. S_K`` on ``problem``'s wall (complex ``(n_vox, K + 1)``): frames on one wall
    share them, each frame's columns are these times its phases (the voxel values are linear)."""
    vox = problem.voxels
    coefficients, center = problem.disk_map.coefficients, problem.disk_map.center
    s = ray_coordinate(coefficients, center, vox.px[vox.inside], vox.py[vox.inside])
    shapes = shapes_at(s, lambdas(k_max, radius_mm, omega, nu_m2_s))
    return vel.voxel_values(problem, shapes.real) + 1j * vel.voxel_values(problem, shapes.imag)


@dataclass
class MomentumFit:
    """The momentum model of one cine slice fitted with ``harmonics`` harmonics."""

    harmonics: int
    coefficients: np.ndarray  # a_0, Re a_1, Im a_1, ... (m/s)
    covariance: np.ndarray  # of the coefficients from the velocity noise, (m/s)^2
    chi2: float
    n_data: int
    omega: float  # rad/s
    nu_m2_s: float


def fit(terms: list[FrameTerms], omega: float, nu_m2_s: float) -> list[MomentumFit]:
    """Weighted least squares over all frames (module notes) with ``K = 0 .. K_max`` harmonics.

    The columns of ``K`` harmonics are the first ``2K + 1`` of ``K_max``'s, so each fit solves the leading
    block of the summed normal matrix; its inverse is the coefficients' covariance.
    """
    normal = np.sum([t.normal for t in terms], axis=0)
    rhs = np.sum([t.rhs for t in terms], axis=0)
    usu, n_data = sum(t.usu for t in terms), sum(t.n_data for t in terms)
    out = []
    for k in range((normal.shape[0] - 1) // 2 + 1):
        j = 2 * k + 1
        try:
            covariance = np.linalg.inv(normal[:j, :j])
        except np.linalg.LinAlgError as exc:
            raise InputError(f"the momentum model's normal matrix is singular ({exc}); too few frames") from exc
        coef = covariance @ rhs[:j]
        chi2 = float(coef @ normal[:j, :j] @ coef - 2 * coef @ rhs[:j] + usu)
        out.append(MomentumFit(k, coef, covariance, chi2, n_data, omega, nu_m2_s))
    return out


def wall_rows(fitted: MomentumFit, frame: FrameTerms, phi: np.ndarray, viscosity_pa_s: float):
    """``D`` with ``tau(phi) = D a`` on a frame's wall at its time (Pa per m/s), shape ``(n_phi, 2K + 1)``."""
    coefficients, time_s = frame.coefficients, frame.time_s
    n_fourier = rad.n_fourier_from_size(coefficients.size)
    grad = np.asarray(normal_gradient_function(n_fourier).map(phi.size)(phi[None, :], coefficients)).ravel()
    k = fitted.harmonics
    lams = lambdas(k, frame.radius_mm, fitted.omega, fitted.nu_m2_s)
    slopes = [wall_slope(0)]
    for lam, e in zip(lams, time_factors(k, fitted.omega, time_s)):
        value = wall_slope(lam) * e
        slopes += [value.real, -value.imag]
    # tau = -mu d_n u with u in m/s and grad sigma in 1/mm
    return -viscosity_pa_s * 1e3 * grad[:, None] * np.real(np.array(slopes))[None, :]


def wall_shear(
    fitted: MomentumFit, frame: FrameTerms, phi: np.ndarray, viscosity_pa_s: float
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``(tau, tau_std, mean, mean_std)`` of the fitted model on a frame's wall (Pa; std: the velocity noise's)."""
    rows = wall_rows(fitted, frame, phi, viscosity_pa_s)
    return linear_wall_shear(rows, fitted.coefficients, fitted.covariance, frame.coefficients, phi)


def linear_wall_shear(rows: np.ndarray, coefficients, covariance, wall, phi: np.ndarray):
    """``(tau, tau_std, mean, mean_std)`` of a WSS linear in the model's coefficients, ``tau = rows @ c``, with
    ``c``'s covariance; the mean is the arc-length mean over uniform angles ``phi`` of the wall ``R(phi)``
    (radius coefficients ``wall``; :func:`wss_nlp.core.radius.arc_length_mean`)."""
    tau = rows @ coefficients
    tau_std = np.sqrt(np.einsum("ij,jk,ik->i", rows, covariance, rows))
    ds = np.hypot(rad.evaluate(wall, phi), rad.evaluate(wall, phi, 1))
    mean_row = (ds / np.sum(ds)) @ rows
    return tau, tau_std, float(mean_row @ coefficients), float(np.sqrt(mean_row @ covariance @ mean_row))


def max_harmonics(n_frames: int, limit: int) -> int:
    """Harmonics the frames can carry: up to the Nyquist harmonic ``n_frames // 2``, at most ``limit``.

    At the Nyquist harmonic the frames see ``e^{i n omega t_k} = (-1)^k`` only, but its two columns still
    differ in space (the real and imaginary parts of ``S_n``), so its complex amplitude stays identifiable.
    """
    return int(max(0, min(limit, n_frames // 2)))
