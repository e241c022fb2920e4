r"""The exponential layer :math:`f(y) = 1 - e^{-y}`: laminar layers that saturate.

Developing entrance flow and the Stokes layers of pulsatile flow; ``l`` is a displacement-type thickness, the
scale that minimizes the criterion over a grid of scales.
"""

from __future__ import annotations

import numpy as np

from . import register
from .base import WallFamily


class Exponential(WallFamily):
    name = "exponential"
    description = "1 - exp(-y): laminar layers that saturate (entrance flow), scale by the BIC"
    scale_rule = "criterion"
    saturating = True

    def f(self, y, lib):
        return 1 - lib.exp(-y)

    def derivative(self, y, order):
        """:math:`f^{(k)} = (-1)^{k+1} e^{-y}`."""
        return (-1.0) ** (order + 1) * np.exp(-y)

    def integrals(self, y, lib):
        e = lib.exp(-y)
        return y - 1 + e, y * y / 2 - y + 1 - e


register(Exponential())
