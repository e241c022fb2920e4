"""Stacks of slices regularized along the vessel (paper Sec. 5): fully coupled or by Kaczmarz sweeps.

Geometry and velocity coefficients of all slices are fitted together, with a
penalty on their m-th difference along z (m = ``z_order``, default 2) added
to the 2D functionals of Secs. 2 and 3:

``sum_k J_k(c_k) + kappa sum_k ||(D_m R)_k||^2_{L2(0, 2pi)}`` (geometry),
``sum_k Q_k(v_k) + kappa_v sum_k ||(D_m v)_k||^2_{L2(B)} / pi`` (velocity),

``D_1 R_k = R_{k+1} - R_k``, ``D_2 R_k = R_{k+2} - 2 R_{k+1} + R_k``. In
coefficients this is ``C^T (L x W) C`` with ``L = D_m^T D_m`` and the L2 Gram
matrix W of the radius (``W0``) or velocity (``G0``) basis.

The weights come from one interpretable length, ``z_smoothing_mm`` = l: the
misfit of one slice changes by about ``2 pi R delta^2 / h`` when the wall
moves by delta (a band of wall voxels of width h), and by about
``||delta v||^2_{L2(B)} / pi`` when the velocity changes by delta v, so
``kappa = (l / dz)^(2m) R / h`` and ``kappa_v = (l / dz)^(2m)`` make l the
length along the vessel over which data of neighbouring slices are pooled.
l = 0 gives independent slices.

Two solvers of the same problem:

* ``coupled``: one CasADi NLP over all geometry coefficients (IPOPT, box
  per slice, Gauss-Newton Hessian: block diagonal plus the z-Laplacian), then
  one CasADi QP over all velocity coefficients (IPOPT);
* ``kaczmarz``: sweeps over the slices (forward then backward), each a 2D
  problem with its neighbours fixed, until the coupled optimality residual
  is below ``tol`` (geometry: Gauss-Newton steps per slice, residual = the
  relative Newton step of every slice for the coupled functional with the
  final neighbours; velocity: block Gauss-Seidel on the normal equations,
  factorized once, residual = relative residual of the coupled equations).

The velocity basis of each slice is the one a single slice would get: the
near-wall model (``--near-wall``, :func:`wss_nlp.parameters.choice.layer_model`) is chosen
per slice, and the z-penalty ties the plain basis coefficients only (a layer's
columns, with their own scale, stay the slice's own).

A slice whose data are unusable (NaN or Inf, no vessel found) is reported by
index, left out, and splits the stack into independent segments.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.linalg

import casadi as ca

from .parameters import noise as nl
from .parameters import rules as pr
from . import dephasing as deph
from . import geometry as geo
from . import preprocess as pp
from . import operators
from . import radius as rad
from . import sensitivity as sens
from . import stack_band
from . import velocity as vel
from . import wss as wss_mod
from .errors import InputError, SolverError, WssNlpError
from .parameters.choice import gcv_beta, layer_model, velocity_beta
from . import coupled as cpl
from .coupled import sparse_dm
from .files import Acquisition
from .results import SliceResult
from .schema import option
from .solver import SolverStats, gauss_newton_ipopt, ipopt_options, run_nlpsol

logger = logging.getLogger(__name__)  # progress of long stack solves (the CLI shows INFO on stderr)

STRATEGIES = ("auto", "coupled", "kaczmarz")

#: Over-relaxation of the velocity sweeps (symmetric SOR; 1 is plain Gauss-Seidel, any value in (0, 2) converges
#: to the same solution). 1.5 cut the sweeps from 53 to 44 on 10-100 slices; for the geometry's Gauss-Newton
#: updates it did not help (20 -> 22 sweeps), so they are not relaxed.
RELAX = 1.5

#: ``strategy = "auto"`` solves segments of at most this many slices fully coupled.
COUPLED_MAX_SLICES = 8


@dataclass(frozen=True)
class StackOptions:
    """How the slices of a stack are tied together.

    Attributes
    ----------
    z_smoothing_mm : float or None
        Length l along the vessel over which neighbouring slices are pooled
        (module notes); None means one slice spacing; 0 independent slices.
    z_order : {1, 2}
        Order of the z-derivative penalized. 2 (default) leaves a linear taper
        unbiased and has no pull at the ends of the stack; 1 (the first
        derivative) biases a radius that changes along z by about
        ``l R'`` at the ends and ``l^2 R''`` inside (measured in the docs).
    strategy : {"auto", "coupled", "kaczmarz"}
        "auto": coupled for segments of at most :data:`COUPLED_MAX_SLICES`.
    tol : float
        Kaczmarz: relative coupled optimality residual at which the sweeps stop.
    max_sweeps : int
    """

    schema_group = "stacks of slices (Sec. 5)"

    z_smoothing_mm: float | None = option(
        None,
        "length in mm along the vessel over which neighbouring slices are "
        "pooled (z-regularization of geometry and velocity); 0 = independent "
        "slices (default: one slice spacing)",
        cli="--z-smoothing",
    )
    z_order: int = option(
        2,
        "order of the z-derivative penalized: 2 keeps linear tapers unbiased, 1 = first derivative",
        cli="--z-order",
        choices=(1, 2),
    )
    strategy: str = option(
        "auto",
        f"one coupled NLP, Kaczmarz sweeps, or auto (coupled up to {COUPLED_MAX_SLICES} slices)",
        cli="--stack-strategy",
        choices=STRATEGIES,
    )
    tol: float = 1e-6
    max_sweeps: int = 300

    def __post_init__(self):
        if self.strategy not in STRATEGIES:
            raise InputError(f"stack strategy must be one of {STRATEGIES}, got {self.strategy!r}")
        if self.z_smoothing_mm is not None and not self.z_smoothing_mm >= 0:
            raise InputError(f"z smoothing must be >= 0 mm, got {self.z_smoothing_mm}")
        if self.z_order not in (1, 2):
            raise InputError(f"z order must be 1 or 2, got {self.z_order}")
        if not self.tol > 0 or self.max_sweeps < 1:
            raise InputError("stack tol must be > 0 and max_sweeps >= 1")


@dataclass
class StackInfo:
    """What the stack solve did (stored in the result file)."""

    strategy: str
    z_smoothing_mm: float
    kappa: float  # geometry z weight, mm^2 (per unit L2 of R differences)
    kappa_velocity: float
    segments: list  # lists of slice indices solved together
    failed: dict  # slice index -> reason
    sweeps: dict = field(default_factory=dict)  # "geometry"/"velocity" -> sweeps per segment
    residuals: dict = field(default_factory=dict)  # "geometry"/"velocity" -> residual history of the last segment
    converged: bool = True
    dephasing_pass: bool = False  # a second pass on dephasing-corrected magnitudes was run
    seconds: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {k: (v if not isinstance(v, dict) else {str(a): b for a, b in v.items()}) for k, v in vars(self).items()}


@dataclass
class _Slice:
    index: int
    problem: geo.GeometryProblem
    norm: pp.Normalization
    lumen: pp.Lumen
    magnitude: np.ndarray  # normalized
    velocity_image: np.ndarray


# ------------------------------------------------------------------ geometry
class SliceGeometry:
    """The CasADi pieces of one slice's geometry functional, with the z-coupling to fixed neighbours.

    The slice's part of the coupled functional, as a function of ``c_k`` alone
    (neighbours fixed), is ``J_k(c) + kappa (L_kk c^T W0 c - 2 c^T W0 s)`` up
    to a constant, ``s = -sum_{j != k} L_kj c_j`` (:func:`neighbour_terms`;
    for m = 1 inside the stack ``L_kk = 2`` and ``s`` is the sum of the two
    neighbours). :meth:`newton` minimizes it by Gauss-Newton steps with a
    backtracking line search (exact CasADi gradient and Gauss-Newton
    Hessian); when a step would leave the box it hands over to IPOPT
    (:meth:`solve`, built on first use), which handles the box.
    """

    def __init__(self, problem: geo.GeometryProblem, options: geo.GeometryOptions, kappa: float):
        self.problem, self.options, self.kappa = problem, options, kappa
        nlp = self.nlp = geo.build_tikhonov(problem, options, separable_jacobian=True)
        c, alpha = nlp.c, nlp.alpha
        n = c.numel()
        self.w0 = rad.sobolev_weights(options.n_fourier, 0)
        assert nlp.jacobian is not None  # separable_jacobian=True
        self._gram = operators.Gram(*nlp.jacobian.shape)  # a callback: kept as long as the functions using it
        gn = 2 * self._gram(nlp.jacobian) + 2 * alpha * ca.diag(ca.DM(nlp.weights))
        # separate functions: derivatives of f must not run through the Gauss-Newton matrix's graph
        self.parts = (ca.Function("slice", [c, alpha], [nlp.f, nlp.g]), ca.Function("slice_gn", [c, alpha], [gn]))
        s, cnt = ca.MX.sym("s", n), ca.MX.sym("l_kk")
        w0 = ca.DM(self.w0)
        self._f = nlp.f + kappa * (cnt * ca.dot(w0 * c, c) - 2 * ca.dot(w0 * s, c))
        self._hess = gn + 2 * kappa * cnt * ca.diag(w0)
        self._c, self._p = c, ca.vertcat(alpha, cnt, s)
        self.objective = ca.Function("f", [c, self._p], [self._f])
        self.local = ca.Function("fgh", [c, self._p], [self._f, ca.gradient(self._f, c), self._hess])
        self.box = ca.DM(rad.design_matrix(options.box_angles(), options.n_fourier)).full()
        self._solver: Any = None  # the IPOPT solver, built on first use
        self.lam_g = np.zeros(self.box.shape[0])

    def solve(self, alpha: float, s: np.ndarray, n_nb: float, x0: np.ndarray):
        """IPOPT on the slice's part of the coupled functional (the box as constraints)."""
        if self._solver is None:
            self._solver = gauss_newton_ipopt(
                "slice_z",
                self._c,
                self._f,
                self.nlp.g,
                self._hess,
                self._p,
                self.options.tol,
                self.options.max_iter,
                {"clip_inactive_lam": True},
            )
        sol, stats = run_nlpsol(
            self._solver,
            "stack geometry slice (IPOPT)",
            x0=x0,
            p=np.concatenate([[alpha, n_nb], s]),
            lbg=self.problem.r0,
            ubg=self.problem.r1,
        )
        self.lam_g = np.asarray(sol["lam_g"]).ravel()
        return np.asarray(sol["x"]).ravel(), stats

    def newton(self, alpha: float, s: np.ndarray, n_nb: float, c: np.ndarray, steps: int, tol: float):
        """Up to ``steps`` Gauss-Newton steps; ``(c, stats)``, or IPOPT's answer if the box gets in the way."""
        p = np.concatenate([[alpha, n_nb], s])
        t0 = time.perf_counter()
        for it in range(1, steps + 1):  # noqa: B007 (the count is reported after the loop)
            f, g, hmat = self.local(c, p)
            f, g, hmat = float(f), np.asarray(g).ravel(), np.asarray(hmat)
            d = np.linalg.solve(hmat, g)
            t, slope = 1.0, float(g @ d)
            # a small Gauss-Newton step on this nearly quadratic functional is taken whole (saves an evaluation
            # per slice and sweep); larger ones are safeguarded by backtracking (Armijo)
            small = np.sqrt(np.sum(self.w0 * d**2) / np.sum(self.w0 * c**2)) < 1e-3
            while not small and t > 1e-6 and float(self.objective(c - t * d, p)) > f - 1e-4 * t * slope:
                t *= 0.5
            new = c - t * d
            r = self.box @ new
            if np.any(r < self.problem.r0) or np.any(r > self.problem.r1) or np.any(self.lam_g != 0):
                return self.solve(alpha, s, n_nb, c)
            step = np.sqrt(np.sum(self.w0 * (new - c) ** 2) / np.sum(self.w0 * new**2))
            c = new
            if step < tol:
                break
        obj = float(self.objective(c, p))
        return c, SolverStats("gauss-newton (stack)", "Solve_Succeeded", True, it, obj, time.perf_counter() - t0)

    def newton_decrement(self, alpha: float, s: np.ndarray, n_nb: float, c: np.ndarray) -> float:
        """``||H^-1 (grad + S^T lambda)||_{W0} / ||c||_{W0}``: the relative distance to the slice's optimum.

        Evaluated with the current neighbours, this is the coupled functional's optimality residual for
        ``c_k`` in coefficient units (``lambda``: the box multipliers of the last IPOPT solve, if any).
        """
        _, g, hmat = (np.asarray(v) for v in self.local(c, np.concatenate([[alpha, n_nb], s])))
        kkt = np.ravel(g) + self.box.T @ self.lam_g
        d = np.linalg.solve(hmat, kkt)
        return float(np.sqrt(np.sum(self.w0 * d**2) / np.sum(self.w0 * c**2)))


