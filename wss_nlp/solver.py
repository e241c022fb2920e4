"""Shared solver plumbing: IPOPT options, status classification, stats."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import casadi as ca

from .errors import SolverError

#: IPOPT statuses after which the iterate is returned but flagged as not converged.
SOFT_FAILURES = {
    "Maximum_Iterations_Exceeded",
    "Maximum_CpuTime_Exceeded",
    "Maximum_WallTime_Exceeded",
    "Solved_To_Acceptable_Level",
    "Search_Direction_Becomes_Too_Small",
}


@dataclass
class SolverStats:
    """What a solver reports about one solve.

    ``converged`` is True only for a clean success; anything in
    :data:`SOFT_FAILURES` returns an iterate with ``converged = False``.
    """

    solver: str
    status: str
    converged: bool
    iterations: int
    objective: float
    seconds: float
    extra: dict = field(default_factory=dict)

    def as_attrs(self, prefix: str = "") -> dict:
        """Flat dictionary for HDF5 attributes."""
        d = asdict(self)
        extra = d.pop("extra")
        d.update({f"extra_{k}": v for k, v in extra.items()})
        return {prefix + k: v for k, v in d.items()}


def ipopt_options(tol: float, max_iter: int, extra: dict | None = None) -> dict:
    """Quiet IPOPT options for ``casadi.nlpsol``."""
    opts = {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
        "ipopt.tol": tol,
        "ipopt.max_iter": max_iter,
    }
    if extra:
        opts.update(extra)
    return opts


def gauss_newton_ipopt(
    name: str, x, f, g, hess, p=None, tol: float = 1e-9, max_iter: int = 200, extra: dict | None = None
) -> ca.Function:
    r"""IPOPT on :math:`\min_x f(x; p)` subject to ``g``, with a Gauss-Newton Hessian of the Lagrangian.

    Notes
    -----
    Every NLP of the package is a regularized least-squares problem with
    linear constraints (the radius box), so the Hessian of the Lagrangian is
    :math:`\sigma \nabla^2 f` and :math:`\nabla^2 f \approx 2 (J^\top J + \text{penalty Hessian})`
    =: ``hess`` (an expression in ``x`` and ``p``; only its upper triangle is
    passed). IPOPT then needs no second derivatives of the residual.
    """
    sigma = ca.MX.sym("sigma")
    io = {"x": x, "lam_f": sigma, "hess_gamma_x_x": sigma * ca.triu(hess)}
    nlp = {"x": x, "f": f, "g": g}
    if p is not None:
        io["p"] = nlp["p"] = p
    hess_lag = ca.Function("nlp_hess_l", io, ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
    return ca.nlpsol(name, "ipopt", nlp, ipopt_options(tol, max_iter, {**(extra or {}), "hess_lag": hess_lag}))


def run_nlpsol(solver: ca.Function, what: str, **args) -> tuple[dict, SolverStats]:
    """Call an ``nlpsol`` and classify its return status.

    Raises
    ------
    SolverError
        For hard failures (invalid numbers, restoration failure, infeasible
        problem, ...): nothing usable was computed.
    """
    t0 = time.perf_counter()
    try:
        sol = solver(**args)
    except RuntimeError as exc:  # evaluation errors surface as RuntimeError
        last = [ln for ln in str(exc).splitlines() if ln.strip()][-1:] or ["unknown error"]
        raise SolverError(f"{what}: IPOPT raised an error: {last[0].strip()}") from exc
    seconds = time.perf_counter() - t0
    st = solver.stats()
    status = str(st.get("return_status", "unknown"))
    success = bool(st.get("success", False))
    if not success and status not in SOFT_FAILURES:
        raise SolverError(f"{what}: IPOPT failed with status {status}")
    stats = SolverStats(
        solver="ipopt",
        status=status,
        converged=success and status == "Solve_Succeeded",
        iterations=int(st.get("iter_count", -1)),
        objective=float(sol["f"]),
        seconds=seconds,
    )
    return sol, stats
