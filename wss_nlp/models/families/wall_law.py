r"""Reichardt's law of the wall: the mean profile of turbulent flow near a wall.

:math:`f(y) = \ln(1 + \kappa y)/\kappa + C\,(1 - e^{-y/11} - (y/11)\,e^{-y/3})`, :math:`\kappa = 0.41`,
:math:`C = 7.8` (Reichardt 1951, *Z. angew. Math. Mech.* 31, 208-219), ``y`` in viscous units: the scale
``l`` is the viscous length :math:`\nu/u_\tau`, found where the fitted layer obeys :math:`u_\tau\ell = \nu`.
"""

from __future__ import annotations

import numpy as np

from . import register
from .base import WallFamily

#: von Karman constant and the additive constant of Reichardt's law.
KAPPA, REICHARDT_C = 0.41, 7.8


class WallLaw(WallFamily):
    name = "wall_law"
    description = "Reichardt's law of the wall (turbulent mean flow), scale from u_tau l = nu"
    scale_rule = "consistent"
    turbulent = True

    def f(self, y, lib):
        return lib.log(1 + KAPPA * y) / KAPPA + REICHARDT_C * (1 - lib.exp(-y / 11) - y / 11 * lib.exp(-y / 3))

    def derivative(self, y, order):
        r"""For :math:`k \ge 1`:
        :math:`f^{(k)} = \frac{(-1)^{k-1}(k-1)!\,\kappa^{k-1}}{(1+\kappa y)^k} - C\big[(-\tfrac{1}{11})^k e^{-y/11}
        + \tfrac{1}{11}\big(y(-\tfrac13)^k + k(-\tfrac13)^{k-1}\big)e^{-y/3}\big]`."""
        z, e11, e3, k = 1 + KAPPA * y, np.exp(-y / 11), np.exp(-y / 3), int(order)
        log_part = (-1) ** (k - 1) * float(np.prod(np.arange(1, k))) * KAPPA ** (k - 1) / z**k
        third = -1.0 / 3
        return log_part - REICHARDT_C * ((-1.0 / 11) ** k * e11 + (y * third**k + k * third ** (k - 1)) / 11 * e3)

    def integrals(self, y, lib):
        z, e11, e3 = 1 + KAPPA * y, lib.exp(-y / 11), lib.exp(-y / 3)
        lz = lib.log(z)
        f1 = (z * lz - KAPPA * y) / KAPPA**2 + REICHARDT_C * (y - 11 * (1 - e11) - (9 - (3 * y + 9) * e3) / 11)
        f2 = (z * z * lz / 2 - 3 * z * z / 4 + z - 0.25) / KAPPA**3 + REICHARDT_C * (
            y * y / 2 - 11 * y + 121 * (1 - e11) - (9 * y - 54 + (9 * y + 54) * e3) / 11
        )
        return f1, f2


register(WallLaw())
