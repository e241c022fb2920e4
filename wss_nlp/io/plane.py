"""A plane through a 4D-flow volume: magnitude and velocity resampled perpendicular to the vessel.

``wss-nlp import MAG.nii VX.nii VY.nii VZ.nii --plane X Y Z NX NY NZ`` cuts a
volume with three velocity components (4D flow) by the plane through the
point ``p = (X, Y, Z)`` (mm, the volume's world frame) with normal ``n``, and
writes the slice (or a stack of parallel slices) as an input file.

Notes
-----
In-plane axes: ``e_1 = (n x a) / |n x a|`` with ``a`` the world axis least
aligned with ``n``, and ``e_2 = n x e_1``, so that ``e_1 x e_2 = n`` (the
results' polar angle turns counter-clockwise about ``n``). The slice ``k`` of
``K`` has voxel centres

.. math:: x_{k,i,j} = p + (j - (m-1)/2) h e_1 + (i - (m-1)/2) h e_2 + (k - (K-1)/2) \\delta n,

``m = round(FOV / h)`` voxels a side. Each plane voxel takes the values of
the nearest volume voxel: its magnitude and its velocity ``u`` (components
along the world axes), giving the through-plane velocity ``u . n`` and the
in-plane components ``u . e_1``, ``u . e_2``. Every value is then one voxel's
measurement, with its own noise and its own partial volume (the velocity the
mean over that voxel's lumen part), consistently in magnitude and velocity,
at the price of placing it up to half a voxel from where it was measured.
Interpolating instead (``order=1``, trilinear) mixes a wall voxel with its
neighbours up to a voxel further in and the background's random phase:
the velocity model (the mean over the plane voxel's lumen part) reads that as
a velocity jump at the wall. On ``scripts/plane_extraction.py``'s phantoms
trilinear values gave WSS errors of 10-415 % (all flagged SUSPECT), the
nearest voxel's 3-5 % on average with radius errors of 3-5 % (1 mm voxels;
the table there), against about 1 % radius error when interpolating.

The plane voxel ``h`` defaults to the volume's largest voxel edge; a finer
plane voxel repeats volume voxels (nearest) and is refused.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

#: Default side of the plane's field of view (mm): a large artery with a margin.
DEFAULT_FOV_MM = 40.0


@dataclass
class Plane:
    """Where to cut: a point and normal in the volume's world frame (mm), the field of view and sampling."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    fov_mm: float = DEFAULT_FOV_MM
    voxel_mm: float | None = None
    slices: int = 1
    spacing_mm: float | None = None
    order: int = 0  # 0: each plane voxel takes the nearest volume voxel's values (see the notes); 1: trilinear

    def check(self) -> None:
        n = np.asarray(self.normal, dtype=float)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) == 0:
            raise InputError(f"--plane: the normal {tuple(self.normal)} must be three finite numbers, not all 0")
        if not np.all(np.isfinite(self.point)):
            raise InputError(f"--plane: the point {tuple(self.point)} must be finite")
        if not self.fov_mm > 0:
            raise InputError(f"--plane-fov {self.fov_mm}: must be > 0 mm")
        if self.voxel_mm is not None and not self.voxel_mm > 0:
            raise InputError(f"--plane-voxel {self.voxel_mm}: must be > 0 mm")
        if self.slices < 1:
            raise InputError(f"--plane-slices {self.slices}: must be >= 1")
        if self.spacing_mm is not None and not self.spacing_mm > 0:
            raise InputError(f"--plane-spacing {self.spacing_mm}: must be > 0 mm")

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(e_1, e_2, n)``, right-handed and orthonormal."""
        n = np.asarray(self.normal, dtype=float)
        n = n / np.linalg.norm(n)
        a = np.eye(3)[int(np.argmin(np.abs(n)))]
        e1 = np.cross(n, a)
        e1 /= np.linalg.norm(e1)
        return e1, np.cross(n, e1), n

    def sampling(self, affine: np.ndarray) -> tuple[float, int, float]:
        """``(h, m, delta)``: voxel size, voxels a side and slice spacing (defaults from the volume's voxels)."""
        edges = np.linalg.norm(np.asarray(affine, dtype=float)[:3, :3], axis=0)
        h = float(self.voxel_mm if self.voxel_mm is not None else edges.max())
        if h < edges.min() * (1 - 1e-6):
            raise InputError(
                f"--plane-voxel {h:g} mm is finer than the volume's voxels ({edges.min():.3g} mm): the plane would "
                "repeat voxels and pretend a resolution the scan does not have; use at least the volume's voxel"
            )
        m = max(int(round(self.fov_mm / h)), 8)
        return h, m, float(self.spacing_mm if self.spacing_mm is not None else h)

    def check_inside(self, affine: np.ndarray, shape, where: str) -> None:
        """InputError unless the plane's field of view lies inside the volume: its corners are checked, from the
        header alone, before any voxel is read or resampled (a plane is convex, and so is the volume's box)."""
        e1, e2, n = self.axes()
        h, m, delta = self.sampling(affine)
        half, depth = (m - 1) / 2 * h, (self.slices - 1) / 2 * delta
        p = np.asarray(self.point, dtype=float)
        corners = np.array([p + a * half * e1 + b * half * e2 + c * depth * n
                            for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])  # fmt: skip
        voxel_index(affine, corners, shape, where)

    def centres(self, affine: np.ndarray) -> np.ndarray:
        """Voxel centres ``(K, m, m, 3)`` in world mm, indexed ``[k, i (rows, e_2), j (columns, e_1)]``."""
        e1, e2, n = self.axes()
        h, m, delta = self.sampling(affine)
        t = (np.arange(m) - (m - 1) / 2) * h
        s = (np.arange(self.slices) - (self.slices - 1) / 2) * delta
        p = np.asarray(self.point, dtype=float)
        return p + s[:, None, None, None] * n + t[None, :, None, None] * e2 + t[None, None, :, None] * e1


def voxel_index(affine: np.ndarray, points: np.ndarray, shape, where: str) -> np.ndarray:
    """Voxel index coordinates ``(3, n)`` of world ``points (..., 3)`` in a volume of ``shape``.

    A point outside the volume (beyond half a voxel) is an error; points within half a voxel of the outer
    centres take the edge value.
    """
    inverse = np.linalg.inv(np.asarray(affine, dtype=float))
    flat = points.reshape(-1, 3)
    index = flat @ inverse[:3, :3].T + inverse[:3, 3]
    upper = np.asarray(shape[:3]) - 1
    outside = np.any((index < -0.5) | (index > upper + 0.5), axis=1)
    if outside.any():
        worst = flat[outside][0]
        raise InputError(
            f"{where}: the plane leaves the volume (e.g. at {np.round(worst, 1).tolist()} mm); move the point, "
            "or shrink --plane-fov / --plane-slices"
        )
    return np.clip(index, 0, upper).T


def sample(volume: np.ndarray, index: np.ndarray, order: int = 1) -> np.ndarray:
    """Values of ``volume`` at voxel coordinates ``index (3, n)``: trilinear (``order`` 1) or nearest voxel (0)."""
    import scipy.ndimage

    return scipy.ndimage.map_coordinates(volume, index, order=order, mode="nearest")


def resample(volume: np.ndarray, affine: np.ndarray, points: np.ndarray, where: str, order: int = 1) -> np.ndarray:
    """Values of ``volume[i, j, k]`` at world ``points (..., 3)`` (:func:`voxel_index`, :func:`sample`)."""
    return sample(volume, voxel_index(affine, points, volume.shape, where), order).reshape(points.shape[:-1])


#: Tilts (degrees) below this are left alone: the WSS error of a tilt theta is at most 1 - cos^2 theta (0.8 % at 5
#: degrees; module :mod:`wss_nlp.pipeline.obliquity`), within what the reconstruction resolves.
TILT_THRESHOLD_DEG = 5.0


def tilt(through: np.ndarray, inplane_x: np.ndarray, inplane_y: np.ndarray, mask: np.ndarray):
    """The angle between a plane's normal and the vessel's axis, from the in-plane velocity.

    Notes
    -----
    Axial flow ``u = w_3 d`` along the axis ``d = cos(theta) n + sin(theta) e`` (``n`` the plane's normal, ``e``
    a unit vector in the plane) has through-plane component ``w = w_3 cos(theta)`` and in-plane components
    ``w_3 sin(theta) e``: their ratio ``tan(theta) e`` is the same in every voxel. It is taken by least squares
    over the voxels of ``mask`` (the lumen), ``tan(theta) e = sum(u_in w) / sum(w^2)``; a rotation about the
    centre (swirl) averages out of it. The relative residual of that fit says how axial the flow is.

    Returns
    -------
    (theta in radians, e as (ex, ey) in the image frame, relative residual of the fit), or None without flow.
    """
    w = np.asarray(through, dtype=float)[mask]
    ux = np.asarray(inplane_x, dtype=float)[mask]
    uy = np.asarray(inplane_y, dtype=float)[mask]
    ok = np.isfinite(w) & np.isfinite(ux) & np.isfinite(uy)
    w, ux, uy = w[ok], ux[ok], uy[ok]
    ww = float(np.sum(w * w))
    if w.size < 4 or not ww > 0:
        return None
    a, b = float(np.sum(ux * w)) / ww, float(np.sum(uy * w)) / ww
    lean = float(np.hypot(a, b))
    residual = float(np.sqrt(np.sum((ux - a * w) ** 2 + (uy - b * w) ** 2) / max(np.sum(ux**2 + uy**2), 1e-300)))
    e = (a / lean, b / lean) if lean > 0 else (1.0, 0.0)
    return float(np.arctan(lean)), e, residual
