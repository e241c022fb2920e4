r"""Pulsatile flow phantoms: Womersley's exact solution in a rigid circular pipe, acquired frame by frame.

Notes
-----
Fully developed pulsatile flow obeys :math:`\rho\,\partial_t u = G(t) + \mu\,\Delta u` with the pressure
gradient :math:`G(t) = G_0 + \sum_n \mathrm{Re}[G_n e^{i n \omega t}]`. With no slip at :math:`r = R`
(Womersley 1955, J. Physiol. 127, 553-563), in Kelvin functions (:math:`\mathrm{ber} + i\,\mathrm{bei}
= J_0(i^{3/2}\,\cdot)`, Abramowitz & Stegun 9.9.1):

.. math::

    u(r, t) = \frac{G_0}{4\mu}(R^2 - r^2) + \sum_n \mathrm{Re}\Big[A_n
    \Big(1 - \frac{K(\alpha_n r/R)}{K(\alpha_n)}\Big) e^{i n\omega t}\Big],
    \qquad K = \mathrm{ber} + i\,\mathrm{bei}, \quad \alpha_n = R\sqrt{n\omega\rho/\mu},

:math:`A_n = G_n/(i\rho n\omega)`, and the wall shear stress :math:`\tau = -\mu\,\partial_r u(R, t)`

.. math::

    \tau(t) = \frac{G_0 R}{2} + \sum_n \mathrm{Re}\Big[\mu A_n \frac{\alpha_n}{R}
    \frac{K'(\alpha_n)}{K(\alpha_n)} e^{i n\omega t}\Big].

The harmonics are given as bulk-velocity harmonics :math:`V_n` (m/s); the bulk velocity of harmonic n is
:math:`A_n \cdot 2\int_0^1 (1 - K(\alpha_n x)/K(\alpha_n))\,x\,dx`, the integral by Gauss-Legendre quadrature
(:data:`BULK_NODES` nodes), which fixes :math:`A_n`. The truth is computed from scipy's Kelvin functions
(Zhang & Jin's series and asymptotic expansions), a computation independent of the reconstruction's
momentum model (:mod:`wss_nlp.models.womersley`, complex-argument Bessel functions, Amos's algorithm); the
tests check that the two agree. Lengths in mm in the interface (as every phantom), SI inside.

Waveforms (:data:`WAVEFORMS`): the bulk velocity over the cycle built from periodic Gaussian pulses that
give the features published flow waveforms show (systolic peak, late-systolic shoulder, dicrotic notch,
early-diastolic reversal, diastolic flow), then its Fourier series to :data:`WAVEFORM_HARMONICS`
harmonics; not digitized data. Carotid after Holdsworth et al. 1999 (Physiol. Meas. 20, 219-240: no
reversal, diastolic flow about a quarter of the peak); ascending aorta (systolic ejection, a brief reversal
at valve closure, no diastolic flow); femoral and brachial (triphasic: forward, reverse, late forward).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._lazy import scipy
from ..errors import InputError
from ..io.files import Acquisition
from ..models.kspace import PSF
from ..models.measurement import VoxelGrid
from .phantoms import PER_MM, Circle, Ellipse, Flow, Truth, _local, acquire, peak_velocity

#: A carotid-like bulk-velocity waveform: mean and harmonics 1-4 (m/s, complex: amplitude and phase).
CAROTID_HARMONICS = (0.18, 0.16 * np.exp(-1.0j), 0.10 * np.exp(-2.1j), 0.05 * np.exp(-3.0j), 0.03 * np.exp(-4.2j))

#: Gauss-Legendre nodes of the bulk velocity's radial integral (the integrand varies on 1/alpha_n of the radius:
#: 400 nodes resolve alpha_n up to about 300, far beyond the waveforms' 20 sqrt(16) = 80).
BULK_NODES = 400

#: Harmonics kept of a published-shape waveform (:data:`WAVEFORMS`).
WAVEFORM_HARMONICS = 16


@dataclass(frozen=True)
class Waveform:
    """A bulk-velocity waveform over the cycle: periodic Gaussian pulses on a baseline (module notes).

    ``pulses`` are ``(centre, width, amplitude)`` with centre and width in fractions of the period and the
    amplitude relative to the systolic peak; ``peak_m_s`` scales the waveform's largest bulk velocity;
    ``radius_mm`` and ``period_ms`` are the vessel's typical size and the cycle's length.
    """

    name: str
    baseline: float
    pulses: tuple
    peak_m_s: float
    radius_mm: float
    period_ms: float

    def values(self, phase: np.ndarray) -> np.ndarray:
        """The waveform at phases in [0, 1) of the cycle, before scaling (periodic pulses)."""
        phase = np.asarray(phase, dtype=float)
        out = np.full(phase.shape, self.baseline)
        for centre, width, amplitude in self.pulses:
            for wrap in (-1.0, 0.0, 1.0):
                out = out + amplitude * np.exp(-0.5 * ((phase - centre - wrap) / width) ** 2)
        return out

    def harmonics(self, n: int = WAVEFORM_HARMONICS) -> tuple:
        """``(V_0, V_1, ..., V_n)`` (m/s; complex, ``V(t) = V_0 + sum Re V_k e^{i k omega t}``)."""
        samples = 4096
        v = self.values(np.arange(samples) / samples)
        coef = np.fft.rfft(v) / samples
        out = [float(coef[0].real)] + [complex(2 * coef[k]) for k in range(1, n + 1)]  # v = c_0 + 2 Re sum c_k e^
        scale = self.peak_m_s / float(np.max(_bulk(tuple(out), np.arange(samples) / samples)))
        return tuple(scale * c for c in out)


def _bulk(harmonics: tuple, phase: np.ndarray) -> np.ndarray:
    """The bulk velocity of ``harmonics`` at phases of the cycle."""
    v = np.full(np.shape(phase), float(np.real(harmonics[0])))
    for k, h in enumerate(harmonics[1:], start=1):
        v = v + np.real(complex(h) * np.exp(2j * np.pi * k * np.asarray(phase)))
    return v


#: Published-shape waveforms (module notes); Womersley numbers with blood (3.5 mPa s, 1060 kg/m^3) about 4.3
#: (carotid), 17 (aorta), 5.9 (femoral) and 3.1 (brachial) at their typical radii.
WAVEFORMS = {
    "carotid": Waveform(
        "carotid", 0.25,
        ((0.12, 0.035, 0.75), (0.22, 0.04, 0.25), (0.33, 0.02, -0.12), (0.40, 0.06, 0.10)),
        0.45, 3.0, 920.0,
    ),
    "aortic": Waveform("aortic", 0.0, ((0.12, 0.05, 1.0), (0.33, 0.02, -0.12)), 0.9, 12.0, 1000.0),
    "femoral": Waveform(
        "femoral", 0.02, ((0.12, 0.035, 1.0), (0.27, 0.045, -0.35), (0.42, 0.05, 0.12)), 0.6, 4.0, 900.0
    ),
    "brachial": Waveform(
        "brachial", 0.02, ((0.13, 0.035, 1.0), (0.28, 0.04, -0.2), (0.42, 0.05, 0.08)), 0.5, 2.0, 850.0
    ),
}  # fmt: skip


def kelvin(x) -> np.ndarray:
    """``ber(x) + i bei(x) = J_0(i^{3/2} x)`` for real ``x >= 0``."""
    x = np.asarray(x, dtype=float)
    return scipy.special.ber(x) + 1j * scipy.special.bei(x)


def kelvin_slope(x) -> np.ndarray:
    """``ber'(x) + i bei'(x)``."""
    x = np.asarray(x, dtype=float)
    return scipy.special.berp(x) + 1j * scipy.special.beip(x)


@dataclass
class WomersleyPipe(Flow):
    """Womersley flow in a rigid circular pipe at time ``t_s`` of the cycle (see the module notes)."""

    density_kg_m3: float = 1060.0
    period_s: float = 1.0
    bulk_harmonics: tuple = CAROTID_HARMONICS  # V_0 (real), V_1, V_2, ... (m/s)
    t_s: float = 0.0
    _table: dict = field(default_factory=dict, repr=False)

    @property
    def radius_m(self) -> float:
        assert isinstance(self.lumen, Circle)
        return float(self.lumen.r) / PER_MM

    def womersley(self, n: int = 1) -> float:
        """Womersley number of harmonic ``n``: ``R sqrt(n omega rho / mu)``."""
        omega = 2 * np.pi / self.period_s
        return self.radius_m * np.sqrt(n * omega * self.density_kg_m3 / self.viscosity_pa_s)

    def _coefficients(self):
        """``(G_0, [(n, alpha_n, A_n)])`` with ``A_n = G_n / (i rho n omega)`` (m/s), from the bulk harmonics."""
        cycle = self._cycle()
        if "coef" not in cycle:
            g0 = 8 * self.viscosity_pa_s * float(np.real(self.bulk_harmonics[0])) / self.radius_m**2  # V = G R^2/8mu
            x, w = np.polynomial.legendre.leggauss(BULK_NODES)
            x, w = (x + 1) / 2, w / 2  # on [0, 1]
            terms = []
            for n, v_n in enumerate(self.bulk_harmonics[1:], start=1):
                alpha = self.womersley(n)
                bulk = 2 * np.sum(w * x * (1 - kelvin(alpha * x) / kelvin(alpha)))
                terms.append((n, alpha, complex(v_n) / bulk))  # the bulk velocity of harmonic n: V_n = A_n * bulk
            cycle["coef"] = (g0, terms)
        return cycle["coef"]

    def _cycle(self) -> dict:
        """What belongs to the whole cycle (coefficients, radial tables), shared by every instant (:meth:`at`)."""
        return self._table.setdefault("cycle", {})

    def _shapes(self, grid_mm: np.ndarray) -> list:
        """Each harmonic's ``A_n (1 - K(alpha_n r/R)/K(alpha_n))`` on a radius grid (once per grid size)."""
        key = ("shapes", grid_mm.size, float(grid_mm[-1]))
        cycle = self._cycle()
        if key not in cycle:
            _, terms = self._coefficients()
            x = np.clip(grid_mm / PER_MM / self.radius_m, 0.0, 1.0)
            cycle[key] = [amp * (1 - kelvin(alpha * x) / kelvin(alpha)) for _, alpha, amp in terms]
        return cycle[key]

    def profile(self, r_mm, t_s: float | None = None) -> np.ndarray:
        """``u(r, t)`` in m/s at radii ``r_mm`` (0 outside the pipe)."""
        t = self.t_s if t_s is None else t_s
        g0, terms = self._coefficients()
        rr = np.asarray(r_mm, dtype=float) / PER_MM
        x = np.clip(rr / self.radius_m, 0.0, 1.0)
        u = g0 / (4 * self.viscosity_pa_s) * (self.radius_m**2 - rr**2)
        omega = 2 * np.pi / self.period_s
        for n, alpha, amp in terms:
            u = u + np.real(amp * (1 - kelvin(alpha * x) / kelvin(alpha)) * np.exp(1j * n * omega * t))
        return np.where(rr < self.radius_m, u, 0.0)

    def wall_shear(self, t_s) -> np.ndarray:
        """Exact ``tau(t)`` in Pa (positive for forward flow)."""
        g0, terms = self._coefficients()
        t = np.asarray(t_s, dtype=float)
        tau = np.full_like(t, g0 * self.radius_m / 2)
        omega = 2 * np.pi / self.period_s
        for n, alpha, amp in terms:
            slope = alpha / self.radius_m * kelvin_slope(alpha) / kelvin(alpha)  # -d/dr of 1 - K(alpha r/R)/K(alpha)
            tau = tau + np.real(self.viscosity_pa_s * amp * slope * np.exp(1j * n * omega * t))
        return tau

    def velocity(self, x, y):
        r = np.hypot(np.asarray(x) - self.lumen.center[0], np.asarray(y) - self.lumen.center[1])
        key = ("grid", self.t_s)
        if key not in self._table:  # the harmonics once per cycle, on a radius grid far finer than any layer
            grid = np.linspace(0.0, float(self.lumen.r), 20001)
            g0, terms = self._coefficients()
            rr = grid / PER_MM
            values = g0 / (4 * self.viscosity_pa_s) * (self.radius_m**2 - rr**2)
            omega = 2 * np.pi / self.period_s
            for (n, _, _), shape in zip(terms, self._shapes(grid)):
                values = values + np.real(shape * np.exp(1j * n * omega * self.t_s))
            self._table[key] = (grid, values)
        grid, values = self._table[key]
        return np.where(r < self.lumen.r, np.interp(r, grid, values), 0.0)

    def wall_gradient(self, phi):
        return np.full_like(
            np.asarray(phi, dtype=float), float(self.wall_shear(self.t_s)) / self.viscosity_pa_s / PER_MM
        )

    def at(self, t_s: float) -> WomersleyPipe:
        """The same flow at another instant (shares the cycle's tables)."""
        other = WomersleyPipe(
            lumen=self.lumen,
            viscosity_pa_s=self.viscosity_pa_s,
            density_kg_m3=self.density_kg_m3,
            period_s=self.period_s,
            bulk_harmonics=self.bulk_harmonics,
            t_s=float(t_s),
        )
        other._table["cycle"] = self._cycle()
        return other


