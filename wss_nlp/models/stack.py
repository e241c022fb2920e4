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
near-wall model (``--near-wall``, :func:`wss_nlp.parameters.layer.layer_model`) is chosen
per slice, and the z-penalty ties the plain basis coefficients only (a layer's
columns, with their own scale, stay the slice's own).

The coupled method (Sec. 4's coupled functional) on a segment: :func:`coupled_segment`.

This module holds the z-coupled mathematics only; the steps every slice goes
through and the driver that runs them on a stack are in :mod:`wss_nlp.pipeline.steps`
(:class:`wss_nlp.pipeline.fitters.ZCoupled`), the band in :mod:`wss_nlp.uncertainty.stack_band`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import casadi as ca

from .._lazy import scipy
from . import geometry as geo
from ..core import operators
from ..core import radius as rad
from . import velocity as vel
from ..errors import InputError, SolverError
from . import coupled as cpl
from .coupled import sparse_dm
from ..core.schema import option
from ..core.solver import (
    SolverStats,
    gauss_newton_ipopt,
    ipopt_options,
    iteration_report_options,
    report_progress,
    run_nlpsol,
)

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
        report_iterations="geometry",  # the joint solve's progress (core.solver.solve_progress)
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
        report_progress(f"geometry: sweep {sweep} of at most {max_sweeps}, largest relative update {step:.2e}")
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
        report_progress(f"velocity: sweep {sweep} of at most {max_sweeps}, relative residual {r:.2e}")
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
    (:func:`wss_nlp.models.coupled.build`, velocity weight :math:`\lambda` common to the segment, so the z-penalty of
    the velocity keeps its weight relative to the velocity misfit as in the decoupled stack), IPOPT with the
    Gauss-Newton Hessian (per-slice blocks plus the z-operators), the box per slice, warm-started from the
    decoupled segment ``starts`` (``(GeometryResult, VelocityResult)`` per slice; their maps' inner radii
    are kept, as for one slice).

    Returns ``(results, stats)``: a :class:`wss_nlp.models.coupled.CoupledResult` per slice.
    """
    copt = copt or cpl.CoupledOptions()
    alpha = gopt.alpha
    nlps = [
        cpl.build(
            pb,
            gopt,
            u,
            vopt,
            v.basis,
            v.disk_map.r_in,
            weight,
            alpha,
            b,
            copt.quad_order,
            start=g.coefficients,
            stretch=cpl.layer_stretch(v),
        )
        for pb, u, (g, v), b in zip(problems, images, starts, betas)
    ]
    sizes = [nlp.x.numel() for nlp in nlps]
    offsets = np.r_[0, np.cumsum(sizes)]
    big = ca.MX.sym("X", int(offsets[-1]))
    # separate functions: derivatives of f must not run through the Gauss-Newton matrix's graph, and the box
    # rows' (constant) Jacobian not through f's
    derivatives = [cpl.gauss_newton_derivatives(nlp) for nlp in nlps]  # holds callbacks: alive while we solve
    parts = [
        (
            ca.Function("F", [nlp.x, nlp.gamma], [nlp.f]),
            ca.Function("G", [nlp.x], [nlp.g]),
            ca.Function("D", [nlp.x, nlp.gamma], [grad, hess]),
        )
        for nlp, (grad, hess, _) in zip(nlps, derivatives)
    ]
    gammas = ca.MX.sym("gamma", len(nlps))
    f: Any = 0  # a CasADi expression once the first term is added
    g_all, grad_blocks, hess_blocks = [], [], []
    for k, (fun, box, deriv) in enumerate(parts):
        xk = big[int(offsets[k]) : int(offsets[k + 1])]
        f += fun(xk, gammas[k])
        g_all.append(box(xk))
        grad_k, hess_k = deriv(xk, gammas[k])
        grad_blocks.append(grad_k)
        hess_blocks.append(hess_k)
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
    grad = ca.vertcat(*grad_blocks) + 2 * ca.mtimes(zl, big)  # zl is symmetric
    solver = gauss_newton_ipopt(
        "stack_coupled", big, f, ca.vertcat(*g_all), hess, gammas, copt.tol, copt.max_iter, dict(cpl.WARM_START),
        grad=grad, report_iterations="coupled geometry+velocity",
    )  # fmt: skip
    x0 = np.concatenate([np.concatenate([g.coefficients, v.coefficients]) for g, v in starts])
    lbg = np.concatenate(
        [
            np.full(nlp.g.numel(), cpl.lower_bound(pb, v.disk_map.r_in))
            for nlp, pb, (_, v) in zip(nlps, problems, starts)
        ]
    )
    ubg = np.concatenate([np.full(nlp.g.numel(), pb.r1) for nlp, pb in zip(nlps, problems)])
    p = np.array([float(nlp.geometry.gamma) for nlp in nlps])
    t0 = time.perf_counter()
    what = "stack coupled geometry+velocity (IPOPT)"
    failed = ""
    try:
        sol, stats = run_nlpsol(solver, what, x0=x0, p=p, lbg=lbg, ubg=ubg)
        failed = "" if stats.converged else stats.status
    except SolverError as exc:
        failed = str(exc)
    if failed:  # as coupled.solve: a stalled Gauss-Newton solve is redone with CasADi's exact Hessian
        logger.info(f"{what}: Gauss-Newton Hessian did not converge ({failed}); solving with the exact Hessian")
        report, callback = iteration_report_options(
            "coupled geometry+velocity, exact Hessian", big, ca.vertcat(*g_all), gammas
        )
        opts = ipopt_options(copt.tol, copt.max_iter, {**cpl.WARM_START, **report})
        exact = ca.nlpsol(
            "stack_coupled_exact", "ipopt", {"x": big, "p": gammas, "f": f, "g": ca.vertcat(*g_all)}, opts
        )
        exact.shared = (callback,)  # type: ignore[attr-defined]  # alive while the solver is; run_nlpsol restarts it
        sol, stats = run_nlpsol(exact, what, x0=x0, p=p, lbg=lbg, ubg=ubg)
        stats.extra["gauss_newton_failed"] = failed
    stats.extra["hessian"] = "exact" if failed else "gauss-newton"
    stats.seconds = time.perf_counter() - t0
    stats.extra["velocity_weight"] = weight
    x = np.asarray(sol["x"]).ravel()
    lam = np.split(np.asarray(sol["lam_g"]).ravel(), np.cumsum([nlp.g.numel() for nlp in nlps])[:-1])
    out = [
        nlp.result(pb, gopt, vopt, u, g0, v0, x[int(offsets[k]) : int(offsets[k + 1])], lam[k], stats)
        for k, (nlp, pb, u, (g0, v0)) in enumerate(zip(nlps, problems, images, starts))
    ]
    return out, stats


# ------------------------------------------------------------------ driver
def z_derivatives(coefficients: np.ndarray, centers: np.ndarray, z: np.ndarray):
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


def segments_of(ok: list[int]) -> list[list[int]]:
    """Runs of consecutive slice indices."""
    out: list[list[int]] = []
    for i in ok:
        if out and out[-1][-1] == i - 1:
            out[-1].append(i)
        else:
            out.append([i])
    return out
