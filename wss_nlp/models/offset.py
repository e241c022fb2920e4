"""Background phase correction: a low-order polynomial fitted to static tissue, robustly.

Eddy currents and concomitant fields add a smooth phase to every voxel, static tissue and lumen alike, which
reads as a velocity offset ``o(x)`` (Dyverfeldt et al. 2015 and Bissell et al. 2023 list its correction as a
required step). Static tissue has no velocity, so there the measured velocity is ``o(x)`` plus noise; a
polynomial fitted to it and evaluated at the vessel removes the offset from the lumen.

* :func:`static_mask`: voxels with signal (magnitude above :data:`SIGNAL_MIN` noise deviations), away from
  every flowing region, and (cine, 4D flow) whose velocity does not vary in time;
* :func:`fit_offset`: MSAC (Torr & Zisserman 2000: the truncated quadratic cost of RANSAC's consensus) over
  random subsets, refined by weighted least squares on the inliers; the polynomial's total degree (0 to
  :data:`MAX_ORDER`) chosen by BIC on the inliers. Dimension-agnostic: 2D slices, 3D volumes.
* :func:`correct`: the whole step with its record and the reasons it refused (too sparse, one-sided static
  tissue, an offset larger than any eddy current).

A second vessel's flow is not static tissue: flowing regions are excluded before the fit, and what flows
unseen (a dark vein) is far outside the consensus band and lands among the outliers (tested).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from itertools import combinations_with_replacement

import numpy as np

from .._lazy import scipy

#: Highest total degree of the offset polynomial.
MAX_ORDER = 3
#: Magnitude (in complex noise deviations) above which a voxel's phase is signal, not noise (phase noise <= 0.2 rad).
SIGNAL_MIN = 5.0
#: Fewest static voxels per polynomial coefficient, and in all, for a fit.
MIN_PER_COEFFICIENT, MIN_STATIC_VOXELS = 8, 60
#: Consensus band of MSAC in noise deviations, and its random subsets.
MSAC_BAND, MSAC_DRAWS = 3.0, 200
#: Of 8 sectors around the vessel (out to 4 of its radii), fewest that must hold static tissue.
MIN_SECTORS = 6
#: An offset beyond this fraction of the venc at the vessel is no eddy current: refused, flagged.
MAX_OFFSET_FRACTION = 0.1
#: How the order is chosen: "aic" (``chi^2 + 2 k``) or "bic" (``chi^2 + k ln n``).
CRITERION = "aic"
#: The offset at the vessel counts as uncertain (a note) when its standard deviation exceeds this fraction of the
#: venc: three deviations then exceed the 0.3 % of the venc that moves a WSS by a few tenths of a point (issue 39).
MAX_STD_FRACTION = 0.001
#: Voxels of dilation around each flowing region kept out of the static mask (partial volume, wall).
FLOW_MARGIN = 2


def monomials(ndim: int, order: int) -> list[tuple[int, ...]]:
    """Exponent tuples of the monomials of total degree <= ``order`` in ``ndim`` variables (degree-ordered)."""
    out: list[tuple[int, ...]] = []
    for deg in range(order + 1):
        for combo in combinations_with_replacement(range(ndim), deg):
            e = [0] * ndim
            for c in combo:
                e[c] += 1
            out.append(tuple(e))
    return out


def design(coords: np.ndarray, order: int) -> np.ndarray:
    """``A[i, k] = prod_j coords[i, j]^e_kj`` over :func:`monomials` (coords already scaled to about [-1, 1])."""
    coords = np.atleast_2d(np.asarray(coords, float))
    cols = [np.prod(coords ** np.array(e)[None, :], axis=1) for e in monomials(coords.shape[1], order)]
    return np.stack(cols, axis=1)


@dataclass
class OffsetFit:
    """A fitted offset polynomial ``o(x) = sum_k c_k prod_j ((x_j - centre_j) / scale)^e_kj`` (m/s)."""

    order: int
    coefficients: np.ndarray  # m/s
    centre: np.ndarray  # mm, per axis
    scale: float  # mm
    inliers: np.ndarray  # bool over the static voxels given
    bic: dict = field(default_factory=dict)  # order -> BIC on the inliers
    chi2_per_dof: float = float("nan")
    covariance: np.ndarray | None = None  # of the coefficients, (m/s)^2
    alternatives: dict = field(default_factory=dict)  # order -> coefficients of the orders fitted on the inliers

    def __call__(self, points_mm: np.ndarray) -> np.ndarray:
        """The offset at points ``(n, ndim)`` in mm."""
        x = (np.atleast_2d(points_mm) - self.centre) / self.scale
        return design(x, self.order) @ self.coefficients

    def order_spread(self, points_mm: np.ndarray) -> np.ndarray:
        """The change of the offset at points (m/s) with one order more than the chosen one (0 where that order
        was not fitted: too few static voxels).

        A field the polynomials hold (degree <= the chosen one) gives the same value at one order more, up to
        the noise; a field they do not hold (a non-polynomial eddy-current pattern that varies under the vessel,
        where no static tissue sees it) gives a value that depends on the order: the interpolation into the
        vessel is then a guess, whatever the noise says."""
        x = (np.atleast_2d(points_mm) - self.centre) / self.scale
        q = self.order + 1
        if q not in self.alternatives:
            return np.zeros(x.shape[0])
        return np.abs(design(x, q) @ self.alternatives[q] - design(x, self.order) @ self.coefficients)

    def std(self, points_mm: np.ndarray) -> np.ndarray:
        """Standard deviation of the fitted offset at points (m/s), from the noise of the static voxels."""
        if self.covariance is None:
            return np.full(np.atleast_2d(points_mm).shape[0], np.nan)
        a = design((np.atleast_2d(points_mm) - self.centre) / self.scale, self.order)
        return np.sqrt(np.einsum("ij,jk,ik->i", a, self.covariance, a))


def _wls(a: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    sw = np.sqrt(w)
    return np.linalg.lstsq(a * sw[:, None], y * sw, rcond=None)[0]


def fit_offset(
    points_mm: np.ndarray,
    values: np.ndarray,
    noise: np.ndarray,
    max_order: int = MAX_ORDER,
    seed: int = 0,
    msac_points: int | None = None,
) -> OffsetFit:
    """Robust polynomial fit of the static-tissue velocities, its order chosen by BIC.

    Parameters
    ----------
    points_mm : (n, ndim) voxel centres of the static tissue, mm
    values : (n,) measured velocity there, m/s
    noise : (n,) the velocity noise deviation of each voxel, m/s (``venc sigma / (pi |d_i|)``)
    max_order : highest total degree tried
    seed : seeds the random subsets (the fit is reproducible)
    msac_points : score MSAC's candidates on this many of the voxels (drawn once, seeded) instead of all: a
        volume's tens of thousands of static voxels need not all vote for the consensus; the refinement uses all

    Notes
    -----
    MSAC at the highest order admissible for ``n`` (at least :data:`MIN_PER_COEFFICIENT` voxels per
    coefficient): subsets of twice the number of coefficients, the cost ``sum_i min(r_i^2, T^2)`` of
    the normalized residuals ``r_i = (v_i - p(x_i)) / noise_i`` with ``T`` = :data:`MSAC_BAND`; the best
    subset's inliers (``|r_i| < T``) are refitted by weighted least squares twice. On those inliers every
    order ``p <= max_order`` is fitted and ``BIC_p = chi^2_p + k_p ln n_in`` chooses it (the noise
    deviations are known, so the likelihood is the chi-square).
    """
    pts = np.asarray(points_mm, float)
    y = np.asarray(values, float)
    s = np.maximum(np.asarray(noise, float), 1e-12)
    n, ndim = pts.shape
    centre = pts.mean(axis=0)
    scale = float(max(np.max(np.abs(pts - centre)), 1e-9))
    x = (pts - centre) / scale
    top = max_order
    while top > 0 and n < MIN_PER_COEFFICIENT * len(monomials(ndim, top)):
        top -= 1
    a_top = design(x, top)
    k = a_top.shape[1]
    w = 1.0 / s**2
    rng = np.random.default_rng(seed)
    best_cost, best_c = np.inf, None
    size = min(n, 2 * k)
    vote = np.arange(n)
    if msac_points is not None and n > msac_points:
        vote = np.sort(np.random.default_rng(seed + 7919).choice(n, size=msac_points, replace=False))
    for _ in range(MSAC_DRAWS if n > size else 1):
        pick = rng.choice(n, size=size, replace=False) if n > size else np.arange(n)
        c = _wls(a_top[pick], y[pick], w[pick])
        r = (y[vote] - a_top[vote] @ c) / s[vote]
        cost = float(np.sum(np.minimum(r**2, MSAC_BAND**2)))
        if cost < best_cost:
            best_cost, best_c = cost, c
    inl = np.abs((y - a_top @ best_c) / s) < MSAC_BAND
    for _ in range(2):  # refine: least squares on the consensus, new consensus
        if inl.sum() < k:
            break
        c = _wls(a_top[inl], y[inl], w[inl])
        inl = np.abs((y - a_top @ c) / s) < MSAC_BAND
    n_in = max(int(inl.sum()), 1)
    bic, coefs = {}, {}
    for p in range(top + 1):
        a = design(x[inl], p)
        c = _wls(a, y[inl], w[inl])
        chi2 = float(np.sum(((y[inl] - a @ c) / s[inl]) ** 2))
        bic[p] = chi2 + a.shape[1] * (np.log(n_in) if CRITERION == "bic" else 2.0)
        coefs[p] = (c, chi2 / max(n_in - a.shape[1], 1))
    order = min(bic, key=lambda p: bic[p])
    alternatives = {p: c for p, (c, _) in coefs.items()}
    # one order more than the choice, also past max_order where the consensus supports it: a check of the
    # interpolation into the vessel (OffsetFit.order_spread), never chosen
    check = order + 1
    if check not in alternatives and n_in >= MIN_PER_COEFFICIENT * len(monomials(ndim, check)):
        alternatives[check] = _wls(design(x[inl], check), y[inl], w[inl])
    a = design(x[inl], order)
    # covariance of the weighted least squares, scaled by chi^2/dof where the residual exceeds the noise (texture
    # of the offset the polynomial does not hold counts as noise then)
    cov = np.linalg.pinv(a.T @ (a * w[inl][:, None])) * max(1.0, coefs[order][1])
    return OffsetFit(order, coefs[order][0], centre, scale, inl, bic, coefs[order][1], cov, alternatives)


def static_mask(
    magnitude: np.ndarray,
    sigma: float,
    flowing: np.ndarray,
    velocity_std: np.ndarray | None = None,
    std_max=None,
    margin: int = FLOW_MARGIN,
) -> np.ndarray:
    """Voxels of static tissue: signal above :data:`SIGNAL_MIN` sigma, ``margin`` voxels from any flow.

    ``velocity_std`` (cine: the temporal standard deviation of each voxel's velocity) keeps out voxels that
    vary by more than ``std_max`` over the cycle. ``margin`` (default :data:`FLOW_MARGIN`) grows with the
    acquisition's blur: a zero-filled k-space image carries a vessel's signal, and its phase, further out
    (:attr:`wss_nlp.models.acquisition.MeasurementModel.blur_voxels`). Any number of dimensions.
    """
    mag = np.asarray(magnitude, float)
    keep = mag > SIGNAL_MIN * sigma
    if flowing is not None and np.any(flowing):
        keep &= ~scipy.ndimage.binary_dilation(flowing, iterations=margin)
    if velocity_std is not None and std_max is not None:
        keep &= np.asarray(velocity_std) <= std_max
    # the outermost voxels of the view carry wrap-around and edge artefacts on scanners: left out
    edge = np.zeros_like(keep)
    edge[tuple(slice(1, -1) for _ in keep.shape)] = True
    return keep & edge


@dataclass
class OffsetRecord:
    """What the offset correction did (stored in the result: ``tissue_json``, shown by ``wss-nlp analyze``)."""

    applied: bool
    reason: str  # why not applied, or "" when applied
    order: int = -1
    coefficients: list = field(default_factory=list)  # m/s, monomials of ((x - centre) / scale) by degree
    centre_mm: list = field(default_factory=list)
    scale_mm: float = float("nan")
    at_vessel_m_s: float = float("nan")  # the fitted offset at the vessel's centre
    at_vessel_fraction_of_venc: float = float("nan")
    at_vessel_std_m_s: float = float("nan")  # its standard deviation from the static voxels' noise
    at_vessel_order_spread_m_s: float = float("nan")  # its change with one order more or less (OffsetFit.order_spread)
    # applied, but the value at the vessel is uncertain beyond MAX_STD_FRACTION of the venc: by the noise (std) or
    # by the model (order spread)
    uncertain: bool = False
    static_voxels: int = 0  # the static mask's size
    inlier_voxels: int = 0  # MSAC's consensus
    sectors: int = 0  # of 8 around the vessel with static tissue
    bic: dict = field(default_factory=dict)
    frames: int = 1  # frames the fit saw: a cine series' one offset is fitted to the mean of its T frames

    def as_dict(self) -> dict:
        return asdict(self)


def coordinates(shape, spacing, origin) -> list[np.ndarray]:
    """Voxel-centre coordinate arrays (mm) of an image ``A[i_0, ..., i_{d-1}]``, axis ``j`` spaced ``spacing[j]``."""
    axes = [origin[j] + np.arange(shape[j]) * spacing[j] for j in range(len(shape))]
    return list(np.meshgrid(*axes, indexing="ij"))


def correct(
    velocity: np.ndarray,
    magnitude: np.ndarray,
    spacing,
    origin,
    sigma: float,
    flowing: np.ndarray,
    vessel_mm,
    vessel_radius_mm: float,
    venc: float | None,
    velocity_std: np.ndarray | None = None,
    seed: int = 0,
    floor_sigma: float | None = None,
    margin: int = FLOW_MARGIN,
) -> tuple[np.ndarray, OffsetRecord, np.ndarray]:
    """Fit the background offset on static tissue and subtract it everywhere: ``(velocity, record, static)``.

    Any number of dimensions: ``spacing`` and ``origin`` are per array axis (a 2D slice ``A[iy, ix]``:
    ``(dy, dx)`` and ``(y0, x0)``), ``vessel_mm`` the vessel's centre in the same axis order.
    ``sigma`` is the complex noise per channel (raw units); ``flowing`` (bool, the image's shape) marks
    every region with flow. The correction is refused, with its reason in the record, when the static
    tissue has fewer than :data:`MIN_STATIC_VOXELS` voxels, does not surround the vessel (fewer than
    :data:`MIN_SECTORS` of 8 sectors out to 4 vessel radii) or the offset at the vessel exceeds
    :data:`MAX_OFFSET_FRACTION` of the venc. ``static`` is the static mask (the fit's inliers); ``margin``: the
    static tissue's distance from flow in voxels (:func:`static_mask`).
    """
    v = np.asarray(velocity, float)
    mag = np.asarray(magnitude, float)
    # signal above SIGNAL_MIN of the frame noise (``floor_sigma``; a series' mean passes sigma / sqrt(T) as the
    # noise of its phases, but a dark voxel's phase is no better for being averaged)
    floor = sigma if floor_sigma is None else floor_sigma
    static = static_mask(mag, floor, flowing, velocity_std, None if venc is None else 0.05 * venc, margin)
    n_static = int(static.sum())
    if n_static == 0:
        return v, OffsetRecord(False, "no static tissue in view (the background is noise)"), static
    coords = coordinates(v.shape, spacing, origin)
    pts = np.stack([c[static] for c in coords], axis=1)
    rel = pts - np.asarray(vessel_mm, float)[None, :]
    near = np.hypot(rel[:, -1], rel[:, -2]) < 4 * vessel_radius_mm if rel.shape[1] >= 2 else np.ones(len(rel), bool)
    angle = np.arctan2(rel[:, -2], rel[:, -1]) if rel.shape[1] >= 2 else np.zeros(len(rel))
    sectors = int(np.unique(np.floor((angle[near] + np.pi) / (np.pi / 4)).astype(int) % 8).size)
    rec = OffsetRecord(False, "", static_voxels=n_static, sectors=sectors)
    if n_static < MIN_STATIC_VOXELS:
        rec.reason = f"static tissue too sparse for the offset fit: {n_static} voxels (< {MIN_STATIC_VOXELS})"
        return v, rec, static
    if sectors < MIN_SECTORS:
        rec.reason = (
            f"static tissue does not surround the vessel ({sectors} of 8 sectors within 4 radii, < {MIN_SECTORS}): "
            "the offset at the vessel would be extrapolated"
        )
        return v, rec, static
    vscale = 1.0 if venc is None else venc
    noise = vscale * sigma / (np.pi * mag[static])
    fit = fit_offset(pts, v[static], noise, seed=seed)
    at_vessel = float(fit(np.asarray(vessel_mm, float)[None, :])[0])
    rec.at_vessel_std_m_s = float(fit.std(np.asarray(vessel_mm, float)[None, :])[0])
    rec.at_vessel_order_spread_m_s = float(fit.order_spread(np.asarray(vessel_mm, float)[None, :])[0])
    rec.order, rec.coefficients = fit.order, [float(c) for c in fit.coefficients]
    rec.centre_mm, rec.scale_mm = [float(c) for c in fit.centre], fit.scale
    rec.at_vessel_m_s, rec.inlier_voxels = at_vessel, int(fit.inliers.sum())
    rec.bic = {str(k): float(b) for k, b in fit.bic.items()}
    if venc is not None:
        rec.at_vessel_fraction_of_venc = at_vessel / venc
        if abs(at_vessel) > MAX_OFFSET_FRACTION * venc:
            rec.reason = (
                f"the fitted offset at the vessel, {100 * at_vessel / venc:.1f} % of the venc, is larger than any "
                f"eddy current ({100 * MAX_OFFSET_FRACTION:g} %): the static tissue may hold flow; not corrected"
            )
            return v, rec, static
    full = np.stack([c.ravel() for c in coords], axis=1)
    offset = fit(full).reshape(v.shape)
    rec.applied = True
    spread = max(rec.at_vessel_std_m_s, rec.at_vessel_order_spread_m_s)
    rec.uncertain = venc is not None and spread > MAX_STD_FRACTION * venc
    inl = np.zeros_like(static)
    inl[static] = fit.inliers
    return v - offset, rec, inl


def correct_series(
    velocities: np.ndarray,
    magnitudes: np.ndarray,
    spacing,
    origin,
    sigma: float,
    flowing: np.ndarray,
    vessel_mm,
    vessel_radius_mm: float,
    venc: float | None,
    seed: int = 0,
    margin: int = FLOW_MARGIN,
) -> tuple[np.ndarray, OffsetRecord, np.ndarray]:
    """One offset for a cine series (or any repeated acquisition of one slice or volume): ``(velocities, record,
    static)``.

    The gradient waveforms, and with them the eddy currents, repeat in every frame: the offset is the same, so
    it is fitted once to the frames' mean velocity (its noise ``sqrt(T)`` times smaller) on the static tissue
    that is also still in time (temporal standard deviation at most 5 % of the venc: a vessel pulses, tissue
    does not; :func:`static_mask`) and subtracted from every frame. ``velocities`` and ``magnitudes``:
    ``(T, ...)``; the rest as :func:`correct` for one frame's shape.
    """
    v = np.asarray(velocities, float)
    mag = np.asarray(magnitudes, float)
    t = v.shape[0]
    mean_v, mean_m, std_v = v.mean(axis=0), mag.mean(axis=0), v.std(axis=0)
    # the mean's noise is the frame noise over sqrt(T): the same as one frame of sigma / sqrt(T)
    fixed, rec, static = correct(
        mean_v, mean_m, spacing, origin, sigma / np.sqrt(t), flowing, vessel_mm, vessel_radius_mm, venc,
        velocity_std=std_v, seed=seed, floor_sigma=sigma, margin=margin,
    )  # fmt: skip
    rec.frames = t
    offset = mean_v - fixed
    return v - offset[None], rec, static


@dataclass
class SeriesOffset:
    """One background offset of a cine series' slice (:func:`correct_series`), subtracted from each of its frames.

    ``image`` is the fitted offset on the slice's grid (m/s; zeros where the correction was refused), ``record``
    what the fit did (its ``frames``: the series' length), ``static`` the voxels it was fitted on (MSAC's inliers)."""

    image: np.ndarray
    record: OffsetRecord
    static: np.ndarray | None = None