@dataclass
class DistendingWomersley(Flow):
    """Womersley flow in a gently distending circular pipe: the rigid pipe's field stretched to ``R(t)``.

    ``R(t) = R_0 (1 + epsilon sin(omega t))`` and ``u(r, t) = u_W(r R_0 / R(t), t)`` with :math:`u_W` the
    rigid pipe's (``base``); the wall shear stress is exact for this field, ``tau(t) = tau_W(t) R_0 / R(t)``.
    A kinematic phantom (the field of a moving wall is not a solution of the momentum balance): it tests that
    every frame finds its own wall and that the momentum model follows it (:mod:`wss_nlp.models.womersley`).
    """

    base: WomersleyPipe | None = None
    distension: float = 0.05
    t_s: float = 0.0

    @property
    def density_kg_m3(self) -> float:
        assert self.base is not None
        return self.base.density_kg_m3

    def stretch(self, t_s) -> np.ndarray:
        """``R(t) / R_0``."""
        assert self.base is not None
        return 1.0 + self.distension * np.sin(2 * np.pi * np.asarray(t_s, dtype=float) / self.base.period_s)

    def velocity(self, x, y):
        assert self.base is not None
        k, c = float(self.stretch(self.t_s)), self.lumen.center
        return self.base.velocity(c[0] + (np.asarray(x) - c[0]) / k, c[1] + (np.asarray(y) - c[1]) / k)

    def wall_gradient(self, phi):
        assert self.base is not None
        return self.base.wall_gradient(phi) / float(self.stretch(self.t_s))

    def wall_shear(self, t_s) -> np.ndarray:
        """Exact WSS (uniform around the wall) at times ``t_s``, Pa."""
        assert self.base is not None
        return self.base.wall_shear(t_s) / self.stretch(t_s)

    def womersley(self, n: int = 1) -> float:
        assert self.base is not None
        return self.base.womersley(n)

    def at(self, t_s: float) -> DistendingWomersley:
        assert self.base is not None
        base = self.base.at(t_s)
        r0 = self.base.radius_m * PER_MM
        base.lumen = Circle(r=r0, center=self.lumen.center)
        lumen = Circle(r=float(r0 * self.stretch(t_s)), center=self.lumen.center)
        return DistendingWomersley(lumen, self.viscosity_pa_s, base, self.distension, float(t_s))


