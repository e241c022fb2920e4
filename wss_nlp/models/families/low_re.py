r"""A law of the wall whose buffer layer depends on the friction Reynolds number (``low_re``).

Reichardt's law (:mod:`~wss_nlp.models.families.wall_law`) is a fit to high-Reynolds-number data; at
:math:`Re_\tau` of a few hundred the mean velocity lies above it in the buffer layer (channel DNS at
:math:`Re_\tau` 186: :math:`U^+ = 12.24` at :math:`y^+ = 20` against Reichardt's 11.93), and a wall layer of that
shape overestimates the wall shear stress. This family keeps Reichardt's closed form with its four constants
as functions of :math:`Re_\tau`:

.. math::

    f(y; Re_\tau) = \frac{\ln(1 + \kappa y)}{\kappa}
        + C\,\big(1 - e^{-y/B_1} - (y/B_1)\,e^{-y/B_2}\big),
    \qquad p(Re_\tau) = p_\infty + p_{low}\,\frac{Re_{min}}{\max(Re_\tau, Re_{min})}

for :math:`p \in \{\kappa, C, B_1, B_2\}` (:data:`CONSTANTS`), ``y`` in viscous units. Every member has
:math:`f(0) = 0` and :math:`f'(0) = 1`. Below the lowest calibrated :math:`Re_\tau` (:data:`RE_MIN`) the shape
stays at that one's; above the highest it tends to :math:`p_\infty` (the :math:`1/Re_\tau` law, 3 % of the way
from the highest to the limit).

**Calibration** (``python scripts/calibrate_low_re.py``, ``scripts/results/calibrate_low_re.md``): the eight
constants are fitted jointly to the mean profiles of turbulent *channel* flow from DNS by the Madrid group at
:math:`Re_\tau` 186, 547, 934 and 2004 (Hoyas & Jimenez, Phys. Fluids 20 (2008) 101511; del Alamo & Jimenez,
Phys. Fluids 15 (2003) L41; del Alamo et al., J. Fluid Mech. 500 (2004) 135; Hoyas & Jimenez, Phys. Fluids 18
(2006) 011702; copies in ``wss_nlp/data/channel_dns``), least squares in :math:`U^+` on 400 points per profile
uniform in :math:`\ln y^+` from 0.2 to the centreline, each profile with its own outer part (a wake
:math:`a_2\eta^2 + a_3\eta^3 + a_4\eta^4`, :math:`\eta = y^+/Re_\tau`: zero value and slope at the wall) that is
fitted beside the constants and then discarded. The wake is where channel and pipe flow differ; the velocity
fit leaves it, like every other smooth outer part, to its penalized polynomials, so it cannot reach the wall
gradient through this profile. No pipe data took part: the pipe DNS in ``wss_nlp/data`` is the test
(``scripts/low_re.py``, ``tests/test_low_re.py``).

**Re_tau from the data.** The profile of a layer of scale ``l`` in a lumen of mean radius ``R`` is the one at
:math:`Re_\tau = R/\ell` (:func:`wss_nlp.models.near_wall.enrich`,
:func:`wss_nlp.parameters.layer.choose_layer`), and ``l`` is where the fitted layer obeys the law of the wall,
:math:`u_\tau\ell = \nu` (``scale_rule = "consistent"``), so :math:`Re_\tau` comes with the scale. A member is
named ``"low_re@<Re_tau>"`` (:func:`wss_nlp.models.families.at_reynolds`); the registered ``"low_re"`` is the
member at :data:`RE_MIN`.
"""

from __future__ import annotations

import functools
from importlib import resources

import numpy as np

from . import register
from .base import WallFamily

#: Lowest friction Reynolds number calibrated (the Re_tau 180 channel's y+ at its centreline): below it
#: the shape stays at this one's.
RE_MIN = 186.33725

#: ``name: (p_inf, p_low)`` of the four shape parameters, ``p(Re_tau) = p_inf + p_low RE_MIN / max(Re_tau,
#: RE_MIN)``. Made by ``python scripts/calibrate_low_re.py`` from the four channel DNS profiles
#: (``wss_nlp/data/channel_dns``, Hoyas & Jimenez); see the module notes.
CONSTANTS = {
    "kappa": (0.400354, 0.113906),
    "C": (7.20489, 1.51788),
    "B1": (8.5756, 1.33486),
    "B2": (3.70029, -0.0766713),
}

#: The channel DNS profiles of the calibration (``wss_nlp/data/channel_dns``), by nominal Re_tau.
CHANNEL_PROFILES = {"re180": "Re180.prof", "re550": "Re550.prof", "re950": "Re950.prof", "re2000": "Re2000.prof"}


def shape(re_tau: float) -> tuple[float, float, float, float]:
    """``(kappa, C, B1, B2)`` at friction Reynolds number ``re_tau`` (:data:`CONSTANTS`)."""
    low = RE_MIN / max(float(re_tau), RE_MIN)
    return tuple(p_inf + p_low * low for p_inf, p_low in CONSTANTS.values())  # type: ignore[return-value]


