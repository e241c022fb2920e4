"""The map phi_R from the unit disk B onto the lumen, eq. (trafo), and its inverse.

    phi_R(rho cos t, rho sin t) = c + (r_in rho + (R(t) - r_in) rho^eta) (cos t, sin t)

with the centre ``c`` (mm), the inner radius ``r_in`` (the paper's r0) and
``eta >= 2``. It preserves angles, so the inverse only solves a scalar,
monotone equation for ``rho`` along each ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import casadi as ca

from . import radius as rad
from ..errors import InputError


def inverse_radius(big_r, r, r_in):
    """The reference radius ``rho`` of points at distance ``r`` from the centre on a ray where the wall is at
    ``R``, for ``eta = 2``: ``r_in rho + (R - r_in) rho^2 = r`` solved by the stable quadratic formula,
    ``rho = 2 r / (r_in + sqrt(r_in^2 + 4 (R - r_in) r))`` (NumPy or CasADi)."""
    sqrt = ca.sqrt if any(isinstance(v, (ca.SX, ca.MX)) for v in (big_r, r, r_in)) else np.sqrt
    return 2 * r / (r_in + sqrt(r_in**2 + 4 * (big_r - r_in) * r))


@dataclass(frozen=True)
class DiskMap:
    """Parameters of phi_R for one radius function.

    Attributes
    ----------
    coefficients : array
        Fourier coefficients of R (mm).
    center : (cx, cy)
        Centre in mm.
    r_in : float
        Inner radius in mm; the map is one-to-one when
        ``r_in < eta / (eta - 1) min R`` and its Jacobian determinant is
        bounded below by ``r_in^2`` when ``r_in <= min R`` (Lemma A.4).
    eta : float
        Exponent, ``eta >= 2``.
    """

    coefficients: np.ndarray
    center: tuple[float, float]
    r_in: float
    eta: float = 2.0

    def __post_init__(self):
        if self.eta < 2:
            raise InputError(f"the map exponent eta must be >= 2 (paper eq. (trafo)), got {self.eta}")
        rmin = float(np.min(rad.evaluate(self.coefficients, rad.uniform_angles(720))))
        if not 0 < self.r_in <= rmin * (1 + 1e-12):
            raise InputError(f"inner radius r_in = {self.r_in:.4g} mm must lie in (0, min R = {rmin:.4g} mm]")

    def forward(self, rho, t):
        """Physical points of reference polar coordinates ``(rho, t)``."""
        big_r = rad.evaluate(self.coefficients, np.ravel(t)).reshape(np.shape(t))
        s = self.r_in * rho + (big_r - self.r_in) * rho**self.eta
        return self.center[0] + s * np.cos(t), self.center[1] + s * np.sin(t)

    def inverse(self, x, y):
        """Reference polar coordinates ``(rho, t)`` of physical points in the lumen.

        Solves ``r_in rho + (R(t) - r_in) rho^eta = |x - c|`` by safeguarded
        Newton iteration (closed form start for eta = 2). Points outside the
        lumen get ``rho > 1``.
        """
        dx, dy = np.asarray(x) - self.center[0], np.asarray(y) - self.center[1]
        r = np.hypot(dx, dy)
        t = np.arctan2(dy, dx)
        big_r = rad.evaluate(self.coefficients, t.ravel()).reshape(t.shape)
        a = big_r - self.r_in
        rho = inverse_radius(big_r, r, self.r_in)  # exact for eta = 2, a good start otherwise
        if self.eta != 2:
            for _ in range(50):
                g = self.r_in * rho + a * rho**self.eta - r
                dg = self.r_in + self.eta * a * rho ** (self.eta - 1)
                step = g / dg
                rho = np.maximum(rho - step, 0.5 * rho)
                if np.max(np.abs(step)) < 1e-15:
                    break
        return rho, t


def symbolic_forward(xi, coefficients, center, r_in: float, eta: float):
    """CasADi expression of phi_R at Cartesian reference point ``xi`` (2-vector).

    ``coefficients`` and ``center`` may be symbols or numbers; used for the
    Jacobian ``J_R = d phi_R / d xi`` by automatic differentiation (Sec. 4).
    Valid away from ``xi = 0`` (polar angle undefined there), in particular
    on the wall ``|xi| = 1``.
    """
    rho = ca.sqrt(ca.dot(xi, xi))
    t = ca.atan2(xi[1], xi[0])
    big_r = rad.symbolic(ca.DM(coefficients) if isinstance(coefficients, np.ndarray) else coefficients, t)
    s = r_in * rho + (big_r - r_in) * rho**eta
    return ca.vertcat(center[0], center[1]) + s * xi / rho