@dataclass
class EllipticWomersley(Flow):
    r"""Fully developed pulsatile flow in a rigid elliptic pipe, exact to rounding (method of particular solutions).

    Harmonic ``n`` of the momentum balance is :math:`A_n(1 - h_n)` with
    :math:`h_n = \sum_m c_{nm} J_m(k_n r)\cos(m\theta)` (even ``m``, polar coordinates of the ellipse's
    axes), :math:`k_n = i^{3/2}\sqrt{n\omega/\nu}`: every term solves :math:`\Delta h + k_n^2 h = 0`
    exactly, so :math:`u_n = A_n(1 - h_n)e^{i n\omega t}` solves :math:`\rho\,\partial_t u = G_n e^{i n
    \omega t} + \mu\Delta u` with :math:`G_n = i\rho n\omega A_n` (as in the circle, where
    :math:`h_n = J_0(k_n r)/J_0(k_n R)`); the coefficients make :math:`h_n = 1` on the wall, by least squares
    at :data:`MPS_POINTS` wall points (Fox, Henrici & Moler 1967), and the wall residual is checked against
    :data:`MPS_TOLERANCE`. The mean part is Poiseuille's elliptic profile. The bulk-velocity harmonics are
    :class:`WomersleyPipe`'s, with :math:`\int h_n\,dA = -k_n^{-2}\oint \partial_n h_n\,ds` (a wall integral).

    Notes
    -----
    The velocity is tabulated in elliptic-polar coordinates (:math:`\sigma` by 1/1200, the angle by 2
    degrees) and interpolated linearly (relative error about 1e-4 in the acquired voxels, far below the
    noise); the wall shear stress is evaluated exactly from the series.
    """

    density_kg_m3: float = 1060.0
    period_s: float = 1.0
    bulk_harmonics: tuple = CAROTID_HARMONICS
    t_s: float = 0.0
    _table: dict = field(default_factory=dict, repr=False)

    def _ellipse(self):
        lumen = self.lumen
        assert isinstance(lumen, Ellipse)
        return lumen.a, lumen.b, lumen.angle

    def _wall_radius(self, theta):
        a, b, _ = self._ellipse()
        return a * b / np.sqrt((b * np.cos(theta)) ** 2 + (a * np.sin(theta)) ** 2)

    def _solution(self):
        """``(u_max of the mean part, [(n, k_n, A_n, orders, coefficients)])``, computed once."""
        if "sol" in self._table:
            return self._table["sol"]
        a, b, _ = self._ellipse()
        nu = self.viscosity_pa_s / self.density_kg_m3
        omega = 2 * np.pi / self.period_s
        orders = np.arange(0, 2 * MPS_TERMS, 2)
        theta = np.linspace(0, np.pi / 2, MPS_POINTS)
        check = np.linspace(0, np.pi / 2, 4 * MPS_POINTS + 1)
        terms = []
        for n, v_n in enumerate(self.bulk_harmonics[1:], start=1):
            k = complex(1j**1.5 * np.sqrt(n * omega / nu) / PER_MM)  # 1/mm
            design = scipy.special.jv(orders[None, :], k * self._wall_radius(theta)[:, None]) * np.cos(
                orders[None, :] * theta[:, None]
            )
            scale = np.max(np.abs(design), axis=0)
            coef = np.linalg.lstsq(design / scale, np.ones(theta.size), rcond=None)[0] / scale
            residual = np.max(np.abs(self._h(k, orders, coef, self._wall_radius(check), check) - 1))
            if residual > MPS_TOLERANCE:
                raise InputError(f"elliptic Womersley harmonic {n}: wall residual {residual:.1e}; a rounder lumen")
            phi = np.linspace(0, 2 * np.pi, 2049)[:-1]
            dn, ds = self._normal_derivative(k, orders, coef, phi)
            integral = -np.sum(dn * ds) * (phi[1] - phi[0]) / k**2  # int h dA from the wall integral
            terms.append((n, k, complex(v_n) / (1 - integral / (np.pi * a * b)), orders, coef))
        u_max = 2 * float(np.real(self.bulk_harmonics[0]))  # elliptic Poiseuille: bulk = u_max / 2
        self._table["sol"] = (u_max, terms)
        return self._table["sol"]

    @staticmethod
    def _h(k, orders, coef, r, theta):
        return np.sum(coef * scipy.special.jv(orders, k * r[..., None]) * np.cos(orders * theta[..., None]), axis=-1)

    def _normal_derivative(self, k, orders, coef, theta):
        """``(dh/dn, ds/dtheta)`` at the wall points of local polar angle ``theta`` (1/mm, mm)."""
        a, b, _ = self._ellipse()
        r = self._wall_radius(theta)
        x, y = r * np.cos(theta), r * np.sin(theta)
        jm = scipy.special.jv(orders, k * r[:, None])
        djm = 0.5 * (scipy.special.jv(orders - 1, k * r[:, None]) - scipy.special.jv(orders + 1, k * r[:, None]))
        d_r = np.sum(coef * k * djm * np.cos(orders * theta[:, None]), axis=1)
        d_t = np.sum(-coef * orders * jm * np.sin(orders * theta[:, None]), axis=1) / r
        gx, gy = x / a**2, y / b**2
        norm = np.hypot(gx, gy)
        n_r = (gx * np.cos(theta) + gy * np.sin(theta)) / norm
        n_t = (-gx * np.sin(theta) + gy * np.cos(theta)) / norm
        dr = self.lumen.radius(theta + self._ellipse()[2], 1)
        return d_r * n_r + d_t * n_t, np.hypot(r, dr)

    def _grid(self):
        """The harmonics tabulated on (sigma, theta) of the first quadrant (module notes)."""
        if "grid" not in self._table:
            _, terms = self._solution()
            sigma = np.linspace(0.0, 1.0, 1201)
            theta = np.radians(np.arange(0.0, 90.0 + 1e-9, 2.0))
            a, b, _ = self._ellipse()
            ss, tt = np.meshgrid(sigma, theta, indexing="ij")
            x, y = a * ss * np.cos(tt), b * ss * np.sin(tt)
            r, th = np.hypot(x, y), np.arctan2(y, x)
            shapes = [1.0 - self._h(k, orders, coef, r, th) for _, k, _, orders, coef in terms]
            self._table["grid"] = (sigma, theta, shapes)
        return self._table["grid"]

    def velocity(self, x, y):
        a, b, angle = self._ellipse()
        xl, yl = _local(self.lumen, x, y, angle)
        sigma = np.sqrt((xl / a) ** 2 + (yl / b) ** 2)
        theta = np.arctan2(np.abs(yl) / b, np.abs(xl) / a)  # the symmetric quadrant's elliptic angle
        u_max, terms = self._solution()
        u = u_max * (1 - sigma**2)
        grid_s, grid_t, shapes = self._grid()
        step = grid_t[1] - grid_t[0]
        j = np.clip((theta / step).astype(int), 0, grid_t.size - 2)
        w = theta / step - j
        s = np.clip(sigma, 0.0, 1.0)
        omega = 2 * np.pi / self.period_s
        for (n, _, amp, _, _), table in zip(terms, shapes):
            value = np.zeros(s.shape, dtype=complex)
            for jj in np.unique(j):
                sel = j == jj
                lo = np.interp(s[sel], grid_s, table[:, jj].real) + 1j * np.interp(s[sel], grid_s, table[:, jj].imag)
                hi = np.interp(s[sel], grid_s, table[:, jj + 1].real) + 1j * np.interp(
                    s[sel], grid_s, table[:, jj + 1].imag
                )
                value[sel] = (1 - w[sel]) * lo + w[sel] * hi
            u = u + np.real(amp * value * np.exp(1j * n * omega * self.t_s))
        return np.where(sigma < 1, u, 0.0)

    def wall_gradient(self, phi):
        a, b, angle = self._ellipse()
        theta = np.asarray(phi, dtype=float) - angle
        r = self._wall_radius(theta)
        u_max, terms = self._solution()
        out = 2 * u_max * np.hypot(r * np.cos(theta) / a**2, r * np.sin(theta) / b**2)
        omega = 2 * np.pi / self.period_s
        for n, k, amp, orders, coef in terms:
            dn, _ = self._normal_derivative(k, orders, coef, np.ravel(theta))
            out = out + np.real(amp * dn.reshape(theta.shape) * np.exp(1j * n * omega * self.t_s))
        return out

    def wall_shear(self, t_s) -> np.ndarray:
        """Exact mean WSS (arc-length mean over the wall) at times ``t_s``, Pa."""
        return np.array([self.at(float(t)).mean_wss() for t in np.atleast_1d(t_s)])

    def womersley(self, n: int = 1) -> float:
        """Womersley number of harmonic ``n`` with the equal-area radius ``sqrt(a b)``."""
        a, b, _ = self._ellipse()
        omega = 2 * np.pi / self.period_s
        return float(np.sqrt(a * b) / PER_MM * np.sqrt(n * omega * self.density_kg_m3 / self.viscosity_pa_s))

    def at(self, t_s: float) -> EllipticWomersley:
        other = EllipticWomersley(
            self.lumen, self.viscosity_pa_s, self.density_kg_m3, self.period_s, self.bulk_harmonics, float(t_s)
        )
        other._table = self._table  # the solution and its table are the cycle's
        return other


