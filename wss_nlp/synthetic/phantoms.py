"""Synthetic phantoms with exact geometry, velocity and wall shear stress.

Lumens (star-shaped about their centre): :class:`Circle`, :class:`Ellipse`,
:class:`FourierLumen`, :class:`LevelSetStar`. Flows with exact WSS:
:class:`PoiseuilleEllipse`, :class:`StarPoiseuille`, :class:`Manufactured`
(a polynomial field vanishing on a star-shaped wall) and
:class:`TurbulentPipe` (the DNS mean profile at Re_tau = 180.9, J. Yao et
al., doi:10.18738/T8/HLC3QY, scaled to the paper's 25.885 mm pipe).

:func:`acquire` simulates a phase-contrast acquisition: the complex signal
``rho exp(i pi u / venc)`` averaged over each voxel (partial volume and
intra-voxel dephasing), complex Gaussian noise at a given SNR, a random
sub-voxel offset of the vessel against the grid; magnitude and phase out.

:func:`make_phantom` is the seeded factory shared by tests, the demo,
scripts and benchmarks; it returns ``(Acquisition, Truth)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache
from importlib import resources

import numpy as np

from ..models import kspace
from ..core import radius as rad
from ..errors import InputError
from ..io.files import Acquisition
from ..models.measurement import VoxelGrid

#: mm -> m: velocity gradients in (m/s)/mm times this are in 1/s.
PER_MM = 1000.0


# --------------------------------------------------------------------- lumens
@dataclass
class Lumen:
    """A star-shaped lumen about ``center`` (mm)."""

    center: tuple[float, float] = (0.0, 0.0)

    def radius(self, phi, derivative: int = 0) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def inside(self, x, y) -> np.ndarray:
        dx, dy = np.asarray(x) - self.center[0], np.asarray(y) - self.center[1]
        return np.hypot(dx, dy) < self.radius(np.arctan2(dy, dx)).reshape(np.shape(dx))

    def radius_about(self, center, phi) -> np.ndarray:
        """Distance from ``center`` to the wall along the rays of angle ``phi``.

        Used to compare a reconstruction made about another centre. Requires
        the lumen to be star-shaped about ``center`` as well (bisection on
        the first exit along each ray).
        """
        phi = np.asarray(phi, dtype=float)
        e = np.stack([np.cos(phi), np.sin(phi)])
        lo = np.zeros_like(phi)
        hi = np.full_like(phi, 4 * float(np.max(self.radius(rad.uniform_angles(256)))))
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            ins = self.inside(center[0] + mid * e[0], center[1] + mid * e[1])
            lo, hi = np.where(ins, mid, lo), np.where(ins, hi, mid)
        return 0.5 * (lo + hi)

    def max_radius(self) -> float:
        return float(np.max(self.radius(rad.uniform_angles(720))))


@dataclass
class Circle(Lumen):
    r: float = 10.0

    def radius(self, phi, derivative=0):
        phi = np.asarray(phi, dtype=float)
        return np.full_like(phi, self.r) if derivative == 0 else np.zeros_like(phi)


@dataclass
class Ellipse(Lumen):
    """Semi-axes ``a`` (along angle ``angle``) and ``b``."""

    a: float = 12.0
    b: float = 9.0
    angle: float = 0.0

    def radius(self, phi, derivative=0):
        t = np.asarray(phi, dtype=float) - self.angle
        q = (np.cos(t) / self.a) ** 2 + (np.sin(t) / self.b) ** 2
        r = q**-0.5
        if derivative == 0:
            return r
        dq = 2 * np.sin(t) * np.cos(t) * (1 / self.b**2 - 1 / self.a**2)
        if derivative == 1:
            return -0.5 * q**-1.5 * dq
        raise ValueError("Ellipse.radius supports derivative 0 and 1")


@dataclass
class FourierLumen(Lumen):
    """``R(phi)`` given by Fourier coefficients ``[b0, b1..bN, a1..aN]`` (lies in V_N)."""

    coefficients: tuple = (10.0,)

    def radius(self, phi, derivative=0):
        return rad.evaluate(np.asarray(self.coefficients), phi, derivative)


@dataclass
class LevelSetStar(Lumen):
    """Wall ``{f = 0}`` of ``f = 1 - r^2/a^2 - eps r^3 cos(3 phi) / a^3`` (local polar coords).

    Star-shaped and smooth for ``|eps| < 0.5``; ``R(phi)`` is the positive
    root of the cubic, found per angle.
    """

    a: float = 11.0
    eps: float = 0.25

    def level(self, x, y):
        """``f`` and its gradient at physical points."""
        u, v = np.asarray(x) - self.center[0], np.asarray(y) - self.center[1]
        a, e = self.a, self.eps
        f = 1 - (u**2 + v**2) / a**2 - e * (u**3 - 3 * u * v**2) / a**3
        fx = -2 * u / a**2 - e * (3 * u**2 - 3 * v**2) / a**3
        fy = -2 * v / a**2 + e * 6 * u * v / a**3
        return f, fx, fy

    def radius(self, phi, derivative=0):
        phi = np.asarray(phi, dtype=float)
        c3 = np.cos(3 * phi)
        t = np.ones_like(phi)
        for _ in range(50):  # Newton on g(t) = 1 - t^2 - eps c3 t^3, t = r / a
            g = 1 - t**2 - self.eps * c3 * t**3
            dg = -2 * t - 3 * self.eps * c3 * t**2
            t = t - g / dg
        r = self.a * t
        if derivative == 0:
            return r
        if derivative == 1:  # implicit differentiation of g(t(phi), phi) = 0
            dgdphi = 3 * self.eps * np.sin(3 * phi) * t**3
            dg = -2 * t - 3 * self.eps * c3 * t**2
            return -self.a * dgdphi / dg
        raise ValueError("LevelSetStar.radius supports derivative 0 and 1")


# ---------------------------------------------------------------------- flows
@dataclass
class Flow:
    """Through-plane velocity in m/s with exact wall shear stress."""

    lumen: Lumen
    viscosity_pa_s: float

    def velocity(self, x, y) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def wall_gradient(self, phi) -> np.ndarray:  # pragma: no cover - abstract
        """``-dU/dn`` in (m/s)/mm at the wall point of angle ``phi`` about the lumen centre."""
        raise NotImplementedError

    def wss(self, phi) -> np.ndarray:
        """``tau = -mu dU/dn`` in Pa at the wall point of angle ``phi``."""
        return self.viscosity_pa_s * PER_MM * self.wall_gradient(phi)

    def mean_wss(self, n: int = 4096) -> float:
        phi = rad.uniform_angles(n)
        r, dr = self.lumen.radius(phi), self.lumen.radius(phi, 1)
        return rad.arc_length_mean(self.wss(phi), r, dr)


def _local(lumen, x, y, angle=0.0):
    u, v = np.asarray(x) - lumen.center[0], np.asarray(y) - lumen.center[1]
    c, s = np.cos(angle), np.sin(angle)
    return c * u + s * v, -s * u + c * v


@dataclass
class PoiseuilleEllipse(Flow):
    """Laminar Poiseuille flow in an elliptic pipe: ``u = U (1 - x'^2/a^2 - y'^2/b^2)``."""

    u_max: float = 0.4

    def velocity(self, x, y):
        e = self.lumen
        xl, yl = _local(e, x, y, e.angle)
        return np.maximum(self.u_max * (1 - (xl / e.a) ** 2 - (yl / e.b) ** 2), 0.0)

    def wall_gradient(self, phi):
        e = self.lumen
        r = e.radius(phi)
        t = np.asarray(phi) - e.angle
        xl, yl = r * np.cos(t), r * np.sin(t)
        return 2 * self.u_max * np.hypot(xl / e.a**2, yl / e.b**2)


@dataclass
class StarPoiseuille(Flow):
    """``u = U (1 - r^2 / R(phi)^2)`` in any star-shaped lumen.

    Notes
    -----
    At the wall ``-dU/dn = 2 U sqrt(R^2 + R'^2) / R^2``. The field is
    C^{1,1} at the centre (not smoother unless R is constant); the wall
    gradient is exact.
    """

    u_max: float = 0.4

    def velocity(self, x, y):
        l = self.lumen
        u, v = np.asarray(x) - l.center[0], np.asarray(y) - l.center[1]
        r2 = u**2 + v**2
        big_r = l.radius(np.arctan2(v, u)).reshape(np.shape(u))
        return self.u_max * np.maximum(1 - r2 / big_r**2, 0.0)  # zero outside, for either flow direction

    def wall_gradient(self, phi):
        r, dr = self.lumen.radius(phi), self.lumen.radius(phi, 1)
        return 2 * self.u_max * np.sqrt(r**2 + dr**2) / r**2


@dataclass
class Manufactured(Flow):
    """Polynomial field ``u = U f(x, y) (1 + kappa x'/a)`` vanishing on the wall of a :class:`LevelSetStar`.

    Smooth (a polynomial) up to and including the wall; ``-dU/dn = U (1 +
    kappa x'/a) |grad f|`` there because ``f = 0`` and ``grad f`` points
    inwards.
    """

    u_max: float = 0.4
    kappa: float = 0.2

    def velocity(self, x, y):
        l = self.lumen
        f, _, _ = l.level(x, y)
        xl = np.asarray(x) - l.center[0]
        return np.maximum(self.u_max * f * (1 + self.kappa * xl / l.a), 0.0)

    def wall_gradient(self, phi):
        l = self.lumen
        r = l.radius(phi)
        x, y = l.center[0] + r * np.cos(phi), l.center[1] + r * np.sin(phi)
        _, fx, fy = l.level(x, y)
        return self.u_max * (1 + self.kappa * r * np.cos(phi) / l.a) * np.hypot(fx, fy)


#: DNS mean profiles of turbulent pipe flow shipped in ``wss_nlp/data`` (see its README for the sources, CC0).
DNS_PROFILES = {"re180": "pipe_re180_mean.dat", "re550": "pipe_re550_mean.dat", "re1000": "pipe_re1000_mean.dat"}


@lru_cache(maxsize=4)
def dns_profile(name: str = "re180"):
    """``(y+, U+, Re_tau)`` of a turbulent pipe DNS (:data:`DNS_PROFILES`; Yao et al., doi:10.18738/T8/HLC3QY)."""
    if name not in DNS_PROFILES:
        raise InputError(f"unknown DNS profile {name!r}; choose from {', '.join(DNS_PROFILES)}")
    with resources.files("wss_nlp.data").joinpath(DNS_PROFILES[name]).open() as fh:
        text = fh.read()
    header = dict(
        (k.strip(), float(v)) for k, v in (ln.lstrip("# ").split("=") for ln in text.splitlines()[:6] if "=" in ln)
    )
    table = np.loadtxt(text.splitlines(), comments="#")
    yplus, uplus = table[:, 2], table[:, 5]
    order = np.argsort(yplus)
    return yplus[order], uplus[order], header["uTau"] / header["nu"]


def _dns_velocity(name: str, yplus):
    """``U+(y+)`` by monotone cubic interpolation of the DNS (``y+`` clipped to the centreline)."""
    import scipy.interpolate  # here: a slow import the command line should not pay at start-up

    table_y, table_u, _ = dns_profile(name)
    interp = scipy.interpolate.PchipInterpolator(table_y, table_u, extrapolate=False)
    return np.nan_to_num(interp(np.clip(yplus, 0, table_y[-1])))


@dataclass
class TurbulentPipe(Flow):
    """Mean turbulent pipe flow from DNS in a circular pipe (Re_tau 180.9, 549 or 998).

    Notes
    -----
    ``u(r) = u_tau U+((R - r) u_tau / nu)`` with ``u_tau = Re_tau nu / R``.
    The DNS has ``dU+/dy+ = 1`` at the wall, so ``tau = rho u_tau^2`` exactly.
    Defaults: water at 22 C in the paper's 25.885 mm pipe, giving a bulk
    velocity of about 0.19 m/s (about 6 l/min) at Re_tau 180.9.
    """

    density_kg_m3: float = 997.8
    dns: str = "re180"

    @property
    def re_tau(self) -> float:
        return dns_profile(self.dns)[2]

    @property
    def radius_mm(self) -> float:
        assert isinstance(self.lumen, Circle)  # a pipe flow
        return float(self.lumen.r)

    @property
    def nu(self) -> float:
        return self.viscosity_pa_s / self.density_kg_m3

    @property
    def u_tau(self) -> float:
        return self.re_tau * self.nu / (self.radius_mm / PER_MM)

    def velocity(self, x, y):
        r = np.hypot(np.asarray(x) - self.lumen.center[0], np.asarray(y) - self.lumen.center[1])
        u = self.u_tau * _dns_velocity(self.dns, (self.radius_mm - r) / PER_MM * self.u_tau / self.nu)
        return np.where(r < self.radius_mm, u, 0.0)

    def wall_gradient(self, phi):
        return np.full_like(np.asarray(phi, dtype=float), self.u_tau**2 / self.nu / PER_MM)


@dataclass
class TurbulentEllipse(Flow):
    """A turbulent mean profile in an elliptic lumen: the DNS law along elliptic level lines.

    Notes
    -----
    ``u = u_tau U+(y+)`` with ``y+ = (1 - q) R_m u_tau / nu``,
    ``q = sqrt(x'^2/a^2 + y'^2/b^2)`` and ``R_m = sqrt(a b)``,
    ``u_tau = Re_tau nu / R_m``. Not a solution of the averaged
    Navier-Stokes equations in a duct (secondary flows are absent), but a
    velocity field with a viscous sublayer of the DNS's shape whose WSS is
    exact: ``tau = mu (u_tau^2/nu) R_m |grad q|`` on the wall
    (``dU+/dy+ = 1`` there), varying around the wall like the local
    wall distance scale.
    """

    density_kg_m3: float = 997.8
    dns: str = "re180"

    @property
    def nu(self) -> float:
        return self.viscosity_pa_s / self.density_kg_m3

    @property
    def r_m(self) -> float:
        e = self.lumen
        assert isinstance(e, Ellipse)  # the level lines are an ellipse's
        return float(np.sqrt(e.a * e.b))

    @property
    def u_tau(self) -> float:
        return dns_profile(self.dns)[2] * self.nu / (self.r_m / PER_MM)

    def velocity(self, x, y):
        e = self.lumen
        xl, yl = _local(e, x, y, e.angle)
        q = np.hypot(xl / e.a, yl / e.b)
        u = self.u_tau * _dns_velocity(self.dns, (1 - q) * self.r_m / PER_MM * self.u_tau / self.nu)
        return np.where(q < 1, u, 0.0)

    def wall_gradient(self, phi):
        e = self.lumen
        r = e.radius(phi)
        t = np.asarray(phi) - e.angle
        xl, yl = r * np.cos(t), r * np.sin(t)
        return self.u_tau**2 / self.nu / PER_MM * self.r_m * np.hypot(xl / e.a**2, yl / e.b**2)


@dataclass
class EntrancePipe(Flow):
    """Developing laminar flow in the entrance length of a circular pipe (Langhaar 1942).

    Notes
    -----
    ``u(r) = U (I_0(a) - I_0(a r/R)) / I_2(a)``: Langhaar's approximate
    solution (H. L. Langhaar, *J. Appl. Mech.* 9, A55-A58, 1942), ``U`` the
    mean velocity and ``a`` growing from 0 (fully developed) to infinity at the
    inlet; the wall layer is about ``R/a`` thick and saturates like
    ``1 - exp(-a (1 - r/R))``. Exact wall gradient
    ``U a I_1(a) / (R I_2(a))``. ``a = 30`` in a 10 mm pipe is a 0.3 mm layer,
    about the first two diameters of a carotid-sized inlet at Re 1000.
    """

    u_mean: float = 0.25
    a: float = 30.0

    def velocity(self, x, y):
        from scipy.special import ive  # exponentially scaled: I_0(30) alone is 7.8e11

        r = np.hypot(np.asarray(x) - self.lumen.center[0], np.asarray(y) - self.lumen.center[1])
        big_r = self.lumen.radius(0.0)
        s = np.minimum(r / big_r, 1.0)
        u = self.u_mean * (ive(0, self.a) - ive(0, self.a * s) * np.exp(self.a * (s - 1))) / ive(2, self.a)
        return np.where(r < big_r, u, 0.0)

    def wall_gradient(self, phi):
        from scipy.special import ive

        big_r = float(self.lumen.radius(0.0))
        grad = self.u_mean * self.a * ive(1, self.a) / (big_r * ive(2, self.a))
        return np.full_like(np.asarray(phi, dtype=float), grad)


# ---------------------------------------------------------------- acquisition
@dataclass
class Truth:
    """What a phantom knows exactly."""

    name: str
    flow: Flow
    velocity_image: np.ndarray  # noise-free voxel-averaged velocity, (ny, nx)
    parameters: dict = field(default_factory=dict)

    @property
    def lumen(self) -> Lumen:
        return self.flow.lumen

    @property
    def center(self):
        return self.flow.lumen.center

    def radius_about(self, center, phi):
        return self.lumen.radius_about(center, phi)

    def wss_at_points(self, x, y) -> np.ndarray:
        """Exact WSS at the true wall point in the direction of ``(x, y)`` from the true centre."""
        phi = np.arctan2(np.asarray(y) - self.center[1], np.asarray(x) - self.center[0])
        return self.flow.wss(phi)

    @property
    def mean_wss(self) -> float:
        return self.flow.mean_wss()


def acquire(
    flow: Flow,
    grid: VoxelGrid,
    snr: float | None,
    rng: np.random.Generator,
    venc: float | None = None,
    rho: float = 1.0,
    spacing_mm: float = 0.025,
    psf: kspace.PSF | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Simulate one phase-contrast slice.

    Notes
    -----
    ``d_i = (1/|V_i|) int_{V_i} rho chi_Omega exp(i pi u / venc) dx + n_i`` with
    ``n_i`` complex Gaussian, standard deviation ``rho / SNR`` per channel;
    the voxel integral uses a midpoint rule with points about ``spacing_mm``
    apart (at most 60 x 60 per voxel). Returns ``|d|``, ``arg d``, the
    noise-free voxel-mean velocity and ``venc`` (default 1.25 max|u|). The
    phase convention is the file format's: ``velocity = venc phase / pi``.
    With ``psf`` the magnitude and phase come from a k-space acquisition
    (:func:`wss_nlp.models.kspace.acquire`; the voxel means stay the truth's).
    """
    n_sub = int(np.clip(np.ceil(grid.h / spacing_mm), 4, 60))
    xc, yc = grid.centers()
    t = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    ox, oy = (a.ravel() for a in np.meshgrid(t * grid.dx, t * grid.dy))
    if venc is None:
        venc = 1.25 * peak_velocity(flow)
    ny, nx = grid.shape
    signal = np.zeros((ny, nx), dtype=complex)
    u_mean = np.zeros((ny, nx))
    for iy in range(ny):  # row by row keeps memory small at fine resolution
        px = xc[iy][:, None] + ox[None, :]
        py = yc[iy][:, None] + oy[None, :]
        ins = flow.lumen.inside(px, py)
        u = np.where(ins, flow.velocity(px, py), 0.0)
        signal[iy] = (rho * ins * np.exp(1j * np.pi * u / venc)).mean(axis=1)
        cnt = ins.sum(axis=1)
        u_mean[iy] = np.where(cnt > 0, (u * ins).sum(axis=1) / np.maximum(cnt, 1), 0.0)
    if psf is not None:
        signal = kspace.acquire(lambda x, y: lumen_signal(flow, x, y, venc, rho), grid, psf, snr, rng, rho)
    elif snr is not None:
        signal = complex_noise(signal, rho / snr, rng)
    return np.abs(signal), np.angle(signal), u_mean, venc


def lumen_signal(flow: Flow, x, y, venc: float, rho: float = 1.0) -> np.ndarray:
    """The complex signal ``rho chi_Omega exp(i pi u / venc)`` at physical points (mm)."""
    ins = flow.lumen.inside(x, y)
    return rho * ins * np.exp(1j * np.pi * np.where(ins, flow.velocity(x, y), 0.0) / venc)


def peak_velocity(flow: Flow) -> float:
    """Largest ``|u|`` of a flow, sampled on 64 radii x 16 angles of its lumen (m/s)."""
    rr = np.linspace(0, flow.lumen.max_radius(), 64)
    probe = [
        flow.velocity(flow.lumen.center[0] + r * np.cos(p), flow.lumen.center[1] + r * np.sin(p))
        for r in rr
        for p in rad.uniform_angles(16)
    ]
    return float(np.max(np.abs(probe)))


def complex_noise(signal: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``signal + sigma (n_1 + i n_2)`` with independent standard normal ``n_1, n_2``."""
    return signal + sigma * (rng.standard_normal(signal.shape) + 1j * rng.standard_normal(signal.shape))


def noisy_copy(acq: Acquisition, snr: float, rng: np.random.Generator, rho: float = 1.0) -> Acquisition:
    """A noise-free phase-data acquisition (``make_phantom(..., snr=None)``) with fresh complex noise.

    For Monte-Carlo studies: the geometry, flow and grid offset stay fixed
    and only the noise changes between draws.
    """
    if acq.phase is None:
        raise InputError("noisy_copy needs phase data (make_phantom(..., as_phase=True))")
    d = complex_noise(acq.magnitude * np.exp(1j * acq.phase), rho / snr, rng)
    return replace(acq, magnitude=np.abs(d), phase=np.angle(d))


def _laminar(h_mm, rng):
    lumen = Ellipse(a=13.0, b=10.0, angle=0.4)
    return PoiseuilleEllipse(lumen=lumen, viscosity_pa_s=3.5e-3, u_max=0.4), 1.5 * 13.0


def _turbulent(h_mm, rng):
    return TurbulentPipe(lumen=Circle(r=25.885 / 2), viscosity_pa_s=0.955e-3), 1.55 * 12.9425


def _turbulent_dns(name):
    def build(h_mm, rng):
        return TurbulentPipe(lumen=Circle(r=25.885 / 2), viscosity_pa_s=0.955e-3, dns=name), 1.55 * 12.9425

    return build


def _turbulent_ellipse(h_mm, rng):
    lumen = Ellipse(a=14.0, b=11.0, angle=-0.3)
    return TurbulentEllipse(lumen=lumen, viscosity_pa_s=0.955e-3, dns="re180"), 1.5 * 14.0


def _entrance(h_mm, rng):
    return EntrancePipe(lumen=Circle(r=10.0), viscosity_pa_s=3.5e-3, u_mean=0.25, a=30.0), 1.5 * 10.0


def _manufactured(h_mm, rng):
    lumen = LevelSetStar(a=11.0, eps=0.25)
    return Manufactured(lumen=lumen, viscosity_pa_s=3.5e-3, u_max=0.4, kappa=0.2), 1.5 * lumen.max_radius()


def _fourier(h_mm, rng):
    coef = np.zeros(rad.n_coefficients(4))
    coef[0], coef[2], coef[3], coef[4 + 3] = 10.0, 0.8, -0.4, 0.5  # b0, b2, b3, a3
    lumen = FourierLumen(coefficients=tuple(coef))
    return StarPoiseuille(lumen=lumen, viscosity_pa_s=3.5e-3, u_max=0.4), 1.5 * lumen.max_radius()


def _circle(h_mm, rng):
    return StarPoiseuille(lumen=Circle(r=10.0), viscosity_pa_s=3.5e-3, u_max=0.4), 1.5 * 10.0


#: Phantom cases: name -> (builder, description).
CASES = {
    "laminar": (_laminar, "Poiseuille flow in an elliptic pipe (13 x 10 mm semi-axes), blood-like viscosity"),
    "turbulent": (_turbulent, "DNS mean turbulent pipe flow, Re_tau 180.9, water, 25.885 mm pipe (paper Sec. 7)"),
    "turbulent550": (_turbulent_dns("re550"), "DNS mean turbulent pipe flow, Re_tau 549, water, 25.885 mm pipe"),
    "turbulent1000": (_turbulent_dns("re1000"), "DNS mean turbulent pipe flow, Re_tau 998, water, 25.885 mm pipe"),
    "turbulent-ellipse": (
        _turbulent_ellipse,
        "the Re_tau 180.9 DNS profile along the level lines of a 14 x 11 mm elliptic lumen",
    ),
    "entrance": (_entrance, "developing laminar pipe flow (Langhaar), 10 mm pipe, 0.33 mm wall layer"),
    "manufactured": (_manufactured, "polynomial flow vanishing on a smooth three-lobed star-shaped wall"),
    "fourier": (_fourier, "Poiseuille-type flow u = U(1 - r^2/R(phi)^2) in a lumen whose R lies in V_4"),
    "circle": (_circle, "Poiseuille flow in a circular pipe of radius 10 mm"),
}


def make_phantom(
    case: str = "laminar",
    h_mm: float = 1.0,
    snr: float | None = 25.0,
    seed: int = 0,
    venc: float | None = None,
    offset: bool = True,
    as_phase: bool = True,
    psf: kspace.PSF | None = None,
) -> tuple[Acquisition, Truth]:
    """Seeded phantom factory: ``(acquisition, truth)`` for one slice.

    Parameters
    ----------
    case : str
        One of :data:`CASES`.
    h_mm : float
        In-plane voxel size (square voxels).
    snr : float or None
        Signal-to-noise ratio of the lumen signal; None for noise-free data.
    seed : int
        Seed of the random sub-voxel offset and of the noise.
    venc : float or None
        Velocity encoding in m/s; None picks 1.25 times the peak velocity.
    offset : bool
        Shift the vessel by a random sub-voxel amount against the grid.
    as_phase : bool
        Store ``phase`` and ``venc_m_s`` (as a scanner does) rather than ``velocity``.
    psf : wss_nlp.models.kspace.PSF or None
        Acquire in k-space with this filter and zero-filling
        (:func:`wss_nlp.models.kspace.acquire`) instead of taking voxel means; the
        file then records ``acquired_voxel_size_mm``.
    """
    if case not in CASES:
        raise InputError(f"unknown phantom case {case!r}; choose from {', '.join(CASES)}")
    if not h_mm > 0:
        raise InputError(f"voxel size must be > 0 mm, got {h_mm}")
    rng = np.random.default_rng(seed)
    flow, half_fov = CASES[case][0](h_mm, rng)
    n = int(np.ceil(2 * half_fov / h_mm))
    shift = rng.uniform(-0.5, 0.5, size=2) * h_mm if offset else np.zeros(2)
    origin = (-(n - 1) / 2 * h_mm, -(n - 1) / 2 * h_mm)
    flow.lumen.center = (float(shift[0]), float(shift[1]))
    grid = VoxelGrid((n, n), (h_mm, h_mm), origin)
    mag, phase, u_mean, venc = acquire(flow, grid, snr, rng, venc=venc, psf=psf)
    acq = Acquisition(
        magnitude=mag[None],
        phase=phase[None] if as_phase else None,
        velocity=None if as_phase else (venc * phase / np.pi)[None],
        voxel_size_mm=(h_mm, h_mm),
        origin_mm=origin,
        venc_m_s=venc,
        viscosity_pa_s=flow.viscosity_pa_s,
        density_kg_m3=getattr(flow, "density_kg_m3", None),
        source=f"phantom:{case}",
        acquired_voxel_size_mm=None if psf is None else (h_mm * psf.zero_fill[0], h_mm * psf.zero_fill[1]),
    )
    params = {"case": case, "h_mm": h_mm, "snr": -1.0 if snr is None else float(snr), "seed": seed, "venc_m_s": venc}
    if psf is not None:
        params["acquisition"] = psf.describe()
    return acq, Truth(name=case, flow=flow, velocity_image=u_mean, parameters=params)


# ------------------------------------------------------------------ stacks (3D)
@dataclass
class _LumenUnion(Lumen):
    """Several lumens seen in one image; for the acquisition only (the union is not star-shaped)."""

    parts: tuple = ()

    def inside(self, x, y) -> np.ndarray:
        return np.any([p.inside(x, y) for p in self.parts], axis=0)


@dataclass
class _SeveralVessels(Flow):
    """The flows of several vessels in one field of view, each zero outside its own lumen."""

    flows: tuple = ()

    def velocity(self, x, y):
        return sum(np.where(f.lumen.inside(x, y), f.velocity(x, y), 0.0) for f in self.flows)


def make_two_vessels(
    h_mm: float = 1.0, snr: float | None = 25.0, seed: int = 0, venc: float | None = None
) -> tuple[Acquisition, Truth]:
    """Seeded phantom with two vessels in view: an artery and, beside it, a smaller vein with reverse flow.

    The artery (Poiseuille, circle of radius 8 mm, peak 0.4 m/s) is the
    larger lumen and the truth; the vein (radius 5 mm, peak -0.25 m/s, its
    centre at (9, 5) mm plus the random sub-voxel shift) is what
    ``--vessel 9,5`` selects. Wall gap 5.4 mm. ``venc`` defaults to 1.25 x 0.4 m/s.
    """
    if not h_mm > 0:
        raise InputError(f"voxel size must be > 0 mm, got {h_mm}")
    rng = np.random.default_rng(seed)
    shift = rng.uniform(-0.5, 0.5, size=2) * h_mm
    artery = StarPoiseuille(
        lumen=Circle(center=(-8.0 + shift[0], -2.0 + shift[1]), r=8.0), viscosity_pa_s=3.5e-3, u_max=0.4
    )
    vein = StarPoiseuille(
        lumen=Circle(center=(9.0 + shift[0], 5.0 + shift[1]), r=5.0), viscosity_pa_s=3.5e-3, u_max=-0.25
    )
    both = _SeveralVessels(
        lumen=_LumenUnion(parts=(artery.lumen, vein.lumen)), viscosity_pa_s=3.5e-3, flows=(artery, vein)
    )
    n = int(np.ceil(2 * 19.0 / h_mm))
    origin = (-(n - 1) / 2 * h_mm, -(n - 1) / 2 * h_mm)
    grid = VoxelGrid((n, n), (h_mm, h_mm), origin)
    mag, phase, u_mean, venc = acquire(both, grid, snr, rng, venc=1.25 * 0.4 if venc is None else venc)
    acq = Acquisition(
        magnitude=mag[None],
        phase=phase[None],
        voxel_size_mm=(h_mm, h_mm),
        origin_mm=origin,
        venc_m_s=venc,
        viscosity_pa_s=3.5e-3,
        source="phantom:two_vessels",
    )
    params = {
        "case": "two_vessels",
        "h_mm": h_mm,
        "snr": -1.0 if snr is None else float(snr),
        "seed": seed,
        "venc_m_s": venc,
    }
    return acq, Truth(name="two_vessels", flow=artery, velocity_image=u_mean, parameters=params)


@dataclass
class StackTruth:
    """What a 3D phantom knows exactly: one :class:`Truth` per slice."""

    name: str
    slices: list
    z_mm: np.ndarray
    parameters: dict = field(default_factory=dict)


def _tapered(z):
    """Circular lumen narrowing smoothly from 10 to 8 mm radius and back over 80 mm (a mild stenosis)."""
    r = 10.0 - 2.0 * 0.5 * (1 - np.cos(2 * np.pi * z / 80.0))
    return Circle(r=float(r)), (0.0, 0.0)


def _curved(z):
    """Elliptic lumen (11 x 9 mm) whose centre follows a circle of 50 mm radius (3 mm drift over 17 mm)."""
    s = 2 * np.pi * z / 100.0
    return Ellipse(a=11.0, b=9.0, angle=0.3), (3.0 * np.sin(s), 3.0 * (1 - np.cos(s)))


@dataclass
class SwirlComponent(Flow):
    """In-plane component ``which`` (0: x, 1: y) of the swirl ``u_theta = Omega r (1 - r^2 / R(theta)^2)``.

    Vanishes on the wall; ``-d u_theta / dr = 2 Omega`` there for a circular lumen (in m/s per m, Omega in 1/s).
    """

    omega: float = 0.0  # 1/s
    which: int = 0

    def velocity(self, x, y):
        l = self.lumen
        dx, dy = np.asarray(x) - l.center[0], np.asarray(y) - l.center[1]
        r, t = np.hypot(dx, dy), np.arctan2(dy, dx)
        big_r = l.radius(t.ravel()).reshape(np.shape(r))
        u_t = np.where(r < big_r, self.omega * r / PER_MM * (1 - r**2 / big_r**2), 0.0)
        return -u_t * np.sin(t) if self.which == 0 else u_t * np.cos(t)


def _straight(z):
    """The paper's 25.885 mm pipe, straight (a developed flow: every slice the same)."""
    return Circle(r=25.885 / 2), (0.0, 0.0)


#: 3D phantom cases: name -> (lumen at height z, description).
STACK_CASES = {
    "tapered": (_tapered, "circular tube narrowing smoothly 10 -> 8 -> 10 mm over 80 mm; Poiseuille-type flow"),
    "curved": (_curved, "elliptic tube (11 x 9 mm) whose centre line curves sideways; Poiseuille-type flow"),
    "turbulent": (_straight, "straight 25.885 mm pipe, DNS mean turbulent flow at Re_tau 549 (water) in every slice"),
}

#: Stack cases whose flow is not the Poiseuille-type default: name -> flow of a slice's lumen.
STACK_FLOWS = {"turbulent": lambda lumen: TurbulentPipe(lumen=lumen, viscosity_pa_s=0.955e-3, dns="re550")}


def make_stack(
    case: str = "tapered",
    nz: int = 10,
    h_mm: float = 1.0,
    spacing_mm: float = 2.0,
    snr: float | None = 25.0,
    seed: int = 0,
    venc: float | None = None,
    flow_rate_ml_s: float = 40.0,
    viscosity_pa_s: float = 3.5e-3,
    swirl_per_s: float | None = None,
    psf: kspace.PSF | None = None,
) -> tuple[Acquisition, StackTruth]:
    """Seeded stack factory: ``nz`` slices ``spacing_mm`` apart through a 3D phantom.

    Notes
    -----
    Slice k at ``z_k = k dz`` holds the lumen of :data:`STACK_CASES` at that
    height with the through-plane velocity ``u = U_k (1 - r^2 / R_k(phi)^2)``
    (:class:`StarPoiseuille`); ``U_k`` keeps the flow rate ``Q`` the same in
    every slice (``Q = U_k |Omega_k| / 2``). The exact WSS of each slice is
    ``mu 2 U_k sqrt(R^2 + R'^2) / R^2``, a manufactured solution (the in-plane
    velocity of a real tapered tube is neglected). One random sub-voxel grid
    offset for the stack; fresh noise in every slice.

    With ``swirl_per_s = Omega`` the acquisition also has the in-plane
    components (4D flow) of the swirl ``u_theta = Omega r (1 - r^2/R^2)``
    (:class:`SwirlComponent`), each acquired as its own phase-contrast
    encoding with fresh noise. For the circular ``tapered`` tube the exact
    WSS vector is then known: axial ``2 mu U / R`` and circumferential
    ``2 mu Omega sqrt(1 + R'(z)^2)`` (docs, "Stacks of slices").
    ``psf`` acquires every slice in k-space (as :func:`make_phantom`).
    """
    if case not in STACK_CASES:
        raise InputError(f"unknown stack phantom {case!r}; choose from {', '.join(STACK_CASES)}")
    if nz < 1 or not h_mm > 0 or not spacing_mm > 0:
        raise InputError(f"need nz >= 1, h > 0 and spacing > 0; got {nz}, {h_mm}, {spacing_mm}")
    rng = np.random.default_rng(seed)
    make = STACK_CASES[case][0]
    z = np.arange(nz) * spacing_mm
    shift = rng.uniform(-0.5, 0.5, size=2) * h_mm
    flows: list[Flow] = []
    for zk in z:
        lumen, offset = make(zk)
        lumen.center = (float(offset[0] + shift[0]), float(offset[1] + shift[1]))
        if case in STACK_FLOWS:
            flows.append(STACK_FLOWS[case](lumen))
            continue
        area = 0.5 * float(np.sum(lumen.radius(rad.uniform_angles(1024)) ** 2)) * 2 * np.pi / 1024  # mm^2
        u_max = 2 * flow_rate_ml_s * 1e3 / area / 1e3  # Q = U A / 2; ml/s -> mm^3/s, mm/s -> m/s
        flows.append(StarPoiseuille(lumen=lumen, viscosity_pa_s=viscosity_pa_s, u_max=u_max))
    half = 1.3 * max(f.lumen.max_radius() + np.hypot(*f.lumen.center) for f in flows)
    n = int(np.ceil(2 * half / h_mm))
    origin = (-(n - 1) / 2 * h_mm, -(n - 1) / 2 * h_mm)
    grid = VoxelGrid((n, n), (h_mm, h_mm), origin)
    if venc is None:  # the peak sits at the centre of each slice's lumen
        venc = 1.25 * max(
            float(f.velocity(np.array([f.lumen.center[0]]), np.array([f.lumen.center[1]]))[0]) for f in flows
        )
    mags, phases, truths, inplane = [], [], [], []
    for k, flow in enumerate(flows):
        mag, phase, u_mean, _ = acquire(flow, grid, snr, rng, venc=venc, psf=psf)
        mags.append(mag)
        phases.append(phase)
        truths.append(Truth(name=f"{case}[{k}]", flow=flow, velocity_image=u_mean))
        if swirl_per_s is not None:
            comps = []
            for which in (0, 1):
                sw = SwirlComponent(lumen=flow.lumen, viscosity_pa_s=viscosity_pa_s, omega=swirl_per_s, which=which)
                _, ph, _, _ = acquire(sw, grid, snr, rng, venc=venc, psf=psf)
                comps.append(venc * ph / np.pi)
            inplane.append(comps)
    acq = Acquisition(
        magnitude=np.array(mags),
        phase=np.array(phases),
        voxel_size_mm=(h_mm, h_mm),
        origin_mm=origin,
        slice_spacing_mm=float(spacing_mm),
        venc_m_s=venc,
        viscosity_pa_s=flows[0].viscosity_pa_s,
        density_kg_m3=getattr(flows[0], "density_kg_m3", None),
        source=f"phantom:{case}-stack",
        velocity_inplane=np.transpose(np.array(inplane), (1, 0, 2, 3)) if inplane else None,
        acquired_voxel_size_mm=None if psf is None else (h_mm * psf.zero_fill[0], h_mm * psf.zero_fill[1]),
    )
    params = {
        "case": case,
        "nz": nz,
        "h_mm": h_mm,
        "spacing_mm": spacing_mm,
        "swirl_per_s": swirl_per_s,
        "snr": -1.0 if snr is None else float(snr),
        "seed": seed,
        "venc_m_s": venc,
    }
    return acq, StackTruth(case, truths, z, params)
