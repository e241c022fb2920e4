"""Accuracy of a vessel wall map against a phantom's truth (issue 38's measures).

The truth is evaluated where the result's wall points are: :meth:`wss_nlp.synthetic.vessels.VesselTruth.locate`
gives each wall point's closest true wall point ``(s, phi)`` and signed distance (mm, positive outside), and the
true WSS, axial WSS, TAWSS and OSI are taken there. The visible part is the truth's (its centreline at least one
radius inside the field of view); sums are weighted by the wall area each point stands for
(:attr:`wss_nlp.vessel.reconstruct.VesselResult.area_mm2`).

* ``wss_rel_l2``: ``sqrt(sum a |tau - tau_true|^2 / sum a |tau_true|^2)`` over the covered visible wall, all
  frames;
* ``axial_rel_l2``: the same for ``tau . t`` (signed);
* ``wall_rms_mm`` (and ``wall_bias_mm``): the signed distance's RMS (mean) over the covered visible wall;
* ``coverage``: the area of the covered visible wall over the true visible wall's (the truth's wall surface over
  its visible s-intervals, :func:`visible_area`), so that a wall map that stops short of the visible part loses
  coverage too;
* ``tawss_rel_l2``, ``osi_rms``, ``osi_max`` (cines): TAWSS's relative L2 error, OSI's RMS and largest absolute
  error over the covered visible wall.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class VesselAccuracy:
    wss_rel_l2: float
    axial_rel_l2: float
    wall_rms_mm: float
    wall_bias_mm: float
    coverage: float
    tawss_rel_l2: float = float("nan")
    osi_rms: float = float("nan")
    osi_max: float = float("nan")
    mean_wss_pa: float = float("nan")  # area mean of |tau| over the covered visible wall (first frame)
    true_mean_wss_pa: float = float("nan")
    points: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


def visible_area(truth, ds: float = 0.25, n_phi: int = 256) -> float:
    """Area (mm^2) of the true wall over the truth's visible s-intervals: ``sum |x_s x x_phi| ds dphi`` with the
    tangents by central differences of :meth:`wss_nlp.synthetic.vessels.VesselTruth.wall_point` (midpoint rule;
    a :class:`SampledTruth` takes its own tangents: :meth:`SampledTruth.visible_area`)."""
    if isinstance(truth, SampledTruth):
        return truth.visible_area(ds)
    total = 0.0
    phi = np.linspace(-np.pi, np.pi, n_phi, endpoint=False) + np.pi / n_phi
    dphi = 2 * np.pi / n_phi
    for a, b in truth.visible:
        n = max(2, int(np.ceil((b - a) / ds)))
        step = (b - a) / n
        s = a + step * (np.arange(n) + 0.5)
        ss, pp = np.meshgrid(s, phi, indexing="ij")
        eps = 1e-4
        x_s = (truth.wall_point(ss + eps, pp) - truth.wall_point(ss - eps, pp)) / (2 * eps)
        x_p = (truth.wall_point(ss, pp + eps) - truth.wall_point(ss, pp - eps)) / (2 * eps)
        total += float(np.sum(np.linalg.norm(np.cross(x_s, x_p), axis=-1))) * step * dphi
    return total


def accuracy(result, truth) -> VesselAccuracy:
    """:class:`VesselAccuracy` of a :class:`wss_nlp.vessel.reconstruct.VesselResult` against a
    :class:`wss_nlp.synthetic.vessels.VesselTruth` (module notes)."""
    pts = result.wall_mm.reshape(-1, 3)
    s_t, phi_t, dist = truth.locate(pts, return_distance=True)
    visible = np.zeros(s_t.size, bool)
    for a, b in truth.visible:
        visible |= (s_t >= a) & (s_t <= b)
    area = result.area_mm2.ravel()
    covered = result.flags.ravel() == 0
    use = covered & visible
    coverage = float(np.sum(area[use]) / max(visible_area(truth), 1e-300))
    if not use.any():
        return VesselAccuracy(*(float("nan"),) * 4, coverage=coverage, points=0)
    a = area[use]
    nt = result.nt
    times = result.time_ms
    num = den = num_ax = den_ax = 0.0
    first_true = None
    for k in range(nt):
        t_ms = float(times[k]) if times.size == nt else None
        tau_true = truth.vessel.wss(s_t[use], phi_t[use], t_ms if t_ms is not None else 0.0)
        ax_true = truth.vessel.axial_wss(s_t[use], phi_t[use], t_ms if t_ms is not None else 0.0)
        tau = result.wss_pa[k].reshape(-1, 3)[use]
        ax = result.axial_pa[k].ravel()[use]
        num += float(np.sum(a * np.sum((tau - tau_true) ** 2, axis=1)))
        den += float(np.sum(a * np.sum(tau_true**2, axis=1)))
        num_ax += float(np.sum(a * (ax - ax_true) ** 2))
        den_ax += float(np.sum(a * ax_true**2))
        if k == 0:
            first_true = tau_true
    assert first_true is not None
    out = VesselAccuracy(
        wss_rel_l2=float(np.sqrt(num / den)),
        axial_rel_l2=float(np.sqrt(num_ax / den_ax)),
        wall_rms_mm=float(np.sqrt(np.sum(a * dist[use] ** 2) / np.sum(a))),
        wall_bias_mm=float(np.sum(a * dist[use]) / np.sum(a)),
        coverage=coverage,
        mean_wss_pa=float(np.sum(a * np.linalg.norm(result.wss_pa[0].reshape(-1, 3)[use], axis=1)) / np.sum(a)),
        true_mean_wss_pa=float(np.sum(a * np.linalg.norm(first_true, axis=1)) / np.sum(a)),
        points=int(use.sum()),
    )
    if result.tawss_pa is not None and nt > 1:
        tawss_true, osi_true, _ = truth.vessel.wss_cycle(s_t[use], phi_t[use])
        tawss = result.tawss_pa.ravel()[use]
        osi = result.osi.ravel()[use]
        out.tawss_rel_l2 = float(np.sqrt(np.sum(a * (tawss - tawss_true) ** 2) / np.sum(a * tawss_true**2)))
        out.osi_rms = float(np.sqrt(np.sum(a * (osi - osi_true) ** 2) / np.sum(a)))
        out.osi_max = float(np.max(np.abs(osi - osi_true)))
    return out


# ------------------------------------------------------------------ a truth file instead of the phantom
class _Surface:
    """Fields sampled on the truth file's grid ``s_i`` (uniform) x ``phi_j`` (``n`` equal steps from ``phi_0``),
    continued by a cubic spline in ``s`` and trigonometric interpolation in ``phi``:
    ``f(s, phi) = Re sum_k c_k(s) exp(i k (phi - phi_0))``, ``c_k(s)`` the splined DFT coefficients of the samples
    at each ``s_i`` (exact for fields of fewer than ``n / 2`` harmonics in ``phi``)."""

    def __init__(self, s: np.ndarray, phi: np.ndarray, values: np.ndarray):
        from scipy.interpolate import CubicSpline

        n = phi.size
        self.phi0 = float(phi[0])
        self.k = np.fft.fftfreq(n, 1.0 / n)
        c = np.fft.fft(np.asarray(values, float), axis=1) / n  # (ns, n, ...)
        self.re = CubicSpline(s, c.real, axis=0)
        self.im = CubicSpline(s, c.imag, axis=0)

    def __call__(self, s, phi, ds: int = 0, dphi: int = 0) -> np.ndarray:
        s, phi = np.broadcast_arrays(np.asarray(s, float), np.asarray(phi, float))
        c = self.re(s.ravel(), ds) + 1j * self.im(s.ravel(), ds)  # (m, n, ...)
        e = np.exp(1j * np.outer(phi.ravel() - self.phi0, self.k)) * (1j * self.k) ** dphi  # (m, n)
        out = np.einsum("mn,mn...->m...", e, c).real
        return out.reshape(*s.shape, *c.shape[2:])

    def with_tangents(self, s, phi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(f, df/ds, df/dphi)`` at the points ``(s, phi)`` (1-D), the exponentials and coefficients computed
        once for the three (what a Gauss-Newton step needs)."""
        s, phi = np.asarray(s, float), np.asarray(phi, float)
        c = self.re(s) + 1j * self.im(s)
        c_s = self.re(s, 1) + 1j * self.im(s, 1)
        e = np.exp(1j * np.outer(phi - self.phi0, self.k))
        f = np.einsum("mn,mn...->m...", e, c).real
        return f, np.einsum("mn,mn...->m...", e, c_s).real, np.einsum("mn,mn...->m...", e * (1j * self.k), c).real