#: Method of particular solutions of :class:`EllipticWomersley`: even Bessel orders 0 .. 2 (terms - 1), wall
#: points in the first quadrant, and the largest wall residual accepted (1e-12 measured at aspect 1.3).
MPS_TERMS, MPS_POINTS, MPS_TOLERANCE = 24, 96, 1e-9


@dataclass
class CineTruth:
    """What a cine phantom knows exactly: one :class:`~wss_nlp.synthetic.phantoms.Truth` per frame and the cycle.

    ``stated_viscosity_pa_s`` is the viscosity the frames' files state (the true one unless the phantom was
    made with a viscosity error); the WSS a reconstruction should give is the true velocity gradient times
    the stated viscosity (:meth:`reference_tau`): the stress scales with the viscosity it is told.
    """

    frames: list
    times_ms: np.ndarray
    period_ms: float
    flow: Any  # WomersleyPipe, DistendingWomersley or QuasiSteadyFlow: each has wall_shear(t_s)
    stated_viscosity_pa_s: float | None = None
    notes: list = field(default_factory=list)

    def tau(self) -> np.ndarray:
        """Exact WSS of each frame (uniform around the pipe), Pa."""
        return self.flow.wall_shear(np.asarray(self.times_ms) / 1000.0)

    @property
    def viscosity_pa_s(self) -> float:
        """The flow's true dynamic viscosity."""
        return float(self.flow.viscosity_pa_s)

    @property
    def scale(self) -> float:
        """Stated over true viscosity."""
        stated = self.stated_viscosity_pa_s
        return 1.0 if stated is None else float(stated / self.viscosity_pa_s)

    def reference_tau(self) -> np.ndarray:
        """The WSS of each frame with the stated viscosity: :meth:`tau` times :attr:`scale` (Pa)."""
        return self.scale * self.tau()

    def cycle_integrals(self, samples: int = 4096) -> tuple[float, float, float]:
        """``(TAWSS, OSI, time average)`` of the reference WSS over the whole cycle (not only at the frames):
        the periodic trapezoid rule on ``samples`` instants (exact for the trigonometric waveform; the kinks of
        ``|tau|`` where the flow reverses cost about ``(T / samples)^2``)."""
        t = np.arange(samples) / samples * self.period_ms / 1000.0
        tau = self.scale * mean_wall_shear(self.flow, t)
        magnitude, net = float(np.mean(np.abs(tau))), float(np.mean(tau))
        return magnitude, (0.5 * (1 - abs(net) / magnitude) if magnitude > 0 else 0.0), net


