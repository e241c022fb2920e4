r"""A function of one variable applied at many points inside CasADi graphs, by NumPy, with exact derivatives.

The coupled velocity misfit (:mod:`wss_nlp.coupled`) evaluates a near-wall
layer's cell means at every sub-voxel point deep inside the wall, tens of
thousands of points whose depth moves with the wall. CasADi's mapped SX
function costs about 0.5 us per point for the law of the wall (a hundred
instructions and the map's per-call overhead), NumPy's vectorized formulas a
tenth of that. A :class:`Ladder` holds the maps

.. math::

    D_d : y \mapsto F^{(d)}(y) \quad \text{(elementwise on a row of } n \text{ points)},

given a NumPy function ``derivative(y, d)`` for every order ``d``.

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
