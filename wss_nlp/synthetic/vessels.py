r"""4D flow phantoms of curved vessels with exact wall shear stress vectors (issue 38, item 6).

Geometry
--------
A vessel is a tube about a centreline ``c(s)`` of arclength ``s`` (mm), built from pieces with closed forms
(:class:`LineSegment`, :class:`ArcSegment`, :class:`HelixSegment`) joined with a continuous tangent, and
continued by straight rays beyond both ends (``s < 0`` and ``s > length``), so that every point near the tube has
one closest centreline point. Along it runs a rotation-minimizing (parallel-transport) frame ``(t, n1, n2)``:
``t' = k1 n1 + k2 n2``, ``n1' = -k1 t``, ``n2' = -k2 t`` (no twist; constant on lines, a rotation about the
plane's normal on arcs, the Frenet frame turned by ``-torsion * s`` on helices). A point has the local
coordinates ``(s, q1, q2)``, ``x = c(s) + q1 n1(s) + q2 n2(s)``, ``q1 = r cos(phi)``, ``q2 = r sin(phi)``,
whose metric is diagonal: ``grad s = t / h``, ``grad q1 = n1``, ``grad q2 = n2`` with
``h = 1 - k1 q1 - k2 q2``. The wall is

    x(s, phi) = c(s) + R(s, phi) (cos(phi) n1(s) + sin(phi) n2(s)),

``R(s, phi) = g(s) / sqrt(cos^2(phi - alpha) / a^2 + sin^2(phi - alpha) / b^2)`` (:class:`Section`: a circle
when ``a = b``, an ellipse of any orientation ``alpha``, scaled by a smooth taper and stenosis/bulge ``g(s)``,
:class:`RadiusProfile`); ``R kappa < 1`` is required (the local coordinates stay valid).

Flow
----
Laminar, manufactured (not a Navier-Stokes solution), exactly zero on the wall, a sum of three modes with time
coefficients (:class:`VesselFlow`): with ``rho^2 = (q'_1/(g a))^2 + (q'_2/(g b))^2`` (the section's level set,
``q'`` the coordinates along the ellipse's axes) and ``l = (q1 cos phi0 + q2 sin phi0) / (g sqrt(a b))``

* axial, parabolic: ``w = (1 - rho^2) (1 + skew l) / g^2`` along ``t`` (``1 / g^2`` keeps the flux of a taper);
* axial, blunt: ``w = (1 - rho^6) (1 + skew l) / g^2`` along ``t``;
* swirl: ``(3 sqrt(3) / 2) (1 - rho^2) (-q2 n1 + q1 n2) / (g sqrt(a b))`` (peak 1 in a circle), along ``e_phi``;

``u(x, t) = c_0(t) parabolic + c_1(t) blunt + c_2(t) swirl`` with ``c_0 = U W(t) (1 - beta(t))``,
``c_1 = U W(t) beta(t)``, ``c_2 = S W(t)``: ``W`` a few harmonics (:class:`Waveform`, :data:`AORTIC_WAVEFORM`
has reverse flow in 18 % of the cycle), ``beta(t) = beta_0 + beta_1 cos(2 pi (t/T - t_b))`` the blend of a
blunt and a parabolic shape.

Wall shear stress
-----------------
``tau = (I - n n^T) (-mu (G + G^T) n)`` with ``n`` the outward unit normal of the true wall
(``n ~ R h e_r - h R_phi e_phi - R R_s t``, ``h = 1 - R (k1 cos phi + k2 sin phi)``) and ``G = grad u`` in world
coordinates: ``G = (du/ds) t^T / h + (du/dq1) n1^T + (du/dq2) n2^T`` with ``du/ds`` carrying the frame's
derivatives (``t' = k1 n1 + k2 n2``, ``n_i' = -k_i t``) and the modes' partial derivatives in ``(s, q1, q2)`` by
the complex step (exact to rounding). For Poiseuille flow ``u = U (1 - r^2/R^2) t`` this is ``+2 mu U / R t``.
``tau`` is linear in the coefficients, so a time series costs one evaluation per mode; TAWSS
``(1/T) int |tau| dt`` and OSI ``0.5 (1 - |int tau dt| / int |tau| dt)`` use the trapezoidal rule on
``n_time`` points of the period (exact for the mean vector, a trigonometric polynomial; ``O(n_time^-2)`` for
``|tau|`` where it has kinks at zeros). No wss_nlp reconstruction module is used.

Acquisition
-----------
:func:`acquire_volume` (:func:`make_vessel_phantom` for the named cases): per voxel of a grid given by an affine
(any rotation, anisotropic voxels) the lumen fraction is the voxel mean of the indicator; the magnitude is
``|mean(rho_l chi + tissue) + n_0|``; the velocity component ``c`` (world axis) is
``venc_c arg(mean(rho_l chi exp(i pi u_c / venc_c) + tissue) + n_c) / pi``; ``n_0 .. n_3`` independent complex
Gaussian, ``sigma = rho_l / SNR`` per channel (``rho_l = 1``). With ``tissue`` the outside carries a wall ring
(``0 <= r - R < wall_mm``) of its own level and smooth textured tissue (a few plane waves) of an intermediate
level, static (phase 0).

The voxel means are midpoint rules: ``n_wall^3`` points in voxels the lumen wall, the ring's outer edge or a cap
may cross, ``n_inner^3`` elsewhere (which voxels: the gap ``r - R`` at the centre against the half-diagonal times
a bound of ``|grad (r - R)|``, so no crossed voxel is missed). A wall voxel's rule runs in two levels
(:func:`wall_cells` sub-cells per axis): a sub-cell no interface can cross takes its centre's value, the others
all their points, so the lumen fraction is the full ``n_wall^3`` rule's exactly for about 500 of its 1728 points
at the default ``n_wall = 12`` (``n_inner = 3``). Measured by refining on 300 wall voxels of the arc at
``h = 2 mm`` (``scripts/bench_vessel_phantoms.py``, ``scripts/results/bench_vessel_phantoms.md``): the lumen
fraction's error falls like ``n_wall^-2``, RMS 1.1e-3 at ``n_wall = 12`` (9.5e-3 at 4, 2.1e-4 at 24; largest
8.5e-3), the noise-free velocity's RMS 1.3e-4 m/s (largest 1e-3 m/s): far below the noise (``1/SNR = 0.05`` in
the fraction, about ``venc / (pi SNR) = 0.017 m/s`` in the velocity at SNR 20). Sums over many voxels do better:
the lumen volume from the magnitude is within 1e-4 (tests). The aorta-sized arc builds in about 2 s at
``h = 2 mm``, the 20-frame pulsatile cine in about 7 s (the same script).

Truth
-----
:class:`VesselTruth` answers the centreline and frame, ``R(s, phi)``, wall points, outward normals, the WSS
vector, its axial part ``tau . t``, TAWSS and OSI at ``(s, phi)`` and a frame or time, :meth:`VesselTruth.locate`
(world points to the ``(s, phi)`` of their closest wall point), and the visible part of the centreline (inside
the field of view at least ``max_phi R(s, phi)`` from its border, :attr:`VesselTruth.visible`).

Truth file (:func:`write_truth`, :func:`read_truth`): HDF5, root attribute ``layout = "vessel-truth"``;
lengths in mm, stresses in Pa, vectors in the world frame of ``affine_mm`` (the volume's); ``ns`` arclengths,
``np`` angles ``phi`` (about ``t`` from ``n1`` towards ``n2``), ``nt`` times:

* ``s_mm`` ``(ns,)``, ``phi_rad`` ``(np,)``, ``time_ms`` ``(nt,)`` (the volume's frames);
* ``centreline/point_mm``, ``tangent``, ``n1``, ``n2`` ``(ns, 3)``; ``centreline/curvature_per_mm`` ``(ns, 2)``
  (``k1, k2``);
* ``wall/radius_mm`` ``(ns, np)``; ``wall/point_mm``, ``wall/normal`` ``(ns, np, 3)`` (outward unit normal);
* ``wss/vector_pa`` ``(nt, ns, np, 3)`` (tangential, exerted by the fluid on the wall), ``wss/axial_pa``
  ``(nt, ns, np)`` (``tau . t``, signed), ``wss/tawss_pa``, ``wss/osi`` ``(ns, np)`` (over one period);
* ``visible_mm`` ``(m, 2)``: the visible s-intervals;
* root attributes ``case``, ``affine_mm`` (4 x 4), ``shape`` (3), ``viscosity_pa_s``, ``density_kg_m3``,
  ``venc_m_s`` (3), ``cardiac_period_ms``, ``parameters`` (JSON: the factory's arguments).

Seeds: :data:`DEVELOPMENT_SEEDS` for tests and tuning, :data:`REPORTED_SEEDS` kept for reported tables.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..io.volume import VolumeAcquisition

log = logging.getLogger(__name__)

#: Seeds for development (tests, tuning, examples).
DEVELOPMENT_SEEDS = tuple(range(10))
#: Seeds reserved for reported tables: never tune on these.
REPORTED_SEEDS = tuple(range(100, 105))

#: mm -> m: velocity gradients in (m/s)/mm times this are in 1/s.
PER_MM = 1000.0
#: Blood (Pa s, kg/m^3).
BLOOD_VISCOSITY = 3.5e-3
BLOOD_DENSITY = 1060.0
#: Complex-step size (the modes' lengths are mm, so ~1e-30 relative).
_CSTEP = 1e-30
#: Swirl normalization: (3 sqrt 3 / 2) rho (1 - rho^2) peaks at 1 (rho = 1/sqrt 3).
_SWIRL_NORM = 1.5 * math.sqrt(3.0)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _outer(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``a[:, None] * v``: a scalar per point times a fixed 3-vector."""
    return a[:, None] * v[None, :]


# ---------------------------------------------------------------- centrelines
@dataclass(frozen=True)
class LineSegment:
    """A straight piece of ``length`` mm."""

    length: float


@dataclass(frozen=True)
class ArcSegment:
    """A circular arc of radius of curvature ``radius`` (mm) over ``angle`` (rad).

    It bends towards ``cos(bend) n1 + sin(bend) n2`` of the frame where it starts.
    """

    radius: float
    angle: float
    bend: float = 0.0


@dataclass(frozen=True)
class HelixSegment:
    """A right-handed helix of coil radius ``coil_radius`` and rise ``rise`` per radian (mm), ``length`` mm long.

    Curvature ``a / (a^2 + b^2)``, torsion ``b / (a^2 + b^2)`` (``a`` the coil radius, ``b`` the rise); its
    principal normal at the start is ``cos(bend) n1 + sin(bend) n2`` of the frame there.
    """

    coil_radius: float
    rise: float
    length: float
    bend: float = 0.0


@dataclass
class CentrelineFrame:
    """Points, unit tangents, rotation-minimizing normals ``n1, n2`` (``(N, 3)``) and curvature ``k1, k2`` (1/mm).

    ``t' = k1 n1 + k2 n2``; ``(t, n1, n2)`` is right-handed (``n2 = t x n1``).
    """

    point: np.ndarray
    tangent: np.ndarray
    n1: np.ndarray
    n2: np.ndarray
    k1: np.ndarray
    k2: np.ndarray


