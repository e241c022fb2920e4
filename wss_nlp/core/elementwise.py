r"""Functions applied at many points inside CasADi graphs, by NumPy, with exact derivatives of every order.

The coupled velocity misfit (:mod:`wss_nlp.models.coupled`) evaluates pointwise
pieces at every sub-voxel point, tens of thousands of points that move with
the wall: the smoothed indicator, the inverse map's radius, a near-wall
layer's cell means and inside fractions. CasADi's mapped SX functions cost
0.2-1 us per point (the instructions and the map's per-call overhead: 6-7 ms
per evaluation for the indicator and for the radius at h = 0.3 mm), NumPy's
vectorized formulas a fraction of that. A :class:`Ladder` holds the maps

.. math::

    D_d : y \mapsto F^{(d)}(y) \quad \text{(elementwise on a row of } n \text{ points)},

given a NumPy function ``derivative(y, d)`` for every order ``d``; a
:class:`ScaledLadder` the mixed derivatives in the row and one scalar (the indicator's width).

Notes
-----
The maps close under differentiation:

.. math::

    \dot D_d = D_{d+1}(y)\, \dot y, \qquad \bar y = D_{d+1}(y)\, \bar D,

so every derivative CasADi asks for (gradients, forward-over-reverse
Hessians) is again one of them (``tests/test_elementwise.py`` checks values,
forward and reverse derivatives and a Hessian against the same function
written in CasADi's SX). Keep the :class:`Ladder` while functions built from
it live (CasADi's rule for callbacks).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

import casadi as ca

from .operators import DenseCallback


class Ladder:
    """The maps :math:`D_d` of ``derivative(y, d)`` at ``n`` points, each built once and kept.

    The values at the last points are kept per order: one evaluation of a
    graph and of its derivatives calls several maps at the same ``y``.
    """

    def __init__(self, n: int, derivative: Callable[[np.ndarray, int], np.ndarray], name: str = "ladder"):
        self.n, self.derivative, self.name = int(n), derivative, name
        self._maps: dict = {}
        self._last: np.ndarray | None = None
        self._values: dict = {}

    def values(self, y: np.ndarray, d: int) -> np.ndarray:
        """:math:`F^{(d)}(y)` (read-only)."""
        if self._last is None or not np.array_equal(y, self._last):
            self._last, self._values = np.array(y, dtype=float), {}
        if d not in self._values:
            out = np.asarray(self.derivative(self._last, d), dtype=float).reshape(self.n)
            out.flags.writeable = False
            self._values[d] = out
        return self._values[d]

    def map(self, d: int = 0) -> _Derivative:
        """:math:`D_d` as a CasADi callback ``(1, n) -> (1, n)``."""
        if d not in self._maps:
            self._maps[d] = _Derivative(self, d)
        return self._maps[d]


class _Derivative(DenseCallback):
    """:math:`D_d(y) = F^{(d)}(y)` on a row of points; its derivatives are :math:`D_{d+1}` times the seeds."""

    def __init__(self, ladder: Ladder, d: int):
        self.ladder, self.d = ladder, int(d)
        super().__init__(f"{ladder.name}_d{d}_{ladder.n}", (1, ladder.n), (1, ladder.n))

    def eval_buffer(self, arg, res):
        out = np.frombuffer(res[0], dtype=np.float64)
        out[:] = self.ladder.values(np.frombuffer(arg[0], dtype=np.float64), self.d)
        return 0

    def has_forward(self, nfwd):
        return True

    def has_reverse(self, nadj):
        return True

    def _seeded(self, nseed: int, name, inames, onames, opts) -> ca.Function:
        # forward and reverse alike: the seeds (side by side) times the next derivative at y
        n = self.ladder.n
        y, out = ca.MX.sym("y", 1, n), ca.MX.sym("out", 1, n)
        seed = ca.MX.sym("seed", 1, n * nseed)
        slope = self.ladder.map(self.d + 1)(y)
        blocks = [slope * part for part in ca.horzsplit(seed, n)]
        return ca.Function(name, [y, out, seed], [ca.horzcat(*blocks)], inames, onames, opts)

    def get_forward(self, nfwd, name, inames, onames, opts):
        return self._seeded(nfwd, name, inames, onames, opts)

    def get_reverse(self, nadj, name, inames, onames, opts):
        return self._seeded(nadj, name, inames, onames, opts)


class ScaledLadder:
    r"""The maps :math:`D_{ij} : (y, g) \mapsto \partial_y^i \partial_g^j F(y, g)` at ``n`` points and one scalar
    ``g``, given ``derivative(y, g, i, j)`` for every order, each built once and kept.

    Notes
    -----
    As for :class:`Ladder`, the maps close under differentiation:

    .. math::

        \dot D_{ij} = D_{i+1,j}\, \dot y + D_{i,j+1}\, \dot g, \qquad
        \bar y = D_{i+1,j}\, \bar D, \quad \bar g = \textstyle\sum_p (D_{i,j+1})_p \bar D_p .

    The values at the last ``(y, g)`` are kept per order.
    """

    def __init__(self, n: int, derivative: Callable[[np.ndarray, float, int, int], np.ndarray], name: str = "ladder"):
        self.n, self.derivative, self.name = int(n), derivative, name
        self._maps: dict = {}
        self._last: np.ndarray | None = None
        self._values: dict = {}

    def values(self, y: np.ndarray, g: float, i: int, j: int) -> np.ndarray:
        r""":math:`\partial_y^i \partial_g^j F(y, g)` (read-only)."""
        point = np.append(y, g)
        if self._last is None or not np.array_equal(point, self._last):
            self._last, self._values = np.array(point, dtype=float), {}
        if (i, j) not in self._values:
            out = np.asarray(self.derivative(self._last[:-1], float(self._last[-1]), i, j), dtype=float)
            out = out.reshape(self.n)
            out.flags.writeable = False
            self._values[i, j] = out
        return self._values[i, j]

    def map(self, i: int = 0, j: int = 0) -> _ScaledDerivative:
        """:math:`D_{ij}` as a CasADi callback ``((1, n), (1, 1)) -> (1, n)``."""
        if (i, j) not in self._maps:
            self._maps[i, j] = _ScaledDerivative(self, i, j)
        return self._maps[i, j]


class _ScaledDerivative(ca.Callback):
    """:math:`D_{ij}(y, g)` on a row of points and a scalar; its derivatives are :math:`D_{i+1,j}` and
    :math:`D_{i,j+1}` times the seeds."""

    def __init__(self, ladder: ScaledLadder, i: int, j: int):
        ca.Callback.__init__(self)
        self.ladder, self.i, self.j = ladder, int(i), int(j)
        self.construct(f"{ladder.name}_d{i}{j}_{ladder.n}", {})

    def get_n_in(self):
        return 2

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, k):
        return ca.Sparsity.dense(1, self.ladder.n) if k == 0 else ca.Sparsity.dense(1, 1)

    def get_sparsity_out(self, k):
        return ca.Sparsity.dense(1, self.ladder.n)

    def has_eval_buffer(self):
        return True

    def eval_buffer(self, arg, res):
        g = float(np.frombuffer(arg[1], dtype=np.float64)[0])
        out = np.frombuffer(res[0], dtype=np.float64)
        out[:] = self.ladder.values(np.frombuffer(arg[0], dtype=np.float64), g, self.i, self.j)
        return 0

    def has_forward(self, nfwd):
        return True

    def has_reverse(self, nadj):
        return True

    def get_forward(self, nfwd, name, inames, onames, opts):
        n = self.ladder.n
        y, g, out = ca.MX.sym("y", 1, n), ca.MX.sym("g"), ca.MX.sym("out", 1, n)
        seed_y, seed_g = ca.MX.sym("seed_y", 1, n * nfwd), ca.MX.sym("seed_g", 1, nfwd)
        along_y, along_g = self.ladder.map(self.i + 1, self.j)(y, g), self.ladder.map(self.i, self.j + 1)(y, g)
        blocks = [along_y * part + along_g * seed_g[k] for k, part in enumerate(ca.horzsplit(seed_y, n))]
        return ca.Function(name, [y, g, out, seed_y, seed_g], [ca.horzcat(*blocks)], inames, onames, opts)

    def get_reverse(self, nadj, name, inames, onames, opts):
        n = self.ladder.n
        y, g, out = ca.MX.sym("y", 1, n), ca.MX.sym("g"), ca.MX.sym("out", 1, n)
        seed = ca.MX.sym("seed", 1, n * nadj)
        along_y, along_g = self.ladder.map(self.i + 1, self.j)(y, g), self.ladder.map(self.i, self.j + 1)(y, g)
        parts = ca.horzsplit(seed, n)
        bar_y = ca.horzcat(*[along_y * part for part in parts])
        bar_g = ca.horzcat(*[ca.dot(along_g, part) for part in parts])
        return ca.Function(name, [y, g, out, seed], [bar_y, bar_g], inames, onames, opts)