def mean_wall_shear(flow, times_s: np.ndarray) -> np.ndarray:
    """The exact wall-mean WSS of a cine phantom's flow at ``times_s`` (Pa): ``flow.wall_shear``, or for the
    elliptic pipe, whose mean WSS is a trigonometric polynomial of the waveform's degree in time, from
    ``2K + 1`` instants (discrete Fourier transform) instead of one wall integral per instant."""
    if not isinstance(flow, EllipticWomersley):
        return flow.wall_shear(times_s)
    m = 2 * (len(flow.bulk_harmonics) - 1) + 1
    samples = flow.wall_shear(np.arange(m) * flow.period_s / m)
    coef = np.fft.fft(samples) / m
    n = np.fft.fftfreq(m, 1.0 / m)
    return np.real(np.exp(2j * np.pi * np.outer(np.asarray(times_s, dtype=float) / flow.period_s, n)) @ coef)


def make_cine(
    h_mm: float = 1.0,
    snr: float | None = 25.0,
    seed: int = 0,
    frames: int = 20,
    radius_mm: float | None = None,
    period_ms: float | None = None,
    bulk_harmonics: tuple | None = None,
    venc: float | None = None,
    psf: PSF | None = None,
    distension: float = 0.0,
    shape: str = "circle",
    waveform: str | None = None,
    viscosity_error: float = 0.0,
    jitter: float = 0.0,
    missing: int | None = None,
) -> tuple[list[Acquisition], CineTruth]:
    """Seeded cine phantom: Womersley flow in a rigid pipe, ``frames`` frames over one cycle.

    ``distension`` > 0 makes the pipe breathe, ``R(t) = R_0 (1 + distension sin(omega t))``
    (:class:`DistendingWomersley`). ``shape="ellipse"`` takes an elliptic pipe of the same area, semi-axes
    ``1.15 R`` and ``R / 1.15`` (aspect 1.32) at 0.3 rad, with its exact pulsatile flow
    (:class:`EllipticWomersley`; rigid).

    ``waveform``: a published-shape waveform of :data:`WAVEFORMS` (its harmonics, and its vessel's radius
    and period unless ``radius_mm`` / ``period_ms`` are given); else ``bulk_harmonics`` (default
    :data:`CAROTID_HARMONICS`), a 10 mm pipe and a 1 s cycle. ``viscosity_error``: the files state the
    viscosity ``(1 + viscosity_error)`` times the true one (the truth's :meth:`CineTruth.reference_tau`
    scales with it). ``jitter``: trigger times ``(k + jitter U(-1/2, 1/2)) T / frames`` (seeded, increasing
    for ``jitter < 1``) instead of equal spacing; ``missing``: the frame of this index is left out of the
    series (the truth notes it).

    Returns the frames (one :class:`~wss_nlp.io.files.Acquisition` each, phase data, one venc for the whole
    series: 1.25 x the peak over the cycle unless given) and the truth. The sub-voxel offset is drawn once
    (the vessel does not move); the noise is fresh in every frame. Womersley number of the first harmonic
    about 14 for the defaults (blood, 10 mm radius, 1 s cycle). ``psf`` acquires every frame in k-space
    (:func:`wss_nlp.synthetic.phantoms.acquire`).
    """
    _check_cine(frames, h_mm)
    if waveform is not None:
        if waveform not in WAVEFORMS:
            raise InputError(f"unknown waveform {waveform!r}; choose from {', '.join(WAVEFORMS)}")
        shape_of = WAVEFORMS[waveform]
        bulk_harmonics = shape_of.harmonics() if bulk_harmonics is None else bulk_harmonics
        radius_mm = shape_of.radius_mm if radius_mm is None else radius_mm
        period_ms = shape_of.period_ms if period_ms is None else period_ms
    bulk_harmonics = CAROTID_HARMONICS if bulk_harmonics is None else bulk_harmonics
    radius_mm = 10.0 if radius_mm is None else float(radius_mm)
    period_ms = 1000.0 if period_ms is None else float(period_ms)
    if not -0.9 < viscosity_error < 10:
        raise InputError(f"viscosity_error must lie in (-0.9, 10), got {viscosity_error}")
    if not 0 <= jitter < 1:
        raise InputError(f"jitter must lie in [0, 1), got {jitter}")
    if missing is not None and not 0 <= missing < frames:
        raise InputError(f"missing frame {missing} is not one of the {frames} frames")
    rng = np.random.default_rng(seed)
    times = _trigger_times(frames, period_ms, jitter, rng)
    kept = [k for k in range(frames) if k != missing]
    name_extra = f", {waveform} waveform" if waveform else ""
    if shape == "ellipse":
        if distension:
            raise InputError("the elliptic cine phantom is rigid: distension must be 0")
        lumen = Ellipse(a=1.15 * radius_mm, b=radius_mm / 1.15, angle=0.3)
        ell = EllipticWomersley(lumen, 3.5e-3, period_s=period_ms / 1000.0, bulk_harmonics=bulk_harmonics)
        half = 1.5 * lumen.a
        out = _acquire_cycle(ell, half, h_mm, snr, rng, times[kept], period_ms, venc, psf,
                             "elliptic womersley" + name_extra)  # fmt: skip
        return _stated(out, viscosity_error, missing, times)
    if shape != "circle":
        raise InputError(f"cine phantom shape must be circle or ellipse, got {shape!r}")
    flow = WomersleyPipe(
        lumen=Circle(r=radius_mm), viscosity_pa_s=3.5e-3, period_s=period_ms / 1000.0, bulk_harmonics=bulk_harmonics
    )
    r = np.linspace(0, radius_mm, 2001)
    grid_t = np.arange(max(frames, 64)) * period_ms / max(frames, 64)
    peak = max(float(np.max(np.abs(flow.profile(r, t / 1000.0)))) for t in grid_t)  # the stretch keeps the peak
    if not 0 <= distension < 0.3:
        raise InputError(f"distension must lie in [0, 0.3), got {distension}")
    cycle: Flow = flow
    if distension > 0:
        cycle = DistendingWomersley(Circle(r=radius_mm), flow.viscosity_pa_s, flow, distension)
    # a background ring of at least three voxels for the noise estimates (small vessels at coarse voxels)
    half_fov = max(1.5 * radius_mm * (1 + distension), radius_mm * (1 + distension) + 3 * h_mm)
    name = ("womersley" if distension == 0 else f"distending womersley ({100 * distension:g} %)") + name_extra
    out = _acquire_cycle(cycle, half_fov, h_mm, snr, rng, times[kept], period_ms, venc, psf, name, peak)
    return _stated(out, viscosity_error, missing, times)


