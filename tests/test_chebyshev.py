"""Chebyshev series callbacks (wss_nlp.core.chebyshev) against CasADi's own recursion, with derivatives."""

import numpy as np

import casadi as ca
from wss_nlp.core import chebyshev

# rounding only: sums of K = 7 terms of size O(1) (T_k is bounded by 1 on [-1, 1], its derivatives by k^(2d))
RTOL = 1e-12


def _recursion(x, degrees: int):
    """T_0 .. T_{K-1} at the points ``x`` (a row) by CasADi's own operations, shape (K, n)."""
    t = [ca.MX.ones(x.shape), x]
    while len(t) < degrees:
        t.append(2 * x * t[-1] - t[-2])
    return ca.vertcat(*t[:degrees])


def test_values_are_the_chebyshev_polynomials_and_their_derivatives():
    """T_k^(d)(x) for d = 0..3 (and d >= K: zero) equals numpy's Chebyshev.basis(k).deriv(d)."""
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, 9)
    fam = chebyshev.Family(x.size, 7)
    for d in range(4):
        want = np.array([np.polynomial.Chebyshev.basis(k).deriv(d)(x) for k in range(7)])
        assert np.max(np.abs(fam.values(x, d) - want)) <= RTOL * max(1.0, np.max(np.abs(want)))
    assert not np.any(fam.values(x, 7))


def test_scaled_and_contracted_have_the_values_and_derivatives_of_the_recursion():
    """S_0 and R_0 inside a nonlinear graph: values, Jacobian (forward mode), gradient (reverse mode) and Hessian
    (forward over reverse) equal those of the same graph written with CasADi's recursion (independent code)."""
    rng = np.random.default_rng(5)
    n, k = 9, 7
    fam = chebyshev.Family(n, k)
    z = ca.MX.sym("z", 3 * n + n * k)
    x = ca.sin(z[:n]).T  # inside [-1, 1], as the coupled misfit's points are
    s, y = z[n : 2 * n].T, ca.reshape(z[2 * n : 2 * n + n * k], n, k)
    extra = z[2 * n + n * k :].T
    z0 = rng.normal(size=z.numel())
    outs = []
    for scaled, contracted in (
        (fam.scaled(0)(x, s), fam.contracted(0)(x, y)),
        ((_recursion(x, k) * ca.repmat(s, k, 1)).T, ca.sum1(_recursion(x, k) * y.T)),
    ):
        g = ca.vertcat(ca.vec(ca.cos(scaled)), ca.vec(contracted * extra), ca.vec(contracted**2))
        f = ca.sumsqr(g) + ca.sum1(ca.sum2(scaled * ca.repmat(ca.vec(extra), 1, k)))
        fun = ca.Function("f", [z], [g, ca.jacobian(g, z), ca.gradient(f, z), ca.hessian(f, z)[0]])
        outs.append([np.asarray(v) for v in fun(z0)])
    for mine, plain in zip(*outs):
        assert np.max(np.abs(mine - plain)) <= RTOL * max(1.0, np.max(np.abs(plain)))
