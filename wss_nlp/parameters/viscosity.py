r"""The kinematic viscosity of a cine slice from its data: the momentum model's Stokes layer fitted, not assumed.

The momentum model (:mod:`wss_nlp.models.womersley`) takes the thickness of the Stokes layer of harmonic
:math:`n`, :math:`\sqrt{2\nu/(n\omega)}`, from the kinematic viscosity :math:`\nu = \mu/\rho`. The stated
:math:`\mu` and :math:`\rho` are guesses for blood (3-4.5 mPa s with the haematocrit, shear-thinning; the
density is rarely measured), and a layer of the wrong thickness puts the frames' WSS off by 5-11 % of the
peak at 15-30 % error in :math:`\nu` (issue 40). The data of all frames decide :math:`\nu` with the
model's coefficients :math:`a`, and with it where the layer starts: the walls' outward offset
:math:`\epsilon` (mm; the magnitude-based walls sit about 0.2 % of the radius inside at SNR 25, and a
layer fitted to a wall 0.02 mm off comes out 4 % thin, scripts/results/cine_viscosity.md):

.. math::

    \min_{\theta, \epsilon, a}\ \sum_k \|\Phi_k(\theta, \epsilon)\, a - u_k\|^2_{\Sigma_k^{-1}}, \qquad
    \theta = \ln(\nu/\nu_s), \quad |\theta| \le \ln 4, \quad |\epsilon| \le h/2,

:math:`\nu_s` the stated value, :math:`h` the voxel size. For fixed :math:`x = (\theta, \epsilon)` this is
the model's linear fit, so :math:`x` is found on the profile :math:`f(x) = \min_a F(a, x)` (variable
projection; Golub & Pereyra 1973, SIAM J. Numer. Anal. 10, 413-432) by Gauss-Newton steps with a
backtracking line search: with :math:`r = u - \Phi a` at the profile's :math:`a(x)` and
:math:`\Phi_j = \partial\Phi/\partial x_j`,

.. math::

    \partial_j f = -2\, r^\top W\Phi_j a, \qquad
    \partial_j\partial_l f \approx 2\big((\Phi_j a)^\top W\Phi_l a - (\Phi_j a)^\top W\Phi\,
    (\Phi^\top W\Phi)^{-1}\Phi^\top W\Phi_l a\big),

with :math:`\Phi_j` exact (the Bessel functions' derivatives in closed form,
:func:`wss_nlp.models.womersley.shape_parts`; the smooth partial volumes of
:func:`wss_nlp.models.womersley.offset_columns`). Why not NLP variables in CasADi: the shapes are Bessel
functions of complex argument, which CasADi does not provide; the profile has two dimensions and each of
its values is one linear solve, so a handful of exact Gauss-Newton steps is both exact and cheaper.

Notes
-----
Interval: the Gauss-Newton information of :math:`(a, \theta, \epsilon)`, :math:`J^\top W J` with
:math:`J = [\Phi, \Phi_\theta a, \Phi_\epsilon a]`, inverted and divided by the effective fraction of
independent voxels (:func:`wss_nlp.parameters.cycle.criterion_scale`), scaled by the reduced
:math:`\chi^2/(N - p)` where it exceeds 1 (misfit the noise does not explain widens the interval instead of
being ignored). :data:`LEVEL` two-sided, symmetric in :math:`\ln\nu`. The same joint covariance carries
the viscosity's and the offset's uncertainty into the WSS band
(:meth:`wss_nlp.models.womersley.MomentumFit.joint_covariance`).

The stress keeps the stated :math:`\mu` (:math:`\tau = -\mu\,\partial_n u`; the data give the velocity's
shape, not the stress's scale): the result reports both the stress with the stated :math:`\mu` and the
viscosity the data imply (:math:`\mu = \rho_s\,\nu`), and flags a stated value outside the interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..models.womersley import CycleData, MomentumFit, NormalBlocks

#: The fitted kinematic viscosity stays within this factor of the stated one (either way): far beyond blood's
#: range, and the shapes stay well conditioned.
VISCOSITY_RANGE = 4.0
#: The walls' offset stays within this fraction of the voxel size (either way).
OFFSET_RANGE = 0.5
#: The interval's coverage, and its normal quantile.
LEVEL, Z_LEVEL = 0.95, 1.959963984540054
#: Gauss-Newton steps at most; converged below these steps in ln(nu) (0.01 %) and in the offset (mm); the
#: largest step in ln(nu).
MAX_STEPS, STEP_TOL, OFFSET_TOL, MAX_STEP = 15, 1e-4, 1e-5, 0.5
#: An interval wider than this factor either way says the data do not determine the viscosity (a low
#: Womersley number: the profile is nearly quasi-steady and hardly depends on it).
UNDETERMINED = 1.5


@dataclass
class ViscosityFit:
    """The kinematic viscosity the frames imply, its interval, the walls' offset and the momentum model."""

    nu_stated: float  # m^2/s
    theta: float  # ln(nu / nu_stated)
    std: float  # standard deviation of theta
    offset_mm: float  # the walls moved outward by this much
    offset_std_mm: float
    fit: MomentumFit  # the model at the fitted parameters (its joint covariance includes theirs)
    chi2_stated: float  # the model's chi^2 at the stated viscosity, no offset, the same harmonics
    steps: int
    at_bound: bool  # the viscosity at the bound of its range
    inflation: float  # the reduced chi^2 the covariance was scaled by (1 where the noise explains the misfit)

    @property
    def nu(self) -> float:
        """The fitted kinematic viscosity, m^2/s."""
        return float(self.nu_stated * np.exp(self.theta))

    def interval(self) -> tuple[float, float]:
        """The :data:`LEVEL` interval of the kinematic viscosity (m^2/s)."""
        return (float(self.nu * np.exp(-Z_LEVEL * self.std)), float(self.nu * np.exp(Z_LEVEL * self.std)))

    @property
    def determined(self) -> bool:
        """The data determine the viscosity: not at a bound, interval within :data:`UNDETERMINED` either way."""
        return bool(not self.at_bound and np.isfinite(self.std) and Z_LEVEL * self.std < np.log(UNDETERMINED))

    @property
    def agrees(self) -> bool:
        """The stated viscosity lies inside the interval (or the data do not determine it)."""
        lo, hi = self.interval()
        return bool(not self.determined or lo <= self.nu_stated <= hi)

    def as_dict(self, mu_stated: float, rho: float, radius_mm: float, omega: float) -> dict:
        """The record stored in the result (``cine_model_json``, key ``viscosity``)."""
        lo, hi = self.interval()

        def womersley_number(nu: float, radius: float) -> float:
            return float(radius * 1e-3 * np.sqrt(omega / nu))

        return {
            "mode": "fit",
            "stated_pa_s": float(mu_stated),
            "density_kg_m3": float(rho),
            "nu_stated_m2_s": float(self.nu_stated),
            "nu_m2_s": self.nu,
            "nu_interval_m2_s": [lo, hi],
            "level": LEVEL,
            "std_log_nu": float(self.std),
            "implied_pa_s": float(self.nu * rho),
            "implied_interval_pa_s": [float(lo * rho), float(hi * rho)],
            "womersley_number": womersley_number(self.nu, radius_mm + self.offset_mm),
            "womersley_number_stated": womersley_number(self.nu_stated, radius_mm),
            "radius_mm": float(radius_mm),
            "wall_offset_mm": float(self.offset_mm),
            "wall_offset_std_mm": float(self.offset_std_mm),
            "harmonics": int(self.fit.harmonics),
            "chi2": float(self.fit.chi2),
            "chi2_stated": float(self.chi2_stated),
            "inflation": float(self.inflation),
            "steps": int(self.steps),
            "at_bound": bool(self.at_bound),
            "determined": self.determined,
            "agrees": self.agrees,
        }