def sweep_order(n: int) -> list[int]:
    """Slices of one symmetric sweep: forward, then backward without repeating the ends."""
    return list(range(n)) + list(range(n - 2, 0, -1))


def z_operator(n: int, order: int) -> np.ndarray:
    """``L = D^T D`` with ``D`` the ``order``-th forward difference on ``n`` slices (zero if ``n <= order``)."""
    d = np.diff(np.eye(n), order, axis=0)
    return d.T @ d


def neighbour_terms(zop: np.ndarray, c: np.ndarray, k: int) -> tuple[np.ndarray, float]:
    """``(s_k, L_kk)`` with ``s_k = -sum_{j != k} L_kj c_j``: slice k's view of the z-penalty ``C^T (L x W) C``."""
    row = zop[k].copy()
    diag = float(row[k])
    row[k] = 0.0
    return -(row @ c), diag


def coupled_geometry(slices: list[SliceGeometry], alpha: float, x0: np.ndarray, order: int):
    """All slices' geometry as one IPOPT NLP; returns ``(coefficients (n_slices, n), stats)``."""
    n, ns = slices[0].w0.size, len(slices)
    big = ca.MX.sym("C", n * ns)
    parts = [
        (*sl.parts[0](big[k * n : (k + 1) * n], alpha), sl.parts[1](big[k * n : (k + 1) * n], alpha))
        for k, sl in enumerate(slices)
    ]
    kappa = slices[0].kappa
    zlap = np.kron(z_operator(ns, order), np.diag(slices[0].w0))  # sum_k ||(D C)_k||^2_{W0} = C^T zlap C
    zl = sparse_dm(zlap)
    f = sum(p[0] for p in parts) + kappa * ca.dot(big, ca.mtimes(zl, big))
    g = ca.vertcat(*[p[1] for p in parts])
    hess = ca.diagcat(*[p[2] for p in parts]) + 2 * kappa * zl
    solver = gauss_newton_ipopt(
        "stack_geometry",
        big,
        f,
        g,
        hess,
        None,
        slices[0].options.tol,
        slices[0].options.max_iter,
        {"clip_inactive_lam": True},
    )
    nb = [sl.nlp.g.numel() for sl in slices]
    lbg = np.concatenate([np.full(m, sl.problem.r0) for m, sl in zip(nb, slices)])
    ubg = np.concatenate([np.full(m, sl.problem.r1) for m, sl in zip(nb, slices)])
    sol, stats = run_nlpsol(solver, "stack geometry (coupled IPOPT)", x0=np.ravel(x0), lbg=lbg, ubg=ubg)
    lam = np.asarray(sol["lam_g"]).ravel()
    for sl, part in zip(slices, np.split(lam, np.cumsum(nb)[:-1])):
        sl.lam_g = part  # the box multipliers (clip_inactive_lam: exactly zero where inactive), for the band
    return np.asarray(sol["x"]).reshape(ns, n), stats