@functools.lru_cache(maxsize=8)
def channel_profile(name: str) -> tuple[np.ndarray, np.ndarray, float]:
    """``(y+, U+, Re_tau)`` of a channel DNS profile of the calibration (:data:`CHANNEL_PROFILES`).

    The files' rows after the ``%`` header (one provisional-data line of ``Re2000.prof`` starts with
    ``WARNING``): columns y/h, y+, U+, ...; Re_tau is y+ at the centreline y/h = 1.
    """
    text = resources.files("wss_nlp.data").joinpath("channel_dns").joinpath(CHANNEL_PROFILES[name]).read_text()
    rows = [ln for ln in text.splitlines() if ln.strip() and ln.lstrip()[0] in "-.0123456789"]
    table = np.loadtxt(rows)
    return table[:, 1], table[:, 2], float(table[-1, 1])


class LowReynoldsWallLaw(WallFamily):
    """Reichardt's form with Re_tau-dependent constants (module notes); ``at(re_tau)`` gives a member."""

    name = "low_re"
    description = (
        "law of the wall with a Re_tau-dependent buffer layer (calibrated on channel DNS), Re_tau = R/l, "
        "scale from u_tau l = nu"
    )
    scale_rule = "consistent"
    turbulent = True
    reynolds_dependent = True
    # on the channel DNS it fits every Re_tau 6-20 x closer than Reichardt's law (scripts/results/calibrate_low_re.md)
    supersedes = ("wall_law",)

    def __init__(self, re_tau: float | None = None):
        self.re_tau = RE_MIN if re_tau is None else float(re_tau)
        if not (np.isfinite(self.re_tau) and self.re_tau > 0):
            raise ValueError(f"a friction Reynolds number must be positive and finite, got {re_tau}")
        if re_tau is not None:
            self.name = f"{LowReynoldsWallLaw.name}@{self.re_tau!r}"
        self.kappa, self.c, self.b1, self.b2 = shape(self.re_tau)

    def at(self, re_tau: float) -> LowReynoldsWallLaw:
        return LowReynoldsWallLaw(re_tau)

    def f(self, y, lib):
        k, c, b1, b2 = self.kappa, self.c, self.b1, self.b2
        return lib.log(1 + k * y) / k + c * (1 - lib.exp(-y / b1) - y / b1 * lib.exp(-y / b2))

    def derivative(self, y, order):
        r"""For :math:`k \ge 1`: :math:`f^{(k)} = \frac{(-1)^{k-1}(k-1)!\,\kappa^{k-1}}{(1+\kappa y)^k}
        - C\big[(-1/B_1)^k e^{-y/B_1} + \big(y(-1/B_2)^k + k(-1/B_2)^{k-1}\big)e^{-y/B_2}/B_1\big]`."""
        k, c, b1, b2, n = self.kappa, self.c, self.b1, self.b2, int(order)
        log_part = (-1) ** (n - 1) * float(np.prod(np.arange(1, n))) * k ** (n - 1) / (1 + k * y) ** n
        t = -1.0 / b2
        return log_part - c * (
            (-1.0 / b1) ** n * np.exp(-y / b1) + (y * t**n + n * t ** (n - 1)) / b1 * np.exp(-y / b2)
        )

    def integrals(self, y, lib):
        r""":math:`F_1 = \frac{z\ln z - \kappa y}{\kappa^2}
        + C\big[y - B_1(1 - e_1) - (B_2^2(1 - e_2) - B_2 y e_2)/B_1\big]`,
        :math:`F_2 = \frac{z^2\ln z/2 - 3z^2/4 + z - 1/4}{\kappa^3} + C\big[y^2/2 - B_1 y + B_1^2(1 - e_1)
        - (B_2^2 y - 2B_2^3 + B_2^2(y + 2B_2)e_2)/B_1\big]`, :math:`z = 1 + \kappa y`, :math:`e_i = e^{-y/B_i}`."""
        k, c, b1, b2 = self.kappa, self.c, self.b1, self.b2
        z, e1, e2 = 1 + k * y, lib.exp(-y / b1), lib.exp(-y / b2)
        lz = lib.log(z)
        f1 = (z * lz - k * y) / k**2 + c * (y - b1 * (1 - e1) - (b2 * b2 * (1 - e2) - b2 * y * e2) / b1)
        f2 = (z * z * lz / 2 - 3 * z * z / 4 + z - 0.25) / k**3 + c * (
            y * y / 2 - b1 * y + b1 * b1 * (1 - e1) - (b2 * b2 * y - 2 * b2**3 + b2 * b2 * (y + 2 * b2) * e2) / b1
        )
        return f1, f2


register(LowReynoldsWallLaw())