def _profile(blocks: NormalBlocks):
    """``(a, f, gradient, Gauss-Newton Hessian, [B_j a])`` of the profile (module notes)."""
    a = np.linalg.solve(blocks.A, blocks.b)
    f = float(blocks.usu - blocks.b @ a)
    ba = [bj @ a for bj in blocks.B]
    grad = np.array([-2.0 * float(cj @ a - a @ v) for cj, v in zip(blocks.c, ba)])
    solved = [np.linalg.solve(blocks.A, v) for v in ba]
    n = len(ba)
    hess = np.array([[2.0 * float(a @ blocks.C[j][m] @ a - ba[j] @ solved[m]) for m in range(n)] for j in range(n)])
    return a, f, grad, hess, ba


def fit_viscosity(
    data: CycleData, harmonics: int, nu_stated: float, nu_eff: float = 1.0, start=(0.0, 0.0), voxel_mm: float = 1.0
) -> ViscosityFit:
    """The viscosity and the walls' offset on the profile (module notes) with ``harmonics`` harmonics, started at
    ``start`` (``theta``, offset in mm); ``nu_eff`` the effective fraction of independent voxels, ``voxel_mm``
    the voxel size (the offset's bound)."""
    upper = np.array([np.log(VISCOSITY_RANGE), OFFSET_RANGE * voxel_mm])
    x = np.clip(np.asarray(start, dtype=float), -upper, upper)

    def at(x):
        return data.blocks(nu_stated * np.exp(x[0]), harmonics, float(x[1]))

    blocks = at(x)
    a, f, grad, hess, ba = _profile(blocks)
    chi2_stated = f if not np.any(x) else float("nan")
    steps = 0
    while steps < MAX_STEPS:
        steps += 1
        try:
            step = -np.linalg.solve(hess, grad)
        except np.linalg.LinAlgError:
            step = -grad / np.maximum(np.abs(np.diag(hess)), 1e-300)
        # a trust region in ln(nu) (the offset moves with it along the step)
        step = step * min(1.0, MAX_STEP / max(abs(step[0]), 1e-300))
        new = np.clip(x + step, -upper, upper)
        accepted = None
        for _ in range(8):  # backtracking: far from the optimum the Gauss-Newton step may overshoot
            if np.array_equal(new, x):
                break
            trial = at(new)
            profile = _profile(trial)
            if profile[1] <= f:
                accepted = (trial, profile)
                break
            new = x + (new - x) / 2
        if accepted is None:
            break
        moved = np.abs(new - x)
        x, (blocks, (a, f, grad, hess, ba)) = new, accepted
        if moved[0] < STEP_TOL and moved[1] < OFFSET_TOL:
            break
    if not np.isfinite(chi2_stated):
        chi2_stated = _profile(data.blocks(nu_stated, harmonics, 0.0, derivative=False))[1]
    p = a.size
    n_nl = len(ba)
    info = np.zeros((p + n_nl, p + n_nl))
    info[:p, :p] = blocks.A
    for j in range(n_nl):
        info[:p, p + j] = info[p + j, :p] = ba[j]
        for m in range(n_nl):
            info[p + j, p + m] = float(a @ blocks.C[j][m] @ a)
    inflation = max(1.0, f / max(blocks.n_data - p - n_nl, 1))
    joint = np.linalg.pinv(info) * inflation / nu_eff
    at_bound = abs(x[0]) >= upper[0] - 1e-9
    std = float(np.sqrt(joint[p, p])) if joint[p, p] > 0 else float("inf")
    offset_std = float(np.sqrt(max(joint[p + 1, p + 1], 0.0)))
    fitted = MomentumFit(
        harmonics, a, joint[:p, :p], f, blocks.n_data, data.omega, float(nu_stated * np.exp(x[0])), float(x[1]),
        joint,
    )  # fmt: skip
    return ViscosityFit(float(nu_stated), float(x[0]), std, float(x[1]), offset_std, fitted, float(chi2_stated),
                        steps, bool(at_bound), inflation)  # fmt: skip