def kaczmarz_geometry(
    slices: list[SliceGeometry], alpha: float, x0: np.ndarray, tol: float, max_sweeps: int, order: int
):
    """Forward-backward sweeps of slice solves; returns ``(coefficients, sweeps, residual history, stats)``.

    The first sweep solves each slice to ``tol`` given its neighbours; later
    sweeps take one Gauss-Newton step per slice (an inexact block
    Gauss-Seidel: the fixed point is the coupled optimum). The sweeps stop
    when the coupled optimality residual, ``max_k`` of
    :meth:`SliceGeometry.newton_decrement` with the final neighbours, is
    below ``tol``; it is evaluated only after sweeps whose largest relative
    update is below ``tol`` (the history holds that update otherwise).
    """
    c = np.array(x0, dtype=float)
    ns = len(slices)
    zop = z_operator(ns, order)
    w0 = slices[0].w0

    def nb_sum(k) -> tuple[np.ndarray, float]:
        return neighbour_terms(zop, c, k)

    history, stats = [], [None] * ns
    for sweep in range(1, max_sweeps + 1):
        step = 0.0
        for k in sweep_order(ns):
            s, cnt = nb_sum(k)
            old = c[k].copy()
            c[k], stats[k] = slices[k].newton(alpha, s, cnt, c[k], 50 if sweep == 1 else 1, tol)
            step = max(step, float(np.sqrt(np.sum(w0 * (c[k] - old) ** 2) / np.sum(w0 * c[k] ** 2))))
        logger.info(f"geometry sweep {sweep}: largest relative update {step:.2e} (stops below {tol:g})")
        # the largest relative update of the sweep is a cheap proxy; the exact residual is evaluated once it is small
        if step < tol:
            res = max(sl.newton_decrement(alpha, *nb_sum(k), c[k]) for k, sl in enumerate(slices))
            history.append(float(res))
            if res < tol:
                return c, sweep, history, stats
        else:
            history.append(step)
    return c, max_sweeps, history, stats


# ------------------------------------------------------------------ velocity
def _padded(gram0: np.ndarray, size: int) -> np.ndarray:
    """``G0`` on the first coefficients of a slice with ``size`` (near-wall layer columns are not z-coupled)."""
    out = np.zeros((size, size))
    m = gram0.shape[0]
    out[:m, :m] = gram0
    return out


def _velocity_system(vps, betas, kappa_v, gram0, zop):
    """Per-slice normal matrices ``H_k + kappa_v L_kk G0 / pi`` and right-hand sides (``betas[k]`` in ``H_k``)."""
    out = []
    for k, vp in enumerate(vps):
        hmat, g = vp.normal_equations(betas[k])
        out.append((hmat + kappa_v * zop[k, k] * _padded(gram0, g.size) / np.pi, g))
    return out


