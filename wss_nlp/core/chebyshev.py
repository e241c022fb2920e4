r"""Chebyshev series at many points inside CasADi graphs, with exact derivatives of every order.

The coupled velocity misfit (:mod:`wss_nlp.models.coupled`) evaluates the velocity
basis at every sub-voxel point, whose reference radius moves with the wall,
as Chebyshev series in ``x_p = 2 rho_p - 1``. CasADi's elementwise
operations on long rows cost about 10 ns per element and node (the
recursion :math:`T_{k+1} = 2 x T_k - T_{k-1}` over 60 000 points and 24
degrees took 45 ms per evaluation, NumPy 3 ms), so the series are NumPy
callbacks. Two maps close under differentiation, for points ``x`` (a row
of ``n``) and degrees ``k < K``:

* :meth:`Family.scaled` :math:`S_d(x, s)_{pk} = T_k^{(d)}(x_p)\, s_p`, shape ``(n, K)``;
* :meth:`Family.contracted` :math:`R_d(x, Y)_p = \sum_k T_k^{(d)}(x_p)\, Y_{pk}`, shape ``(1, n)``.

Notes
-----
Both are linear in their second argument and

.. math::

    \dot S_d = S_{d+1}(x, s \dot x) + S_d(x, \dot s), \qquad
    \bar x = s\, R_{d+1}(x, \bar S), \quad \bar s = R_d(x, \bar S),

    \dot R_d = R_{d+1}(x, Y)\, \dot x + R_d(x, \dot Y), \qquad
    \bar x = \bar R\, R_{d+1}(x, Y), \quad \bar Y = S_d(x, \bar R),

so every derivative is again one of the two maps (``tests/test_chebyshev.py``
checks values, forward and reverse derivatives and the Hessian against the
same graph written with CasADi's own recursion).
:math:`T_k^{(d)}` comes from the derivative's Chebyshev coefficients
(``numpy.polynomial.chebyshev.chebder``). Keep the :class:`Family` while
functions built from it live (CasADi's rule for callbacks).
"""

from __future__ import annotations

import numpy as np

import casadi as ca


class Family:
    """The maps :math:`S_d`, :math:`R_d` for ``n`` points and ``K`` degrees, each built once and kept."""

    def __init__(self, n: int, degrees: int):
        self.n, self.degrees = int(n), int(degrees)
        self._kept: dict = {}
        self._last_x: np.ndarray | None = None
        self._values: dict = {}

    def values(self, x: np.ndarray, d: int) -> np.ndarray:
        """:math:`T_k^{(d)}(x_p)` as a ``(K, n)`` array (read-only).

        The arrays for the last points are kept: one evaluation of a graph (and of its derivatives) calls
        several maps at the same ``x``, and comparing ``x`` costs far less than the polynomials.
        """
        if self._last_x is None or not np.array_equal(x, self._last_x):
            self._last_x, self._values = np.array(x, dtype=float), {}
        if d not in self._values:
            out = self._compute(self._last_x, d)
            out.flags.writeable = False
            self._values[d] = out
        return self._values[d]

    def _compute(self, x: np.ndarray, d: int) -> np.ndarray:
        k = self.degrees
        if d >= k:
            return np.zeros((k, x.size))
        vander = np.polynomial.chebyshev.chebvander(x, k - 1 - d)  # (n, K - d)
        if d == 0:
            return np.ascontiguousarray(vander.T)
        coef = np.polynomial.chebyshev.chebder(np.eye(k), d)  # (K - d, K): column k is T_k^(d)
        return coef.T @ vander.T

    def scaled(self, d: int = 0) -> _Scaled:
        return self._get(("S", d), lambda: _Scaled(self, d))

    def contracted(self, d: int = 0) -> _Contracted:
        return self._get(("R", d), lambda: _Contracted(self, d))

    def _get(self, key, make):
        if key not in self._kept:
            self._kept[key] = make()
        return self._kept[key]


