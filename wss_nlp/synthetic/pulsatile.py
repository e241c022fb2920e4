r"""Pulsatile flow phantoms: Womersley's exact solution in a rigid circular pipe, acquired frame by frame.

Notes
-----
Fully developed pulsatile flow obeys :math:`\rho\,\partial_t u = G(t) + \mu\,\Delta u` with the pressure
gradient :math:`G(t) = G_0 + \sum_n \mathrm{Re}[G_n e^{i n \omega t}]`. With no slip at :math:`r = R`
(Womersley 1955, J. Physiol. 127, 553-563):

.. math::

    u(r, t) = \frac{G_0}{4\mu}(R^2 - r^2) + \sum_n \mathrm{Re}\Big[\frac{G_n}{i\rho n\omega}
    \Big(1 - \frac{J_0(\Lambda_n r/R)}{J_0(\Lambda_n)}\Big) e^{i n\omega t}\Big],
    \qquad \Lambda_n = i^{3/2}\alpha_n,\ \alpha_n = R\sqrt{n\omega\rho/\mu},

and the wall shear stress :math:`\tau = -\mu\,\partial_r u(R, t)`

.. math::

    \tau(t) = \frac{G_0 R}{2} + \sum_n \mathrm{Re}\Big[-\mu \frac{G_n}{i\rho n\omega}
    \frac{\Lambda_n}{R}\frac{J_1(\Lambda_n)}{J_0(\Lambda_n)} e^{i n\omega t}\Big].

The harmonics are given as bulk-velocity harmonics :math:`V_n` (m/s); the flow rate of harmonic n is
:math:`\pi R^2 G_n/(i\rho n\omega)\,(1 - 2J_1(\Lambda_n)/(\Lambda_n J_0(\Lambda_n)))`, which fixes
:math:`G_n`. Lengths in mm in the interface (as every phantom), SI inside.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._lazy import scipy
from ..models import womersley
from ..errors import InputError
from ..io.files import Acquisition
from ..models.kspace import PSF
from ..models.measurement import VoxelGrid
from .phantoms import PER_MM, Circle, Ellipse, Flow, Truth, _local, acquire, peak_velocity

#: A carotid-like bulk-velocity waveform: mean and harmonics 1-4 (m/s, complex: amplitude and phase).
CAROTID_HARMONICS = (0.18, 0.16 * np.exp(-1.0j), 0.10 * np.exp(-2.1j), 0.05 * np.exp(-3.0j), 0.03 * np.exp(-4.2j))


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
        """``(G_0, [(n, Lambda_n, A_n)])`` with ``A_n = G_n / (i rho n omega)`` (m/s), from the bulk harmonics."""
        if "coef" not in self._table:
            g0 = 8 * self.viscosity_pa_s * float(np.real(self.bulk_harmonics[0])) / self.radius_m**2  # V = G R^2/8mu
            terms = []
            for n, v_n in enumerate(self.bulk_harmonics[1:], start=1):
                lam = 1j**1.5 * self.womersley(n)  # = womersley.womersley_parameter(n, R, omega, nu)
                shape = 1 - 2 * scipy.special.jv(1, lam) / (lam * scipy.special.jv(0, lam))
                terms.append((n, lam, complex(v_n) / shape))  # the bulk velocity of harmonic n: V_n = A_n * shape
            self._table["coef"] = (g0, terms)
        return self._table["coef"]

    def profile(self, r_mm, t_s: float | None = None) -> np.ndarray:
        """``u(r, t)`` in m/s at radii ``r_mm`` (0 outside the pipe)."""
        t = self.t_s if t_s is None else t_s
        g0, terms = self._coefficients()
        rr = np.asarray(r_mm, dtype=float) / PER_MM
        x = np.clip(rr / self.radius_m, 0.0, 1.0)
        u = g0 / (4 * self.viscosity_pa_s) * (self.radius_m**2 - rr**2)
        omega = 2 * np.pi / self.period_s
        for n, lam, amp in terms:
            u = u + np.real(amp * womersley.shape(x, lam) * np.exp(1j * n * omega * t))
        return np.where(rr < self.radius_m, u, 0.0)

    def wall_shear(self, t_s) -> np.ndarray:
        """Exact ``tau(t)`` in Pa (positive for forward flow)."""
        g0, terms = self._coefficients()
        t = np.asarray(t_s, dtype=float)
        tau = np.full_like(t, g0 * self.radius_m / 2)
        omega = 2 * np.pi / self.period_s
        for n, lam, amp in terms:
            slope = womersley.wall_slope(lam) / self.radius_m  # dS/dr at the wall
            tau = tau + np.real(-self.viscosity_pa_s * amp * slope * np.exp(1j * n * omega * t))
        return tau

    def velocity(self, x, y):
        r = np.hypot(np.asarray(x) - self.lumen.center[0], np.asarray(y) - self.lumen.center[1])
        key = ("grid", self.t_s)
        if key not in self._table:  # the Bessel sums once per frame, on a radius grid far finer than any layer
            grid = np.linspace(0.0, float(self.lumen.r), 20001)
            self._table[key] = (grid, self.profile(grid))
        grid, values = self._table[key]
        return np.where(r < self.lumen.r, np.interp(r, grid, values), 0.0)

    def wall_gradient(self, phi):
        return np.full_like(
            np.asarray(phi, dtype=float), float(self.wall_shear(self.t_s)) / self.viscosity_pa_s / PER_MM
        )

    def at(self, t_s: float) -> WomersleyPipe:
        """The same flow at another instant (shares the coefficient table)."""
        other = WomersleyPipe(
            lumen=self.lumen,
            viscosity_pa_s=self.viscosity_pa_s,
            density_kg_m3=self.density_kg_m3,
            period_s=self.period_s,
            bulk_harmonics=self.bulk_harmonics,
            t_s=float(t_s),
        )
        other._table["coef"] = self._coefficients()
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
    """What a cine phantom knows exactly: one :class:`~wss_nlp.synthetic.phantoms.Truth` per frame and the cycle."""

    frames: list
    times_ms: np.ndarray
    period_ms: float
    flow: Any  # WomersleyPipe, DistendingWomersley or QuasiSteadyFlow: each has wall_shear(t_s)

    def tau(self) -> np.ndarray:
        """Exact WSS of each frame (uniform around the pipe), Pa."""
        return self.flow.wall_shear(np.asarray(self.times_ms) / 1000.0)


def make_cine(
    h_mm: float = 1.0,
    snr: float | None = 25.0,
    seed: int = 0,
    frames: int = 20,
    radius_mm: float = 10.0,
    period_ms: float = 1000.0,
    bulk_harmonics: tuple = CAROTID_HARMONICS,
    venc: float | None = None,
    psf: PSF | None = None,
    distension: float = 0.0,
    shape: str = "circle",
) -> tuple[list[Acquisition], CineTruth]:
    """Seeded cine phantom: Womersley flow in a rigid pipe, ``frames`` frames evenly over one cycle.

    ``distension`` > 0 makes the pipe breathe, ``R(t) = R_0 (1 + distension sin(omega t))``
    (:class:`DistendingWomersley`). ``shape="ellipse"`` takes an elliptic pipe of the same area, semi-axes
    ``1.15 R`` and ``R / 1.15`` (aspect 1.32) at 0.3 rad, with its exact pulsatile flow
    (:class:`EllipticWomersley`; rigid).

    Returns the frames (one :class:`~wss_nlp.io.files.Acquisition` each, phase data, one venc for the whole
    series: 1.25 x the peak over the cycle unless given) and the truth. The sub-voxel offset is drawn once
    (the vessel does not move); the noise is fresh in every frame. Womersley number of the first harmonic
    about 15 for the defaults (blood, 10 mm radius, 1 s cycle). ``psf`` acquires every frame in k-space
    (:func:`wss_nlp.synthetic.phantoms.acquire`).
    """
    _check_cine(frames, h_mm)
    rng = np.random.default_rng(seed)
    if shape == "ellipse":
        if distension:
            raise InputError("the elliptic cine phantom is rigid: distension must be 0")
        lumen = Ellipse(a=1.15 * radius_mm, b=radius_mm / 1.15, angle=0.3)
        ell = EllipticWomersley(lumen, 3.5e-3, period_s=period_ms / 1000.0, bulk_harmonics=bulk_harmonics)
        half = 1.5 * lumen.a
        return _acquire_cycle(ell, half, h_mm, snr, rng, frames, period_ms, venc, psf, "elliptic womersley")
    if shape != "circle":
        raise InputError(f"cine phantom shape must be circle or ellipse, got {shape!r}")
    flow = WomersleyPipe(
        lumen=Circle(r=radius_mm), viscosity_pa_s=3.5e-3, period_s=period_ms / 1000.0, bulk_harmonics=bulk_harmonics
    )
    times = np.arange(frames) * period_ms / frames
    r = np.linspace(0, radius_mm, 2001)
    peak = max(float(np.max(np.abs(flow.profile(r, t / 1000.0)))) for t in times)  # the stretch keeps the peak
    if not 0 <= distension < 0.3:
        raise InputError(f"distension must lie in [0, 0.3), got {distension}")
    cycle: Flow = flow
    if distension > 0:
        cycle = DistendingWomersley(Circle(r=radius_mm), flow.viscosity_pa_s, flow, distension)
    # a background ring of at least three voxels for the noise estimates (small vessels at coarse voxels)
    half_fov = max(1.5 * radius_mm * (1 + distension), radius_mm * (1 + distension) + 3 * h_mm)
    name = "womersley" if distension == 0 else f"distending womersley ({100 * distension:g} %)"
    return _acquire_cycle(cycle, half_fov, h_mm, snr, rng, frames, period_ms, venc, psf, name, peak)


def _check_cine(frames: int, h_mm: float) -> None:
    if frames < 2:
        raise InputError(f"a cine phantom needs >= 2 frames, got {frames}")
    if not h_mm > 0:
        raise InputError(f"voxel size must be > 0 mm, got {h_mm}")


def _acquire_cycle(flow, half_fov: float, h_mm, snr, rng, frames: int, period_ms: float, venc, psf, name, peak=None):
    """Frames of ``flow`` (a flow with ``at(t_s)``) over one cycle, and the truth.

    The sub-voxel offset is drawn once (the vessel does not move); the noise is fresh in every frame; one venc
    for the series, 1.25 x the ``peak`` speed over the cycle (default: sampled) unless given.
    """
    n = int(np.ceil(2 * half_fov / h_mm))
    shift = rng.uniform(-0.5, 0.5, size=2) * h_mm
    origin = (-(n - 1) / 2 * h_mm, -(n - 1) / 2 * h_mm)
    flow.lumen.center = (float(shift[0]), float(shift[1]))
    grid = VoxelGrid((n, n), (h_mm, h_mm), origin)
    times = np.arange(frames) * period_ms / frames
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
    return _acquire_cycle(flow, half_fov, h_mm, snr, rng, frames, period_ms, venc, None, f"quasi-steady {case}")


def write_truth(path: str, truth: CineTruth, n_phi: int = 1440) -> None:
    """The exact cycle in the time-resolved result layout (atomic): radius, WSS(t, phi), TAWSS, OSI.

    Radius and WSS per frame from each frame's flow about the lumen centre; ``geometry/coefficients`` holds
    each frame's mean radius only (exact for the circular pipes of :func:`make_cine`).
    """
    from ..core.periodic import cycle_weights, tawss_osi
    from ..io.files import atomic_h5, provenance

    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    nt = len(truth.frames)
    tau = np.array([frame.flow.wss(phi) for frame in truth.frames])
    weights = cycle_weights(truth.times_ms, truth.period_ms)
    tawss, osi = tawss_osi(tau, weights)
    radius = np.array([frame.flow.lumen.radius(phi) for frame in truth.frames])
    with atomic_h5(path) as f:
        for k, v in provenance({"truth": truth.frames[0].name, "times_ms": truth.times_ms.tolist()}).items():
            f.attrs[k] = v
        f.attrs["trigger_times_ms"] = truth.times_ms
        f.attrs["cardiac_period_ms"] = truth.period_ms
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
        g["wss"].attrs["mean_pa"] = float(np.sum(weights * truth.tau()) / np.sum(weights))