def coupled_velocity(vps, betas, kappa_v: float, gram0: np.ndarray, order: int):
    """All slices' velocity as one CasADi QP (IPOPT), beta ``betas[k]`` in slice k; ``(coefficients, stats)``.

    The z-penalty ties the plain basis coefficients (the first ``len(gram0)`` of each slice); a slice's
    near-wall layer columns, where it has them, are its own.
    """
    sizes = [vp.operator.shape[1] for vp in vps]
    offsets = np.r_[0, np.cumsum(sizes)]
    m = gram0.shape[0]
    big = ca.MX.sym("V", int(offsets[-1]))
    f: Any = 0  # a CasADi expression once the first term is added
    for k, vp in enumerate(vps):
        ck = big[int(offsets[k]) : int(offsets[k + 1])]
        hmat, g = vp.normal_equations(betas[k])
        f += ca.dot(ck, ca.mtimes(ca.DM(hmat), ck)) - 2 * ca.dot(ca.DM(g), ck)
    base = ca.vertcat(*[big[int(o) : int(o) + m] for o in offsets[:-1]])
    zlap = np.kron(z_operator(len(vps), order), gram0 / np.pi)
    f += kappa_v * ca.dot(base, ca.mtimes(sparse_dm(zlap), base))
    solver = ca.nlpsol(
        "stack_velocity", "ipopt", {"x": big, "f": f}, ipopt_options(1e-12, 50, {"ipopt.hessian_constant": "yes"})
    )
    sol, stats = run_nlpsol(solver, "stack velocity (coupled IPOPT)", x0=np.zeros(int(offsets[-1])))
    x = np.asarray(sol["x"]).ravel()
    return [x[int(offsets[k]) : int(offsets[k + 1])] for k in range(len(vps))], stats


def kaczmarz_velocity(vps, betas, kappa_v: float, gram0: np.ndarray, tol: float, max_sweeps: int, order: int):
    """Block Gauss-Seidel sweeps (forward, backward) on the coupled normal equations (``betas`` per slice).

    The z-coupling acts on the plain basis coefficients (the first ``len(gram0)`` of each slice).
    """
    zop = z_operator(len(vps), order)
    system = _velocity_system(vps, betas, kappa_v, gram0, zop)
    factors = [scipy.linalg.cho_factor(h) for h, _ in system]
    ns, m = len(vps), gram0.shape[0]
    c = [scipy.linalg.cho_solve(fc, g) for fc, (_, g) in zip(factors, system)]
    if ns == 1:
        return c, 0, [0.0]
    coupling = kappa_v * gram0 / np.pi
    base = np.array([ck[:m] for ck in c])  # the z-coupled coefficients of every slice, kept current

    def pull(k: int) -> np.ndarray:
        """``[G0 s_k; 0]``: what slice k's neighbours add to its right-hand side."""
        out = np.zeros(c[k].size)
        out[:m] = coupling @ neighbour_terms(zop, base, k)[0]
        return out

    history = []
    for sweep in range(1, max_sweeps + 1):
        for k in sweep_order(ns):
            new = scipy.linalg.cho_solve(factors[k], system[k][1] + pull(k))
            c[k] = c[k] + RELAX * (new - c[k])
            base[k] = c[k][:m]
        # relative residual of the coupled normal equations
        r = max(
            np.linalg.norm(system[k][0] @ c[k] - system[k][1] - pull(k)) / max(np.linalg.norm(system[k][1]), 1e-300)
            for k in range(ns)
        )
        history.append(float(r))
        if r < tol:
            return c, sweep, history
    return c, max_sweeps, history


