#!/usr/bin/env python
"""The geometry solve in evaluation-equivalents: IPOPT against the Gauss-Newton floor, in one run.

Issue 19: the geometry NLP stays an IPOPT problem with the box, but should cost at most 30
evaluation-equivalents at every h, with a NumPy Gauss-Newton cross-check reporting the floor beside it.
One evaluation-equivalent is the time of one residual-and-Jacobian evaluation of the same functional
(the Gauss-Newton solver form, ``geometry.build_tikhonov(..., separable_jacobian=True)``), measured in
the same run; a solve's count is its wall time over that, the start included. Laminar phantom, SNR 25,
default geometry options and alpha, ``--seeds`` slices per h (medians), each solver built before the
timing (built once per grid, centre and box and reused: ``geometry.solver_for``). Columns: IPOPT with the
default Newton Hessian (``--hessian newton``) from the default start (``geometry.initial_guess``, the
half-maximum contour: the first geometry of a slice); the same with the Gauss-Newton Hessian, from that
start and from the equal-area circle (the defaults before); IPOPT from the solution with a warm barrier
(``geometry.WARM_START``: the dephasing pass, cine frames and the band's anchor start there); the projected
Gauss-Newton method of the paper (Sec. 7.1, ``geometry.solve_projected_gauss_newton``, NumPy steps on the
same CasADi residual), whose iterations (one residual-and-Jacobian evaluation each; its line-search trials
evaluate only the objective) are a floor for methods without second derivatives; and the largest
coefficient difference between the default IPOPT and the Gauss-Newton solutions. Writes
``scripts/results/bench_geometry.md``.

    python scripts/bench_geometry.py [--seeds 3] [--h 1.5,1.0,0.6,0.3]
"""

import argparse
import time

import numpy as np

import casadi as ca
from _report import RESULTS, write_report
from wss_nlp.models import geometry as geo
from wss_nlp.synthetic import phantoms
from wss_nlp.models import preprocess as pp

TARGET = 30.0  # issue 19: at most 30 evaluation-equivalents per geometry solve


def _timed(fun, *args, repeat: int = 1):
    """Median wall time of ``repeat`` calls and the last result."""
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fun(*args)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def one(h: float, seed: int) -> dict:
    acq, _ = phantoms.make_phantom("laminar", h_mm=h, snr=25, seed=seed)
    _, m, lumen = pp.preprocess(acq.magnitude[0], acq.grid, clip_upper=False)
    problem = geo.GeometryProblem(acq.grid, m, lumen.center, lumen.r0, lumen.r1, lumen.r_area)
    opts = geo.GeometryOptions()
    cold, warm = geo.IpoptGeometrySolver(problem, opts), geo.IpoptGeometrySolver(problem, opts, warm=True)
    gn = geo.IpoptGeometrySolver(problem, geo.with_options(opts, hessian="gauss-newton"))
    nlp = gn.nlp  # the residual and its chain-rule Jacobian: what one evaluation-equivalent evaluates
    evaluate = ca.Function("rj", [nlp.c, nlp.data], [nlp.residual, nlp.jacobian])
    circle = np.zeros(nlp.c.numel())
    circle[0] = problem.r_ref
    data = problem.magnitude.ravel()[nlp.model.annulus]
    t_eval, _ = _timed(evaluate, circle, data, repeat=21)
    t_cold, sol = _timed(cold.solve, opts.alpha, None, problem, repeat=3)
    t_gn, sol_gn = _timed(gn.solve, opts.alpha, None, problem, repeat=3)
    t_circle, sol_circle = _timed(gn.solve, opts.alpha, circle, problem, repeat=3)
    lam = np.zeros(nlp.g.numel())
    t_warm, sol_w = _timed(warm.solve, opts.alpha, sol.coefficients, problem, lam, repeat=3)
    # the floor: the paper's projected Gauss-Newton method from the same start, one residual-and-Jacobian
    # evaluation per iteration (its line-search trials evaluate the objective only)
    floor = geo.solve_projected_gauss_newton(problem, opts)
    return {
        "ipopt_iter": sol.stats.iterations,
        "ipopt_eq": t_cold / t_eval,
        "gn_ipopt": f"{sol_gn.stats.iterations} / {t_gn / t_eval:.0f}",
        "circle_ipopt": f"{sol_circle.stats.iterations} / {t_circle / t_eval:.0f}",
        "warm_iter": sol_w.stats.iterations,
        "warm_eq": t_warm / t_eval,
        "gn_iter": floor.stats.iterations,
        "diff": float(np.max(np.abs(sol.coefficients - floor.coefficients))),
        "eval_ms": 1e3 * t_eval,
        "converged": all(s.stats.converged for s in (sol, sol_gn, sol_circle, sol_w, floor)),
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--h", default="1.5,1.0,0.6,0.3")
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    lines = [
        f"Laminar phantom, SNR 25, seeds 100-{99 + args.seeds} (medians); one evaluation-equivalent = one "
        "residual-and-Jacobian evaluation, timed in the same run. Made by `python scripts/bench_geometry.py`.",
        "",
        "| h [mm] | one evaluation [ms] | IPOPT iterations | IPOPT [eval-eq] (<= 30) | "
        "Gauss-Newton Hessian: iterations / eval-eq | the same from the circle | warm IPOPT iterations | "
        "warm IPOPT [eval-eq] | projected Gauss-Newton iterations | "
        "max coefficient difference [mm] | all converged |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for h in (float(v) for v in args.h.split(",")):
        rows = [one(h, 100 + s) for s in range(args.seeds)]

        def med(key):
            return float(np.median([r[key] for r in rows]))

        over = "" if med("ipopt_eq") <= TARGET else " (over)"
        lines.append(
            f"| {h:g} | {med('eval_ms'):.2f} | {med('ipopt_iter'):.0f} | {med('ipopt_eq'):.0f}{over} | "
            f"{', '.join(r['gn_ipopt'] for r in rows)} | {', '.join(r['circle_ipopt'] for r in rows)} | "
            f"{med('warm_iter'):.0f} | {med('warm_eq'):.0f} | {med('gn_iter'):.0f} | "
            f"{max(r['diff'] for r in rows):.1e} | {all(r['converged'] for r in rows)} |"
        )
    write_report(args.out, "bench_geometry.md", lines)


if __name__ == "__main__":
    main()
