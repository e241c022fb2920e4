"""The centreline of a vessel: an arclength-parametrized spline with a rotation-minimizing frame, from points,
a file or a lumen mask.

Notes
-----
Representation. :meth:`Centerline.from_points` fits a cubic smoothing spline ``X(u)`` through the ordered points
(chord-length parameter ``u``; FITPACK's ``splprep`` with ``sum |w_i (X(u_i) - p_i)|^2 <= n``, ``w_i = 1 /
sigma_i``, so that ``sigma`` is the RMS distance the spline may keep from the points; no smoothing interpolates).
Its arclength ``s(u) = int_0^u |X'|`` is integrated by 5-point Gauss-Legendre on a fine grid, inverted by cubic
Hermite interpolation with the exact slopes ``du/ds = 1 / |X'(u)|``, and the curve is resampled at ``N`` equally
spaced ``s_i`` and stored as the quintic interpolating spline ``P(s)`` through ``X(u(s_i))``: ``|P'(s)| = 1`` to
the interpolation error (below 1e-6 for curves sampled finer than their curvature radius), and every derivative
of ``P`` is exact for that spline. The stored samples ``(s_i, P_i, N_i)`` define the object: :meth:`write` /
:meth:`read` round-trip it bit for bit.

Frame. ``t = P' / |P'|``. The normal ``n1`` is rotation-minimizing (parallel transport: ``n1' = -(n1 . t') t``,
no twist about ``t``), computed on the samples by the double-reflection method (Wang, Juettler, Zheng, Liu,
"Computation of rotation minimizing frames", ACM TOG 27(1), 2008) and stored as the quintic spline ``N(s)``;
``n1 = (N - (N . t) t) / |N - (N . t) t|`` and ``n2 = t x n1``, so ``(t, n1, n2)`` is orthonormal and right-handed
and its derivatives (:meth:`Centerline.frame_derivative`) are those of these formulas, exact for the
representation. Rule at ``s = 0``: ``n1(0) = (t(0) x a) / |t(0) x a|`` with ``a`` the world axis least aligned
with ``t(0)`` (the rule of :meth:`wss_nlp.io.plane.Plane.axes` for the plane normal to ``t(0)``).

Coordinates. A point ``x`` has ``(s, r, phi)`` with ``P(s)`` the closest centreline point, ``r = |x - P(s)|`` and
``phi`` the angle of ``x - P(s)`` from ``n1`` towards ``n2`` (counter-clockwise about ``t``): ``x = P(s) + r (cos
phi n1(s) + sin phi n2(s))`` (:meth:`Centerline.to_world`). :meth:`Centerline.project` finds ``s`` by Newton's
method on ``f(s) = (P(s) - x) . P'(s)`` from the nearest sample; ``f' = |P'|^2 + (P - x) . P'' > 0`` when ``r`` is
below the curvature radius, where the closest point is unique.

From a mask (:func:`centerline_from_mask`), with SciPy only: a minimal-path skeleton in the spirit of TEASAR
(Sato, Bitter, Kaufman, Wan, "TEASAR: tree-structure extraction algorithm for accurate and robust skeletons",
Pacific Graphics 2000), chosen over a thinning skeleton (scikit-image's ``skeletonize``) because it gives paths,
not voxel sets to repair (thinning leaves spurs from every surface bump and loops from every hole, which need
pruning rules of their own), and needs no new dependency. The lumen voxels form a graph (26 neighbours, edge
lengths in world mm from the affine); an edge costs its length times ``(1 / D^2)`` averaged over its ends, with
``D`` the Euclidean distance transform (mm), so minimal paths run along the middle of every vessel, thick or thin.
From a root, the voxel geodesically farthest and not yet covered is traced back along the minimal paths to the
tree; the voxels within ``1.5 D + h`` of the new path are covered; a path shorter than the parent's radius plus
``min_branch_mm`` is a surface bump, not a branch. The main vessel is the tree's longest path weighted by ``D``
(``int D ds``, the thickest long path, found by two sweeps over the tree), re-traced as the minimal path between
its two ends. The voxel path is then made sub-voxel: at stations about a voxel apart the mask is sampled in the
plane normal to the spline (nearest voxel, a grid of a quarter of the smallest voxel), and where that cross-section
is clean (no lumen in a ring just outside the distance-transform radius, the disk inside the field of view) its
centroid is the centre and ``sqrt(area / pi)`` the radius; elsewhere (near branches, at the border) the spline
keeps the voxel path with a looser weight. Two such rounds. Side branches are reported where their paths leave
the main lumen.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

#: Samples of the arclength resampling per input point (at least :data:`MIN_SAMPLES` in all).
SAMPLES_PER_POINT = 8
MIN_SAMPLES = 256
#: Newton iterations of :meth:`Centerline.project` (quadratic convergence from the nearest sample).
NEWTON_STEPS = 8
#: The wall region flagged around a branch: this many branch radii along s (and the matching angle).
BRANCH_FLAG_RADII = 1.5


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum(a * b, axis=-1, keepdims=True)


def initial_normal(t0: np.ndarray) -> np.ndarray:
    """``n1(0) = (t0 x a) / |t0 x a|``, ``a`` the world axis least aligned with ``t0`` (module notes)."""
    t0 = np.asarray(t0, float) / np.linalg.norm(t0)
    a = np.eye(3)[int(np.argmin(np.abs(t0)))]
    return _unit(np.cross(t0, a))


def rotation_minimizing(points: np.ndarray, tangents: np.ndarray, n0: np.ndarray) -> np.ndarray:
    """Rotation-minimizing normals at ``points (N, 3)`` with unit ``tangents`` from ``n0``: double reflection."""
    n = np.empty_like(points)
    n[0] = n0 - np.dot(n0, tangents[0]) * tangents[0]
    n[0] /= np.linalg.norm(n[0])
    for i in range(len(points) - 1):
        v1 = points[i + 1] - points[i]
        c1 = float(v1 @ v1)
        if c1 == 0.0:
            n[i + 1] = n[i]
            continue
        r_l = n[i] - (2.0 / c1) * float(v1 @ n[i]) * v1
        t_l = tangents[i] - (2.0 / c1) * float(v1 @ tangents[i]) * v1
        v2 = tangents[i + 1] - t_l
        c2 = float(v2 @ v2)
        n[i + 1] = r_l if c2 < 1e-300 else r_l - (2.0 / c2) * float(v2 @ r_l) * v2
    return n


@dataclass(frozen=True)
class Projection:
    """Centreline coordinates of points: ``s`` (mm), ``r`` (mm), ``phi`` (rad), and where a point lies past an end.

    Unpacks as ``s, r, phi = centerline.project(x)``. ``beyond`` is -1 for a point before ``s = 0``, +1 after
    ``s = length``, 0 otherwise; ``axial_mm`` its distance past that end along the end's tangent (0 inside). For
    points past an end ``s`` is clamped and ``r`` is the full distance to the end point.
    """

    s: np.ndarray
    r: np.ndarray
    phi: np.ndarray
    beyond: np.ndarray
    axial_mm: np.ndarray

    def __iter__(self):
        return iter((self.s, self.r, self.phi))


class Centerline:
    """A vessel centreline ``P(s)``, ``s`` in ``[0, length_mm]`` the arclength in mm, with a rotation-minimizing
    frame (module notes). Build with :meth:`from_points`, :meth:`from_file`, :meth:`read` or
    :func:`centerline_from_mask`; the constructor takes the stored samples."""

    def __init__(self, s_mm: np.ndarray, points_mm: np.ndarray, normals: np.ndarray | None = None, source: str = ""):
        from scipy.interpolate import make_interp_spline
        from scipy.spatial import cKDTree

        s = np.asarray(s_mm, float).ravel()
        x = np.asarray(points_mm, float)
        if x.shape != (s.size, 3) or s.size < 6 or s[0] != 0.0 or np.any(np.diff(s) <= 0):
            raise InputError(f"{source or 'centerline'}: samples must be (n >= 6, 3) at increasing s from 0")
        self.source = source
        self._s = s
        self._x = x
        self._p = make_interp_spline(s, x, k=5)
        self._dp = [self._p.derivative(nu) for nu in (1, 2, 3)]
        if normals is None:
            t = _unit(self._dp[0](s))
            normals = rotation_minimizing(x, t, initial_normal(t[0]))
        self._n = np.asarray(normals, float)
        self._N = make_interp_spline(s, self._n, k=5)
        self._dN = self._N.derivative(1)
        self._tree = cKDTree(x)

    # --- construction -------------------------------------------------------------------------------------------
    @classmethod
    def from_points(cls, points_mm: np.ndarray, smoothing_mm: float | None = None, source: str = "") -> Centerline:
        """A smoothing cubic spline through ordered points ``(n, 3)`` (world mm), reparametrized by arclength.

        ``smoothing_mm``: the RMS distance the spline may keep from the points (None: through every point).
        """
        pts = np.asarray(points_mm, float)
        where = source or "centerline points"
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 2:
            raise InputError(f"{where}: need at least 2 points as an (n, 3) array of x, y, z (mm), got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise InputError(f"{where}: the points hold NaN or Inf")
        if smoothing_mm is not None and not smoothing_mm >= 0:
            raise InputError(f"{where}: smoothing {smoothing_mm} mm must be >= 0")
        sigma = None if not smoothing_mm else np.full(len(pts), float(smoothing_mm))
        return cls._fit(pts, sigma, where)

    @classmethod
    def _fit(cls, pts: np.ndarray, sigma: np.ndarray | None, where: str) -> Centerline:
        """Spline through ``pts`` with per-point tolerances ``sigma`` (mm; None interpolates), resampled in s."""
        from scipy.interpolate import CubicHermiteSpline, splev, splprep

        step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        keep = np.concatenate([[True], step > 1e-9 * max(float(step.max(initial=0.0)), 1e-300)])
        pts = pts[keep]
        if sigma is not None:
            sigma = np.asarray(sigma, float)[keep]
        if len(pts) < 2:
            raise InputError(f"{where}: the points coincide; need a curve")
        chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        u = chord / chord[-1]
        k = min(3, len(pts) - 1)
        if sigma is None:
            tck, _ = splprep(pts.T, u=u, k=k, s=0.0)
        else:
            tck, _ = splprep(pts.T, u=u, w=1.0 / sigma, k=k, s=float(len(pts)))
        # arclength on a fine grid of u: 5-point Gauss-Legendre on each cell
        fine = np.linspace(0.0, 1.0, max(64 * len(pts), 2048) + 1)
        g, gw = np.polynomial.legendre.leggauss(5)
        a, b = fine[:-1, None], fine[1:, None]
        nodes = 0.5 * (a + b) + 0.5 * (b - a) * g
        speed = np.linalg.norm(np.asarray(splev(nodes.ravel(), tck, der=1)), axis=0).reshape(nodes.shape)
        cell = 0.5 * (b - a)[:, 0] * (speed @ gw)
        s_of_u = np.concatenate([[0.0], np.cumsum(cell)])
        length = float(s_of_u[-1])
        if not length > 0:
            raise InputError(f"{where}: the curve has zero length")
        du_ds = 1.0 / np.linalg.norm(np.asarray(splev(fine, tck, der=1)), axis=0)
        u_of_s = CubicHermiteSpline(s_of_u, fine, du_ds)
        n = max(MIN_SAMPLES, SAMPLES_PER_POINT * len(pts))
        s = np.linspace(0.0, length, n)
        x = np.asarray(splev(np.clip(u_of_s(s), 0.0, 1.0), tck)).T
        return cls(s, x, source=where)

    def reversed(self) -> Centerline:
        """The same curve traversed from its other end (``s' = length - s``), its frame by the rule at the new start."""
        return Centerline(self.length_mm - self._s[::-1], self._x[::-1], None, self.source)

    # --- geometry ------------------------------------------------------------------------------------------------
    @property
    def length_mm(self) -> float:
        return float(self._s[-1])

    @property
    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """The stored samples ``(s (N,), P (N, 3))``."""
        return self._s.copy(), self._x.copy()

    def position(self, s, nu: int = 0) -> np.ndarray:
        """``d^nu P / ds^nu`` at ``s (m,)`` -> ``(m, 3)`` (``nu`` 0 to 3; outside ``[0, length]`` the end
        polynomials extrapolate)."""
        s = np.atleast_1d(np.asarray(s, float))
        if nu == 0:
            return self._p(s)
        if nu not in (1, 2, 3):
            raise ValueError(f"nu must be 0, 1, 2 or 3, got {nu}")
        return self._dp[nu - 1](s)

    def _frame_parts(self, s):
        s = np.atleast_1d(np.asarray(s, float))
        d1, d2 = self._dp[0](s), self._dp[1](s)
        speed = np.linalg.norm(d1, axis=-1, keepdims=True)
        t = d1 / speed
        dt = (d2 - t * _dot(t, d2)) / speed
        N, dN = self._N(s), self._dN(s)
        m = N - _dot(N, t) * t
        norm_m = np.linalg.norm(m, axis=-1, keepdims=True)
        n1 = m / norm_m
        n2 = np.cross(t, n1)
        return t, dt, N, dN, m, norm_m, n1, n2

    def frame(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t, n1, n2)`` at ``s (m,)``, each ``(m, 3)``: unit tangent and the rotation-minimizing normals."""
        t, _, _, _, _, _, n1, n2 = self._frame_parts(s)
        return t, n1, n2

    def frame_derivative(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t', n1', n2')`` (1/mm) at ``s``: the exact s-derivatives of :meth:`frame`'s formulas (module notes)."""
        t, dt, N, dN, m, norm_m, n1, n2 = self._frame_parts(s)
        dm = dN - (_dot(dN, t) + _dot(N, dt)) * t - _dot(N, t) * dt
        dn1 = (dm - n1 * _dot(n1, dm)) / norm_m
        dn2 = np.cross(dt, n1) + np.cross(t, dn1)
        return dt, dn1, dn2

    def curvature(self, s) -> np.ndarray:
        """Curvature ``|t'(s)|`` (1/mm)."""
        return np.linalg.norm(self.frame_derivative(s)[0], axis=-1)

    # --- coordinates ---------------------------------------------------------------------------------------------
    def project(self, points_mm) -> Projection:
        """``(s, r, phi)`` of points ``(m, 3)`` (module notes); points past an end get ``s`` clamped and marked."""
        x = np.asarray(points_mm, float).reshape(-1, 3)
        _, nearest = self._tree.query(x)
        h = float(self._s[1] - self._s[0])
        lo = np.maximum(self._s[nearest] - 2 * h, 0.0)
        hi = np.minimum(self._s[nearest] + 2 * h, self.length_mm)
        s = self._s[nearest].copy()
        for _ in range(NEWTON_STEPS):
            d = self._p(s) - x
            d1, d2 = self._dp[0](s), self._dp[1](s)
            f = np.sum(d * d1, axis=1)
            fp = np.sum(d1 * d1, axis=1) + np.sum(d * d2, axis=1)
            step = np.where(fp > 0, f / np.where(fp > 0, fp, 1.0), 0.0)
            s = np.clip(s - step, lo, hi)
        d = x - self._p(s)
        t, n1, n2 = self.frame(s)
        axial = np.sum(d * t, axis=1)
        tol = 1e-6 * max(self.length_mm, 1.0)
        beyond = np.where((s <= 0.0) & (axial < -tol), -1, np.where((s >= self.length_mm) & (axial > tol), 1, 0))
        return Projection(
            s=s,
            r=np.linalg.norm(d, axis=1),
            phi=np.arctan2(np.sum(d * n2, axis=1), np.sum(d * n1, axis=1)),
            beyond=beyond,
            axial_mm=np.where(beyond != 0, np.abs(axial), 0.0),
        )

    def to_world(self, s, r, phi) -> np.ndarray:
        """``P(s) + r (cos phi n1(s) + sin phi n2(s))`` for arrays ``s, r, phi`` of one shape ``(m,)`` -> ``(m, 3)``."""
        s, r, phi = np.broadcast_arrays(*(np.atleast_1d(np.asarray(v, float)) for v in (s, r, phi)))
        _, n1, n2 = self.frame(s.ravel())
        offset = r.ravel()[:, None] * (np.cos(phi.ravel())[:, None] * n1 + np.sin(phi.ravel())[:, None] * n2)
        return self._p(s.ravel()) + offset

    # --- files ---------------------------------------------------------------------------------------------------
    def write(self, group) -> None:
        """Store in an h5py group: ``s_mm (N,)``, ``points_mm (N, 3)`` (world mm), ``normals (N, 3)``."""
        group.attrs["kind"] = "centerline"
        group.attrs["length_mm"] = self.length_mm
        group.attrs["source"] = self.source
        group.create_dataset("s_mm", data=self._s)
        group.create_dataset("points_mm", data=self._x)
        group.create_dataset("normals", data=self._n)

    @classmethod
    def read(cls, group) -> Centerline:
        """The centreline :meth:`write` stored (bit-identical)."""
        where = getattr(group, "name", "centerline group")
        for name in ("s_mm", "points_mm", "normals"):
            if name not in group:
                raise InputError(f"{where}: missing dataset '{name}' of a centerline")
        source = group.attrs.get("source", "")
        return cls(
            np.asarray(group["s_mm"][()], float),
            np.asarray(group["points_mm"][()], float),
            np.asarray(group["normals"][()], float),
            source.decode() if isinstance(source, bytes) else str(source),
        )

    @classmethod
    def from_file(cls, path, smoothing_mm: float | None = None) -> Centerline:
        """``--centerline FILE``: a CSV of x, y, z (world mm; header optional) or a VTK polyline, ordered along
        the vessel (:func:`read_polyline`), through :meth:`from_points`."""
        return cls.from_points(read_polyline(path), smoothing_mm, source=os.fspath(path))

    def save(self, path, spacing_mm: float | None = None) -> str:
        """Write points along the centreline every ``spacing_mm`` (default: the stored samples) as CSV (``.csv``)
        or a legacy ASCII VTK polyline (``.vtk``), both read back by :meth:`from_file`."""
        path = os.fspath(path)
        s = (
            self._s
            if spacing_mm is None
            else np.linspace(0, self.length_mm, int(np.ceil(self.length_mm / spacing_mm)) + 1)
        )
        x = self.position(s)
        if path.lower().endswith(".csv"):
            np.savetxt(path, x, delimiter=",", header="x,y,z", comments="", fmt="%.9g")
        elif path.lower().endswith(".vtk"):
            write_vtk_polyline(path, x)
        else:
            raise InputError(f"{path}: write a centerline as .csv or .vtk")
        return path


# --- polyline files ----------------------------------------------------------------------------------------------
def write_vtk_polyline(path, points: np.ndarray) -> None:
    """A legacy ASCII VTK POLYDATA file with one polyline through ``points (n, 3)``."""
    n = len(points)
    with open(path, "w") as fh:
        fh.write("# vtk DataFile Version 3.0\nwss-nlp centerline (world mm)\nASCII\nDATASET POLYDATA\n")
        fh.write(f"POINTS {n} double\n")
        np.savetxt(fh, points, fmt="%.9g")
        fh.write(f"LINES 1 {n + 1}\n{n} " + " ".join(str(i) for i in range(n)) + "\n")


def _read_csv(path: str) -> np.ndarray:
    with open(path) as fh:
        lines = [ln.strip() for ln in fh if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError(f"{path}: empty; give x, y, z (mm) on each line")

    def split(line):
        return [v.strip() for v in line.replace(";", ",").replace("\t", ",").split(",")] if "," in line or ";" in line \
            or "\t" in line else line.split()  # fmt: skip

    columns = [0, 1, 2]
    first = split(lines[0])
    try:
        [float(v) for v in first]
    except ValueError:
        names = [v.strip().strip('"').lower() for v in first]
        if all(c in names for c in "xyz"):
            columns = [names.index(c) for c in "xyz"]
        lines = lines[1:]
    rows = []
    for number, line in enumerate(lines, start=1):
        values = split(line)
        try:
            rows.append([float(values[c]) for c in columns])
        except (ValueError, IndexError):
            raise InputError(f"{path}: line {number} {line!r} is not x, y, z numbers (mm)") from None
    return np.asarray(rows, float).reshape(-1, 3)


def _chain(segments: np.ndarray, path: str) -> np.ndarray:
    """Order 2-point line segments ``(m, 2)`` into one path of point indices; anything but one path is refused."""
    from collections import defaultdict

    adjacent: dict[int, list[int]] = defaultdict(list)
    for a, b in segments:
        adjacent[int(a)].append(int(b))
        adjacent[int(b)].append(int(a))
    ends = [v for v, nb in adjacent.items() if len(nb) == 1]
    if any(len(nb) > 2 for nb in adjacent.values()) or len(ends) != 2:
        raise InputError(f"{path}: the lines branch, close or break; give one ordered polyline along the vessel")
    order = [min(ends)]
    previous = -1
    while len(order) < len(adjacent):
        nxt = [v for v in adjacent[order[-1]] if v != previous]
        if not nxt:
            break
        previous = order[-1]
        order.append(nxt[0])
    if len(order) != len(adjacent):
        raise InputError(f"{path}: the lines do not form one connected polyline")
    return np.asarray(order)


def _read_legacy_polydata(path: str) -> np.ndarray | None:
    """Points of the one polyline of an ASCII legacy VTK POLYDATA file, or None if the file is not one."""
    with open(path, "rb") as fh:
        head = fh.read(1024)
    if b"POLYDATA" not in head or b"ASCII" not in head:
        return None
    with open(path) as fh:  # closed here: an open file left to the collector is a ResourceWarning
        tokens = fh.read().split()
    upper = [t.upper() for t in tokens]
    try:
        at = upper.index("POINTS")
        n = int(tokens[at + 1])
        points = np.asarray(tokens[at + 3 : at + 3 + 3 * n], float).reshape(n, 3)
    except (ValueError, IndexError):
        raise InputError(f"{path}: unreadable POINTS section of a VTK POLYDATA file") from None
    if "LINES" not in upper:
        return points
    at = upper.index("LINES")
    count = int(tokens[at + 1])
    values = [int(v) for v in tokens[at + 3 : at + 3 + int(tokens[at + 2])]]
    lines, i = [], 0
    for _ in range(count):
        lines.append(values[i + 1 : i + 1 + values[i]])
        i += 1 + values[i]
    if len(lines) == 1:
        return points[np.asarray(lines[0])]
    if all(len(line) == 2 for line in lines):
        return points[_chain(np.asarray(lines), path)]
    raise InputError(
        f"{path}: {len(lines)} polylines (e.g. one per outlet, as VMTK writes them); keep the one along the vessel"
    )


def read_polyline(path) -> np.ndarray:
    """Ordered points ``(n, 3)`` (world mm) of a centreline file: ``.csv``/``.txt`` (x, y, z a line, header
    optional, columns named x, y, z or the first three), ``.vtk`` (ASCII legacy POLYDATA with one polyline, read
    here; other legacy VTK and ``.vtu`` through meshio, optional extra ``vtk``, as 2-point line cells chained in
    order, or the points in file order when there are no cells).

    meshio 5 reads neither legacy POLYDATA nor VTK XML PolyData (``.vtp``, VMTK's default) nor VTK_POLY_LINE
    cells, so ``.vtp`` is refused with the fix (save as legacy ``.vtk`` or CSV).
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(f"{path}: no such file (--centerline)")
    low = path.lower()
    if low.endswith((".csv", ".txt")):
        return _read_csv(path)
    if low.endswith(".vtp"):
        raise InputError(
            f"{path}: VTK XML PolyData (.vtp) is not read; save the centreline as legacy ASCII .vtk (e.g. VMTK's "
            "vmtksurfacewriter/vmtkcenterlines -ofile name.vtk) or as CSV of x, y, z (mm)"
        )
    if not low.endswith((".vtk", ".vtu")):
        raise InputError(f"{path}: give the centreline as .csv (x, y, z in mm) or a VTK polyline (.vtk, .vtu)")
    if low.endswith(".vtk"):
        found = _read_legacy_polydata(path)
        if found is not None:
            return found
    try:
        import meshio
    except ImportError:
        raise InputError(
            f"{path}: reading VTK needs meshio, an optional dependency: pip install 'wss-nlp[vtk]' (or give a CSV)"
        ) from None
    try:
        mesh = meshio.read(path)
    except Exception as exc:  # meshio raises several types for files it cannot read
        raise InputError(f"{path}: not a VTK file meshio reads ({type(exc).__name__}: {exc}); give a CSV") from None
    points = np.asarray(mesh.points, float)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InputError(f"{path}: points of shape {points.shape}; a centreline needs x, y, z")
    points = points[:, :3]
    lines = [c.data for c in mesh.cells if c.type == "line"]
    others = [c.type for c in mesh.cells if c.type not in ("line", "vertex")]
    if others:
        raise InputError(f"{path}: holds {', '.join(sorted(set(others)))} cells; a centreline is a polyline")
    if not lines:
        return points
    return points[_chain(np.concatenate(lines), path)]


# --- from a mask ----------------------------------------------------------------------------------------------------
#: Half of the 26 neighbour offsets (the other half are their negatives).
_OFFSETS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) > (0, 0, 0)])
#: The 8 corners of a voxel cell.
_OFFSETS_CUBE = np.array([(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)])


@dataclass
class _Graph:
    """The lumen voxels as a graph: voxel indices, world positions, distance transform and two edge weightings."""

    index: np.ndarray  # (n, 3) voxel indices
    world: np.ndarray  # (n, 3) mm
    dt: np.ndarray  # (n,) mm
    cost: object  # csr (n, n): length x mean(1 / D^2)
    length: object  # csr (n, n): length in mm
    dt_field: np.ndarray  # (ni, nj, nk) mm


def _lumen_graph(mask: np.ndarray, affine: np.ndarray) -> _Graph:
    import scipy.ndimage as ndi
    from scipy.sparse import coo_matrix

    a3 = np.asarray(affine, float)[:3, :3]
    spacing = np.linalg.norm(a3, axis=0)
    gram = (a3.T @ a3) / np.outer(spacing, spacing)
    if np.abs(gram - np.eye(3)).max() > 1e-3:
        log.warning("the voxel axes are not orthogonal; the distance transform uses the axes' lengths only")
    dt_field = ndi.distance_transform_edt(mask, sampling=spacing)
    index = np.argwhere(mask)
    lookup = np.full(mask.shape, -1, dtype=np.int64)
    lookup[tuple(index.T)] = np.arange(len(index))
    world = index @ a3.T + np.asarray(affine, float)[:3, 3]
    dt = dt_field[tuple(index.T)]
    rows, cols, lengths = [], [], []
    shape = np.asarray(mask.shape)
    for o in _OFFSETS:
        q = index + o
        ok = np.all((q >= 0) & (q < shape), axis=1)
        j = np.full(len(index), -1)
        j[ok] = lookup[tuple(q[ok].T)]
        hit = j >= 0
        rows.append(np.flatnonzero(hit))
        cols.append(j[hit])
        lengths.append(np.full(int(hit.sum()), float(np.linalg.norm(a3 @ o))))
    r, c, ln = np.concatenate(rows), np.concatenate(cols), np.concatenate(lengths)
    n = len(index)
    penalty = 1.0 / dt**2
    cost = coo_matrix((ln * 0.5 * (penalty[r] + penalty[c]), (r, c)), shape=(n, n)).tocsr()
    length = coo_matrix((ln, (r, c)), shape=(n, n)).tocsr()
    return _Graph(index, world, dt, cost, length, dt_field)


def _trace(pred: np.ndarray, start: int, stop: np.ndarray) -> list[int]:
    """Nodes from ``start`` along the predecessors until one where ``stop`` is True (included)."""
    path = [start]
    while not stop[path[-1]]:
        p = int(pred[path[-1]])
        if p < 0:
            break
        path.append(p)
    return path


def _path_length(world: np.ndarray, path) -> float:
    return float(np.sum(np.linalg.norm(np.diff(world[np.asarray(path)], axis=0), axis=1)))


def _teasar(g: _Graph, root: int, h: float, min_branch_mm: float, first: int | None = None) -> list[list[int]]:
    """Minimal-path tree from ``root``: paths (tip first, ending on the tree), the first to ``first`` if given."""
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    _, pred = dijkstra(g.cost, directed=False, indices=root, return_predecessors=True)
    geodesic = dijkstra(g.length, directed=False, indices=root)
    tree = cKDTree(g.world)
    covered = ~np.isfinite(geodesic)  # voxels not connected to the root are not this tree's
    on_tree = np.zeros(len(g.dt), bool)
    on_tree[root] = True
    paths: list[list[int]] = []
    while True:
        if first is not None and not paths:
            tip = first
        else:
            candidate = np.where(covered, -np.inf, geodesic)
            tip = int(np.argmax(candidate))
            if not np.isfinite(candidate[tip]):
                break
        path = _trace(pred, tip, on_tree)
        near = tree.query_ball_point(g.world[path], r=1.5 * g.dt[path] + h)
        covered[np.concatenate([np.asarray(v, dtype=np.int64) for v in near] + [np.asarray(path)])] = True
        junction = path[-1]
        if not paths or _path_length(g.world, path) - g.dt[junction] > min_branch_mm:
            on_tree[path] = True
            paths.append(path)
    return paths


def _tree_longest(g: _Graph, paths: list[list[int]]) -> tuple[int, int]:
    """The two ends of the tree's longest path weighted by the distance transform (``int D ds``): two sweeps."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    a = np.concatenate([p[:-1] for p in paths if len(p) > 1])
    b = np.concatenate([p[1:] for p in paths if len(p) > 1])
    w = np.linalg.norm(g.world[a] - g.world[b], axis=1) * 0.5 * (g.dt[a] + g.dt[b])
    n = len(g.dt)
    graph = coo_matrix((w, (a, b)), shape=(n, n)).tocsr()
    d = dijkstra(graph, directed=False, indices=int(a[0]))
    end1 = int(np.argmax(np.where(np.isfinite(d), d, -1)))
    d = dijkstra(graph, directed=False, indices=end1)
    end2 = int(np.argmax(np.where(np.isfinite(d), d, -1)))
    return end1, end2


@dataclass
class _Sections:
    s: np.ndarray
    centre: np.ndarray  # (m, 3) refined centre (or the spline's point where not clean)
    clean: np.ndarray  # (m,) bool
    radius_area: np.ndarray  # (m,) mm, NaN where not clean
    radius_dt: np.ndarray  # (m,) mm


def _sections(cl: Centerline, mask: np.ndarray, affine: np.ndarray, dt_field: np.ndarray, step: float) -> _Sections:
    """Cross-sections of the mask normal to ``cl`` every ``step`` mm (module notes)."""
    import scipy.ndimage as ndi

    a = np.asarray(affine, float)
    inverse = np.linalg.inv(a)
    spacing = np.linalg.norm(a[:3, :3], axis=0)
    h_min, h_max = float(spacing.min()), float(spacing.max())
    m = max(int(np.ceil(cl.length_mm / step)) + 1, 2)
    s = np.linspace(0.0, cl.length_mm, m)
    centres = cl.position(s)
    _, n1, n2 = cl.frame(s)
    index = centres @ inverse[:3, :3].T + inverse[:3, 3]
    # the distance transform's ridge near each centre: its largest value on the 8 voxels around it (interpolating
    # would cut the ridge's peak, by about 0.4 voxel on straight tubes)
    corners = np.floor(index).astype(int)[:, None, :] + _OFFSETS_CUBE[None]
    corners = np.clip(corners, 0, np.asarray(mask.shape) - 1)
    dt = dt_field[corners[..., 0], corners[..., 1], corners[..., 2]].max(axis=1)
    shape = np.asarray(mask.shape)
    q = h_min / 3.0
    mask_f = mask.astype(float)
    out_c = centres.copy()
    clean = np.zeros(m, bool)
    r_area = np.full(m, np.nan)
    for k in range(m):
        rho = 2.0 * dt[k] + 2.0 * h_max
        grid = np.arange(-rho, rho + q / 2, q)
        u, v = np.meshgrid(grid, grid, indexing="ij")
        disk = np.hypot(u, v) <= rho
        pts = centres[k] + u[..., None] * n1[k] + v[..., None] * n2[k]
        fidx = pts @ inverse[:3, :3].T + inverse[:3, 3]
        inside_fov = np.all((fidx >= -0.5) & (fidx <= shape - 0.5), axis=-1)
        weight = np.zeros(u.shape)
        weight[inside_fov] = ndi.map_coordinates(mask_f, fidx[inside_fov].T, order=1, mode="nearest")
        weight[~disk] = 0.0
        lumen = weight >= 0.5
        labels, count = ndi.label(lumen)
        if count == 0:
            continue
        middle = labels[len(grid) // 2, len(grid) // 2]
        own = labels == (middle if middle else 1 + int(np.argmax(np.bincount(labels.ravel())[1:])))
        # clean: the section's own lumen is closed inside the disk and the field of view, and round (no bulge)
        touches = ndi.binary_dilation(own) & ((~disk) | (disk & ~inside_fov) | (np.hypot(u, v) > rho - q))
        if touches.any():
            continue
        w = np.where(ndi.binary_dilation(own, iterations=int(np.ceil(h_max / q))), weight, 0.0)
        cu, cv = float(np.sum(w * u) / np.sum(w)), float(np.sum(w * v) / np.sum(w))
        area = float(np.sum(w)) * q * q
        r_eq = np.sqrt(area / np.pi)
        if np.hypot(u[own] - cu, v[own] - cv).max() > r_eq + h_max:
            continue
        clean[k] = True
        out_c[k] = centres[k] + cu * n1[k] + cv * n2[k]
        r_area[k] = r_eq
    return _Sections(s, out_c, clean, r_area, dt)


def _fit_sections(sec: _Sections, sigma_clean: float, sigma_rough: float, where: str) -> Centerline:
    sigma = np.where(sec.clean, sigma_clean, sigma_rough)
    return Centerline._fit(sec.centre, sigma, where)


def intervals(s: np.ndarray, ok: np.ndarray, digits: int | None = None) -> list[list[float]]:
    """``[start, end]`` s-intervals where ``ok`` holds on the samples ``s`` (rounded to ``digits`` if given)."""
    out, start = [], None
    for i, flag in enumerate(ok):
        if flag and start is None:
            start = s[i]
        if (not flag or i == len(ok) - 1) and start is not None:
            ends = [float(start), float(s[i] if flag else s[i - 1])]
            out.append(ends if digits is None else [round(e, digits) for e in ends])
            start = None
    return out


def distance_to_border(points: np.ndarray, affine: np.ndarray, shape) -> np.ndarray:
    """Distance (mm) of world points to the field of view's faces (the outer voxels' outer faces)."""
    inverse = np.linalg.inv(np.asarray(affine, float))
    index = points @ inverse[:3, :3].T + inverse[:3, 3]
    gradient = np.linalg.norm(inverse[:3, :3], axis=1)  # |grad i|, |grad j|, |grad k| in 1/mm
    upper = np.asarray(shape, float) - 0.5
    steps = np.minimum(index + 0.5, upper - index)
    return np.min(steps / gradient, axis=1)


def centerline_from_mask(
    mask: np.ndarray,
    vol,
    smoothing_mm: float | None = None,
    min_branch_mm: float | None = None,
    orient: str = "flow",
) -> tuple[Centerline, dict]:
    """The main vessel's centreline from a lumen mask on ``vol``'s grid, its side branches and radius (module notes).

    Parameters
    ----------
    mask : bool array (ni, nj, nk)
        The lumen (e.g. :func:`wss_nlp.vessel.segmentation.segment_vessel`); its largest 26-connected part is used.
    vol : VolumeAcquisition
        For the affine, the field of view and (``orient="flow"``) the velocity.
    smoothing_mm : float, optional
        RMS tolerance of the spline at clean cross-sections' centroids (default a tenth of the mean voxel edge;
        the voxel path elsewhere gets half a voxel).
    min_branch_mm : float, optional
        A side path counts as a branch when it reaches this far beyond the parent's radius (default 3 voxels).
    orient : "flow" or "thick"
        Where ``s = 0`` is: ``"flow"`` so that the mean velocity along ``t`` (over frames, at the centreline) is
        positive when that mean is clear of its standard error 3-fold, else (and for ``"thick"``) the thicker end
        (mean radius over the first and last fifth).

    Returns
    -------
    (Centerline, dict)
        The record: ``length_mm``; ``radius`` (``s_mm``, ``radius_mm`` (equivalent radius ``sqrt(area / pi)`` of
        clean cross-sections, else ``radius_dt_mm``: the distance transform's ridge, its largest value on the 8
        voxels around the centre), ``radius_dt_mm``, ``clean``);
        ``visible`` (s-intervals where the centreline lies at least one radius inside the field of view);
        ``branches`` (each: ``s_mm``, ``position_mm`` and ``phi`` where its path crosses the main lumen's radius,
        ``radius_mm`` (median equivalent radius of its clean cross-sections, else of the distance transform;
        ``radius_from`` says which), ``length_mm`` beyond the main lumen, ``direction``, ``flag`` with the wall
        region ``s_mm`` interval and ``phi`` sector within 1.5 branch radii, ``sub_branches``); ``orientation``;
        ``voxels``, ``ignored_voxels``.
    """
    import scipy.ndimage as ndi
    from scipy.sparse.csgraph import dijkstra

    m = np.asarray(mask, bool)
    if m.shape != tuple(vol.shape):
        raise InputError(f"mask of shape {m.shape} is not on the volume's grid {vol.shape}")
    labels, n = ndi.label(m, structure=np.ones((3, 3, 3), bool))
    if n == 0:
        raise InputError(f"{vol.source}: the lumen mask is empty; nothing to follow")
    sizes = np.bincount(labels.ravel())[1:]
    part = labels == 1 + int(np.argmax(sizes))
    ignored = int(m.sum() - part.sum())
    affine = np.asarray(vol.affine_mm, float)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    h_mean = float(np.exp(np.mean(np.log(spacing))))
    h_max = float(spacing.max())
    min_branch = 3.0 * h_mean if min_branch_mm is None else float(min_branch_mm)
    sigma_clean = 0.1 * h_mean if smoothing_mm is None else float(smoothing_mm)
    g = _lumen_graph(part, affine)
    if len(g.dt) < 8:
        raise InputError(f"{vol.source}: the lumen has {len(g.dt)} voxels; too few for a centreline")
    start = dijkstra(g.length, directed=False, indices=int(np.argmax(g.dt)))
    root = int(np.argmax(np.where(np.isfinite(start), start, -1)))
    end1, end2 = _tree_longest(g, _teasar(g, root, h_max, min_branch))
    paths = _teasar(g, end1, h_max, min_branch, first=end2)
    main = paths[0][::-1]
    # the path ends on the rim of the lumen's end (the geodesically farthest voxel); trim where it veers there
    thick = np.flatnonzero(g.dt[main] >= 0.5 * np.median(g.dt[main]))
    main = main[thick[0] : thick[-1] + 1]
    if len(main) < 4:
        raise InputError(f"{vol.source}: the lumen is too short for a centreline ({len(main)} voxels along it)")
    where = f"centreline of {vol.source}"
    cl = Centerline._fit(g.world[main], np.full(len(main), 0.5 * h_mean), where)
    for _ in range(2):
        sec = _sections(cl, part, affine, g.dt_field, h_mean)
        cl = _fit_sections(sec, sigma_clean, 0.5 * h_mean, where)
    sec = _sections(cl, part, affine, g.dt_field, 0.5 * h_mean)
    radius = np.where(sec.clean, sec.radius_area, sec.radius_dt)
    orientation = _orientation(cl, sec.s, radius, vol, orient)
    if orientation["reversed"]:
        cl = cl.reversed()
        sec = _Sections(cl.length_mm - sec.s[::-1], sec.centre[::-1], sec.clean[::-1], sec.radius_area[::-1],
                        sec.radius_dt[::-1])  # fmt: skip
        radius = radius[::-1]
    # visible: one radius inside the field of view; the radius's largest value within a voxel along s, so that the
    # switch between the two estimates does not cut single samples out
    width = 2 * int(np.ceil(h_mean / max(float(sec.s[1] - sec.s[0]), 1e-12))) + 1
    reach = ndi.maximum_filter1d(radius, size=width, mode="nearest")
    visible = distance_to_border(cl.position(sec.s), affine, vol.shape) >= reach
    record: dict = {
        "length_mm": round(cl.length_mm, 4),
        "radius": {
            "s_mm": sec.s.tolist(),
            "radius_mm": radius.tolist(),
            "radius_dt_mm": sec.radius_dt.tolist(),
            "clean": sec.clean.tolist(),
        },
        "visible": [iv for iv in intervals(sec.s, visible, 4) if iv[1] - iv[0] >= h_mean],
        "branches": _branches(cl, paths, main, g, sec.s, radius, h_mean, part, affine),
        "orientation": orientation,
        "voxels": int(part.sum()),
        "ignored_voxels": ignored,
        "method": "minimal-path tree (1/D^2 cost), main = longest path weighted by D, cross-section centroids",
    }
    log.info(
        "centreline %.1f mm, %d side branch(es), %d of %d sections clean", cl.length_mm, len(record["branches"]),
        int(sec.clean.sum()), len(sec.s),
    )  # fmt: skip
    return cl, record


def _orientation(cl: Centerline, s: np.ndarray, radius: np.ndarray, vol, orient: str) -> dict:
    """Whether to reverse ``cl`` so that ``s = 0`` is upstream (``"flow"``) or at the thicker end."""
    if orient not in ("flow", "thick"):
        raise InputError(f"orient {orient!r}: choose 'flow' or 'thick'")
    if orient == "flow":
        inverse = np.linalg.inv(np.asarray(vol.affine_mm, float))
        x = cl.position(s)
        idx = np.clip(np.rint(x @ inverse[:3, :3].T + inverse[:3, 3]).astype(int), 0, np.asarray(vol.shape) - 1)
        t = cl.frame(s)[0]
        v = np.asarray(vol.velocity, float)[:, :, idx[:, 0], idx[:, 1], idx[:, 2]]  # (nt, 3, m)
        along = np.einsum("tcm,mc->tm", v, t).ravel()
        mean, err = float(along.mean()), float(along.std() / np.sqrt(max(along.size, 1)))
        if abs(mean) > 3 * err and mean != 0:
            return {"rule": "mean velocity along t positive", "mean_m_s": mean, "reversed": mean < 0}
    fifth = max(1, len(s) // 5)
    head, tail = float(np.mean(radius[:fifth])), float(np.mean(radius[-fifth:]))
    return {"rule": "s = 0 at the thicker end", "radius_ends_mm": [head, tail], "reversed": tail > head}


def _branches(
    cl: Centerline, paths, main, g: _Graph, s_grid: np.ndarray, radius: np.ndarray, h: float, mask, affine
) -> list[dict]:
    """First-level side branches of the tree ``paths`` off the ``main`` path, where they leave the main lumen."""
    on_main = np.zeros(len(g.dt), bool)
    on_main[paths[0]] = True  # the whole main path (``main`` is trimmed at its ends)
    owner: dict[int, int] = {}  # node -> index of the path it belongs to
    for i, p in enumerate(paths):
        for v in p[:-1] if i else p:
            owner.setdefault(v, i)
    first_level: dict[int, list[int]] = {}
    for i in range(1, len(paths)):
        j = i
        while not on_main[paths[j][-1]]:  # up the tree to the branch that leaves the main path
            j = owner[paths[j][-1]]
        first_level.setdefault(j, []).append(i)
    out = []
    for i, members in sorted(first_level.items()):
        path = paths[i][::-1]  # from the junction to the tip
        pts = g.world[path]
        proj = cl.project(pts)
        r_main = np.interp(proj.s, s_grid, radius)
        outside = np.flatnonzero(proj.r > r_main)
        if outside.size == 0:
            continue
        k = int(outside[0])
        beyond = np.asarray(path)[k:]
        r_branch = float(np.median(g.dt[beyond]))  # the distance transform on the branch's minimal path (its ridge)
        radius_from = "distance transform"
        if len(beyond) >= 4:  # better, where the branch has clean cross-sections: their equivalent radius
            try:
                sec = _sections(Centerline._fit(g.world[beyond], np.full(len(beyond), 0.5 * h), "branch"), mask,
                                affine, g.dt_field, 0.5 * h)  # fmt: skip
            except InputError:
                sec = None
            if sec is not None and sec.clean.any():
                r_branch, radius_from = float(np.median(sec.radius_area[sec.clean])), "cross-sections"
        ahead = min(len(path) - 1, k + max(2, int(np.ceil(2 * max(r_branch, h) / max(h, 1e-9)))))
        direction = pts[ahead] - pts[k]
        direction = direction / (np.linalg.norm(direction) or 1.0)
        s_b, phi_b = float(proj.s[k]), float(proj.phi[k])
        half_s = BRANCH_FLAG_RADII * r_branch
        half_phi = min(np.pi, BRANCH_FLAG_RADII * r_branch / max(float(r_main[k]), 1e-9))
        out.append(
            {
                "s_mm": round(s_b, 4),
                "position_mm": [round(float(v), 4) for v in pts[k]],
                "phi": round(phi_b, 5),
                "radius_mm": round(r_branch, 4),
                "radius_from": radius_from,
                "length_mm": round(_path_length(g.world, path[k:]), 4),
                "direction": [round(float(v), 5) for v in direction],
                "flag": {
                    "s_mm": [round(max(0.0, s_b - half_s), 4), round(min(cl.length_mm, s_b + half_s), 4)],
                    "phi": [round(phi_b - half_phi, 5), round(phi_b + half_phi, 5)],
                },
                "sub_branches": len(members) - 1,
            }
        )
    return sorted(out, key=lambda b: b["s_mm"])