# ------------------------------------------------------------------ coupled geometry + velocity
def coupled_segment(
    problems: list,
    images: list,
    starts: list,
    gopt: geo.GeometryOptions,
    vopt: vel.VelocityOptions,
    weight: float,
    betas: list,
    kappa: float,
    kappa_v: float,
    order: int,
    copt=None,
):
    r"""The coupled geometry+velocity NLP of a segment (paper Sec. 4's coupled functional per slice, z-tied).

    Minimizes :math:`\sum_k F_k(c_k, v_k) + \kappa\, C^\top (L \otimes W_0) C
    + \lambda \kappa_v V_0^\top (L \otimes G_0/\pi) V_0` with :math:`F_k` the coupled functional of slice k
    (:func:`wss_nlp.coupled.build`, velocity weight :math:`\lambda` common to the segment, so the z-penalty of
    the velocity keeps its weight relative to the velocity misfit as in the decoupled stack), IPOPT with the
    Gauss-Newton Hessian (per-slice blocks plus the z-operators), the box per slice, warm-started from the
    decoupled segment ``starts`` (``(GeometryResult, VelocityResult)`` per slice; their maps' inner radii
    are kept, as for one slice).

    Returns ``(results, stats)``: a :class:`wss_nlp.coupled.CoupledResult` per slice.
    """
    copt = copt or cpl.CoupledOptions()
    alpha = gopt.alpha
    nlps = [
        cpl.build(pb, gopt, u, vopt, v.basis, v.disk_map.r_in, weight, alpha, b, copt.quad_order, start=g.coefficients)
        for pb, u, (g, v), b in zip(problems, images, starts, betas)
    ]
    sizes = [nlp.x.numel() for nlp in nlps]
    offsets = np.r_[0, np.cumsum(sizes)]
    big = ca.MX.sym("X", int(offsets[-1]))
    # separate functions: derivatives of f must not run through the Gauss-Newton matrix's graph
    parts = [
        (ca.Function("F", [nlp.x, nlp.gamma], [nlp.f, nlp.g]), ca.Function("J", [nlp.x, nlp.gamma], [nlp.jacobian]))
        for nlp in nlps
    ]
    gammas = ca.MX.sym("gamma", len(nlps))
    grams = [operators.Gram(*nlp.jacobian.shape) for nlp in nlps]  # kept alive with the solver below
    f: Any = 0  # a CasADi expression once the first term is added
    g_all, hess_blocks = [], []
    for k, (nlp, (fun, jac)) in enumerate(zip(nlps, parts)):
        xk = big[int(offsets[k]) : int(offsets[k + 1])]
        fk, gk = fun(xk, gammas[k])
        jk = jac(xk, gammas[k])
        f += fk
        g_all.append(gk)
        reg = np.zeros((sizes[k], sizes[k]))
        reg[: nlp.n_r, : nlp.n_r] = alpha * np.diag(nlp.geometry.weights)
        reg[nlp.n_r :, nlp.n_r :] = weight * nlp.beta / np.pi * nlp.gram
        hess_blocks.append(2 * grams[k](jk) + 2 * ca.DM(reg))
    zop = z_operator(len(nlps), order)
    w0 = rad.sobolev_weights(gopt.n_fourier, 0)
    gram0 = getattr(starts[0][1].basis, "base", starts[0][1].basis).laplacian_gram(0)
    n_r, m = nlps[0].n_r, gram0.shape[0]
    select_c = np.zeros((len(nlps) * n_r, int(offsets[-1])))
    select_v = np.zeros((len(nlps) * m, int(offsets[-1])))
    for k in range(len(nlps)):
        select_c[k * n_r : (k + 1) * n_r, offsets[k] : offsets[k] + n_r] = np.eye(n_r)
        select_v[k * m : (k + 1) * m, offsets[k] + n_r : offsets[k] + n_r + m] = np.eye(m)
    zpen = kappa * select_c.T @ np.kron(zop, np.diag(w0)) @ select_c
    zpen += weight * kappa_v * select_v.T @ np.kron(zop, gram0 / np.pi) @ select_v
    zl = sparse_dm(zpen)
    f += ca.dot(big, ca.mtimes(zl, big))
    hess = ca.diagcat(*hess_blocks) + 2 * zl
    extra = {
        "clip_inactive_lam": True,
        "ipopt.mu_init": 1e-6,
        "ipopt.warm_start_init_point": "yes",
        "ipopt.warm_start_bound_push": 1e-9,
        "ipopt.warm_start_mult_bound_push": 1e-9,
    }
    solver = gauss_newton_ipopt(
        "stack_coupled", big, f, ca.vertcat(*g_all), hess, gammas, copt.tol, copt.max_iter, extra
    )
    x0 = np.concatenate([np.concatenate([g.coefficients, v.coefficients]) for g, v in starts])
    lbg = np.concatenate(
        [
            np.full(nlp.g.numel(), max(pb.r0, 1.000001 * v.disk_map.r_in))
            for nlp, pb, (_, v) in zip(nlps, problems, starts)
        ]
    )
    ubg = np.concatenate([np.full(nlp.g.numel(), pb.r1) for nlp, pb in zip(nlps, problems)])
    p = np.array([float(nlp.geometry.gamma) for nlp in nlps])
    t0 = time.perf_counter()
    sol, stats = run_nlpsol(solver, "stack coupled geometry+velocity (IPOPT)", x0=x0, p=p, lbg=lbg, ubg=ubg)
    stats.seconds = time.perf_counter() - t0
    stats.extra["velocity_weight"] = weight
    x = np.asarray(sol["x"]).ravel()
    lam = np.split(np.asarray(sol["lam_g"]).ravel(), np.cumsum([nlp.g.numel() for nlp in nlps])[:-1])
    out = []
    for k, (nlp, pb, u, (g0, v0), b) in enumerate(zip(nlps, problems, images, starts, betas)):
        x_k = x[int(offsets[k]) : int(offsets[k + 1])]
        c_r, c_v = x_k[:n_r], x_k[n_r:]
        gnlp = nlp.geometry  # its residual holds the gamma parameter: substitute the value for the report
        numeric = replace(gnlp, residual=ca.substitute(gnlp.residual, nlp.gamma, ca.MX(gnlp.gamma)))
        g = geo.finish(pb, gopt, numeric, c_r, stats, alpha)
        g.box_multipliers = lam[k]
        vopt_fixed = replace(vopt, inner_radius=v0.disk_map.r_in)
        vp = vel.assemble(pb.grid, u, c_r, g.center, vopt_fixed, basis=v0.basis, psf=pb.psf)
        v = vel.result(vp, vopt_fixed, c_v, b, stats)
        out.append(cpl.CoupledResult(g, v, stats, weight, (g0.coefficients, v0.coefficients), nlp))
    return out, stats


# ------------------------------------------------------------------ driver
def _prepare(acq: Acquisition, iz: int, magnitude, velocity, finite: bool, vessel=None, psf=None) -> _Slice:
    where = f"{acq.source} slice {iz}"
    if not finite:
        raise InputError(f"{where}: the images contain NaN or Inf")
    norm, m, lumen = pp.preprocess(magnitude, acq.grid, where, vessel, clip_upper=psf is None)
    problem = geo.GeometryProblem(acq.grid, m, lumen.center, lumen.r0, lumen.r1, lumen.r_area, psf=psf)
    return _Slice(iz, problem, norm, lumen, m, np.asarray(velocity, dtype=float))


def _z_derivatives(coefficients: np.ndarray, centers: np.ndarray, z: np.ndarray):
    """z-derivatives at the slices of the cubic-spline interpolants (in z) of the radius coefficients and centres.

    The stack's wall model between slices; differentiated exactly (a straight line through two slices, zero
    for a single slice).
    """
    if len(z) == 1:
        return np.zeros_like(coefficients), np.zeros_like(centers)
    import scipy.interpolate

    kind = "not-a-knot" if len(z) > 3 else "natural"
    out = []
    for values in (coefficients, centers):
        spline = scipy.interpolate.CubicSpline(z, values, axis=0, bc_type=kind)
        out.append(spline.derivative()(z))
    return out[0], out[1]


def _segment_band(acq, options, seg, slices, problems, geoms, sgs, vps, vcoef, betas, nears, kappa, kappa_v, zop, mu):
    """The band of a solved segment (:func:`wss_nlp.stack_band.segment_band`) and a note: ``(bands, "")``, or
    ``(None, why)`` when it cannot be computed (the reconstruction itself stands)."""
    from . import stack_band

    band_slices = []
    try:
        for k, p, pb, g, sl, vp, cv, b, near in zip(seg, slices, problems, geoms, sgs, vps, vcoef, betas, nears):
            sigma_m, sigma_u = _noise_levels(acq, options, k, p, vp.voxels.index)
            band_slices.append(stack_band.BandSlice(pb, g, sl.lam_g, vp, cv, b, near, sigma_m, sigma_u))
        bands = stack_band.segment_band(
            band_slices, options.geometry, options.velocity, kappa, kappa_v, zop, mu, options.n_phi
        )
    except WssNlpError as exc:
        return None, f"no uncertainty band: {exc}"
    return bands, ""