class SampledTruth:
    """A vessel phantom's truth read from its truth file (``wss-nlp phantom --volume-case ... --truth FILE``; the
    layout of :func:`wss_nlp.synthetic.vessels.write_truth`), standing in for the phantom in :func:`accuracy`.

    The wall, the WSS vectors of every frame, TAWSS and OSI are continued between the samples by
    :class:`_Surface`; :meth:`locate` finds each point's closest wall point by Gauss-Newton on that surface.
    ``vessel`` is this object too, so ``truth.vessel.wss(s, phi, t_ms)`` reads as for a phantom; ``t_ms`` must be
    one of the file's frame times.
    """

    def __init__(self, path):
        import h5py

        from ..errors import InputError

        with h5py.File(path, "r") as f:
            if f.attrs.get("layout") != "vessel-truth":
                raise InputError(
                    f"{path}: not a vessel truth file (layout {f.attrs.get('layout')!r}); a vessel result is compared "
                    "with the truth of 'wss-nlp phantom --volume-case CASE --truth FILE'"
                )
            s, phi = f["s_mm"][()], f["phi_rad"][()]
            self.times_ms = np.atleast_1d(f["time_ms"][()]).astype(float)
            self.visible = [tuple(v) for v in f["visible_mm"][()].reshape(-1, 2)]
            self.case = str(f.attrs["case"])
            self.period_ms = float(f.attrs["cardiac_period_ms"])
            self._wall = _Surface(s, phi, f["wall/point_mm"][()])
            wss = f["wss/vector_pa"][()].reshape(self.times_ms.size, s.size, phi.size, 3)
            axial = f["wss/axial_pa"][()].reshape(self.times_ms.size, s.size, phi.size)
            self._wss = _Surface(s, phi, np.moveaxis(wss, 0, 2))  # (ns, nphi, nt, 3)
            self._axial = _Surface(s, phi, np.moveaxis(axial, 0, 2))
            self._cycle = _Surface(s, phi, np.stack([f["wss/tawss_pa"][()], f["wss/osi"][()]], axis=-1))
            centre = f["centreline/point_mm"][()]
        self._s, self._phi = s, phi
        self._centre = centre
        self.vessel = self

    def _frame(self, t_ms) -> int:
        k = int(np.argmin(np.abs(self.times_ms - float(t_ms))))
        if abs(self.times_ms[k] - float(t_ms)) > 1e-6 * max(self.period_ms, 1.0):
            raise ValueError(f"the truth has no frame at {float(t_ms):g} ms (its frames: {self.times_ms.tolist()})")
        return k

    def wall_point(self, s, phi) -> np.ndarray:
        return self._wall(s, phi)

    def wss(self, s, phi, t_ms=0.0) -> np.ndarray:
        return self._wss(s, phi)[..., self._frame(t_ms), :]

    def axial_wss(self, s, phi, t_ms=0.0) -> np.ndarray:
        return self._axial(s, phi)[..., self._frame(t_ms)]

    def wss_cycle(self, s, phi):
        both = self._cycle(s, phi)
        return both[..., 0], both[..., 1], None

    def locate(self, points, return_distance: bool = False, iterations: int = 30):
        """``(s, phi)`` of the closest sampled-wall point of each world point (and its signed distance, mm,
        positive outside: the side of the wall the centreline is not on)."""
        p = np.asarray(points, float).reshape(-1, 3)
        grid = self._wall(self._s[:, None], self._phi[None, :])  # the samples themselves
        from scipy.spatial import cKDTree

        _, nearest = cKDTree(grid.reshape(-1, 3)).query(p)
        s = self._s[nearest // self._phi.size].astype(float)
        phi = self._phi[nearest % self._phi.size].astype(float)
        lo, hi = float(self._s[0]), float(self._s[-1])
        beyond = np.zeros(s.size, bool)
        for _ in range(iterations):
            x, xs, xp = self._wall.with_tangents(s, phi)
            res = x - p
            a11, a12, a22 = np.sum(xs * xs, 1), np.sum(xs * xp, 1), np.sum(xp * xp, 1)
            b1, b2 = -np.sum(xs * res, 1), -np.sum(xp * res, 1)
            det = a11 * a22 - a12**2
            d_s, d_phi = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
            beyond = (s + d_s < lo) | (s + d_s > hi)
            s, phi = np.clip(s + d_s, lo, hi), phi + d_phi
            if max(np.max(np.abs(np.where(beyond, 0.0, d_s))), 20.0 * np.max(np.abs(d_phi))) < 1e-8:
                break  # 1e-8 mm: the interpolant's own rounding; quadratic convergence gets there in a few steps
        # a point whose closest wall point lies past the sampled arclengths is not located: NaN (never visible)
        s = np.where(beyond, np.nan, s)
        phi = np.angle(np.exp(1j * phi))
        at = np.clip(np.nan_to_num(s, nan=lo), lo, hi)
        wall, x_s, x_phi = self._wall.with_tangents(at, phi)
        normal = np.cross(x_s, x_phi)
        axis = wall - self._centre_at(at)
        # the surface normal x_s x x_phi points outwards or inwards depending on the parametrization: orient it
        # by the centreline, which is inside the lumen
        normal *= np.sign(np.sum(normal * axis, axis=1))[:, None]
        dist = np.linalg.norm(p - wall, axis=1) * np.sign(np.sum((p - wall) * normal, axis=1))
        dist[beyond] = np.nan
        return (s, phi, dist) if return_distance else (s, phi)

    def visible_area(self, ds: float = 0.25) -> float:
        """Area (mm^2) of the wall over the visible s-intervals: midpoint rule in ``s``, the file's angles in
        ``phi`` (the trapezoid rule of a periodic function: exact for the interpolant's harmonics), tangents
        from the interpolant's derivatives."""
        total = 0.0
        dphi = 2 * np.pi / self._phi.size
        for a, b in self.visible:
            n = max(2, int(np.ceil((b - a) / ds)))
            step = (b - a) / n
            ss, pp = np.meshgrid(a + step * (np.arange(n) + 0.5), self._phi, indexing="ij")
            x_s, x_p = self._wall(ss, pp, ds=1), self._wall(ss, pp, dphi=1)
            total += float(np.sum(np.linalg.norm(np.cross(x_s, x_p), axis=-1))) * step * dphi
        return total

    def _centre_at(self, s) -> np.ndarray:
        return np.stack([np.interp(s, self._s, self._centre[:, j]) for j in range(3)], axis=1)


def read_truth(path) -> SampledTruth:
    """The truth file of a vessel phantom (:class:`SampledTruth`)."""
    return SampledTruth(path)
