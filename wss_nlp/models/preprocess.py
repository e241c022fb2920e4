"""Preprocessing of the raw images (paper Appendix B).

* magnitude normalization ``m = T((m_raw - m0) / (m1 - m0))`` from the two
  histogram peaks ``m0`` (background) and ``m1`` (lumen), ``T`` truncation
  to [0, 1];
* the lumen: the largest connected region of ``m > 1/2`` (or the one a
  user names by a point, ``--vessel X,Y``), its centre (the barycenter of
  ``m`` over that region and a two-voxel rim), its equal-area radius and an
  admissible box ``[r0, r1]`` for R. Other regions large enough to be
  vessels are reported (:attr:`Lumen.others`), never silently dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .._lazy import scipy
from ..errors import LumenTouchesBorderError, NoVesselError
from .measurement import VoxelGrid

#: Fewest voxels a lumen may cover before we refuse to fit it.
MIN_LUMEN_VOXELS = 12
#: Smallest (m1 - m0) / (background spread) accepted as a vessel; pure
#: Rayleigh noise splits into two classes with a ratio of about 2.
MIN_CONTRAST_TO_NOISE = 4.0


def where_prefix(source: str) -> str:
    """``"source: "`` for error messages, or nothing when there is no source name."""
    return f"{source}: " if source else ""


def robust_std(values) -> float:
    """``1.4826 x median |x - median x|``: the standard deviation for Gaussian data, robust to outliers."""
    values = np.asarray(values, dtype=float)
    return 1.4826 * float(np.median(np.abs(values - np.median(values))))


@dataclass
class Normalization:
    m0: float  # background peak of the raw magnitude
    m1: float  # lumen peak of the raw magnitude
    threshold: float  # Otsu split between the two classes
    background_spread: float  # robust standard deviation (1.4826 MAD) of the background class

    @property
    def contrast_to_noise(self) -> float:
        return (self.m1 - self.m0) / max(self.background_spread, 1e-300)


def _otsu(values: np.ndarray, bins: int) -> float:
    hist, edges = np.histogram(values, bins=bins)
    mids = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    s0 = np.cumsum(hist * mids)
    m0 = s0 / np.maximum(w0, 1)
    m1 = (s0[-1] - s0) / np.maximum(w1, 1)
    between = w0 * w1 * (m0 - m1) ** 2
    return float(mids[np.argmax(between[:-1])])


def _peak(values: np.ndarray, bins: int) -> float:
    """Mode of a sample from a smoothed histogram."""
    hist, edges = np.histogram(values, bins=bins)
    smooth = scipy.ndimage.gaussian_filter1d(hist.astype(float), 1.5)
    i = int(np.argmax(smooth))
    return float(0.5 * (edges[i] + edges[i + 1]))


def histogram_peaks(magnitude: np.ndarray, source: str = "") -> Normalization:
    """Background and lumen peaks ``m0``, ``m1`` of the magnitude histogram (Fig. B1).

    The histogram is split in two classes by Otsu's threshold; each peak is
    the mode of its class. Raises :class:`NoVesselError` when the image has
    no contrast, or when the lumen peak is not clearly above the background
    (contrast-to-noise ratio below :data:`MIN_CONTRAST_TO_NOISE`).
    """
    src = where_prefix(source)
    vals = np.asarray(magnitude, dtype=float).ravel()
    lo, hi = np.percentile(vals, [0.5, 99.5])
    if not hi > lo:
        raise NoVesselError(f"{src}magnitude image has no contrast (constant image): no vessel in view")
    bins = int(np.clip(np.sqrt(vals.size), 32, 256))
    thr = _otsu(vals, bins)
    low, high = vals[vals <= thr], vals[vals > thr]
    if low.size == 0 or high.size == 0:
        raise NoVesselError(f"{src}magnitude histogram is not bimodal: no vessel in view")
    m0, m1 = _peak(low, bins), _peak(high, bins)
    spread = robust_std(low)
    norm = Normalization(m0=m0, m1=m1, threshold=thr, background_spread=spread)
    if not m1 > m0 or norm.contrast_to_noise < MIN_CONTRAST_TO_NOISE:
        raise NoVesselError(
            f"{src}no vessel in view: the magnitude histogram has no lumen peak clearly above the background "
            f"(contrast-to-noise {norm.contrast_to_noise:.2g} < {MIN_CONTRAST_TO_NOISE:g})"
        )
    return norm


def normalize_magnitude(magnitude: np.ndarray, norm: Normalization, clip_upper: bool = True) -> np.ndarray:
    """``T((m_raw - m0)/(m1 - m0))`` with ``T(x) = max(0, min(1, x))`` (Appendix B).

    ``clip_upper=False`` keeps values above 1: with a k-space acquisition
    (:mod:`wss_nlp.models.kspace`) the Gibbs overshoot inside the wall is signal the
    model predicts, not noise.
    """
    return np.clip(
        (np.asarray(magnitude, dtype=float) - norm.m0) / (norm.m1 - norm.m0), 0.0, 1.0 if clip_upper else None
    )


@dataclass
class Lumen:
    """What the preprocessing knows about the vessel before any fit."""

    mask: np.ndarray  # (ny, nx) bool, the connected region m > 1/2
    center: tuple[float, float]  # mm
    r_area: float  # equal-area radius, mm
    r_min: float  # smallest distance centre -> region boundary, mm
    r_max: float  # largest distance centre -> region boundary, mm
    r0: float  # box lower bound, mm
    r1: float  # box upper bound, mm
    others: list = field(default_factory=list)  # other vessels in view: dicts center_mm, equal_area_radius_mm, voxels
    chosen_by: str = "the largest lumen"
    others_mask: np.ndarray | None = None  # (ny, nx) bool, the regions of the other vessels
    # predicted noise-free magnitude (raw units) where a k-space PSF carries the vessel's signal into the
    # background; the noise estimates subtract it (wss_nlp.parameters.noise.complex_noise_sigma). None: box model
    signal: np.ndarray | None = None
    # what the surround model and the offset correction found and did (wss_nlp.models.surround); None: not run
    tissue: dict | None = None

    @property
    def noise_mask(self) -> np.ndarray:
        """Every vessel in view: what a noise estimate must keep out of its background."""
        return self.mask if self.others_mask is None else self.mask | self.others_mask

    def others_note(self) -> str:
        """One line on the vessels in view that were not chosen, or ``""``."""
        if not self.others:
            return ""
        where = "; ".join(
            f"({o['center_mm'][0]:.1f}, {o['center_mm'][1]:.1f}) mm, r ~ {o['equal_area_radius_mm']:.2g} mm"
            for o in self.others
        )
        return (
            f"{len(self.others)} other vessel(s) in view, not reconstructed: {where}; reconstructed "
            f"{self.chosen_by} (pass --vessel X,Y to choose another)"
        )


@dataclass(frozen=True)
class LumenBox:
    """The polar origin and radius box of the geometry fit, shared by several images of one vessel.

    The frames of a cine slice see the same vessel; with one origin, box and reference radius they share
    one built geometry solver (:func:`wss_nlp.models.geometry.solver_for`) instead of building their own.
    ``start`` (radius coefficients, e.g. the previous frame's) warm-starts the geometry solve.
    """

    center: tuple[float, float]  # mm
    r0: float  # mm
    r1: float  # mm
    r_area: float  # mm, the reference radius (median of the images')
    start: tuple[float, ...] | None = None  # radius coefficients to start the geometry from (mm)
    # the series' one background offset of this slice (wss_nlp.models.offset.SeriesOffset), or None: each image
    # fits its own (wss_nlp.models.surround.preprocess)
    offset: Any = field(default=None, compare=False)

    @classmethod
    def covering(cls, lumens: list[Lumen]) -> LumenBox:
        """The box about the mean centre that contains every lumen's own box about its own centre.

        A radius admissible about centre ``c_k`` lies within ``|c_k - c|`` of one admissible about ``c``,
        so the bounds widen by the largest centre offset.
        """
        if not lumens:
            raise ValueError("LumenBox.covering needs at least one lumen")
        centers = np.array([lu.center for lu in lumens], dtype=float)
        center = centers.mean(axis=0)
        shift = float(np.max(np.hypot(*(centers - center).T)))
        r0 = max(min(lu.r0 for lu in lumens) - shift, 0.25 * min(lu.r_area for lu in lumens))
        return cls(
            (float(center[0]), float(center[1])),
            float(r0),
            float(max(lu.r1 for lu in lumens) + shift),
            float(np.median([lu.r_area for lu in lumens])),
        )

    def apply(self, lumen: Lumen) -> Lumen:
        """``lumen`` with this origin, box and reference radius (its mask and noise regions unchanged)."""
        return replace(lumen, center=self.center, r0=self.r0, r1=self.r1, r_area=self.r_area)


def _region_summary(region: np.ndarray, grid: VoxelGrid) -> dict:
    xc, yc = grid.centers()
    n = int(region.sum())
    return {
        "center_mm": [float(xc[region].mean()), float(yc[region].mean())],
        "equal_area_radius_mm": float(np.sqrt(n * grid.voxel_area / np.pi)),
        "voxels": n,
    }


def find_lumen(m: np.ndarray, grid: VoxelGrid, source: str = "", vessel=None) -> Lumen:
    """Locate the lumen in a normalized magnitude image.

    Parameters
    ----------
    vessel : (x, y) in mm or None
        Take the bright region containing (or, failing that, nearest to)
        this point instead of the largest one.

    Notes
    -----
    The paper takes the barycenter of ``m`` over the whole field of view;
    with noise the truncated background pulls that towards the image
    centre, so we take it over the largest region of ``m > 1/2`` grown by
    two voxels (which holds all partial-volume voxels). The box is
    ``r0 = max(r_min - 2h, r_area / 4)`` and ``r1 = r_max + 2h``: wide
    enough never to bind at the solution of a star-shaped lumen, tight
    enough to keep the forward model small.
    """
    src = where_prefix(source)
    labels, n = scipy.ndimage.label(m > 0.5)
    if n == 0:
        raise NoVesselError(f"{src}no voxel of the normalized magnitude exceeds 1/2: no vessel in view")
    sizes = scipy.ndimage.sum_labels(np.ones_like(m), labels, index=np.arange(1, n + 1))
    k = int(np.argmax(sizes)) + 1
    if vessel is not None:
        k = _label_at(labels, sizes, grid, vessel, src)
    mask = labels == k
    if mask.sum() < MIN_LUMEN_VOXELS:
        raise NoVesselError(
            f"{src}largest bright region has {int(mask.sum())} voxels (< {MIN_LUMEN_VOXELS}): no vessel in view"
        )
    if mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any():
        raise LumenTouchesBorderError(
            f"{src}the lumen touches the border of the field of view; crop or re-centre the images"
        )
    grown = scipy.ndimage.binary_dilation(mask, iterations=2)
    # a region counts as another vessel when it could be fitted on its own; specks and pieces of the chosen
    # lumen's own rim (within two voxels of it) do not
    other_labels = [
        j for j in range(1, n + 1) if j != k and sizes[j - 1] >= MIN_LUMEN_VOXELS and not np.any(grown & (labels == j))
    ]
    others = [_region_summary(labels == j, grid) for j in other_labels]
    others_mask = np.isin(labels, other_labels) if other_labels else None
    xc, yc = grid.centers()
    w = m * grown
    cx, cy = float(np.sum(w * xc) / np.sum(w)), float(np.sum(w * yc) / np.sum(w))
    r_area = float(np.sqrt(np.sum(w) * grid.voxel_area / np.pi))
    edge = mask & ~scipy.ndimage.binary_erosion(mask)
    dist = np.hypot(xc[edge] - cx, yc[edge] - cy)
    h = grid.h
    r_min, r_max = float(dist.min()), float(dist.max()) + 0.5 * h
    if not mask[
        int(np.clip(round((cy - grid.origin_mm[1]) / grid.dy), 0, m.shape[0] - 1)),
        int(np.clip(round((cx - grid.origin_mm[0]) / grid.dx), 0, m.shape[1] - 1)),
    ]:
        raise NoVesselError(f"{src}the barycenter of the bright region lies outside it; the lumen is not star-shaped")
    return Lumen(
        mask=mask,
        center=(cx, cy),
        r_area=r_area,
        r_min=r_min,
        r_max=r_max,
        r0=max(r_min - 2 * h, 0.25 * r_area),
        r1=r_max + 2 * h,
        others=others,
        others_mask=others_mask,
        chosen_by="the largest lumen" if vessel is None else f"the vessel at ({vessel[0]:g}, {vessel[1]:g}) mm",
    )


def _label_at(labels: np.ndarray, sizes: np.ndarray, grid: VoxelGrid, point, src: str) -> int:
    """Label of the region of at least :data:`MIN_LUMEN_VOXELS` voxels that contains ``point`` (mm) or lies nearest."""
    xc, yc = grid.centers()
    px, py = (float(v) for v in point)
    d = np.hypot(xc - px, yc - py)
    best, best_d = 0, np.inf
    for j in range(1, len(sizes) + 1):
        if sizes[j - 1] < MIN_LUMEN_VOXELS:
            continue
        dj = float(d[labels == j].min())
        if dj < best_d:
            best, best_d = j, dj
    if best == 0 or best_d > 2 * grid.h:
        found = [
            _region_summary(labels == j, grid)["center_mm"]
            for j in range(1, len(sizes) + 1)
            if sizes[j - 1] >= MIN_LUMEN_VOXELS
        ]
        listed = ", ".join(f"({c[0]:.1f}, {c[1]:.1f})" for c in found) or "none"
        raise NoVesselError(f"{src}no vessel at --vessel ({px:g}, {py:g}) mm; vessels found at {listed} mm")
    return best


def preprocess(
    magnitude: np.ndarray, grid: VoxelGrid, source: str = "", vessel=None, clip_upper: bool = True
) -> tuple[Normalization, np.ndarray, Lumen]:
    """Appendix B for one slice: histogram peaks, the normalized magnitude and the lumen found in it.

    ``vessel`` (x, y in mm) chooses among several vessels (:func:`find_lumen`); ``clip_upper``
    as for :func:`normalize_magnitude`.
    """
    norm = histogram_peaks(magnitude, source)
    m = normalize_magnitude(magnitude, norm, clip_upper)
    return norm, m, find_lumen(m, grid, source, vessel)