def _noise_levels(acq, options, k: int, p: _Slice, u_index: np.ndarray):
    """Slice k's ``(sigma_m, sigma_u on u_index)`` as the single-slice band takes them (venc, or the noise
    venc when the lumen has no plateau)."""
    venc = acq.venc_m_s
    if venc is None and nl.velocity_plateau(p.lumen.noise_mask).sum() < nl.MIN_PLATEAU_VOXELS:
        venc = acq.noise_venc_m_s
    sigma_m, sigma_u, _ = sens.noise_levels(
        acq.magnitude[k], p.lumen.noise_mask, p.norm.m0, p.norm.m1, u_index, venc, options.noise_sigma, p.lumen.signal
    )
    return sigma_m, sigma_u


def _coupled_segment_band(acq, options, seg, slices, problems, cres, kappa, kappa_v, zop, mu):
    """:func:`wss_nlp.stack_band.coupled_segment_band` of a coupled segment: ``(bands, "")`` or ``(None, why)``."""
    try:
        bands = stack_band.coupled_segment_band(
            cres, problems, lambda i, _, u_index: _noise_levels(acq, options, seg[i], slices[i], u_index),
            options.geometry, options.velocity, kappa, kappa_v, zop, mu, options.n_phi,
        )  # fmt: skip
    except WssNlpError as exc:
        return None, f"no uncertainty band: {exc}"
    return bands, ""


def _coupled_pass(acq, options, seg, slices, problems, images, starts, betas, kappa, kappa_v, order):
    """The segment's coupled NLP (:func:`coupled_segment`) from its decoupled solution, with one velocity weight:
    ``--velocity-weight``, or the geometric median of the slices' likelihood weights
    (:func:`wss_nlp.coupled.weight_from_data`). Returns the results and each slice's record of the weight."""
    copt = options.coupled
    own = []
    for k, p, pb in zip(seg, slices, problems):
        if copt.velocity_weight is not None:
            own.append((copt.velocity_weight, {"weight_method": "given (--velocity-weight)"}))
            continue
        venc = acq.venc_m_s
        if venc is None and nl.velocity_plateau(p.lumen.noise_mask).sum() < nl.MIN_PLATEAU_VOXELS:
            venc = acq.noise_venc_m_s
        weight, how = cpl.weight_from_data(
            pb, options.geometry, acq.magnitude[k], p.norm, p.lumen.noise_mask, p.velocity_image, venc,
            f"{acq.source} slice {k}", p.lumen.signal,
        )  # fmt: skip
        how["weight_method"] = "likelihood: W sigma_m^2 / sigma_u^2 from the estimated noise levels"
        own.append((weight, how))
    weight = float(np.exp(np.median(np.log([w for w, _ in own]))))
    vopt = replace(options.velocity, near_wall="off")
    res, _ = coupled_segment(
        problems, images, starts, options.geometry, vopt, weight, betas, kappa, kappa_v, order, copt
    )
    info = [
        {
            "velocity_weight": weight,
            **how,
            "velocity_weight_slice_alone": w,
            "decoupled_mean_radius_mm": float(g.coefficients[0]),
            "decoupled_converged": bool(g.stats.converged and v.stats.converged),
        }
        for (w, how), (g, v) in zip(own, starts)
    ]
    if len(seg) > 1 and copt.velocity_weight is None:
        for d in info:
            d["weight_method"] += f"; the geometric median over slices {seg[0]}-{seg[-1]}"
    return res, info


def supports(options) -> bool:
    """Whether z-regularization applies to these reconstruction options (decoupled or coupled method, fixed
    alpha).

    beta may come from any rule: a segment is fitted with one beta, the
    median (on a log scale) of its slices' own choices (:func:`segment_beta`).
    """
    return options.method in ("decoupled", "coupled") and options.alpha_rule == "fixed"


def segment_beta(choices) -> float:
    """One beta for a z-coupled segment from its slices' choices: their geometric median.

    The z-penalty pools neighbouring slices, so they need a common beta; the
    median keeps one slice with an outlying choice (a noisier image, a
    fallback) from setting it, and the log scale matches the 2^-n grids.
    """
    return float(np.exp(np.median(np.log([c.chosen for c in choices]))))


def segments_of(ok: list[int]) -> list[list[int]]:
    """Runs of consecutive slice indices."""
    out: list[list[int]] = []
    for i in ok:
        if out and out[-1][-1] == i - 1:
            out[-1].append(i)
        else:
            out.append([i])
    return out