def _trigger_times(frames: int, period_ms: float, jitter: float, rng) -> np.ndarray:
    """Equally spaced trigger times, or jittered by up to ``jitter / 2`` spacings either way (ms)."""
    step = period_ms / frames
    offsets = rng.uniform(-0.5, 0.5, frames) * jitter if jitter else np.zeros(frames)
    offsets[0] = 0.0  # the first frame at the trigger
    return (np.arange(frames) + offsets) * step


def _stated(out, viscosity_error: float, missing, times):
    """The frames with the stated viscosity ``(1 + viscosity_error)`` times the true one, and the truth's record."""
    from dataclasses import replace

    frames, truth = out
    truth.stated_viscosity_pa_s = truth.viscosity_pa_s * (1 + viscosity_error)
    if viscosity_error:
        frames = [replace(f, viscosity_pa_s=truth.stated_viscosity_pa_s) for f in frames]
    if missing is not None:
        truth.notes.append(f"the frame at {times[missing]:g} ms is missing from the series")
    return frames, truth


def _check_cine(frames: int, h_mm: float) -> None:
    if frames < 2:
        raise InputError(f"a cine phantom needs >= 2 frames, got {frames}")
    if not h_mm > 0:
        raise InputError(f"voxel size must be > 0 mm, got {h_mm}")