class _Map(ca.Callback):
    """Inputs ``x`` (1, n) and a second argument; one output; NumPy buffers in CasADi's column-major order."""

    def __init__(self, family: Family, d: int, name: str, second: tuple, out: tuple):
        ca.Callback.__init__(self)
        self.family, self.d, self.second, self.out = family, int(d), second, out
        self.construct(f"{name}{d}_{family.n}x{family.degrees}", {})

    def get_n_in(self):
        return 2

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(1, self.family.n) if i == 0 else ca.Sparsity.dense(*self.second)

    def get_sparsity_out(self, i):
        return ca.Sparsity.dense(*self.out)

    def has_eval_buffer(self):
        return True

    def has_forward(self, nfwd):
        return True

    def has_reverse(self, nadj):
        return True

    def _symbols(self, nseed: int, seed_shapes: list):
        x, a = ca.MX.sym("x", 1, self.family.n), ca.MX.sym("a", *self.second)
        y = ca.MX.sym("y", *self.out)
        seeds = [ca.MX.sym(f"seed{i}", r, c * nseed) for i, (r, c) in enumerate(seed_shapes)]
        return x, a, y, seeds


class _Scaled(_Map):
    """:math:`S_d(x, s)_{pk} = T_k^{(d)}(x_p) s_p`, ``(1, n), (1, n) -> (n, K)``."""

    def __init__(self, family: Family, d: int):
        super().__init__(family, d, "cheb_scaled", (1, family.n), (family.n, family.degrees))

    def eval_buffer(self, arg, res):
        n, k = self.family.n, self.family.degrees
        x, s = np.frombuffer(arg[0], dtype=np.float64), np.frombuffer(arg[1], dtype=np.float64)
        out = np.frombuffer(res[0], dtype=np.float64).reshape(k, n)  # column k of the (n, K) output
        np.multiply(self.family.values(x, self.d), s[None, :], out=out)
        return 0

    def get_forward(self, nfwd, name, inames, onames, opts):
        fam = self.family
        x, s, y, (dx, ds) = self._symbols(nfwd, [(1, fam.n), (1, fam.n)])
        blocks = [
            fam.scaled(self.d + 1)(x, s * dxi) + self(x, dsi)
            for dxi, dsi in zip(ca.horzsplit(dx, fam.n), ca.horzsplit(ds, fam.n))
        ]
        return ca.Function(name, [x, s, y, dx, ds], [ca.horzcat(*blocks)], inames, onames, opts)

    def get_reverse(self, nadj, name, inames, onames, opts):
        fam = self.family
        x, s, y, (adj,) = self._symbols(nadj, [(fam.n, fam.degrees)])
        parts = ca.horzsplit(adj, fam.degrees)
        xbar = [s * fam.contracted(self.d + 1)(x, a) for a in parts]
        sbar = [fam.contracted(self.d)(x, a) for a in parts]
        return ca.Function(name, [x, s, y, adj], [ca.horzcat(*xbar), ca.horzcat(*sbar)], inames, onames, opts)


class _Contracted(_Map):
    """:math:`R_d(x, Y)_p = \\sum_k T_k^{(d)}(x_p) Y_{pk}`, ``(1, n), (n, K) -> (1, n)``."""

    def __init__(self, family: Family, d: int):
        super().__init__(family, d, "cheb_contracted", (family.n, family.degrees), (1, family.n))

    def eval_buffer(self, arg, res):
        n, k = self.family.n, self.family.degrees
        x = np.frombuffer(arg[0], dtype=np.float64)
        yt = np.frombuffer(arg[1], dtype=np.float64).reshape(k, n)
        out = np.frombuffer(res[0], dtype=np.float64)
        out[:] = np.einsum("kp,kp->p", self.family.values(x, self.d), yt)
        return 0

    def get_forward(self, nfwd, name, inames, onames, opts):
        fam = self.family
        x, a, y, (dx, da) = self._symbols(nfwd, [(1, fam.n), (fam.n, fam.degrees)])
        slope = fam.contracted(self.d + 1)(x, a)
        blocks = [
            slope * dxi + self(x, dai) for dxi, dai in zip(ca.horzsplit(dx, fam.n), ca.horzsplit(da, fam.degrees))
        ]
        return ca.Function(name, [x, a, y, dx, da], [ca.horzcat(*blocks)], inames, onames, opts)

    def get_reverse(self, nadj, name, inames, onames, opts):
        fam = self.family
        x, a, y, (adj,) = self._symbols(nadj, [(1, fam.n)])
        slope = fam.contracted(self.d + 1)(x, a)
        parts = ca.horzsplit(adj, fam.n)
        xbar = [r * slope for r in parts]
        abar = [fam.scaled(self.d)(x, r) for r in parts]
        return ca.Function(name, [x, a, y, adj], [ca.horzcat(*xbar), ca.horzcat(*abar)], inames, onames, opts)