def reconstruct_stack(acq: Acquisition, options, stack: StackOptions | None = None, progress=None, psf=None):
    """Reconstruct all slices of a stack with z-regularization.

    Parameters
    ----------
    acq : Acquisition with ``nz >= 1`` and ``slice_spacing_mm`` when ``nz > 1``.
    options : :class:`wss_nlp.reconstruct.ReconstructionOptions` (alpha, beta, bases, ...).
    stack : StackOptions
    progress : callable ``(done, total, slice_result)`` or None, called per finished slice.
    psf : wss_nlp.kspace.PSF or None
        The k-space acquisition model of every slice (None: voxel means).

    Returns
    -------
    (results, info): ``results[k]`` is a :class:`wss_nlp.reconstruct.SliceResult`
    or None for a slice that failed (``info.failed[k]`` says why).

    Notes
    -----
    What a long solve is doing (segments, sweeps) goes to the ``wss_nlp.stack`` logger at INFO level.
    """
    stack = stack or StackOptions()
    if not supports(options):
        raise InputError(
            "stacks with z-regularization support the decoupled and coupled methods with a fixed alpha; "
            "pass --z-smoothing 0 for independent slices with other settings"
        )
    mu = acq.viscosity(options.viscosity_pa_s)
    density = acq.density(options.density_kg_m3)
    dz = float(acq.slice_spacing_mm or 1.0) if acq.nz > 1 else 1.0  # validate() requires it for nz > 1
    ell = dz if stack.z_smoothing_mm is None else float(stack.z_smoothing_mm)
    velocity = acq.velocity_images()
    t = {"preprocess": time.perf_counter()}
    prepared, failed = {}, {}
    bad = set(acq.nonfinite_slices())  # any image of the slice, in-plane velocity components included
    for iz in range(acq.nz):
        try:
            prepared[iz] = _prepare(acq, iz, acq.magnitude[iz], velocity[iz], iz not in bad, options.screen.vessel, psf)
        except WssNlpError as exc:
            failed[iz] = str(exc)
    if not prepared:
        raise InputError(f"{acq.source}: no usable slice: " + "; ".join(f"{k}: {v}" for k, v in failed.items()))
    t["preprocess"] = time.perf_counter() - t["preprocess"]
    r_ref = float(np.mean([s.lumen.r_area for s in prepared.values()]))
    h = acq.grid.h
    m = stack.z_order
    kappa = (ell / dz) ** (2 * m) * r_ref / h
    kappa_v = (ell / dz) ** (2 * m)
    segs = segments_of(sorted(prepared))
    info = StackInfo("", ell, kappa, kappa_v, segs, failed)
    results: list = [None] * acq.nz
    gopt, vopt = options.geometry, options.velocity
    layer_notes = []
    if options.method == "coupled" and vopt.near_wall != "off":  # as reconstruct_slice
        layer_notes.append("the coupled method does not take a near-wall layer yet: plain velocity basis")
        vopt = replace(vopt, near_wall="off")
    basis = vopt.make_basis()
    gram0 = basis.laplacian_gram(0)
    done = 0

    def choose_velocity_models(seg, vps, around=None):
        """Each slice's near-wall model (as a single slice chooses it; ``around``: the first pass's choices,
        refined on the corrected geometry where they took a layer) and the velocity problems it gives."""
        nears: list = [None] * len(seg)
        if vopt.near_wall == "off":
            return vps, nears
        out = []
        for i, (k, vp) in enumerate(zip(seg, vps)):
            before = None if around is None else around[i]
            if before is not None and before.model == "plain":  # as reconstruct_slice: a plain slice stays plain
                out.append(vp)
                nears[i] = before
                continue
            where = f"{acq.source} slice {k}"
            problem, nears[i] = layer_model(
                vp, acq.magnitude[k], prepared[k].lumen, acq.venc_m_s, options, where, mu, density, around=before
            )
            out.append(problem)
        return out, nears

    def choose_betas(seg, vps, nears):
        """Each slice's own beta choice (the rule of ``options``, or its layer's BIC beta) and the betas used:
        one per segment if coupled."""
        choices = [
            velocity_beta(vp, near, acq.magnitude[k], prepared[k].lumen, acq.venc_m_s, options,
                          f"{acq.source} slice {k}", mu)
            for k, vp, near in zip(seg, vps, nears)
        ]  # fmt: skip
        if kappa_v == 0 or len({c.chosen for c in choices}) == 1:
            return choices, [c.chosen for c in choices]
        return choices, [segment_beta(choices)] * len(seg)

    def fit_velocity(vps, strategy, betas, record=True):
        """The z-coupled velocity fit of one segment (any component: the data sit in ``vps``)."""
        if strategy == "coupled":
            vcoef, vstats = coupled_velocity(vps, betas, kappa_v, gram0, m)
            return vcoef, [vstats] * len(vps)
        vcoef, sweeps, hist = kaczmarz_velocity(vps, betas, kappa_v, gram0, stack.tol, stack.max_sweeps, m)
        ok = hist[-1] < stack.tol or len(vps) == 1
        if record:
            info.sweeps.setdefault("velocity", []).append(sweeps)
            info.residuals["velocity"] = hist
        info.converged &= ok
        return vcoef, [
            SolverStats(
                "kaczmarz (block Gauss-Seidel, Cholesky)",
                "Solve_Succeeded" if ok else "Maximum_Iterations_Exceeded",
                ok,
                sweeps,
                float("nan"),
                0.0,
            )
        ] * len(vps)

    def predict_dephasing(seg, vps, geoms, windows=None):
        """Each slice's :class:`wss_nlp.dephasing.Correction` from a GCV-beta velocity (windows: k-space misfits)."""
        out = []
        for i, (k, vp) in enumerate(zip(seg, vps)):
            v_deph = vel.solve(vp, replace(vopt, solver="cholesky"), beta=gcv_beta(vp, options).chosen)
            p, g = prepared[k], geoms[i]
            out.append(
                deph.correct(
                    p.magnitude, acq.magnitude[k], p.norm.m0, p.velocity_image, vp, v_deph.evaluate_physical,
                    acq.venc_m_s, g.coefficients, g.center, acq.grid, psf, None if windows is None else windows[i],
                )
            )  # fmt: skip
        return out

    def solve_segment(seg, problems, x0, strategy, velocity_images=None, around=None):
        """Geometry then velocity of one segment; ``(coef, geoms, vps, vcoef, vstats, beta choices, betas,
        near-wall choices, the slices' SliceGeometry, the geometry problems)``."""
        t0 = time.perf_counter()
        sg = [SliceGeometry(pb, gopt, kappa) for pb in problems]
        t["geometry_build"] = t.get("geometry_build", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        if strategy == "coupled":
            coef, gstats = coupled_geometry(sg, gopt.alpha, x0, m)
            gstats = [gstats] * len(seg)
            info.sweeps.setdefault("geometry", []).append(0)
        else:
            coef, sweeps, hist, gstats = kaczmarz_geometry(sg, gopt.alpha, x0, stack.tol, stack.max_sweeps, m)
            info.sweeps.setdefault("geometry", []).append(sweeps)
            info.residuals["geometry"] = hist
            if hist[-1] >= stack.tol and len(seg) > 1:
                info.converged = False
        t["geometry"] = t.get("geometry", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        geoms = [
            geo.finish(pb, gopt, sl.nlp, coef[i], gstats[i], gopt.alpha) for i, (pb, sl) in enumerate(zip(problems, sg))
        ]
        images = velocity_images or [prepared[k].velocity_image for k in seg]
        vps = [
            vel.assemble(acq.grid, u, g.coefficients, g.center, vopt, basis=basis, psf=psf)
            for u, g in zip(images, geoms)
        ]
        vps, nears = choose_velocity_models(seg, vps, around)
        choices, betas = choose_betas(seg, vps, nears)
        vcoef, vstats = fit_velocity(vps, strategy, betas)
        t["velocity"] = t.get("velocity", 0.0) + time.perf_counter() - t0
        return coef, geoms, vps, vcoef, vstats, choices, betas, nears, sg, problems

    unexplained: list[int] = []  # slices whose k-space dephasing prediction was rejected
    for seg in segs:
        strategy = stack.strategy
        if strategy == "auto":
            strategy = "coupled" if len(seg) <= COUPLED_MAX_SLICES else "kaczmarz"
        info.strategy = strategy if not info.strategy or info.strategy == strategy else "mixed"
        logger.info(f"slices {seg[0]}-{seg[-1]}: {strategy} solve of {len(seg)} slice(s)")
        problems = [prepared[k].problem for k in seg]
        x0 = np.array([geo.initial_guess(pb, gopt.n_fourier) for pb in problems])
        coef, geoms, vps, vcoef, vstats, choices, betas, nears, sgs, used = solve_segment(seg, problems, x0, strategy)
        factors: list[Any] = [None] * len(seg)
        if options.dephasing_correction and acq.venc_m_s is not None:
            # as reconstruct_slice (one pass): predict the signal loss from a GCV-beta velocity, then solve again
            t0 = time.perf_counter()
            corrections = predict_dephasing(seg, vps, geoms)
            factors = [c.factors for c in corrections]
            t["dephasing_check"] = t.get("dephasing_check", 0.0) + time.perf_counter() - t0
            if any(c.worth_a_pass for c in corrections):
                logger.info(f"slices {seg[0]}-{seg[-1]}: second pass on dephasing-corrected magnitudes")
                before = (coef, geoms, vps, vcoef, vstats, choices, betas, nears, sgs, used)
                corrected = [replace(pb, magnitude=c.magnitude) for pb, c in zip(problems, corrections)]
                coef, geoms, vps, vcoef, vstats, choices, betas, nears, sgs, used = solve_segment(
                    seg, corrected, coef, strategy, [c.velocity for c in corrections], around=nears
                )
                info.dephasing_pass = True
                if psf is not None:  # judged as in reconstruct_slice: undone if it explains the magnitude worse
                    after = predict_dephasing(seg, vps, geoms, [c.window for c in corrections])
                    if any(a.misfit_moving >= c.misfit_still for a, c in zip(after, corrections)):
                        coef, geoms, vps, vcoef, vstats, choices, betas, nears, sgs, used = before
                        unexplained.extend(seg)
                        info.dephasing_pass = False
        cres, cinfo = None, [{} for _ in seg]  # type: list | None, list[dict]
        if options.method == "coupled":
            t0 = time.perf_counter()
            starts = [(g, vel.result(vp, vopt, c, b, st)) for g, vp, c, b, st in zip(geoms, vps, vcoef, betas, vstats)]
            cres, cinfo = _coupled_pass(
                acq, options, seg, [prepared[k] for k in seg], used, [vp.data_image for vp in vps], starts, betas,
                kappa, kappa_v, m,
            )  # fmt: skip
            geoms = [c.geometry for c in cres]
            t["coupled"] = t.get("coupled", 0.0) + time.perf_counter() - t0
        planar = None
        if acq.velocity_inplane is not None:
            t0 = time.perf_counter()
            planar = []
            for comp in acq.velocity_inplane:
                vps_c = [
                    replace(vp, data=comp[k].ravel()[vp.voxels.index], data_image=comp[k]) for k, vp in zip(seg, vps)
                ]
                coef_c, st_c = fit_velocity(vps_c, strategy, betas, record=False)
                planar.append(
                    [
                        wss_mod.from_reconstruction(vel.result(vp, vopt, cc, b, st), options.n_phi, mu).tau
                        for vp, cc, st, b in zip(vps_c, coef_c, st_c, betas)
                    ]
                )
            dcoef, dcenter = _z_derivatives(
                np.array([g.coefficients for g in geoms]), np.array([g.center for g in geoms]), np.array(seg) * dz
            )
            t["velocity_inplane"] = t.get("velocity_inplane", 0.0) + time.perf_counter() - t0
        bands, band_note = None, ""
        if options.uncertainty and cres is not None:
            t0 = time.perf_counter()
            bands, band_note = _coupled_segment_band(
                acq, options, seg, [prepared[k] for k in seg], used, cres, kappa, kappa_v, z_operator(len(seg), m), mu
            )
            t["uncertainty"] = t.get("uncertainty", 0.0) + time.perf_counter() - t0
        elif options.uncertainty:
            t0 = time.perf_counter()
            bands, band_note = _segment_band(
                acq, options, seg, [prepared[k] for k in seg], used, geoms, sgs, vps, vcoef, betas, nears, kappa,
                kappa_v, z_operator(len(seg), m), mu,
            )  # fmt: skip
            t["uncertainty"] = t.get("uncertainty", 0.0) + time.perf_counter() - t0
        for i, k in enumerate(seg):
            v = vel.result(vps[i], vopt, vcoef[i], betas[i], vstats[i]) if cres is None else cres[i].velocity
            w = wss_mod.from_reconstruction(v, options.n_phi, mu)
            if bands is not None:
                w.tau_std, w.mean_std = bands[i].tau_std, bands[i].mean_std
                if nears[i] is not None and np.isfinite(bands[i].scale_std_log):
                    nears[i].scale_std_log = bands[i].scale_std_log
            if planar is not None:
                w.vector = wss_mod.wss_vector(
                    w.phi,
                    geoms[i].coefficients,
                    dcoef[i],
                    dcenter[i],
                    np.stack([planar[0][i], planar[1][i], w.tau], axis=1),
                    mu,
                )
            if not np.all(np.isfinite(w.tau)):
                raise SolverError(f"{acq.source} slice {k}: wall shear stress is not finite")
            p = prepared[k]
            sec = {"min_dephasing_factor": float(np.min(factors[i], initial=1.0)) if factors[i] is not None else 1.0}
            notes = [deph.UNEXPLAINED_NOTE] if k in unexplained else []
            notes += [band_note] if band_note else []
            if betas[i] != choices[i].chosen:
                notes.append(
                    f"stack: beta = {betas[i]:.3g}, the geometric median of the {choices[i].rule} choices "
                    f"of slices {seg[0]}-{seg[-1]} (this slice alone: {choices[i].chosen:.3g})"
                )
            results[k] = SliceResult(
                k,
                geoms[i],
                v,
                w,
                p.norm,
                p.lumen,
                acq.grid,
                p.magnitude,
                p.velocity_image,
                sec,
                pr.ParameterChoice("alpha", "fixed", gopt.alpha),
                replace(choices[i], chosen=betas[i]),
                options.method,
                cinfo[i],
                None,
                notes + layer_notes,
                near_wall=nears[i],
            )
            done += 1
            if progress is not None:
                progress(done, len(prepared), results[k])
    if not info.converged:
        for r in results:
            if r is not None:
                r.notes.append(
                    f"stack: Kaczmarz sweeps stopped before the coupled optimality residual reached {stack.tol:g}"
                )
    info.seconds = t
    return results, info