def _acquire_cycle(flow, half_fov: float, h_mm, snr, rng, times, period_ms: float, venc, psf, name, peak=None):
    """Frames of ``flow`` (a flow with ``at(t_s)``) at trigger times ``times`` (ms), and the truth.

    The sub-voxel offset is drawn once (the vessel does not move); the noise is fresh in every frame; one venc
    for the series, 1.25 x the ``peak`` speed over the cycle (default: sampled at the frames) unless given.
    """
    n = int(np.ceil(2 * half_fov / h_mm))
    shift = rng.uniform(-0.5, 0.5, size=2) * h_mm
    origin = (-(n - 1) / 2 * h_mm, -(n - 1) / 2 * h_mm)
    flow.lumen.center = (float(shift[0]), float(shift[1]))
    grid = VoxelGrid((n, n), (h_mm, h_mm), origin)
    times = np.asarray(times, dtype=float)
    if peak is None:
        peak = max(peak_velocity(flow.at(t / 1000.0)) for t in times)
    venc = 1.25 * peak if venc is None else venc
    out, truths = [], []
    for t in times:
        frame_flow = flow.at(t / 1000.0)
        mag, phase, u_mean, _ = acquire(frame_flow, grid, snr, rng, venc=venc, psf=psf)
        out.append(
            Acquisition(
                magnitude=mag[None],
                phase=phase[None],
                voxel_size_mm=(h_mm, h_mm),
                origin_mm=origin,
                venc_m_s=venc,
                viscosity_pa_s=flow.viscosity_pa_s,
                density_kg_m3=flow.density_kg_m3,
                source=f"phantom:{name} t = {t:g} ms",
                acquired_voxel_size_mm=None if psf is None else (h_mm * psf.zero_fill[0], h_mm * psf.zero_fill[1]),
            )
        )
        truths.append(Truth(name=name, flow=frame_flow, velocity_image=u_mean, parameters={"t_ms": t}))
    return out, CineTruth(truths, times, float(period_ms), flow)


@dataclass
class QuasiSteadyFlow(Flow):
    """A steady phantom flow scaled over the cycle by the bulk waveform: ``u(x, t) = f(t) u_s(x)``.

    ``f(t) = V(t) / V_0`` with the bulk-velocity harmonics of :data:`CAROTID_HARMONICS` (flow reversal
    included). Exact WSS ``f(t) tau_s``; it is not a solution of the momentum balance at the cycle's
    Womersley number (the profile keeps its steady shape), so the momentum model
    (:mod:`wss_nlp.models.womersley`) should turn it down: a phantom for the model choice.
    """

    base: Flow | None = None
    density_kg_m3: float = 1060.0
    period_s: float = 1.0
    bulk_harmonics: tuple = CAROTID_HARMONICS
    t_s: float = 0.0

    def factor(self, t_s) -> np.ndarray:
        """``f(t) = V(t) / V_0``."""
        t = np.asarray(t_s, dtype=float)
        omega = 2 * np.pi / self.period_s
        v = np.full_like(t, float(np.real(self.bulk_harmonics[0])))
        for n, v_n in enumerate(self.bulk_harmonics[1:], start=1):
            v = v + np.real(complex(v_n) * np.exp(1j * n * omega * t))
        return v / float(np.real(self.bulk_harmonics[0]))

    def velocity(self, x, y):
        assert self.base is not None
        return float(self.factor(self.t_s)) * self.base.velocity(x, y)

    def wall_gradient(self, phi):
        assert self.base is not None
        return float(self.factor(self.t_s)) * self.base.wall_gradient(phi)

    def wall_shear(self, t_s) -> np.ndarray:
        """Exact mean WSS (arc-length mean over the wall) at times ``t_s``, Pa."""
        assert self.base is not None
        return self.factor(t_s) * self.base.mean_wss()

    def at(self, t_s: float) -> QuasiSteadyFlow:
        return QuasiSteadyFlow(
            self.lumen, self.viscosity_pa_s, self.base, self.density_kg_m3, self.period_s, self.bulk_harmonics, t_s
        )