_FRAME_FIELDS = ("point", "tangent", "n1", "n2", "k1", "k2")


class _Piece:
    """One closed-form piece of a centreline on ``[s_lo, s_hi]`` (global arclength)."""

    s_lo: float
    s_hi: float
    curvature: float = 0.0

    def point(self, s: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def frame(self, s: np.ndarray) -> CentrelineFrame:  # pragma: no cover - abstract
        raise NotImplementedError

    def coords(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
        """``(s, d2, q1, q2)`` of each point ``x`` ``(N, 3)``: the arclength of this piece's closest point, the squared
        distance to it and the offset's components along ``n1, n2`` there (closed forms)."""
        raise NotImplementedError

    def end(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        f = self.frame(np.array([self.s_hi]))
        return f.point[0], f.tangent[0], f.n1[0]


class _Line(_Piece):
    """``c = p0 + (s - s_ref) t`` on ``[s_lo, s_hi]`` (either may be infinite: a ray)."""

    def __init__(self, s_lo, s_hi, p0, t, n1, s_ref=None):
        self.s_lo, self.s_hi = float(s_lo), float(s_hi)
        self.s_ref = float(s_ref if s_ref is not None else (s_lo if np.isfinite(s_lo) else s_hi))
        self.p0, self.t, self.n1 = np.asarray(p0, float), _unit(t), _unit(n1)
        self.n2 = np.cross(self.t, self.n1)

    def point(self, s):
        return self.p0 + _outer(s - self.s_ref, self.t)

    def frame(self, s):
        n = s.shape[0]
        zero = np.zeros(n)
        return CentrelineFrame(
            self.point(s), *(np.broadcast_to(v, (n, 3)) for v in (self.t, self.n1, self.n2)), zero, zero.copy()
        )

    def coords(self, x):
        p = (x - self.p0) @ np.stack([self.t, self.n1, self.n2], axis=1)
        u = np.clip(p[:, 0], self.s_lo - self.s_ref, self.s_hi - self.s_ref)
        return u + self.s_ref, (p[:, 0] - u) ** 2 + p[:, 1] ** 2 + p[:, 2] ** 2, p[:, 1], p[:, 2]


class _Arc(_Piece):
    """``c = C + Rc (cos th e1 + sin th e2)``, ``th = (s - s_lo) / Rc``; the frame turns about ``e3``."""

    def __init__(self, s_lo, p0, t0, n1, seg: ArcSegment):
        t0, n1 = _unit(t0), _unit(n1)
        n2 = np.cross(t0, n1)
        d = np.cos(seg.bend) * n1 + np.sin(seg.bend) * n2  # towards the centre of curvature
        self.rc, self.span = float(seg.radius), float(seg.angle)
        self.s_lo, self.s_hi = float(s_lo), float(s_lo) + self.rc * self.span
        self.centre = np.asarray(p0, float) + self.rc * d
        self.e1, self.e2 = -d, t0
        self.e3 = np.cross(self.e1, self.e2)
        self.n1_0, self.n2_0 = n1, n2
        self._basis = np.stack([self.e1, self.e2, self.e3], axis=1)
        self._n1c, self._n2c = n1 @ self._basis, n2 @ self._basis  # components in (e1, e2, e3)
        self.curvature = 1.0 / self.rc
        # the principal normal turns with the frame, so its components in (n1, n2) are constant
        self.k1, self.k2 = self.curvature * float(d @ n1), self.curvature * float(d @ n2)

    def point(self, s):
        th = (s - self.s_lo) / self.rc
        return self.centre + self.rc * (_outer(np.cos(th), self.e1) + _outer(np.sin(th), self.e2))

    def _turn(self, v, c, sn):
        """Rodrigues: ``v`` turned by the angles (cosines ``c``, sines ``sn``) about ``e3``."""
        return _outer(c, v) + _outer(sn, np.cross(self.e3, v)) + _outer((1 - c) * float(self.e3 @ v), self.e3)

    def frame(self, s):
        th = (s - self.s_lo) / self.rc
        c, sn = np.cos(th), np.sin(th)
        n = s.shape[0]
        return CentrelineFrame(
            self.point(s),
            _outer(-sn, self.e1) + _outer(c, self.e2),
            self._turn(self.n1_0, c, sn),
            self._turn(self.n2_0, c, sn),
            np.full(n, self.k1),
            np.full(n, self.k2),
        )

    def coords(self, x):
        p = (x - self.centre) @ self._basis
        th = np.arctan2(p[:, 1], p[:, 0])
        mid = 0.5 * self.span  # angles measured about the arc's middle: the nearer end wins when outside
        th = np.clip(mid + np.mod(th - mid + np.pi, 2 * np.pi) - np.pi, 0.0, self.span)
        c, sn = np.cos(th), np.sin(th)
        d1, d2, d3 = p[:, 0] - self.rc * c, p[:, 1] - self.rc * sn, p[:, 2]
        a, b = self._n1c, self._n2c  # n1, n2 at th: their (e1, e2) parts turned by th, e3 parts fixed
        q1 = d1 * (a[0] * c - a[1] * sn) + d2 * (a[0] * sn + a[1] * c) + d3 * a[2]
        q2 = d1 * (b[0] * c - b[1] * sn) + d2 * (b[0] * sn + b[1] * c) + d3 * b[2]
        return self.s_lo + self.rc * th, d1 * d1 + d2 * d2 + d3 * d3, q1, q2


class _Helix(_Piece):
    """``c = O + a (cos th e1 + sin th e2) + b th A``, ``th = (s - s_lo) / l``, ``l = sqrt(a^2 + b^2)``."""

    def __init__(self, s_lo, p0, t0, n1, seg: HelixSegment):
        t0, n1 = _unit(t0), _unit(n1)
        n2 = np.cross(t0, n1)
        a, b = float(seg.coil_radius), float(seg.rise)
        if not (a > 0 and b > 0):
            raise InputError(f"helix: coil radius and rise must be > 0 mm, got {a}, {b}")
        self.a, self.b = a, b
        self.ell = math.hypot(a, b)
        self.s_lo, self.s_hi = float(s_lo), float(s_lo) + float(seg.length)
        normal = np.cos(seg.bend) * n1 + np.sin(seg.bend) * n2
        binormal = np.cross(t0, normal)
        self.axis = (b * t0 + a * binormal) / self.ell
        self.e1 = -normal
        self.e2 = (a * t0 - b * binormal) / self.ell
        self.origin = np.asarray(p0, float) - a * self.e1
        self.curvature, self.torsion = a / self.ell**2, b / self.ell**2
        self.psi0 = math.atan2(float(n1 @ binormal), float(n1 @ normal))

    def point(self, s):
        th = (s - self.s_lo) / self.ell
        return (
            self.origin
            + self.a * (_outer(np.cos(th), self.e1) + _outer(np.sin(th), self.e2))
            + _outer(self.b * th, self.axis)
        )

    def frame(self, s):
        th = (s - self.s_lo) / self.ell
        c, sn = np.cos(th), np.sin(th)
        tangent = (self.a * (_outer(-sn, self.e1) + _outer(c, self.e2)) + self.b * self.axis) / self.ell
        normal = -(_outer(c, self.e1) + _outer(sn, self.e2))
        binormal = (self.a * self.axis + self.b * (_outer(sn, self.e1) - _outer(c, self.e2))) / self.ell
        psi = self.psi0 - self.torsion * (s - self.s_lo)  # rotation-minimizing: psi' = -torsion
        cp, sp = np.cos(psi), np.sin(psi)
        return CentrelineFrame(
            self.point(s),
            tangent,
            cp[:, None] * normal + sp[:, None] * binormal,
            -sp[:, None] * normal + cp[:, None] * binormal,
            self.curvature * cp,
            -self.curvature * sp,
        )

    def coords(self, x):
        """Newton on ``(c(th) - x) . c'(th) = 0`` from the best of 13 starts within half a turn either side of the
        height's angle (enough when the tube does not overlap itself: then ``|q . A| < pi b``)."""
        p = (x - self.origin) @ np.stack([self.e1, self.e2, self.axis], axis=1)
        x1, x2, z = p[:, 0], p[:, 1], p[:, 2]
        a, b = self.a, self.b
        guess = z / b
        best = guess.copy()
        best_d = np.full(guess.shape, np.inf)
        for off in np.linspace(-np.pi, np.pi, 13):
            th = guess + off
            d = (a * np.cos(th) - x1) ** 2 + (a * np.sin(th) - x2) ** 2 + (b * th - z) ** 2
            better = d < best_d
            best, best_d = np.where(better, th, best), np.where(better, d, best_d)
        th = best
        for _ in range(8):
            c, sn = np.cos(th), np.sin(th)
            g = a * (x1 * sn - x2 * c) + b * (b * th - z)
            dg = a * (x1 * c + x2 * sn) + b * b
            dg = np.where(dg > 0.1 * self.ell**2, dg, self.ell**2)  # a gradient step where not convex (far away)
            th = th - g / dg
        th = np.clip(th, 0.0, (self.s_hi - self.s_lo) / self.ell)
        c, sn = np.cos(th), np.sin(th)
        d1, d2, d3 = x1 - a * c, x2 - a * sn, z - b * th
        # the frame's components in (e1, e2, axis): N = -(c, sn, 0), B = (b sn, -b c, a) / l
        psi = self.psi0 - self.torsion * self.ell * th
        dn = -(d1 * c + d2 * sn)
        db = (b * (d1 * sn - d2 * c) + a * d3) / self.ell
        cp, sp = np.cos(psi), np.sin(psi)
        return self.s_lo + self.ell * th, d1 * d1 + d2 * d2 + d3 * d3, cp * dn + sp * db, -sp * dn + cp * db


class Centreline:
    """A centreline of closed-form pieces on ``[0, length]`` continued by straight rays at both ends.

    Build with :func:`build_centreline`.
    """

    def __init__(self, pieces: list[_Piece], length: float):
        self.pieces = pieces
        self.length = float(length)
        self._bounds = np.array([p.s_hi for p in pieces[:-1]])

    @property
    def max_curvature(self) -> float:
        return max(p.curvature for p in self.pieces)

    def _which(self, s: np.ndarray) -> np.ndarray:
        return np.searchsorted(self._bounds, s, side="right")

    def frame(self, s) -> CentrelineFrame:
        """The frame at arclengths ``s`` (any shape; arrays of shape ``s.shape + (3,)``)."""
        s = np.asarray(s, dtype=float)
        flat = s.ravel()
        n = flat.size
        out = {k: np.empty((n, 3)) for k in ("point", "tangent", "n1", "n2")}
        k1, k2 = np.empty(n), np.empty(n)
        which = self._which(flat)
        for i, piece in enumerate(self.pieces):
            sel = np.flatnonzero(which == i)
            if sel.size == 0:
                continue
            f = piece.frame(flat[sel])
            for k in out:
                out[k][sel] = getattr(f, k)
            k1[sel], k2[sel] = f.k1, f.k2
        shape = s.shape
        vec = {k: out[k].reshape(*shape, 3) for k in out}
        return CentrelineFrame(vec["point"], vec["tangent"], vec["n1"], vec["n2"], k1.reshape(shape), k2.reshape(shape))

    def point(self, s) -> np.ndarray:
        return self.frame(s).point

    def coords(self, x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local coordinates ``(s, q1, q2)`` of world points ``x`` ``(N, 3)``: the arclength of the closest centreline
        point (closed form on lines and arcs, Newton on helices; the nearest over the pieces) and the offset's
        components along ``n1, n2`` there."""
        flat = np.asarray(x, dtype=float).reshape(-1, 3)
        best = None
        for piece in self.pieces:
            s, d, q1, q2 = piece.coords(flat)
            if best is None:
                best = [s, d, q1, q2]
                continue
            better = d < best[1]
            for b, new in zip(best, (s, d, q1, q2)):
                b[better] = new[better]
        assert best is not None
        return best[0], best[2], best[3]

    def project(self, x) -> np.ndarray:
        """Arclength of the closest centreline point to each world point ``x`` ``(..., 3)``."""
        x = np.asarray(x, dtype=float)
        return self.coords(x)[0].reshape(x.shape[:-1])


def build_centreline(start, tangent, n1, segments) -> Centreline:
    """A centreline from ``start`` (mm) along ``tangent`` with first normal ``n1`` (made orthogonal to it), through
    ``segments`` (:class:`LineSegment`, :class:`ArcSegment`, :class:`HelixSegment`) joined with continuous tangent
    and frame; straight rays continue it beyond ``s = 0`` and ``s = length``."""
    p, t = np.asarray(start, float), _unit(tangent)
    n1 = np.asarray(n1, float)
    n1 = _unit(n1 - (n1 @ t) * t)
    segments = list(segments)
    pieces: list[_Piece] = []
    s = 0.0
    for i, seg in enumerate(segments):
        piece: _Piece
        if isinstance(seg, LineSegment):
            if not seg.length > 0:
                raise InputError(f"centreline: a line segment needs a length > 0 mm, got {seg.length}")
            # the rays continue the end lines: one piece each (fewer pieces to project on)
            lo = -np.inf if i == 0 else s
            hi = np.inf if i == len(segments) - 1 else s + seg.length
            piece = _Line(lo, hi, p, t, n1, s_ref=s)
        elif isinstance(seg, ArcSegment):
            if not (seg.radius > 0 and 0 < seg.angle < 2 * np.pi):
                raise InputError(f"centreline: an arc needs radius > 0 mm and 0 < angle < 2 pi, got {seg}")
            piece = _Arc(s, p, t, n1, seg)
        elif isinstance(seg, HelixSegment):
            piece = _Helix(s, p, t, n1, seg)
        else:
            raise InputError(f"centreline: unknown segment {seg!r}; use LineSegment, ArcSegment or HelixSegment")
        if not pieces and not isinstance(seg, LineSegment):
            pieces.append(_Line(-np.inf, 0.0, p, t, n1))
        pieces.append(piece)
        if i == len(segments) - 1:
            s = s + seg.length if isinstance(seg, LineSegment) else piece.s_hi
            if not isinstance(seg, LineSegment):
                p, t, n1 = piece.end()
                pieces.append(_Line(s, np.inf, p, t, n1))
            break
        s = piece.s_hi
        p, t, n1 = piece.end()
    if not pieces:
        raise InputError("centreline: give at least one segment")
    return Centreline(pieces, s)


# ------------------------------------------------------------- cross-sections
@dataclass(frozen=True)
class RadiusProfile:
    """The scale ``g(s)`` of a section: a smooth taper times a Gaussian stenosis (``bump < 0``) or bulge.

    ``g = (1 + (taper_ratio - 1) (1 + tanh((s - taper_at_mm) / taper_width_mm)) / 2)
    (1 + bump exp(-((s - bump_at_mm) / bump_width_mm)^2))``; analytic, so complex arguments work.
    """

    taper_ratio: float = 1.0
    taper_at_mm: float = 0.0
    taper_width_mm: float = 10.0
    bump: float = 0.0
    bump_at_mm: float = 0.0
    bump_width_mm: float = 6.0

    def scale(self, s):
        g = 1.0 + (self.taper_ratio - 1.0) * 0.5 * (1.0 + np.tanh((s - self.taper_at_mm) / self.taper_width_mm))
        if self.bump:
            g = g * (1.0 + self.bump * np.exp(-(((s - self.bump_at_mm) / self.bump_width_mm) ** 2)))
        return g

    def slope(self, s):
        """``g'(s)`` (1/mm)."""
        z = (s - self.taper_at_mm) / self.taper_width_mm
        taper = 1.0 + (self.taper_ratio - 1.0) * 0.5 * (1.0 + np.tanh(z))
        dtaper = (self.taper_ratio - 1.0) * 0.5 / np.cosh(z) ** 2 / self.taper_width_mm
        if not self.bump:
            return dtaper
        zb = (s - self.bump_at_mm) / self.bump_width_mm
        e = np.exp(-(zb**2))
        return dtaper * (1.0 + self.bump * e) + taper * self.bump * e * (-2.0 * zb / self.bump_width_mm)


@dataclass(frozen=True)
class Section:
    """Cross-section: an ellipse of semi-axes ``a_mm`` (along ``angle`` from ``n1``) and ``b_mm`` (a circle if None),
    scaled by ``profile``."""

    a_mm: float
    b_mm: float | None = None
    angle: float = 0.0
    profile: RadiusProfile = field(default_factory=RadiusProfile)

    @property
    def b(self) -> float:
        return self.a_mm if self.b_mm is None else self.b_mm

    @property
    def mean_radius(self) -> float:
        """``sqrt(a b)`` at ``g = 1`` (mm)."""
        return math.sqrt(self.a_mm * self.b)

    def rho2(self, s, q1, q2):
        """Normalized radius squared ``rho^2`` (1 on the wall); analytic in ``(s, q1, q2)``."""
        g = self.profile.scale(s)
        c, sn = math.cos(self.angle), math.sin(self.angle)
        u = (c * q1 + sn * q2) / (g * self.a_mm)
        v = (-sn * q1 + c * q2) / (g * self.b)
        return u * u + v * v

    def radius(self, s, phi) -> np.ndarray:
        """``R(s, phi)`` (mm)."""
        return self.radius_derivatives(s, phi)[0]

    def radius_derivatives(self, s, phi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``R``, ``dR/ds`` (1) and ``dR/dphi`` (mm)."""
        s, phi = np.broadcast_arrays(np.asarray(s, float), np.asarray(phi, float))
        psi = phi - self.angle
        c, sn = np.cos(psi), np.sin(psi)
        q = c**2 / self.a_mm**2 + sn**2 / self.b**2
        g = self.profile.scale(s)
        base = q**-0.5
        dbase = -0.5 * q**-1.5 * 2 * sn * c * (1 / self.b**2 - 1 / self.a_mm**2)
        return g * base, self.profile.slope(s) * base, g * dbase

    def max_radius(self, s) -> np.ndarray:
        return self.profile.scale(np.asarray(s, float)) * max(self.a_mm, self.b)

    def area(self, s) -> np.ndarray:
        """``pi a b g(s)^2`` (mm^2)."""
        return np.pi * self.a_mm * self.b * self.profile.scale(np.asarray(s, float)) ** 2


# ------------------------------------------------------------------- flows
@dataclass(frozen=True)
class Waveform:
    """``W(tau) = mean + sum_k cos_k cos(2 pi k tau) + sin_k sin(2 pi k tau)``, ``tau = t / T``."""

    mean: float = 1.0
    cos: tuple[float, ...] = ()
    sin: tuple[float, ...] = ()

    @property
    def steady(self) -> bool:
        return not any(self.cos) and not any(self.sin)

    def __call__(self, tau) -> np.ndarray:
        tau = np.asarray(tau, float)
        w = np.full(tau.shape, self.mean)
        for k, c in enumerate(self.cos, start=1):
            w = w + c * np.cos(2 * np.pi * k * tau)
        for k, c in enumerate(self.sin, start=1):
            w = w + c * np.sin(2 * np.pi * k * tau)
        return w


#: An aortic flow waveform (four harmonics): peak 0.999 at t = 0.154 T, reverse flow down to -0.21 at 0.34 T
#: (18 % of the cycle below zero), mean 0.168.
AORTIC_WAVEFORM = Waveform(0.168, (0.184, -0.062, -0.204, -0.072), (0.175, 0.259, 0.036, -0.087))


@dataclass(frozen=True)
class VesselFlow:
    """The manufactured flow (module docstring): peak axial speed ``u_peak_m_s`` (m/s, at the centre of a circular
    section with ``g = 1``, ``W = 1``, no skew), skew ``skew`` towards ``phi = skew_angle``, peak swirl speed
    ``swirl_m_s`` (m/s), the blunt shape's weight ``beta(t) = blunt + blunt_swing cos(2 pi (t/T - blunt_phase))``,
    the waveform ``W`` and the period ``period_ms``."""

    u_peak_m_s: float = 0.8
    skew: float = 0.0
    skew_angle: float = 0.0
    swirl_m_s: float = 0.0
    blunt: float = 0.0
    blunt_swing: float = 0.0
    blunt_phase: float = 0.0
    waveform: Waveform = field(default_factory=Waveform)
    period_ms: float = 1000.0
    viscosity_pa_s: float = BLOOD_VISCOSITY
    density_kg_m3: float = BLOOD_DENSITY

    @property
    def steady(self) -> bool:
        return self.waveform.steady and self.blunt_swing == 0.0

    def coefficients(self, t_ms) -> np.ndarray:
        """The modes' coefficients ``(3, ...)`` (m/s) at times ``t_ms``: parabolic, blunt, swirl."""
        tau = np.asarray(t_ms, float) / self.period_ms
        w = self.waveform(tau)
        beta = self.blunt + self.blunt_swing * np.cos(2 * np.pi * (tau - self.blunt_phase))
        return np.stack([self.u_peak_m_s * w * (1 - beta), self.u_peak_m_s * w * beta, self.swirl_m_s * w])


@dataclass
class Local:
    """Local coordinates of points: arclength ``s``, ``q1, q2`` along ``n1, n2`` (and the frame at ``s`` if asked)."""

    s: np.ndarray
    q1: np.ndarray
    q2: np.ndarray
    frame: CentrelineFrame | None = None

    def take(self, sel: np.ndarray) -> Local:
        f = self.frame
        sub = None if f is None else CentrelineFrame(*(getattr(f, k)[sel] for k in _FRAME_FIELDS))
        return Local(self.s[sel], self.q1[sel], self.q2[sel], sub)

    @property
    def r(self) -> np.ndarray:
        return np.hypot(self.q1, self.q2)

    @property
    def phi(self) -> np.ndarray:
        return np.arctan2(self.q2, self.q1)


def _traction(grad: np.ndarray, normal: np.ndarray, mu: float) -> np.ndarray:
    """Tangential part of ``-mu (G + G^T) n`` (Pa) for ``G`` ``(..., 3, 3)`` in 1/s, ``n`` ``(..., 3)``."""
    strain = grad + np.swapaxes(grad, -1, -2)
    tau = -mu * np.einsum("...ij,...j->...i", strain, normal)
    return tau - np.sum(tau * normal, axis=-1, keepdims=True) * normal


@dataclass
class Vessel:
    """A tube (centreline, section) with a flow; ``capped`` limits the lumen to ``0 <= s <= length``.

    Raises :class:`InputError` if the section reaches a centre of curvature or the tube overlaps itself.
    """

    centreline: Centreline
    section: Section
    flow: VesselFlow = field(default_factory=VesselFlow)
    capped: bool = False

    def __post_init__(self):
        self._check()

    # ------------------------------------------------------------ geometry
    def _check(self) -> None:
        cl, sec = self.centreline, self.section
        for piece in cl.pieces:
            if piece.curvature == 0:
                continue
            s = np.linspace(piece.s_lo, piece.s_hi, 200)
            r_max = float(np.max(sec.max_radius(s)))
            if r_max * piece.curvature >= 1.0:
                raise InputError(
                    f"vessel: the section's radius {r_max:.3g} mm reaches the centre of curvature (radius of "
                    f"curvature {1 / piece.curvature:.3g} mm); keep R below it"
                )
        lo, hi = -20.0, cl.length + 20.0
        r_all = float(np.max(sec.max_radius(np.linspace(lo, hi, 400))))
        s = np.arange(lo, hi, min(0.5, r_all / 4))
        pts = cl.point(s)
        for i0 in range(0, s.size, 256):
            d = np.linalg.norm(pts[i0 : i0 + 256, None] - pts[None], axis=-1)
            far = np.abs(s[i0 : i0 + 256, None] - s[None]) > np.pi * r_all
            if np.any(far & (d < 2 * r_all)):
                raise InputError(
                    f"vessel: the tube of radius {r_all:.3g} mm overlaps itself (centreline points {np.min(d[far]):.3g}"
                    " mm apart); use a smaller radius or a wider curve"
                )

    def local(self, x, frame: bool = True) -> Local:
        """Local coordinates of world points ``x`` ``(N, 3)`` (mm), with the frame at their ``s`` if ``frame``."""
        s, q1, q2 = self.centreline.coords(x)
        return Local(s, q1, q2, self.centreline.frame(s) if frame else None)

    def gap(self, loc: Local) -> np.ndarray:
        """``r - R(s, phi)`` (mm): negative in the lumen (``R = r / rho``: the section is homogeneous in ``q``)."""
        r = loc.r
        pos = r > 0
        u1 = np.divide(loc.q1, r, out=np.ones_like(r), where=pos)  # on the centreline: any direction
        u2 = np.divide(loc.q2, r, out=np.zeros_like(r), where=pos)
        return r - 1.0 / np.sqrt(self.section.rho2(loc.s, u1, u2))

    def inside(self, loc: Local, gap: np.ndarray | None = None) -> np.ndarray:
        ins = (self.gap(loc) if gap is None else gap) < 0
        if self.capped:
            ins &= (loc.s >= 0) & (loc.s <= self.centreline.length)
        return ins

    def radius(self, s, phi) -> np.ndarray:
        return self.section.radius(s, phi)

    def wall_point(self, s, phi) -> np.ndarray:
        """``x(s, phi) = c(s) + R(s, phi) (cos phi n1 + sin phi n2)`` (mm), shape ``broadcast(s, phi) + (3,)``."""
        s, phi = np.broadcast_arrays(np.asarray(s, float), np.asarray(phi, float))
        f = self.centreline.frame(s)
        r = self.section.radius(s, phi)[..., None]
        return f.point + r * (np.cos(phi)[..., None] * f.n1 + np.sin(phi)[..., None] * f.n2)

    def _wall(self, s, phi):
        s, phi = np.broadcast_arrays(np.asarray(s, float), np.asarray(phi, float))
        shape = s.shape
        s, phi = s.ravel(), phi.ravel()
        f = self.centreline.frame(s)
        rr, r_s, r_phi = self.section.radius_derivatives(s, phi)
        c, sn = np.cos(phi), np.sin(phi)
        e_r = c[:, None] * f.n1 + sn[:, None] * f.n2
        e_phi = -sn[:, None] * f.n1 + c[:, None] * f.n2
        h = 1.0 - rr * (f.k1 * c + f.k2 * sn)
        normal = (rr * h)[:, None] * e_r - (h * r_phi)[:, None] * e_phi - (rr * r_s)[:, None] * f.tangent
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        return shape, s, phi, f, rr, r_s, r_phi, e_r, e_phi, h, normal

    def normal(self, s, phi) -> np.ndarray:
        """Outward unit normal of the wall at ``(s, phi)``: ``n ~ R h e_r - h R_phi e_phi - R R_s t``."""
        shape, *_, normal = self._wall(s, phi)
        return normal.reshape(*shape, 3)

    # ---------------------------------------------------------------- flow
    def modes(self, s, q1, q2) -> np.ndarray:
        """The three modes' local components ``(mode, [w, v1, v2], N)`` per unit coefficient (m/s).

        Analytic in ``(s, q1, q2)``: complex arguments give the complex step.
        """
        sec, fl = self.section, self.flow
        g = sec.profile.scale(s)
        rho2 = sec.rho2(s, q1, q2)
        f = 1.0 - rho2
        rref = g * sec.mean_radius
        skew = 1.0 + fl.skew * (q1 * math.cos(fl.skew_angle) + q2 * math.sin(fl.skew_angle)) / rref
        axial = skew / (g * g)
        zero = 0.0 * f
        swirl = _SWIRL_NORM * f / rref
        return np.array(
            [
                [f * axial, zero, zero],
                [(1.0 - rho2**3) * axial, zero, zero],
                [zero, -q2 * swirl, q1 * swirl],
            ]
        )

    def mode_vectors(self, loc: Local) -> np.ndarray:
        """The modes as world vectors ``(mode, N, 3)`` (m/s per unit coefficient), not cut at the wall."""
        m = self.modes(loc.s, loc.q1, loc.q2)
        f = loc.frame if loc.frame is not None else self.centreline.frame(loc.s)
        return m[:, 0, :, None] * f.tangent + m[:, 1, :, None] * f.n1 + m[:, 2, :, None] * f.n2

    def velocity(self, x, t_ms: float = 0.0, extend: bool = False) -> np.ndarray:
        """Velocity (m/s, world axes) at world points ``x`` ``(..., 3)``; zero outside the lumen unless ``extend``
        (then the closed form continued smoothly through the wall)."""
        x = np.asarray(x, float)
        loc = self.local(x)
        u = np.einsum("m,mnk->nk", self.flow.coefficients(t_ms), self.mode_vectors(loc))
        if not extend:
            u[~self.inside(loc)] = 0.0
        return u.reshape(x.shape)

    def _mode_traction(self, s, phi):
        """Tangential WSS of each mode ``(3, N, 3)`` (Pa per m/s of coefficient), and the wall data."""
        shape, s, phi, f, rr, _, _, _, _, _, normal = self._wall(s, phi)
        q1, q2 = rr * np.cos(phi), rr * np.sin(phi)
        val = self.modes(s, q1, q2)
        ds = self.modes(s + 1j * _CSTEP, q1, q2).imag / _CSTEP
        d1 = self.modes(s, q1 + 1j * _CSTEP, q2).imag / _CSTEP
        d2 = self.modes(s, q1, q2 + 1j * _CSTEP).imag / _CSTEP
        k1, k2 = f.k1, f.k2
        hq = 1.0 - k1 * q1 - k2 * q2

        def vec(a, b, c):  # a t + b n1 + c n2 for (mode, N) coefficient arrays
            return a[..., None] * f.tangent + b[..., None] * f.n1 + c[..., None] * f.n2

        w, v1, v2 = val[:, 0], val[:, 1], val[:, 2]
        du_ds = vec(ds[:, 0] - v1 * k1 - v2 * k2, ds[:, 1] + w * k1, ds[:, 2] + w * k2)
        du_d1 = vec(d1[:, 0], d1[:, 1], d1[:, 2])
        du_d2 = vec(d2[:, 0], d2[:, 1], d2[:, 2])
        grad = (
            du_ds[..., :, None] * (f.tangent / hq[:, None])[None, :, None, :]
            + du_d1[..., :, None] * f.n1[None, :, None, :]
            + du_d2[..., :, None] * f.n2[None, :, None, :]
        ) * PER_MM  # (m/s)/mm -> 1/s
        return _traction(grad, normal[None], self.flow.viscosity_pa_s), shape, f

    def wss(self, s, phi, t_ms=0.0) -> np.ndarray:
        """WSS vector (Pa, world axes) at wall points ``(s, phi)`` and time ``t_ms``: ``broadcast(s, phi) + (3,)``,
        or ``(nt,) + ... + (3,)`` for an array of times."""
        tau, shape, _ = self._mode_traction(s, phi)
        coef = self.flow.coefficients(t_ms)
        out = np.einsum("m...,mnk->...nk", coef, tau)
        return out.reshape(*np.shape(t_ms), *shape, 3)

    def axial_wss(self, s, phi, t_ms=0.0) -> np.ndarray:
        """``tau . t(s)`` (Pa, signed: positive along the centreline's direction)."""
        tau, shape, f = self._mode_traction(s, phi)
        axial = np.sum(tau * f.tangent[None], axis=-1)  # (mode, N)
        return np.einsum("m...,mn->...n", self.flow.coefficients(t_ms), axial).reshape(*np.shape(t_ms), *shape)

    def wss_cycle(self, s, phi, n_time: int = 4096, chunk: int = 2048) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(TAWSS (Pa), OSI, time-averaged WSS vector (Pa))`` over one period.

        Trapezoidal rule on ``n_time`` equally spaced times: exact for the mean vector (the coefficients are
        trigonometric polynomials of degree below ``n_time / 2``), ``O(n_time^-2)`` for ``mean |tau|``. A steady
        flow gives ``|tau|`` and 0.
        """
        tau, shape, _ = self._mode_traction(s, phi)
        fl = self.flow
        times = np.arange(n_time) * fl.period_ms / n_time if not fl.steady else np.zeros(1)
        coef = fl.coefficients(times)  # (3, nt)
        mean_vec = np.einsum("m,mnk->nk", coef.mean(axis=1), tau)
        gram = np.einsum("mnk,pnk->nmp", tau, tau)
        tawss = np.empty(tau.shape[1])
        for i0 in range(0, tau.shape[1], chunk):
            g = gram[i0 : i0 + chunk]
            mag2 = np.einsum("mt,nmp,pt->nt", coef, g, coef)
            tawss[i0 : i0 + chunk] = np.sqrt(np.maximum(mag2, 0.0)).mean(axis=1)
        size = np.linalg.norm(mean_vec, axis=1)
        osi = np.clip(0.5 * (1.0 - np.divide(size, tawss, out=np.ones_like(size), where=tawss > 0)), 0.0, 0.5)
        return tawss.reshape(shape), osi.reshape(shape), mean_vec.reshape(*shape, 3)

    def peak_speed(self, s_lo: float, s_hi: float, times_ms) -> float:
        """Largest speed ``|u|`` (m/s) over the lumen between ``s_lo`` and ``s_hi`` at ``times_ms`` (sampled:
        100 sections x 15 radii x 24 angles)."""
        s = np.linspace(s_lo, s_hi, 100)[:, None, None]
        rho = np.linspace(0.0, 0.999, 15)[None, :, None]
        phi = np.linspace(-np.pi, np.pi, 24, endpoint=False)[None, None, :]
        s, rho, phi = (a.ravel() for a in np.broadcast_arrays(s, rho, phi))
        r = rho * self.section.radius(s, phi)
        m = self.modes(s, r * np.cos(phi), r * np.sin(phi))  # (mode, comp, N): the frame is orthonormal
        times = np.zeros(1) if self.flow.steady else np.atleast_1d(np.asarray(times_ms, float))
        u = (self.flow.coefficients(times).T @ m.reshape(3, -1)).reshape(times.size, 3, -1)
        return float(np.sqrt(np.max(np.sum(u**2, axis=1))))

    # ------------------------------------------------------------- locate
    def locate(self, points, iterations: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(s, phi, signed distance)`` of the closest wall point to each world point ``(..., 3)`` near the wall.

        Gauss-Newton on ``|x(s, phi) - p|^2`` from the point's own ``(s, phi)``, with the exact tangents
        ``x_s = h e_s + R_s e_r``, ``x_phi = R_phi e_r + R e_phi``; ``phi`` in ``(-pi, pi]``, the distance
        positive outside the lumen.
        """
        p = np.asarray(points, float)
        flat = p.reshape(-1, 3)
        loc = self.local(flat)
        s, phi = loc.s.copy(), loc.phi.copy()
        for _ in range(iterations):
            _, _, _, f, rr, r_s, r_phi, e_r, e_phi, h, _ = self._wall(s, phi)
            x = f.point + rr[:, None] * e_r
            xs = h[:, None] * f.tangent + r_s[:, None] * e_r
            xp = r_phi[:, None] * e_r + rr[:, None] * e_phi
            res = x - flat
            a11, a12, a22 = np.sum(xs * xs, 1), np.sum(xs * xp, 1), np.sum(xp * xp, 1)
            b1, b2 = -np.sum(xs * res, 1), -np.sum(xp * res, 1)
            det = a11 * a22 - a12**2
            ds, dphi = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
            s, phi = s + ds, phi + dphi
            if max(np.max(np.abs(ds)), np.max(np.abs(dphi)) * 20.0) < 1e-13:
                break
        phi = np.angle(np.exp(1j * phi))
        wall = self.wall_point(s, phi)
        dist = np.linalg.norm(flat - wall, axis=1) * np.where(self.inside(self.local(flat)), -1.0, 1.0)
        shape = p.shape[:-1]
        return s.reshape(shape), phi.reshape(shape), dist.reshape(shape)


# ----------------------------------------------------------------- tissue
@dataclass(frozen=True)
class Tissue:
    """Static signal outside the lumen: a wall ring ``0 <= r - R < wall_mm`` at ``wall_level`` and tissue at
    ``level (1 + texture mean_j cos(k_j . x + theta_j))`` beyond it (``waves``: rows ``(k_x, k_y, k_z, theta)``,
    1/mm and rad). Levels relative to the lumen's signal 1."""

    wall_mm: float = 2.0
    wall_level: float = 0.12
    level: float = 0.35
    texture: float = 0.3
    waves: tuple = ()

    @staticmethod
    def random(rng: np.random.Generator, wall_mm: float = 2.0, n_waves: int = 6, **kw) -> Tissue:
        """Texture of ``n_waves`` plane waves of random direction, wavelength 20-40 mm and phase."""
        d = rng.standard_normal((n_waves, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        k = d * (2 * np.pi / rng.uniform(20.0, 40.0, size=(n_waves, 1)))
        theta = rng.uniform(0.0, 2 * np.pi, size=(n_waves, 1))
        return Tissue(wall_mm=wall_mm, waves=tuple(map(tuple, np.hstack([k, theta]).tolist())), **kw)

    def texture_signal(self, x: np.ndarray) -> np.ndarray:
        if not self.waves:
            return np.full(x.shape[0], self.level)
        w = np.asarray(self.waves, float)
        return self.level * (1.0 + self.texture * np.cos(x @ w[:, :3].T + w[:, 3]).mean(axis=1))

    def signal(self, x: np.ndarray, gap: np.ndarray) -> np.ndarray:
        """The static signal at points ``x`` of wall gap ``r - R`` (0 in the lumen, ``gap < 0``)."""
        out = np.where(gap < 0, 0.0, self.wall_level)
        far = np.flatnonzero(gap >= self.wall_mm)
        out[far] = self.texture_signal(x[far])
        return out


# ------------------------------------------------------------ acquisition
@dataclass
class VoxelMeans:
    """Noise-free voxel means: lumen fraction ``(V,)``, reference signal ``(V,)`` (the magnitude image's, real) and
    the velocity-encoded signals ``(nt, 3, V)`` (complex)."""

    fraction: np.ndarray
    reference: np.ndarray
    encoded: np.ndarray


def _offsets(n: int) -> np.ndarray:
    """Midpoints of ``n^3`` sub-cells of the unit voxel about its centre, in index units ``(n^3, 3)``."""
    t = (np.arange(n) + 0.5) / n - 0.5
    return np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)


def wall_cells(n: int) -> int:
    """Sub-cells per axis of a wall voxel's two-level rule with ``n`` points per axis (``n`` when none fits).

    The divisor ``d`` of ``n`` (``1 < d < n``) that minimizes the points a cut voxel needs, ``d^3`` sub-cell
    centres plus about ``1.8 d^2`` cut sub-cells of ``(n / d)^3`` points each (the band of a smooth wall):
    4 for ``n = 8``, 6 for 12, 8 for 16 and 24, 16 for 48.
    """
    best, cost = n, float(n) ** 3
    for d in range(2, n):
        if n % d == 0 and d**3 + 1.8 * n**3 / d < cost:
            best, cost = d, d**3 + 1.8 * n**3 / d
    return best


def _near_interface(vessel: Vessel, loc: Local, gap: np.ndarray, margin: float, ring: float | None) -> np.ndarray:
    """Points whose ball of radius ``margin / slope`` may cross the wall, the wall ring's outer edge or a cap."""
    near = np.abs(gap) <= margin
    if ring is not None:
        near |= np.abs(gap - ring) <= margin
    if vessel.capped:
        length = vessel.centreline.length
        near |= ((np.abs(loc.s) <= margin) | (np.abs(loc.s - length) <= margin)) & (gap <= margin + (ring or 0.0))
    return near


def voxel_means(
    vessel: Vessel,
    affine_mm,
    index,
    n: int,
    times_ms,
    venc_m_s,
    tissue: Tissue | None = None,
    lumen_level: float = 1.0,
    lumen_possible: bool = True,
    slope: float | None = None,
    chunk_points: int = 20_000,
    cells: int | None = None,
) -> VoxelMeans:
    """Midpoint-rule voxel means (``n^3`` points a voxel) of the signals of the voxels ``index`` ``(V, 3)``.

    The lumen part is ``lumen_level chi exp(i pi u_c / venc_c)`` per world component ``c``; the static part is
    ``tissue.signal``. ``lumen_possible = False`` skips the vessel (tissue only, far outside). The geometry of a
    chunk of points is computed once for all times.

    Notes
    -----
    With ``cells`` (default :func:`wall_cells`; 1 or ``n``: the plain midpoint rule) a divisor of ``n`` between 1
    and ``n``, a voxel is split into ``cells^3`` sub-cells;
    a sub-cell that no interface can cross (its centre's gap ``r - R`` against its half-diagonal times ``slope``,
    a bound of ``|grad (r - R)|``) is all in or all out and takes its centre's value, the others the
    ``(n / cells)^3`` points of the full rule in it. The lumen fraction is then the full ``n^3`` rule's
    exactly; the smooth parts (velocity phase, tissue) use the sub-cells' midpoints there.
    """
    a = np.asarray(affine_mm, float)
    index = np.asarray(index, float).reshape(-1, 3)
    coef = vessel.flow.coefficients(np.atleast_1d(np.asarray(times_ms, float)))  # (3, nt)
    nt = coef.shape[1]
    scale = np.pi / np.broadcast_to(np.asarray(venc_m_s, float), (3,))
    nv = index.shape[0]
    cells = wall_cells(n) if cells is None else int(cells)
    cells = cells if (lumen_possible and n > cells > 1 and n % cells == 0) else n
    fine = n // cells
    ring = tissue.wall_mm if tissue is not None else None
    if fine > 1 and slope is None:
        slope = _slope_bound(vessel, np.linspace(-10.0, vessel.centreline.length + 10.0, 256), 3.0 + (ring or 0.0))
    off1, off2 = _offsets(cells), _offsets(fine) / cells
    half_cell = 0.5 * float(np.linalg.norm(np.linalg.norm(a[:3, :3], axis=0))) / cells
    fraction, reference = np.zeros(nv), np.zeros(nv)
    encoded = np.zeros((nt, 3, nv), dtype=complex)
    per_voxel = off1.shape[0] + (1.8 * n**3 / cells if fine > 1 else 0)  # about 1.8 cells^2 sub-cells are cut
    step = max(1, int(chunk_points // per_voxel))
    for v0 in range(0, nv, step):
        idx = index[v0 : v0 + step]
        nc = idx.shape[0]
        ipts = (idx[:, None, :] + off1[None]).reshape(-1, 3)
        vox = np.repeat(np.arange(nc), off1.shape[0])
        weight = np.full(ipts.shape[0], 1.0 / off1.shape[0])
        loc = gap = None
        if lumen_possible:
            pts = ipts @ a[:3, :3].T + a[:3, 3]
            loc = vessel.local(pts, frame=False)
            gap = vessel.gap(loc)
            if fine > 1:
                assert slope is not None
                cut = _near_interface(vessel, loc, gap, 1.05 * slope * half_cell, ring)
                if cut.any():
                    keep = np.flatnonzero(~cut)
                    c_idx = np.flatnonzero(cut)
                    fpts = (ipts[c_idx][:, None, :] + off2[None]).reshape(-1, 3)
                    floc = vessel.local(fpts @ a[:3, :3].T + a[:3, 3], frame=False)
                    ipts = np.concatenate([ipts[keep], fpts])
                    vox = np.concatenate([vox[keep], np.repeat(vox[c_idx], off2.shape[0])])
                    weight = np.concatenate([weight[keep], np.full(fpts.shape[0], weight[0] / off2.shape[0])])
                    s_, q1_, q2_ = (
                        np.concatenate([getattr(loc, k)[keep], getattr(floc, k)]) for k in ("s", "q1", "q2")
                    )
                    loc = Local(s_, q1_, q2_)
                    gap = vessel.gap(loc)
            chi = vessel.inside(loc, gap)
            if vessel.capped:  # beyond the caps: the tissue as outside the wall ring
                gap = np.where(chi | (gap >= 0), gap, np.inf)
        else:
            gap = np.full(ipts.shape[0], np.inf)
            chi = np.zeros(ipts.shape[0], bool)
        if tissue is not None:
            static = tissue.signal(ipts @ a[:3, :3].T + a[:3, 3], gap)
            static_mean = np.bincount(vox, weights=weight * static, minlength=nc)
        else:
            static_mean = np.zeros(nc)
        frac = np.bincount(vox, weights=weight * chi, minlength=nc)
        fraction[v0 : v0 + nc] = frac
        reference[v0 : v0 + nc] = static_mean + lumen_level * frac
        encoded[:, :, v0 : v0 + nc] = static_mean
        if not chi.any():
            continue
        assert loc is not None
        sel = np.flatnonzero(chi)
        lv, lw = vox[sel], lumen_level * weight[sel]
        modes = vessel.mode_vectors(loc.take(sel))  # (mode, P, 3)
        for it in range(nt):
            u = np.einsum("m,mpk->kp", coef[:, it], modes)
            for c in range(3):
                ph = u[c] * scale[c]
                re = np.bincount(lv, weights=lw * np.cos(ph), minlength=nc)
                im = np.bincount(lv, weights=lw * np.sin(ph), minlength=nc)
                encoded[it, c, v0 : v0 + nc] += re + 1j * im
    return VoxelMeans(fraction, reference, encoded)


def _slope_bound(vessel: Vessel, s: np.ndarray, reach: float) -> float:
    """An upper bound of ``|grad (r - R(s, phi))|`` within ``reach`` mm of the wall at arclengths ``s``:
    ``sqrt(1 + (R_phi / r)^2 + (R_s / h)^2)`` with ``r >= R - reach`` and ``h >= 1 - kappa (R + reach)``."""
    phi = np.linspace(-np.pi, np.pi, 64, endpoint=False)
    ss, pp = np.meshgrid(s, phi, indexing="ij")
    rr, r_s, r_phi = vessel.section.radius_derivatives(ss, pp)
    r_min = max(float(np.min(rr)) - reach, 1e-3)
    h_min = max(1.0 - vessel.centreline.max_curvature * (float(np.max(rr)) + reach), 1e-3)
    return float(np.sqrt(1.0 + (np.max(np.abs(r_phi)) / r_min) ** 2 + (np.max(np.abs(r_s)) / h_min) ** 2))


@dataclass
class Acquired:
    """What :func:`acquire_volume` returns: the volume, the noise-free lumen fraction ``(ni, nj, nk)`` and
    noise-free velocity ``(nt, 3, ni, nj, nk)`` (``venc arg(mean) / pi`` without noise), and counts."""

    volume: VolumeAcquisition
    lumen_fraction: np.ndarray
    noise_free_velocity: np.ndarray
    noise_free_magnitude: np.ndarray
    counts: dict


def acquire_volume(
    vessel: Vessel,
    affine_mm,
    shape,
    times_ms,
    venc_m_s,
    snr: float | None,
    rng: np.random.Generator,
    tissue: Tissue | None = None,
    n_inner: int = 3,
    n_wall: int = 12,
    lumen_level: float = 1.0,
    source: str = "phantom:vessel",
    cardiac_period_ms: float | None = None,
) -> Acquired:
    """Simulate a 4D flow acquisition of ``vessel`` on the grid ``affine_mm``, ``shape`` at ``times_ms``.

    Notes
    -----
    Per voxel ``V`` and frame: magnitude ``|(1/|V|) int_V (rho_l chi + T) dx + n_0|``, velocity component ``c``
    (world axis) ``venc_c arg((1/|V|) int_V (rho_l chi exp(i pi u_c / venc_c) + T) dx + n_c) / pi``, ``T`` the
    static tissue signal, ``n_k`` complex Gaussian with ``sigma = rho_l / SNR`` per channel, drawn per frame in
    the order magnitude, x, y, z. Midpoint rules with ``n_wall^3`` points in voxels the wall (or the wall ring's
    outer edge, or a cap) may cross and ``n_inner^3`` elsewhere; voxels far outside hold tissue only (zero
    without ``tissue``). ``venc_m_s`` is one value or three.
    """
    t0 = time.perf_counter()
    a = np.asarray(affine_mm, float)
    shape = tuple(int(v) for v in shape)
    times = np.atleast_1d(np.asarray(times_ms, float))
    nt = times.size
    venc = np.broadcast_to(np.asarray(venc_m_s, float), (3,)).copy()
    if not np.all(venc > 0):
        raise InputError(f"venc must be > 0 m/s, got {venc_m_s}")
    if snr is not None and not snr > 0:
        raise InputError(f"SNR must be > 0 (or None for noise-free data), got {snr}")
    if n_inner < 1 or n_wall < 1:
        raise InputError(f"sub-voxel points per axis must be >= 1, got n_inner={n_inner}, n_wall={n_wall}")
    index = np.stack(np.meshgrid(*(np.arange(n, dtype=float) for n in shape), indexing="ij"), -1).reshape(-1, 3)
    centres = index @ a[:3, :3].T + a[:3, 3]
    half_diag = 0.5 * float(np.linalg.norm(np.linalg.norm(a[:3, :3], axis=0)))
    loc = vessel.local(centres, frame=False)
    gap = vessel.gap(loc)
    ring = tissue.wall_mm if tissue is not None else None
    reach = half_diag + (ring or 0.0)
    band = np.abs(gap) < 3 * reach
    s_band = loc.s[band] if band.any() else np.zeros(1)
    slope = _slope_bound(vessel, np.linspace(s_band.min() - reach, s_band.max() + reach, 64), reach)
    h_min = 1.0 - vessel.centreline.max_curvature * (float(np.max(vessel.section.max_radius(s_band))) + reach)
    # a cap's distance is |s| h: the margin in s grows by 1 / h
    cap_factor = 1.0 / max(h_min, 0.1) if vessel.capped else 1.0
    margin = 1.05 * half_diag * slope * cap_factor
    near = _near_interface(vessel, loc, gap, margin, ring)
    inner = ~near & (gap < 0)
    outer = ~near & ~inner
    if vessel.capped:  # beyond a cap the lumen ends: tissue only
        beyond = (loc.s < 0) | (loc.s > vessel.centreline.length)
        outer |= inner & beyond
        inner &= ~beyond
    nv = index.shape[0]
    fraction, reference = np.zeros(nv), np.zeros(nv)
    encoded = np.zeros((nt, 3, nv), dtype=complex)
    groups = [(near, n_wall, True), (inner, n_inner, True)]
    if tissue is not None:
        groups.append((outer, n_inner, False))
    for mask, n, lumen in groups:
        sel = np.flatnonzero(mask)
        if sel.size == 0:
            continue
        vm = voxel_means(vessel, a, index[sel], n, times, venc, tissue, lumen_level, lumen, slope * cap_factor)
        fraction[sel], reference[sel], encoded[:, :, sel] = vm.fraction, vm.reference, vm.encoded
    sigma = 0.0 if snr is None else lumen_level / snr
    magnitude = np.empty((nt, *shape))
    velocity = np.empty((nt, 3, *shape))
    for it in range(nt):
        m = reference.astype(complex)
        if snr is not None:
            m = m + sigma * (rng.standard_normal(nv) + 1j * rng.standard_normal(nv))
        magnitude[it] = np.abs(m).reshape(shape)
        for c in range(3):
            d = encoded[it, c]
            if snr is not None:
                d = d + sigma * (rng.standard_normal(nv) + 1j * rng.standard_normal(nv))
            velocity[it, c] = (venc[c] * np.angle(d) / np.pi).reshape(shape)
    counts = {
        "voxels": nv,
        "wall_voxels": int(near.sum()),
        "inner_voxels": int(inner.sum()),
        "seconds": time.perf_counter() - t0,
    }
    log.debug("acquire_volume: %s", counts)
    vol = VolumeAcquisition(
        magnitude=magnitude,
        velocity=velocity,
        affine_mm=a,
        venc_m_s=(float(venc[0]), float(venc[1]), float(venc[2])),
        viscosity_pa_s=vessel.flow.viscosity_pa_s,
        density_kg_m3=vessel.flow.density_kg_m3,
        trigger_times_ms=times.copy() if nt > 1 else None,
        cardiac_period_ms=cardiac_period_ms if nt > 1 else None,
        source=source,
    )
    clean_v = (venc[None, :, None] * np.angle(encoded) / np.pi).reshape(nt, 3, *shape)
    return Acquired(vol, fraction.reshape(shape), clean_v, np.abs(reference).reshape(shape), counts)


# ------------------------------------------------------------------ truth
@dataclass
class VesselTruth:
    """What a vessel phantom knows exactly (module docstring, "Truth").

    ``times_ms`` are the volume's frame times (``[0]`` for one frame); a ``frame`` argument picks one of them,
    ``t_ms`` any time. Arclengths ``s`` in mm, angles ``phi`` in rad about ``t`` from ``n1`` towards ``n2``.
    """

    name: str
    vessel: Vessel
    affine_mm: np.ndarray
    shape: tuple[int, int, int]
    times_ms: np.ndarray
    venc_m_s: tuple[float, float, float]
    lumen_fraction: np.ndarray
    noise_free_velocity: np.ndarray
    noise_free_magnitude: np.ndarray
    tissue: Tissue | None = None
    parameters: dict = field(default_factory=dict)
    visible: list = field(default_factory=list)

    @property
    def period_ms(self) -> float:
        return self.vessel.flow.period_ms

    @property
    def viscosity_pa_s(self) -> float:
        return self.vessel.flow.viscosity_pa_s

    def _time(self, frame: int | None, t_ms) -> float | np.ndarray:
        if t_ms is not None:
            return t_ms
        return float(self.times_ms[0 if frame is None else frame])

    def centreline(self, s) -> CentrelineFrame:
        """Centreline points and rotation-minimizing frame at ``s``."""
        return self.vessel.centreline.frame(s)

    def radius(self, s, phi) -> np.ndarray:
        return self.vessel.radius(s, phi)

    def wall_point(self, s, phi) -> np.ndarray:
        return self.vessel.wall_point(s, phi)

    def normal(self, s, phi) -> np.ndarray:
        return self.vessel.normal(s, phi)

    def wss(self, s, phi, frame: int | None = None, t_ms=None) -> np.ndarray:
        """WSS vector (Pa) at ``(s, phi)``, frame ``frame`` (default 0) or time ``t_ms``."""
        return self.vessel.wss(s, phi, self._time(frame, t_ms))

    def axial_wss(self, s, phi, frame: int | None = None, t_ms=None) -> np.ndarray:
        """``tau . t`` (Pa, signed)."""
        return self.vessel.axial_wss(s, phi, self._time(frame, t_ms))

    def tawss(self, s, phi) -> np.ndarray:
        """``(1/T) int_0^T |tau| dt`` (Pa)."""
        return self.vessel.wss_cycle(s, phi)[0]

    def osi(self, s, phi) -> np.ndarray:
        """``0.5 (1 - |int tau dt| / int |tau| dt)``."""
        return self.vessel.wss_cycle(s, phi)[1]

    def locate(self, points, return_distance: bool = False):
        """``(s, phi)`` of the closest true wall point of each world point (mm) near the wall, and with
        ``return_distance`` its signed distance (mm, positive outside)."""
        s, phi, d = self.vessel.locate(points)
        return (s, phi, d) if return_distance else (s, phi)

    def write_truth(self, path, s_mm=None, phi=None) -> None:
        write_truth(path, self, s_mm, phi)


def visible_ranges(vessel: Vessel, affine_mm, shape, s_lo: float, s_hi: float, ds: float = 0.05) -> list:
    """The s-intervals ``[(s0, s1), ...]`` of ``[s_lo, s_hi]`` where the centreline lies inside the field of view
    (the outer voxel faces) at least ``max_phi R(s, phi)`` from its border (sampled every ``ds`` mm)."""
    a = np.asarray(affine_mm, float)
    if vessel.capped:
        s_lo, s_hi = max(s_lo, 0.0), min(s_hi, vessel.centreline.length)
    s = np.arange(s_lo, s_hi + ds / 2, ds)
    idx = np.linalg.solve(a[:3, :3], (vessel.centreline.point(s) - a[:3, 3]).T).T
    h = np.linalg.norm(a[:3, :3], axis=0)
    dist = np.minimum((idx + 0.5) * h, (np.asarray(shape) - 0.5 - idx) * h).min(axis=1)
    if np.any(np.abs(np.linalg.svd(a[:3, :3] / h, compute_uv=False) - 1) > 1e-9):
        log.warning("visible_ranges: the voxel axes are not orthogonal; distances along the index axes")
    ok = dist >= vessel.section.max_radius(s)
    out = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(int), [0]])))
    for i0, i1 in zip(edges[::2], edges[1::2]):
        out.append((float(s[i0]), float(s[i1 - 1])))
    return out


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed rotation (3 x 3, det +1): QR of a Gaussian matrix with the signs fixed."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# ------------------------------------------------------------------ cases
def _arch(radius, rc=30.0, angle=np.pi, legs=40.0, section=None, flow=None) -> tuple[Vessel, tuple[float, float]]:
    """Aortic-arch-like: ``legs`` mm up, a 180 degree arc of radius ``rc``, ``legs`` mm down; n1 points to the centre
    of curvature on the arc (phi = 0 the inner wall, phi = pi the outer)."""
    cl = build_centreline(
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 1.0),
        (1.0, 0.0, 0.0),
        [LineSegment(legs), ArcSegment(rc, angle, 0.0), LineSegment(legs)],
    )
    sec = section if section is not None else Section(radius)
    arc_end = legs + rc * angle
    return Vessel(cl, sec, flow if flow is not None else VesselFlow()), (legs - 5.0, arc_end + 5.0)


def _case_straight(o):
    cl = build_centreline((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), [LineSegment(100.0)])
    return Vessel(cl, Section(o.get("radius_mm", 11.0)), VesselFlow(u_peak_m_s=o.get("u_peak_m_s", 0.8))), (0, 100.0)


def _case_arc(o):
    return _arch(o.get("radius_mm", 11.0), flow=VesselFlow(u_peak_m_s=o.get("u_peak_m_s", 0.8)))


def _case_helix(o):
    cl = build_centreline((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), [HelixSegment(8.0, 14.0, 100.0)])
    return Vessel(cl, Section(o.get("radius_mm", 10.0)), VesselFlow(u_peak_m_s=o.get("u_peak_m_s", 0.8))), (0, 100.0)


def _case_taper(o):
    cl = build_centreline((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), [LineSegment(100.0)])
    profile = RadiusProfile(taper_ratio=0.75, taper_at_mm=45.0, taper_width_mm=15.0, bump=-0.2, bump_at_mm=72.0)
    flow = VesselFlow(u_peak_m_s=o.get("u_peak_m_s", 0.5))
    return Vessel(cl, Section(o.get("radius_mm", 12.0), profile=profile), flow), (0, 100.0)


def _case_ellipse(o):
    return _arch(0.0, section=Section(12.0, 9.0, 0.5), flow=VesselFlow(u_peak_m_s=o.get("u_peak_m_s", 0.8)))


def _swirl_flow(o, **kw):
    return VesselFlow(
        u_peak_m_s=o.get("u_peak_m_s", 0.8),
        skew=o.get("skew", 0.3),
        skew_angle=np.pi,  # towards the outer wall of the arc, as the Dean flow pushes the peak
        swirl_m_s=o.get("swirl_m_s", 0.2),
        **kw,
    )


def _case_swirl(o):
    return _arch(o.get("radius_mm", 11.0), flow=_swirl_flow(o))


def _case_pulsatile(o):
    flow = _swirl_flow(
        {"u_peak_m_s": 1.0, "skew": 0.2, "swirl_m_s": 0.15, **o},
        blunt=0.4,
        blunt_swing=0.4,
        blunt_phase=0.15,  # bluntest at peak systole
        waveform=AORTIC_WAVEFORM,
        period_ms=o.get("period_ms", 1000.0),
    )
    return _arch(o.get("radius_mm", 11.0), flow=flow)


def _case_carotid(o):
    cl = build_centreline(
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 1.0),
        (1.0, 0.0, 0.0),
        [LineSegment(30.0), ArcSegment(30.0, np.pi / 3, 0.0), LineSegment(30.0)],
    )
    flow = VesselFlow(u_peak_m_s=o.get("u_peak_m_s", 0.6))
    return Vessel(cl, Section(o.get("radius_mm", 3.0)), flow), (15.0, 30.0 + 10 * np.pi + 15.0)


def _case_leaving(o):
    return _case_arc(o)


#: Named cases: name -> (builder, description). Aorta-sized cases have radius 10-12 mm and ~100 mm in view.
CASES = {
    "straight": (_case_straight, "oblique straight tube, radius 11 mm, Poiseuille flow 0.8 m/s, 100 mm in view"),
    "arc": (_case_arc, "aortic-arch-like tube, radius 11 mm: 180 degree arc of radius 30 mm with straight legs"),
    "helix": (_case_helix, "helical tube, radius 10 mm, coil radius 8 mm, rise 14 mm/rad (curvature 1/32.5 mm)"),
    "taper": (_case_taper, "straight tube tapering 12 -> 9 mm with a 20 % stenosis, flux-conserving flow"),
    "ellipse": (_case_ellipse, "the arc with an elliptic section 12 x 9 mm (major axis 0.5 rad from n1)"),
    "swirl": (_case_swirl, "the arc with the peak skewed 0.3 to the outer wall and a 0.2 m/s swirl"),
    "pulsatile": (_case_pulsatile, "the arc with an aortic waveform (reverse flow), blunt-parabolic blend, swirl"),
    "carotid": (_case_carotid, "carotid-sized tube, radius 3 mm, 60 degree bend of radius 30 mm, 0.6 m/s"),
    "leaving": (_case_leaving, "the arc, its field of view cut through the arch's apex: the vessel leaves sideways"),
}

#: Keyword overrides of :func:`make_vessel_phantom`.
OVERRIDES = {
    "radius_mm": "the section's radius (circular cases) or semi-axis a",
    "u_peak_m_s": "peak axial speed scale (m/s)",
    "swirl_m_s": "peak swirl speed (swirl, pulsatile)",
    "skew": "skew of the axial profile (swirl, pulsatile)",
    "period_ms": "cardiac period (pulsatile; default 1000 ms)",
    "vessel": "a Vessel replacing the case's",
    "visible_mm": "(s0, s1): the centreline range the field of view covers",
    "voxel_mm": "three voxel edge lengths (anisotropic voxels; default h_mm each)",
    "rotation": "3 x 3 rotation of the grid's axes (default: uniformly random from the seed)",
    "margin_mm": "padding of the field of view around the tube (default max(2 h, 4) mm)",
    "venc_m_s": "velocity encoding (default 1.3 x the peak speed, to the cm/s above)",
    "n_inner": "sub-voxel points per axis away from the wall (default 3)",
    "n_wall": "sub-voxel points per axis in voxels the wall crosses (default 12)",
    "wall_mm": "thickness of the wall ring with tissue (default 2 mm, carotid 0.8 mm)",
}


def make_vessel_phantom(
    case: str,
    h_mm: float = 2.0,
    snr: float | None = 20,
    seed: int = 0,
    tissue: bool = False,
    frames: int = 1,
    **overrides,
) -> tuple[VolumeAcquisition, VesselTruth]:
    """Seeded 4D flow phantom of a vessel: ``(volume, truth)``.

    Parameters
    ----------
    case : str
        One of :data:`CASES`.
    h_mm : float
        Isotropic voxel size (mm); ``voxel_mm=(hx, hy, hz)`` overrides it.
    snr : float or None
        Lumen signal over the noise's standard deviation per channel; None for noise-free data.
    seed : int
        Seeds the grid's rotation and sub-voxel offset, the tissue texture and the noise
        (:data:`DEVELOPMENT_SEEDS`, :data:`REPORTED_SEEDS`).
    tissue : bool
        Static tissue and a wall ring outside the lumen (:class:`Tissue`); else zero signal there.
    frames : int
        Frames at ``t_k = k T / frames`` (T the period, 1000 ms); one frame is at ``t = 0``.
    **overrides
        :data:`OVERRIDES`.

    Notes
    -----
    The grid's axes are the columns of a rotation (uniformly random from the seed) times the voxel sizes; the
    field of view is the box, in the grid's axes, around the tube over the case's visible centreline range, padded
    by ``margin_mm``, shifted by a random sub-voxel offset. The vessel continues beyond it (straight rays), so it
    leaves through the box's faces. ``leaving`` moves the face beyond which the centreline rises highest above both
    its ends to the centreline's extremum there: the vessel's outer half leaves the box at the arch and comes back.
    Viscosity 3.5e-3 Pa s, density 1060 kg/m^3.
    """
    if case not in CASES:
        raise InputError(f"unknown vessel phantom case {case!r}; choose from {', '.join(CASES)}")
    unknown = sorted(set(overrides) - set(OVERRIDES))
    if unknown:
        raise InputError(
            f"make_vessel_phantom: unknown override(s) {', '.join(unknown)}; choose from {', '.join(OVERRIDES)}"
        )
    if not h_mm > 0:
        raise InputError(f"voxel size must be > 0 mm, got {h_mm}")
    if frames < 1:
        raise InputError(f"frames must be >= 1, got {frames}")
    rng = np.random.default_rng(seed)
    vessel, visible = CASES[case][0](overrides)
    if "vessel" in overrides:
        vessel = overrides["vessel"]
    visible = tuple(overrides.get("visible_mm", visible))
    h = np.broadcast_to(np.asarray(overrides.get("voxel_mm", h_mm), float), (3,)).copy()
    if not np.all(h > 0):
        raise InputError(f"voxel sizes must be > 0 mm, got {h.tolist()}")
    rotation = overrides.get("rotation")
    q = random_rotation(rng) if rotation is None else np.asarray(rotation, float)
    if q.shape != (3, 3) or not np.allclose(q.T @ q, np.eye(3), atol=1e-9):
        raise InputError(f"rotation must be a 3 x 3 orthogonal matrix, got {np.asarray(rotation).tolist()}")
    offset = rng.uniform(0.0, 1.0, size=3)
    wall_mm = float(overrides.get("wall_mm", 0.8 if case == "carotid" else 2.0))
    tis = Tissue.random(rng, wall_mm=wall_mm) if tissue else None
    margin = float(overrides.get("margin_mm", max(2 * float(h.max()), 4.0)))
    # the box around the tube (and its wall ring) over the visible range, in the grid's axes
    s = np.arange(visible[0], visible[1] + 0.5, 1.0)
    phi = np.linspace(-np.pi, np.pi, 48, endpoint=False)
    ss, pp = np.meshgrid(s, phi, indexing="ij")
    f = vessel.centreline.frame(ss)
    rr = (vessel.radius(ss, pp) + (wall_mm if tissue else 0.0))[..., None]
    wall = f.point + rr * (np.cos(pp)[..., None] * f.n1 + np.sin(pp)[..., None] * f.n2)
    coords = wall.reshape(-1, 3) @ q
    lo, hi = coords.min(axis=0) - margin, coords.max(axis=0) + margin
    if case == "leaving":
        lo, hi = _cut_at_apex(vessel, q, s, lo, hi)
    start = lo + (offset - 1.0) * h  # a random sub-voxel shift of the grid against the vessel
    shape = tuple(int(n) for n in np.ceil((hi - start) / h).astype(int) + 1)
    affine = np.eye(4)
    affine[:3, :3] = q * h
    affine[:3, 3] = q @ start
    period = float(vessel.flow.period_ms)
    times = np.arange(frames) * period / frames
    peak = vessel.peak_speed(
        visible[0], visible[1], np.concatenate([times, np.linspace(0, period, 128, endpoint=False)])
    )
    venc = float(overrides.get("venc_m_s", math.ceil(130.0 * peak) / 100.0))  # 1.3 x peak, up to the cm/s
    acq = acquire_volume(
        vessel,
        affine,
        shape,
        times,
        venc,
        snr,
        rng,
        tissue=tis,
        n_inner=int(overrides.get("n_inner", 3)),
        n_wall=int(overrides.get("n_wall", 12)),
        source=f"phantom:vessel-{case}",
        cardiac_period_ms=period,
    )
    vol = acq.volume
    params = {
        "case": case,
        "h_mm": float(h_mm),
        "voxel_mm": h.tolist(),
        "snr": None if snr is None else float(snr),
        "seed": int(seed),
        "tissue": bool(tissue),
        "frames": int(frames),
        "venc_m_s": venc,
        "peak_speed_m_s": peak,
        "visible_design_mm": [float(v) for v in visible],
        "overrides": {k: v for k, v in overrides.items() if k not in ("vessel", "rotation")},
        "counts": acq.counts,
    }
    vol.extra_attrs = {"phantom_case": case, "phantom_seed": int(seed), "phantom_snr": -1.0 if snr is None else snr}
    truth = VesselTruth(
        name=case,
        vessel=vessel,
        affine_mm=affine,
        shape=(shape[0], shape[1], shape[2]),
        times_ms=times,
        venc_m_s=(venc, venc, venc),
        lumen_fraction=acq.lumen_fraction,
        noise_free_velocity=acq.noise_free_velocity,
        noise_free_magnitude=acq.noise_free_magnitude,
        tissue=tis,
        parameters=params,
        visible=visible_ranges(vessel, affine, shape, visible[0] - 100.0, visible[1] + 100.0),
    )
    return vol, truth


def _cut_at_apex(vessel: Vessel, q: np.ndarray, s: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Move one box face to the centreline's extremum along its normal: the face (grid axis and side) where the
    centreline rises highest above both of its ends (the arch's apex), so that the vessel leaves through it and
    comes back."""
    u = vessel.centreline.point(s) @ q  # (ns, 3): the centreline in the grid's axes
    best = (-np.inf, 0, 1, 0)
    for k in range(3):
        for side in (1, -1):
            v = side * u[:, k]
            i = int(np.argmax(v))
            rise = v[i] - max(v[0], v[-1])
            if rise > best[0]:
                best = (rise, k, side, i)
    _, k, side, i = best
    lo, hi = lo.copy(), hi.copy()
    if side > 0:
        hi[k] = u[i, k]
    else:
        lo[k] = u[i, k]
    return lo, hi


# --------------------------------------------------------------- truth files
#: The value of the root attribute ``layout`` of a truth file.
TRUTH_LAYOUT = "vessel-truth"


@dataclass
class TruthGrid:
    """A truth file's contents (module docstring, "Truth file"): arrays on the ``(s, phi)`` grid and attributes."""

    s_mm: np.ndarray
    phi_rad: np.ndarray
    time_ms: np.ndarray
    centreline: dict
    wall: dict
    wss: dict
    visible_mm: np.ndarray
    attrs: dict


def write_truth(path, truth: VesselTruth, s_mm=None, phi=None) -> None:
    """Write ``truth`` on the grid ``s_mm`` x ``phi`` (default: the visible range's hull every 1 mm, 64 angles)."""
    from ..io.files import atomic_h5

    if s_mm is None:
        if truth.visible:
            lo, hi = min(v[0] for v in truth.visible), max(v[1] for v in truth.visible)
        else:
            lo, hi = truth.parameters.get("visible_design_mm", (0.0, truth.vessel.centreline.length))
        s_mm = np.linspace(lo, hi, max(2, int(round(hi - lo)) + 1))
    if phi is None:
        phi = np.linspace(-np.pi, np.pi, 64, endpoint=False)
    s_mm, phi = np.asarray(s_mm, float).ravel(), np.asarray(phi, float).ravel()
    ss, pp = np.meshgrid(s_mm, phi, indexing="ij")
    v = truth.vessel
    f = v.centreline.frame(s_mm)
    times = np.asarray(truth.times_ms, float)
    tawss, osi, _ = v.wss_cycle(ss, pp)
    with atomic_h5(path) as h5:
        h5.attrs["layout"] = TRUTH_LAYOUT
        h5.attrs["case"] = truth.name
        h5.attrs["affine_mm"] = np.asarray(truth.affine_mm, float)
        h5.attrs["shape"] = np.asarray(truth.shape, int)
        h5.attrs["viscosity_pa_s"] = v.flow.viscosity_pa_s
        h5.attrs["density_kg_m3"] = v.flow.density_kg_m3
        h5.attrs["venc_m_s"] = np.asarray(truth.venc_m_s, float)
        h5.attrs["cardiac_period_ms"] = v.flow.period_ms
        h5.attrs["parameters"] = json.dumps(truth.parameters, default=str)
        h5["s_mm"], h5["phi_rad"], h5["time_ms"] = s_mm, phi, times
        h5["centreline/point_mm"], h5["centreline/tangent"] = f.point, f.tangent
        h5["centreline/n1"], h5["centreline/n2"] = f.n1, f.n2
        h5["centreline/curvature_per_mm"] = np.stack([f.k1, f.k2], axis=1)
        h5["wall/radius_mm"] = v.radius(ss, pp)
        h5["wall/point_mm"] = v.wall_point(ss, pp)
        h5["wall/normal"] = v.normal(ss, pp)
        h5["wss/vector_pa"] = v.wss(ss, pp, times)
        h5["wss/axial_pa"] = v.axial_wss(ss, pp, times)
        h5["wss/tawss_pa"], h5["wss/osi"] = tawss, osi
        h5["visible_mm"] = np.asarray(truth.visible, float).reshape(-1, 2)


def read_truth(path) -> TruthGrid:
    """Read a truth file written by :func:`write_truth`; an :class:`InputError` names what is wrong."""
    import h5py

    src = str(path)
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{src}: cannot read as HDF5 ({exc})") from None
    with h5:
        if h5.attrs.get("layout", None) not in (TRUTH_LAYOUT, TRUTH_LAYOUT.encode()):
            raise InputError(f"{src}: not a vessel truth file (root attribute 'layout' is not '{TRUTH_LAYOUT}')")

        def get(name):
            if name not in h5:
                raise InputError(f"{src}: missing dataset '{name}'")
            return np.asarray(h5[name][()])

        groups = {g: {k: get(f"{g}/{k}") for k in h5[g]} if g in h5 else {} for g in ("centreline", "wall", "wss")}
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in h5.attrs.items()}
        if "parameters" in attrs:
            attrs["parameters"] = json.loads(attrs["parameters"])
        return TruthGrid(
            get("s_mm"), get("phi_rad"), get("time_ms"), groups["centreline"], groups["wall"], groups["wss"],
            get("visible_mm"), attrs,
        )  # fmt: skip


# ------------------------------------------------------------------ NIfTI
def write_volume_nifti(folder, vol: VolumeAcquisition) -> list[str]:
    """``mag.nii.gz`` and ``flow_vx/vy/vz.nii.gz`` with JSON sidecars, as a converter writes 4D flow.

    Data ``(x, y, z[, t])`` float32 on ``vol.affine_mm``; the velocity in m/s along the affine's world axes (the
    ``_vx/_vy/_vz`` names say which, as :func:`wss_nlp.io.nifti.component_of` reads them); frame interval in
    ``pixdim[4]`` (ms; xyzt units mm and msec). Sidecars: ``Manufacturer`` (``wss-nlp``: not a vendor's phase
    convention, so the plane route takes ``--phase-units m/s``), ``ImageType`` (``M`` or ``VELOCITY``),
    ``VelocityUnits`` ``m/s``, ``VelocityComponent`` ``x|y|z``, ``VelocityEncodingVelocity_m_s`` (venc),
    ``TriggerTimes_ms``. nibabel is needed (``pip install 'wss-nlp[nifti]'``).
    """
    from .scanner_exports import _save_nifti

    vol.validate()
    os.makedirs(folder, exist_ok=True)
    interval = None
    if vol.nt > 1:
        dt = np.diff(np.asarray(vol.trigger_times_ms, float))
        if np.ptp(dt) > 1e-6 * max(float(dt.mean()), 1e-12):
            raise InputError(
                f"{vol.source}: trigger times {np.asarray(vol.trigger_times_ms).tolist()} are not evenly spaced; "
                "NIfTI stores one frame interval (pixdim[4])"
            )
        interval = float(dt.mean())

    def data(arr):  # (nt, ni, nj, nk) -> (x, y, z[, t])
        out = np.moveaxis(np.asarray(arr, float), 0, -1).astype(np.float32)
        return out[..., 0] if vol.nt == 1 else out

    common: dict[str, object] = {
        "Manufacturer": "wss-nlp",
        "ManufacturersModelName": "synthetic 4D flow phantom",
        "ConversionSoftware": "wss_nlp.synthetic.vessels",
        "SeriesDescription": vol.source,
    }
    if vol.trigger_times_ms is not None:
        common["TriggerTimes_ms"] = [float(t) for t in vol.trigger_times_ms]
    if vol.cardiac_period_ms is not None:
        common["CardiacPeriod_ms"] = float(vol.cardiac_period_ms)
    items: list[tuple[str, np.ndarray, dict[str, object]]] = [
        ("mag", vol.magnitude, {"ImageType": ["ORIGINAL", "PRIMARY", "M", "ND"]})
    ]
    for c, axis in enumerate("xyz"):
        meta: dict[str, object] = {
            "ImageType": ["DERIVED", "PRIMARY", "VELOCITY", "ND"],
            "VelocityUnits": "m/s",
            "VelocityComponent": axis,
            "VelocityAxes": "world axes of the NIfTI affine",
        }
        if vol.venc_m_s is not None:
            meta["VelocityEncodingVelocity_m_s"] = float(vol.venc_m_s[c])
        items.append((f"flow_v{axis}", vol.velocity[:, c], meta))
    files = []
    for name, arr, meta in items:
        path = _save_nifti(os.path.join(folder, f"{name}.nii.gz"), data(arr), np.asarray(vol.affine_mm), interval)
        with open(os.path.join(folder, f"{name}.json"), "w") as fh:
            json.dump({**common, **meta}, fh, indent=1)
        files.append(path)
    return files
