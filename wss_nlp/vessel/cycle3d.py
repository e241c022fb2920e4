r"""The velocity of a cine volume over the cycle: each frame's own fit or a periodic temporal prior, by the data.

Model
-----
Every frame ``t = 0 .. n-1`` of a cine volume has the functional of :mod:`wss_nlp.vessel.velocity3d` on one rigid
wall with one ``beta`` for the cycle, so one Hessian ``H = K + beta/(pi L) G_Delta + kappa_v/(pi L) G_ss``
(``K = T^T W T``) and its own right-hand side ``r_t = T^T W u_t``. The prior ties the frames' coefficients by
their periodic second difference in time, as :mod:`wss_nlp.models.temporal` does for a cine slice:

.. math::

    \min_{a_0, \dots, a_{n-1}} \sum_t Q_t(a_t)
    + \frac{\gamma}{\pi L} \sum_t \|(D_2 a)_t\|^2_{L^2(B \times [s_0, s_1])},
    \qquad (D_2 a)_t = a_{t+1} - 2 a_t + a_{t-1} \ \text{(periodic)},

with ``M`` the :math:`L^2` Gram matrix of the velocity basis over the reference cylinder (B-splines in ``s`` times
the wall basis on the unit disk ``B``): per unit length the penalty is the mean square of the second difference
over the reference section, so ``gamma`` is dimensionless as ``beta`` is. Its normal equations
``(I (x) H + c D_2^T D_2 (x) M) A = R``, ``c = gamma / (pi L)``, have a circulant block structure: the temporal
DFT ``hat a_k = sum_t a_t exp(-2 pi i k t / n)`` splits them into ``n`` independent systems

.. math:: (H + c \lambda_k M) \hat a_k = \hat r_k, \qquad \lambda_k = (2 - 2 \cos(2 \pi k / n))^2,

the eigenvalues of the periodic ``D_2^T D_2``; modes ``k`` and ``n - k`` share a matrix, so ``n // 2 + 1`` banded
Cholesky factorizations of the bandwidth of ``H`` (``M`` has the same block band) solve the joint problem
exactly (:func:`solve_prior`). ``gamma -> 0`` gives the frames' own fits back. This needs the frames equally
spaced over the whole cycle (the periodic difference assumes it, :func:`spacing_refusal`); otherwise the frames
keep their own fits and a note says why (a general block solve for irregular trigger times is not implemented:
scanners' cine reconstructions give equally spaced frames).

Choice (notes)
--------------
Over all ``N = 3 V n`` voxel values of the cycle, with ``chi^2 = sum_t sum_i |T_i a_t - u_{t,i}|^2_{Sigma_i^{-1}}``
(the per-voxel, per-component velocity noise of :func:`wss_nlp.vessel.velocity3d.velocity_noise`: the venc and
the magnitude's noise) and ``dof`` the smoother's trace ``3 sum_k tr((H + c lambda_k M)^{-1} K)``:

* ``gamma`` minimizes the predictive risk (Mallows' ``C_p``, the unbiased predictive risk estimator)
  ``chi^2 + 2 dof`` over decades (:data:`GAMMAS`), then quarter decades about the best;
* the prior at that ``gamma`` competes with the frames' own fits (``gamma = 0``) by Schwarz's criterion
  ``BIC = chi^2 + ln(N) dof``, as for a cine slice (:mod:`wss_nlp.parameters.cycle`), and must lead by
  :data:`wss_nlp.parameters.cycle.EVIDENCE`; otherwise the frames keep their own fits.

Why not the BIC for ``gamma`` too: its ``ln N`` per degree of freedom over-smooths a few frames' worth of
harmonics. On a smooth 12-frame tube the BIC's ``gamma`` damped the fundamental and left the velocity error above
the frames' own, where the predictive risk's gamma lowered it (``scripts/results/vessel_cycle_choice.md``).
Without the venc (no noise model) both are generalized cross-validation over the cycle,
``GCV = N sum_t sum_i w_i |T_i a_t - u_{t,i}|^2 / (N - dof)^2``, the smaller value winning.

The trace is exact: one generalized eigendecomposition ``H X = M X diag(mu)``, ``X^T M X = I``
(:class:`_Spectrum`) gives ``tr((H + c lambda_k M)^{-1} K) = sum_j d_j / (mu_j + c lambda_k)``,
``d = diag(X^T K X)``, and every mode's solution at every ``gamma`` from ``X^T hat r_k``; the chosen ``gamma``'s
coefficients come from the banded solves. The chosen model, its criterion values, the curve over ``gamma`` and the
margin go into the result's ``parameters['cycle']`` (:meth:`CycleChoice.as_dict`) and one note.

What is not carried from 2D: each frame's own beta (one beta serves the cycle: the rigid wall's one
factorization; with per-frame betas the DFT would not decouple the frames), and the momentum balance
(Womersley) model, whose profiles solve ``rho u_t = G(t) + mu Delta u`` for fully developed axial flow in a
straight pipe: curvature (Dean flow), taper and swirl break it (``docs/guide/4d-flow.md``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from .._lazy import scipy
from ..errors import InputError
from ..parameters.cycle import EVIDENCE
from . import band3d
from . import velocity3d as v3

log = logging.getLogger(__name__)

#: The cycle's velocity models of a cine volume: the criterion's choice, each frame's own fit, the temporal prior
#: (``gamma`` by the criterion); a number is a fixed ``gamma``.
CYCLE_MODELS = ("auto", "frames", "temporal")
#: The decades of gamma the criterion is evaluated on first (then quarter decades about the best).
GAMMAS = 10.0 ** np.arange(-4.0, 6.01, 1.0)
#: Frames count as equally spaced over the cycle when every spacing (the last one wrapping to the next cycle's
#: first frame) is within this fraction of ``T / n`` (as for a cine slice, :mod:`wss_nlp.pipeline.cine`).
SPACING_RTOL = 0.01


def check_setting(value) -> str | float:
    """``value`` as a cycle-model setting: one of :data:`CYCLE_MODELS` or a fixed ``gamma > 0``."""
    if isinstance(value, str):
        if value in CYCLE_MODELS:
            return value
        try:
            value = float(value)
        except ValueError:
            raise InputError(
                f"cycle model must be one of {', '.join(CYCLE_MODELS)} or a number gamma > 0, got {value!r}"
            ) from None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise InputError(f"cycle model must be one of {', '.join(CYCLE_MODELS)} or a number gamma > 0, got {value!r}")
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"a fixed temporal prior weight gamma must be a finite number > 0, got {value}")
    return float(value)


def temporal_eigenvalues(n: int) -> np.ndarray:
    """``lambda_k = (2 - 2 cos(2 pi k / n))^2``, ``k = 0 .. n // 2``: the eigenvalues of the periodic ``D_2^T D_2``
    (:func:`wss_nlp.models.temporal.second_difference`) on the temporal DFT's modes."""
    k = np.arange(n // 2 + 1)
    return (2.0 - 2.0 * np.cos(2.0 * np.pi * k / n)) ** 2


def mode_multiplicity(n: int) -> np.ndarray:
    """How many of the ``n`` DFT modes each real-DFT mode ``k = 0 .. n // 2`` stands for (``k`` and ``n - k``)."""
    m = np.full(n // 2 + 1, 2.0)
    m[0] = 1.0
    if n % 2 == 0:
        m[-1] = 1.0
    return m


def mass_gram(problem: v3.VelocityProblem3D) -> np.ndarray:
    """``M``: the :math:`L^2` Gram matrix of the velocity basis over the reference cylinder,
    ``int int v_i v_j dxi ds`` (B-splines' Gram in ``s`` times the wall basis's on the unit disk)."""
    return np.kron(problem.basis.spline.gram(0), problem.basis.disk.laplacian_gram(0))


def spacing_refusal(times_ms, period_ms: float | None) -> str | None:
    """Why the periodic prior cannot take these frames (None: it can): fewer than 3, or not equally spaced over
    the whole cycle (:data:`SPACING_RTOL`)."""
    t = np.asarray(times_ms, float).ravel()
    if t.size < 3:
        return f"the temporal prior needs at least 3 frames, got {t.size}"
    if period_ms is None or not period_ms > 0:
        return "the temporal prior needs the cardiac period (the frames' periodic differences)"
    step = float(period_ms) / t.size
    gaps = np.diff(np.r_[t, t[0] + float(period_ms)])
    if not np.allclose(gaps, step, rtol=SPACING_RTOL, atol=0.0):
        return (
            f"the frames are not equally spaced over the {period_ms:g} ms cycle (spacings {gaps.min():.4g} to "
            f"{gaps.max():.4g} ms against {step:.4g} ms): the temporal prior's periodic differences need that"
        )
    return None


def solve_prior(problem: v3.VelocityProblem3D, beta: float, gamma: float, rhs: np.ndarray,
                mass: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """The prior's coefficients ``(n, size, k)`` for the frames' right-hand sides ``rhs`` ``(n, size, k)``
    (``T^T W u_t``), exactly: one banded Cholesky solve per real-DFT mode (module notes)."""
    rhs = np.asarray(rhs, float)
    n = rhs.shape[0]
    mass = mass_gram(problem) if mass is None else mass
    c = float(gamma) / (np.pi * problem.length_mm)
    hat = np.fft.rfft(rhs, axis=0)  # (n // 2 + 1, size, k)
    h0 = problem.hessian(beta)
    bw = problem.bandwidth()
    k = rhs.shape[2]
    out = np.empty_like(hat)
    for j, lam in enumerate(temporal_eigenvalues(n)):
        cb = scipy.linalg.cholesky_banded(v3.to_banded(h0 + c * lam * mass, bw), lower=False)
        both = scipy.linalg.cho_solve_banded((cb, False), np.hstack([hat[j].real, hat[j].imag]))
        out[j] = both[:, :k] + 1j * both[:, k:]
    return np.fft.irfft(out, n=n, axis=0)


class _Spectrum:
    """``H X = M X diag(mu)``, ``X^T M X = I``: every mode's solve and the smoother's trace at any ``gamma``."""

    def __init__(self, problem: v3.VelocityProblem3D, beta: float, rhs: np.ndarray, mass: np.ndarray):
        self.n = rhs.shape[0]
        self.scale = 1.0 / (np.pi * problem.length_mm)
        self.mu, self.x = scipy.linalg.eigh(problem.hessian(beta), mass)
        self.d = np.einsum("ij,ij->j", self.x, problem.normal() @ self.x)  # diag(X^T K X)
        hat = np.fft.rfft(np.asarray(rhs, float), axis=0)
        self.k = hat.shape[2]
        self.y = self.x.T @ np.concatenate([hat.real, hat.imag], axis=2)  # X^T hat r_k, real and imaginary parts
        self.lam = temporal_eigenvalues(self.n)
        self.mult = mode_multiplicity(self.n)

    def coefficients(self, gamma: float) -> np.ndarray:
        """``(n, size, k)`` at ``gamma``."""
        shift = self.mu[None, :] + gamma * self.scale * self.lam[:, None]  # (modes, size)
        both = self.x @ (self.y / shift[:, :, None])  # (modes, size, 2 k): matrix products, not einsum
        return np.fft.irfft(both[:, :, : self.k] + 1j * both[:, :, self.k :], n=self.n, axis=0)

    def trace(self, gamma: float) -> float:
        """``sum_k tr((H + c lambda_k M)^{-1} K)`` over all ``n`` modes (one velocity component)."""
        shift = self.mu[None, :] + gamma * self.scale * self.lam[:, None]
        return float(np.sum(self.mult[:, None] * self.d[None, :] / shift))


@dataclass
class CycleChoice:
    """Which velocity model a cine volume got over the cycle, and why (``parameters['cycle']`` of the result)."""

    model: str  # "frames" or "temporal"
    gamma: float = 0.0
    how: str = ""  # "chosen by the BIC", "forced", ...
    criterion: str = ""  # the models' comparison: "bic", "gcv" or "" (not evaluated)
    values: dict = field(default_factory=dict)  # model -> criterion value
    margin: float = float("nan")  # the chosen model's lead over the other, EVIDENCE included (BIC)
    curve: dict = field(default_factory=dict)  # gamma -> the selection criterion's value (gamma = 0: the frames)
    dof: dict = field(default_factory=dict)  # model -> smoother's trace (three components, all frames)
    chi2: dict = field(default_factory=dict)  # model -> chi^2 (BIC) or weighted residual (GCV)
    n_data: int = 0
    reason: str = ""  # why the prior was not considered
    seconds: float = 0.0
    selection: str = ""  # gamma's criterion: "upre" (with the noise model) or "gcv"
    #: In memory only: the prior with the eigenpairs its fit computed (the band reuses them), when it was chosen.
    prior: band3d.TemporalPrior | None = field(default=None, repr=False)

    def as_dict(self) -> dict:
        def num(v):
            return None if v is None or not np.isfinite(v) else float(v)

        return {
            "model": self.model, "gamma": num(self.gamma), "how": self.how, "criterion": self.criterion,
            "values": {k: num(v) for k, v in self.values.items()}, "margin": num(self.margin),
            "evidence_required": EVIDENCE if self.criterion == "bic" else None,
            "selection": self.selection, "curve": {f"{g:g}": num(v) for g, v in self.curve.items()},
            "dof": {k: num(v) for k, v in self.dof.items()}, "chi2": {k: num(v) for k, v in self.chi2.items()},
            "n_data": self.n_data, "reason": self.reason,
        }  # fmt: skip

    def note(self) -> str:
        """One line for the result's notes."""
        crit = {"bic": "BIC", "gcv": "GCV"}.get(self.criterion, "")
        vals = ", ".join(f"{k} {v:.6g}" for k, v in self.values.items() if np.isfinite(v))
        tail = f" ({crit}: {vals}" + (f"; margin {self.margin:.3g}" if np.isfinite(self.margin) else "") + ")"
        tail = tail if vals else ""
        if self.model == "temporal":
            by = {"upre": " (by the predictive risk)", "gcv": " (by GCV)"}.get(self.selection, "")
            return f"velocity over the cycle: the frames tied by a periodic temporal prior, gamma {self.gamma:.3g}" \
                f"{by}, {self.how}{tail}"  # fmt: skip
        why = f": {self.reason}" if self.reason else ""
        return f"velocity over the cycle: each frame's own fit, {self.how}{why}{tail}"


def summary(record: dict | None, nt: int) -> str:
    """One line naming the cycle model of a stored ``parameters['cycle']`` of a result with ``nt`` frames
    (``analyze``)."""
    if nt == 1:
        return "velocity: one frame (no cycle model)"
    if not record:
        return "velocity over the cycle: not recorded (a result written before the cycle models: each frame's own fit)"
    if record.get("model") == "temporal":
        head = f"periodic temporal prior, gamma {record.get('gamma')}"
    else:
        head = "each frame's own fit"
    crit = str(record.get("criterion") or "").upper()
    vals = ", ".join(f"{k} {v:.6g}" for k, v in (record.get("values") or {}).items() if v is not None)
    out = f"velocity over the cycle: {head} ({record.get('how', '')})"
    if vals:
        out += f"; {crit} {vals}"
        if record.get("margin") is not None:
            out += f", margin {record['margin']:.3g}"
    if record.get("reason"):
        out += f"; {record['reason']}"
    return out


def fit_cycle(vol, problem: v3.VelocityProblem3D, velocity: v3.Velocity3DResult, setting="auto", times_ms=None,
              period_ms: float | None = None, levels=None) -> tuple[v3.Velocity3DResult, CycleChoice]:  # fmt: skip
    """The cine volume's velocity over the cycle (module notes): ``velocity`` (the frames' own fits, one beta)
    kept or replaced by the temporal prior's.

    ``setting``: "auto" (the criterion's choice), "frames", "temporal" (gamma by the criterion, the prior
    whatever the comparison) or a fixed ``gamma``; ``levels``: the magnitude's levels and noise (the BIC's noise
    model with the venc; GCV without).
    """
    t0 = time.perf_counter()
    setting = check_setting(setting)
    nt = velocity.coefficients.shape[0]
    if nt == 1:
        return velocity, CycleChoice("frames", how="one frame")
    if setting == "frames":
        return velocity, CycleChoice("frames", how="forced (--cine-model independent)")
    reason = spacing_refusal(times_ms, period_ms)
    if reason is not None:
        log.info("cycle: %s", reason)
        return velocity, CycleChoice("frames", how="the prior refused", reason=reason)
    u = v3.voxel_velocities(vol, problem)  # (nt, V, 3)
    rhs = np.stack([problem.rhs(u[t]) for t in range(nt)])  # (nt, size, 3)
    mass = mass_gram(problem)
    spec = _Spectrum(problem, velocity.beta, rhs, mass)
    op = problem.operator()
    n_data = int(u.size)
    sigma = None
    noise_free = levels is None or not levels.noise_sigma > 1e-9 * float(np.mean(levels.lumen))
    if vol.venc_m_s is not None and not noise_free:
        sigma = v3.velocity_noise(vol, problem, levels)  # (V, 3)
    w = problem.weights

    def evaluate(gamma: float) -> tuple[float, float]:
        """(chi^2 with the noise model, or the weighted residual without; dof) at gamma."""
        coef = spec.coefficients(gamma)
        fit = np.stack([op @ coef[t] for t in range(nt)])
        dof = 3.0 * spec.trace(gamma)
        if sigma is not None:
            return float(np.sum(((fit - u) / sigma[None]) ** 2)), dof
        return float(np.sum(w[None, :, None] * (fit - u) ** 2)), dof

    def gcv(part: tuple[float, float]) -> float:
        return n_data * part[0] / max(n_data - part[1], 1e-12) ** 2

    if sigma is not None:
        selection, criterion = "upre", "bic"

        def select(part):  # the unbiased predictive risk (Mallows' C_p) less its constant -N
            return part[0] + 2.0 * part[1]

        def compare(part):
            return part[0] + np.log(n_data) * part[1]
    else:
        selection = criterion = "gcv"
        select = compare = gcv
    parts: dict = {}  # gamma -> (chi2 or residual, dof)

    def at(gamma: float) -> float:
        if gamma not in parts:
            parts[gamma] = evaluate(gamma)
        return select(parts[gamma])

    at(0.0)
    if isinstance(setting, float):
        gamma = setting
        at(gamma)
    else:
        for g in GAMMAS:
            at(float(g))
        best = min((g for g in parts if g > 0), key=at)
        for e in (-0.75, -0.5, -0.25, 0.25, 0.5, 0.75):
            g = float(best * 10.0**e)
            if GAMMAS[0] <= g <= GAMMAS[-1]:
                at(g)
        gamma = min((g for g in parts if g > 0), key=at)
    frames_value, prior_value = compare(parts[0.0]), compare(parts[gamma])
    values = {"frames": frames_value, "temporal": prior_value}
    if criterion == "bic":
        lead = frames_value - prior_value - EVIDENCE
        rule = f"the BIC (the prior must lead by {EVIDENCE:g})"
    else:
        lead = frames_value - prior_value
        rule = "GCV (no velocity noise model: the venc or the magnitude's noise is missing)"
    if setting == "auto":
        model = "temporal" if lead > 0 else "frames"
        how = f"chosen by {rule}"
        margin = abs(lead) if criterion == "bic" else abs(lead) / max(frames_value, 1e-300)
    else:
        model = "temporal"
        how = "forced (--cine-model temporal)" if setting == "temporal" else f"forced, gamma fixed at {gamma:g}"
        margin = float("nan")
    choice = CycleChoice(
        model, gamma if model == "temporal" else 0.0, how, criterion, values, margin,
        {g: at(g) for g in sorted(parts)}, {"frames": parts[0.0][1], "temporal": parts[gamma][1]},
        {"frames": parts[0.0][0], "temporal": parts[gamma][0]}, n_data, selection=selection,
    )  # fmt: skip
    if model == "frames":
        choice.seconds = time.perf_counter() - t0
        return velocity, choice
    coef = solve_prior(problem, velocity.beta, gamma, rhs, mass)
    res = np.stack([problem.residual_norm(coef[t], u[t]) for t in range(nt)])
    choice.prior = band3d.TemporalPrior(gamma, spec.mu, spec.x, spec.lam, spec.mult)
    choice.seconds = time.perf_counter() - t0
    log.info("cycle: temporal prior, gamma %.3g (%s), %.1f s", gamma, how, choice.seconds)
    out = v3.Velocity3DResult(problem, coef, velocity.beta, velocity.beta_choice, res,
                              velocity.seconds + choice.seconds)  # fmt: skip
    return out, choice