def make_quasi_steady_cine(
    case: str = "laminar",
    h_mm: float = 1.0,
    snr: float | None = 25.0,
    seed: int = 0,
    frames: int = 20,
    period_ms: float = 1000.0,
    venc: float | None = None,
) -> tuple[list[Acquisition], CineTruth]:
    """Seeded cine phantom of a steady case of :data:`wss_nlp.synthetic.phantoms.CASES` scaled by the bulk waveform.

    See :class:`QuasiSteadyFlow`; the frames as :func:`make_cine` makes them.
    """
    from .phantoms import CASES

    if case not in CASES:
        raise InputError(f"unknown phantom case {case!r}; choose from {', '.join(CASES)}")
    _check_cine(frames, h_mm)
    rng = np.random.default_rng(seed)
    base, half_fov = CASES[case][0](h_mm, rng)
    flow = QuasiSteadyFlow(base.lumen, base.viscosity_pa_s, base, period_s=period_ms / 1000.0)
    times = np.arange(frames) * period_ms / frames
    return _acquire_cycle(flow, half_fov, h_mm, snr, rng, times, period_ms, venc, None, f"quasi-steady {case}")


#: Instants over the cycle of the truth file's TAWSS and OSI (:func:`write_truth`): the whole cycle, not only
#: the frames (the periodic trapezoid rule; |tau|'s kinks where the flow reverses cost about (T / 512)^2).
TRUTH_SAMPLES = 512


def wss_over_cycle(flow, phi: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Exact WSS ``(len(times_s), len(phi))`` of a cine phantom's flow (Pa, true viscosity).

    Uniform WSS (circular pipes) from ``wall_shear``; a quasi-steady flow is its steady WSS times the
    waveform; the elliptic pipe's WSS is a trigonometric polynomial of the waveform's degree in time at every
    wall point, so ``2K + 1`` instants give it everywhere (discrete Fourier transform).
    """
    times_s = np.asarray(times_s, dtype=float)
    if isinstance(flow, (WomersleyPipe, DistendingWomersley)):
        return np.outer(flow.wall_shear(times_s), np.ones(phi.size))
    if isinstance(flow, QuasiSteadyFlow):
        assert flow.base is not None
        return np.outer(flow.factor(times_s), flow.base.wss(phi))
    if isinstance(flow, EllipticWomersley):
        k = len(flow.bulk_harmonics) - 1
        m = 2 * k + 1
        samples = np.array([flow.at(j * flow.period_s / m).wss(phi) for j in range(m)])
        coef = np.fft.fft(samples, axis=0) / m
        n = np.fft.fftfreq(m, 1.0 / m)
        phase = np.exp(2j * np.pi * np.outer(times_s / flow.period_s, n))
        return np.real(phase @ coef)
    raise InputError(f"no exact WSS over the cycle for {type(flow).__name__}")


def write_truth(path: str, truth: CineTruth, n_phi: int = 1440) -> None:
    """The exact cycle in the time-resolved result layout (atomic): radius, WSS(t, phi), TAWSS, OSI.

    Radius and WSS per frame from each frame's flow about the lumen centre (with the true viscosity, stored in
    ``wss`` attribute ``viscosity_pa_s``; the root holds ``viscosity_pa_s``, ``stated_viscosity_pa_s`` and
    ``density_kg_m3``); ``geometry/coefficients`` holds each frame's mean radius only (exact for the circular
    pipes of :func:`make_cine`). TAWSS, OSI and ``wss/mean_pa`` integrate the exact WSS over the whole cycle
    (:data:`TRUTH_SAMPLES` instants, :func:`wss_over_cycle`), not only the frames.
    """
    from ..core.periodic import tawss_osi
    from ..io.files import atomic_h5, provenance

    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    nt = len(truth.frames)
    tau = np.array([frame.flow.wss(phi) for frame in truth.frames])
    grid = np.arange(TRUTH_SAMPLES) * truth.period_ms / 1000.0 / TRUTH_SAMPLES
    over_cycle = wss_over_cycle(truth.flow, phi, grid)
    tawss, osi = tawss_osi(over_cycle, np.full(TRUTH_SAMPLES, truth.period_ms / TRUTH_SAMPLES))
    radius = np.array([frame.flow.lumen.radius(phi) for frame in truth.frames])
    with atomic_h5(path) as f:
        for k, v in provenance({"truth": truth.frames[0].name, "times_ms": truth.times_ms.tolist()}).items():
            f.attrs[k] = v
        f.attrs["trigger_times_ms"] = truth.times_ms
        f.attrs["cardiac_period_ms"] = truth.period_ms
        f.attrs["viscosity_pa_s"] = truth.viscosity_pa_s
        f.attrs["stated_viscosity_pa_s"] = truth.viscosity_pa_s * truth.scale
        f.attrs["density_kg_m3"] = float(getattr(truth.flow, "density_kg_m3", 1060.0))
        f.attrs["notes"] = "; ".join(truth.notes)
        if hasattr(truth.flow, "womersley"):
            f.attrs["womersley_number"] = truth.flow.womersley(1)
        g = f.create_group("slice_000")
        g["geometry/center_mm"] = np.tile(np.asarray(truth.flow.lumen.center, dtype=float), (nt, 1))
        g["geometry/coefficients"] = np.hstack([radius.mean(axis=1, keepdims=True), np.zeros((nt, 16))])
        g["geometry/phi"] = phi
        g["geometry/radius_mm"] = radius
        g["wss/phi"] = phi
        g["wss/tau_pa"] = tau
        g["wss/time_ms"] = truth.times_ms
        g["wss/mean_pa_t"] = truth.tau()
        g["wss/tawss_pa"] = tawss
        g["wss/osi"] = osi
        g["wss"].attrs["mean_pa"] = float(np.mean(over_cycle))
        g["wss"].attrs["viscosity_pa_s"] = truth.viscosity_pa_s
