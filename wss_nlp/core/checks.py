r"""Checks of derivatives and adjoints, for tests and for users' own operators.

* :func:`dottest`: a hand-written pair ``A``, ``A^T`` satisfies
  :math:`\langle A x, y\rangle = \langle x, A^\top y\rangle` for random ``x``, ``y``.
* :func:`taylor_ratios`: for a derivative ``J`` of ``f`` at ``x`` the remainder
  :math:`r(t) = \|f(x + t d) - f(x) - t J d\|` is :math:`O(t^2)`, so halving ``t``
  divides it by 4; :func:`assert_taylor` checks that.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def _flat(value) -> np.ndarray:
    """A value as a flat float array; a CasADi ``DM`` through its ``full()`` (NumPy functions called on CasADi values
    take a deprecated path: CasADi's FutureWarning of issue 2959)."""
    full = getattr(value, "full", None)
    return np.ravel(np.asarray(full() if callable(full) else value, dtype=float))


def dottest(
    forward: Callable, adjoint: Callable, n_in: int, n_out: int, rng: np.random.Generator, rtol: float = 1e-10
) -> float:
    r"""Relative mismatch of :math:`\langle A x, y\rangle` and :math:`\langle x, A^\top y\rangle`, at most ``rtol``.

    Parameters
    ----------
    forward, adjoint : callable
        ``x (n_in,) -> A x (n_out,)`` and ``y (n_out,) -> A^T y (n_in,)``.
    rtol : float
        Allowed relative mismatch; rounding alone gives about ``eps`` times
        the condition of the sums, so ``1e-10`` leaves room for large operators.
    """
    x, y = rng.normal(size=n_in), rng.normal(size=n_out)
    lhs = float(np.dot(_flat(forward(x)), y))
    rhs = float(np.dot(x, _flat(adjoint(y))))
    mismatch = abs(lhs - rhs) / max(abs(lhs), abs(rhs), 1e-300)
    if mismatch > rtol:
        raise AssertionError(f"dot test failed: <Ax, y> = {lhs:.16g}, <x, A^T y> = {rhs:.16g} (rel. {mismatch:.2e})")
    return mismatch


def taylor_ratios(f: Callable, jvp: Callable, x: np.ndarray, d: np.ndarray, steps=(1e-2, 5e-3, 2.5e-3)) -> np.ndarray:
    """``r(t_k) / r(t_{k+1})`` of the first-order Taylor remainders along ``d`` (about 4 for halved steps)."""
    f0 = _flat(f(x))
    jd = _flat(jvp(x, d))
    rem = np.array([np.linalg.norm(_flat(f(x + t * d)) - f0 - t * jd) for t in steps])
    return rem[:-1] / rem[1:]


def assert_taylor(
    f: Callable, jvp: Callable, x: np.ndarray, d: np.ndarray, steps=(1e-2, 5e-3, 2.5e-3), tol: float = 0.5
) -> np.ndarray:
    """Raise unless every ratio of :func:`taylor_ratios` (halved steps) lies in ``4 +- tol``.

    ``tol`` allows the :math:`O(t^3)` term; choose steps where rounding is far
    below the remainder (about ``eps |f| / t^2``).
    """
    ratios = taylor_ratios(f, jvp, x, d, steps)
    if not np.all(np.abs(ratios - 4.0) <= tol):
        raise AssertionError(f"Taylor test failed: remainder ratios {ratios} (second order gives 4)")
    return ratios
