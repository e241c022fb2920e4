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

import numpy as np
import scipy.special

from .errors import InputError
from .files import Acquisition
from .kspace import PSF
from .measurement import VoxelGrid
from .phantoms import PER_MM, Circle, Flow, Truth, acquire

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
                lam = 1j**1.5 * self.womersley(n)
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
            shape = 1 - scipy.special.jv(0, lam * x) / scipy.special.jv(0, lam)
            u = u + np.real(amp * shape * np.exp(1j * n * omega * t))
        return np.where(rr < self.radius_m, u, 0.0)

    def wall_shear(self, t_s) -> np.ndarray:
        """Exact ``tau(t)`` in Pa (positive for forward flow)."""
        g0, terms = self._coefficients()
        t = np.asarray(t_s, dtype=float)
        tau = np.full_like(t, g0 * self.radius_m / 2)
        omega = 2 * np.pi / self.period_s
        for n, lam, amp in terms:
            ratio = scipy.special.jv(1, lam) / scipy.special.jv(0, lam)
            tau = tau + np.real(-self.viscosity_pa_s * amp * lam / self.radius_m * ratio * np.exp(1j * n * omega * t))
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
class CineTruth:
    """What a cine phantom knows exactly: one :class:`~wss_nlp.phantoms.Truth` per frame and the cycle."""

    frames: list
    times_ms: np.ndarray
    period_ms: float
    flow: WomersleyPipe

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
) -> tuple[list[Acquisition], CineTruth]:
    """Seeded cine phantom: Womersley flow in a rigid pipe, ``frames`` frames evenly over one cycle.

    Returns the frames (one :class:`~wss_nlp.files.Acquisition` each, phase data, one venc for the whole
    series: 1.25 x the peak over the cycle unless given) and the truth. The sub-voxel offset is drawn once
    (the vessel does not move); the noise is fresh in every frame. Womersley number of the first harmonic
    about 15 for the defaults (blood, 10 mm radius, 1 s cycle). ``psf`` acquires every frame in k-space
    (:func:`wss_nlp.phantoms.acquire`).
    """
    if frames < 2:
        raise InputError(f"a cine phantom needs >= 2 frames, got {frames}")
    if not h_mm > 0:
        raise InputError(f"voxel size must be > 0 mm, got {h_mm}")
    rng = np.random.default_rng(seed)
    flow = WomersleyPipe(
        lumen=Circle(r=radius_mm), viscosity_pa_s=3.5e-3, period_s=period_ms / 1000.0, bulk_harmonics=bulk_harmonics
    )
    half_fov = 1.5 * radius_mm
    n = int(np.ceil(2 * half_fov / h_mm))
    shift = rng.uniform(-0.5, 0.5, size=2) * h_mm
    origin = (-(n - 1) / 2 * h_mm, -(n - 1) / 2 * h_mm)
    flow.lumen.center = (float(shift[0]), float(shift[1]))
    grid = VoxelGrid((n, n), (h_mm, h_mm), origin)
    times = np.arange(frames) * period_ms / frames
    r = np.linspace(0, radius_mm, 2001)
    peak = max(float(np.max(np.abs(flow.profile(r, t / 1000.0)))) for t in times)
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
                source=f"phantom:womersley t = {t:g} ms",
                acquired_voxel_size_mm=None if psf is None else (h_mm * psf.zero_fill[0], h_mm * psf.zero_fill[1]),
            )
        )
        truths.append(Truth(name="womersley", flow=frame_flow, velocity_image=u_mean, parameters={"t_ms": t}))
    return out, CineTruth(truths, times, float(period_ms), flow)


def write_truth(path: str, truth: CineTruth, n_phi: int = 1440) -> None:
    """The exact cycle in the time-resolved result layout (atomic): radius, WSS(t, phi), TAWSS, OSI."""
    from .cine import cycle_weights, tawss_osi
    from .files import atomic_h5, provenance

    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    nt = len(truth.frames)
    tau = np.repeat(truth.tau()[:, None], n_phi, axis=1)
    weights = cycle_weights(truth.times_ms, truth.period_ms)
    tawss, osi = tawss_osi(tau, weights)
    radius = truth.flow.radius_m * PER_MM
    with atomic_h5(path) as f:
        for k, v in provenance({"truth": "womersley", "times_ms": truth.times_ms.tolist()}).items():
            f.attrs[k] = v
        f.attrs["trigger_times_ms"] = truth.times_ms
        f.attrs["cardiac_period_ms"] = truth.period_ms
        f.attrs["womersley_number"] = truth.flow.womersley(1)
        g = f.create_group("slice_000")
        g["geometry/center_mm"] = np.tile(np.asarray(truth.flow.lumen.center, dtype=float), (nt, 1))
        g["geometry/coefficients"] = np.tile(np.r_[radius, np.zeros(16)], (nt, 1))
        g["geometry/phi"] = phi
        g["geometry/radius_mm"] = np.full((nt, n_phi), radius)
        g["wss/phi"] = phi
        g["wss/tau_pa"] = tau
        g["wss/time_ms"] = truth.times_ms
        g["wss/mean_pa_t"] = truth.tau()
        g["wss/tawss_pa"] = tawss
        g["wss/osi"] = osi
        g["wss"].attrs["mean_pa"] = float(np.sum(weights * truth.tau()) / np.sum(weights))
