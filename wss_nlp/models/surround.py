"""What surrounds the lumen: a measurement model of the outside signal, flow-aware lumen detection.

Appendix B normalizes the magnitude by two histogram peaks, ``m = (raw - m0) / (m1 - m0)``: right where the
data are two-level and the outside has no signal (a tube in air), wrong in a patient, where the lumen sits in a wall,
in textured tissue, beside fat and other vessels, and its own signal varies (inflow, coil shading). This
module generalizes the model of a voxel to

    d_i = l_i f_i e^{i theta_i} + s_i,   s_i = w (F_t,i - f_i) + b(x_i) (1 - F_t,i),

with ``f_i`` the lumen's volume fraction (what :mod:`wss_nlp.models.geometry` fits), ``theta_i`` the lumen part's
phase relative to the static tissue's, ``l`` a smooth lumen level (a low-order polynomial fitted on the voxels
fully inside, with a term proportional to the speed where BIC takes it: inflow and coil shading are not read
as a wall displacement), ``w`` and ``t`` the level and thickness of a wall ring (``F_t`` the fraction within
``R + t``; :func:`fit_wall`, a fixed point with preliminary geometry solves) and ``b`` the outside level (a
low-order polynomial on a ring of voxels from 2.5 mm (two voxels at least) 4 mm (three voxels at least)
outwards, fat and texture trimmed; :func:`fit_surround`).
The data the geometry fits are then ``f_i`` (:func:`fractions`). The model is chosen from the data: where the
outside ring is noise (air), the two-level model stays and nothing changes (:attr:`SurroundModel.kind`
"two-level"). An outside of one level (a bath, tissue without texture) takes the fitted model with constant
levels: Appendix B's histogram peaks need not be that level, and its partial-volume voxels' phase is mixed too.

In tissue the partial-volume voxels' phase mixes the lumen's with the static signal's, so the measured velocity
is diluted towards 0: :func:`lumen_velocity` takes the lumen's phase back, ``theta_i = arg(d_i - s_i)``. The
background noise is no longer Rayleigh: the complex noise comes from the lumen plateau (:func:`lumen_noise_sigma`).

Lumen detection asks the velocity which bright regions flow (:func:`flowing_regions`): fat is bright and
static, and is neither the vessel nor "another vessel in view".

:func:`preprocess` is the one call of :func:`wss_nlp.pipeline.steps.prepare`; :func:`screen_preprocess`
serves the plausibility screen and the cine series' shared box.
"""

from __future__ import annotations

import hashlib
import logging
from collections import OrderedDict
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from .._lazy import scipy
from ..core.schema import option
from ..errors import InputError, NoVesselError
from . import acquisition as acq_model
from . import offset as off
from . import preprocess as pp
from .measurement import VoxelGrid

logger = logging.getLogger(__name__)

SURROUND_MODELS = ("auto", "two-level")
#: A bright region flows when the median speed of its core exceeds this fraction of the venc ...
FLOW_FRACTION_OF_VENC = 0.06
#: ... and this many phase-noise deviations of its core.
FLOW_NOISE_FACTOR = 4.0
#: The outside ring is noise (air) while its mean is below this many complex noise deviations
#: (a Rayleigh background's mean is 1.25 sigma; the mean exceeds 3 sigma with probability < 1e-100 on 20 voxels).
NOISE_FLOOR = 3.0
#: Where Appendix B refuses the histogram for its contrast, a flowing region must be this coherent to stand in:
#: the median of its velocity's 4-neighbour high-pass below this fraction of its median speed.
COHERENCE = 0.3
#: Highest total degree of the lumen and outside level polynomials.
LEVEL_ORDER = 2
#: Width of the outside ring in mm (at least three voxels).
RING_MM = 4.0
#: The surround model is ambiguous when more than this fraction of the outside ring are outliers ...
AMBIGUOUS_OUTLIERS = 0.25
#: ... or when a decision statistic lies within this relative distance of its threshold.
AMBIGUOUS_BAND = 0.15


@dataclass(frozen=True)
class TissueOptions:
    """The surround model and the background phase correction (:mod:`wss_nlp.models.surround`, :mod:`.offset`)."""

    schema_group = "input checks"

    surround: str = option(
        "auto",
        "model of the signal around the lumen: auto (chosen from the data: the two-level model of Appendix B "
        "where the background is air or uniform, else a smooth lumen level and outside level) or two-level",
        cli="--surround",
        toml=("surround",),
        choices=SURROUND_MODELS,
    )
    offset_correction: bool = option(
        True,
        "keep the background phase offset: no polynomial fitted to static tissue and subtracted",
        cli="--no-offset-correction",
        toml=("offset_correction",),
        flag_off=True,
    )

    def __post_init__(self):
        if self.surround not in SURROUND_MODELS:
            raise InputError(f"surround must be one of {SURROUND_MODELS}, got {self.surround!r}")

    @property
    def off(self) -> bool:
        """Everything this module adds is switched off: :func:`preprocess` is Appendix B's."""
        return self.surround == "two-level" and not self.offset_correction


def _highpass(a: np.ndarray) -> np.ndarray:
    return a - 0.25 * (np.roll(a, 1, 0) + np.roll(a, -1, 0) + np.roll(a, 1, 1) + np.roll(a, -1, 1))


def lumen_noise_sigma(
    raw: np.ndarray, lumen_mask: np.ndarray, velocity=None, venc: float | None = None, highpass_variance: float = 1.25
) -> float:
    """Complex noise per channel from the lumen plateau (two voxels inside), NaN without one.

    Notes
    -----
    ``r = a - (mean of the 4 neighbours)`` has variance ``1.25 sigma^2`` for white noise; smooth inflow,
    shading and a parabolic profile leave a constant in ``r`` (a constant Laplacian) that the median removes.
    At the lumen's SNR the magnitude's noise is Gaussian with the channels' sigma and, with ``venc``, the
    phase's is ``sigma / |d|``: both samples are pooled, ``r_m`` and ``pi |d| r_u / venc``. The deviation is
    the standard deviation after trimming beyond 3.5 robust deviations (1.4826 MAD), more efficient than the
    MAD itself on the 50-100 plateau voxels of a coarse slice. ``highpass_variance``: the 1.25 for correlated
    noise (a k-space PSF: :meth:`wss_nlp.models.acquisition.MeasurementModel.highpass_noise_variance`).
    """
    inner = scipy.ndimage.binary_erosion(lumen_mask, iterations=2)
    if inner.sum() < 20:
        return float("nan")
    parts = [_highpass(raw)[inner]]
    if velocity is not None and venc is not None:
        parts.append(np.pi * raw[inner] * _highpass(np.asarray(velocity, float))[inner] / venc)
    out = []
    for r in parts:
        r = r - np.median(r)
        s0 = pp.robust_std(r)
        out.append(r[np.abs(r) < 3.5 * max(s0, 1e-300)])
    return float(np.sqrt(np.mean(np.concatenate(out) ** 2) / highpass_variance))


# ------------------------------------------------------------------ which bright regions flow
@dataclass
class Regions:
    """The bright regions (``m > 1/2``) of a slice and which of them flow."""

    labels: np.ndarray
    flowing: list  # labels
    static: list  # labels of bright regions that do not flow (fat)
    speeds: dict  # label -> median |u| of its core (m/s)

    def mask(self, which: list) -> np.ndarray:
        return np.isin(self.labels, which) if which else np.zeros(self.labels.shape, bool)


def _speed_image(velocity) -> np.ndarray:
    """``|u|``, or for a cine series ``(T, ny, nx)`` each voxel's largest ``|u|`` over the frames."""
    u = np.asarray(velocity, float)
    return np.max(np.abs(u), axis=0) if u.ndim == 3 else np.abs(u)


#: Fewest voxels of a connected flow core (voxels above the flow threshold) that reach out to a lumen's rim:
#: noise lifts single voxels of static tissue over the threshold, never a connected patch of this size.
CORE_MIN_VOXELS = 4


def beyond_flow(m: np.ndarray, velocity, venc: float | None) -> np.ndarray:
    """Bright voxels (``m > 1/2``) of a region that flows but out of the flow's reach: static tissue touching a lumen.

    Notes
    -----
    Fat touching a vessel (through its thin wall, by partial volume) joins the lumen in one bright region of
    the magnitude; its velocity tells them apart. The flow core is the bright voxels faster than
    :data:`FLOW_FRACTION_OF_VENC` of the venc (``T``; without a venc, of the 99th percentile of the bright
    voxels' speed), in connected patches of at least :data:`CORE_MIN_VOXELS`. A lumen's voxels slower than
    ``T`` lie in a band along its wall (no slip) and in its partial-volume rim: a profile that falls from the
    core's peak ``u_p`` (95th percentile) at its centre to ``T`` at the core's edge (equal-area radius ``r_c``)
    reaches 0 within ``b = T r_c / (u_p - T)`` more (linear; a parabola's band is half that, a turbulent
    profile's thinner still), so the lumen is the core grown within the bright region by ``1 + floor(b)``
    voxels (one for the partial-volume rim). A core barely above ``T`` (``u_p <= 2 T``) reaches its whole
    radius: slow flow is never cut. What the growth leaves of a flowing region, in connected parts of at least
    :data:`wss_nlp.models.preprocess.MIN_LUMEN_VOXELS` voxels, is returned; regions without a core are left
    to :func:`flowing_regions` to judge whole. A velocity ``(T, ny, nx)`` (cine) uses each voxel's largest
    ``|u|`` over the frames.
    """
    nd = scipy.ndimage
    bright = np.asarray(m) > 0.5
    speed = _speed_image(velocity)
    if not bright.any():
        return np.zeros_like(bright)
    scale = venc if venc is not None else float(np.percentile(speed[bright], 99))
    thr = FLOW_FRACTION_OF_VENC * scale
    cores, n = nd.label(bright & (speed > thr))
    reach = np.zeros_like(bright)
    for j in range(1, n + 1):
        core = cores == j
        size = int(core.sum())
        if size < CORE_MIN_VOXELS:
            continue
        peak = float(np.percentile(speed[core], 95))
        r_c = float(np.sqrt(size / np.pi))
        band = r_c if peak <= 2 * thr else thr * r_c / (peak - thr)
        reach |= nd.binary_dilation(core, iterations=1 + int(band), mask=bright)
    regions, _ = nd.label(bright)
    flowing = np.unique(regions[reach])
    far = bright & ~reach & np.isin(regions, flowing[flowing > 0])
    parts, n_parts = nd.label(far)
    if n_parts == 0:
        return far
    sizes = nd.sum_labels(np.ones_like(m, dtype=float), parts, index=np.arange(1, n_parts + 1))
    big = np.flatnonzero(sizes >= pp.MIN_LUMEN_VOXELS) + 1
    return np.isin(parts, big)


#: The last few :func:`flowing_regions` results, keyed by a digest of their inputs: a slice's preparation, its
#: screens and its dephasing passes ask the same question of the same images (142 calls, 82 distinct, for a
#: 20-frame cine), and the answer is a pure function of them.
_REGIONS: OrderedDict[bytes, Regions] = OrderedDict()
_REGIONS_KEPT = 16


def _digest(*arrays, extra=()) -> bytes:
    h = hashlib.blake2b(repr(extra).encode(), digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(repr((a.shape, a.dtype.str)).encode())
        h.update(a.tobytes())
    return h.digest()


def _copy(r: Regions) -> Regions:
    return Regions(r.labels.copy(), list(r.flowing), list(r.static), dict(r.speeds))


def flowing_regions(m: np.ndarray, raw: np.ndarray, velocity: np.ndarray, venc: float | None, sigma: float) -> Regions:
    """:func:`_flowing_regions`, kept for the same inputs (:data:`_REGIONS`); the caller gets its own copy."""
    key = _digest(m, raw, velocity, extra=(venc, sigma))
    if key in _REGIONS:
        _REGIONS.move_to_end(key)
        return _copy(_REGIONS[key])
    out = _flowing_regions(m, raw, velocity, venc, sigma)
    _REGIONS[key] = _copy(out)
    while len(_REGIONS) > _REGIONS_KEPT:
        _REGIONS.popitem(last=False)
    return out


def _flowing_regions(m: np.ndarray, raw: np.ndarray, velocity: np.ndarray, venc: float | None, sigma: float) -> Regions:
    """Label the bright regions of ``m`` and tell those that flow from static ones.

    A bright region that flows is first split from the static tissue touching it (:func:`beyond_flow`: fat
    against the vessel's wall). A region of at least :data:`wss_nlp.models.preprocess.MIN_LUMEN_VOXELS` voxels
    flows when the median ``|u|`` of its core (eroded by a voxel where it keeps some) exceeds
    :data:`FLOW_FRACTION_OF_VENC` of the venc (without one: of the fastest region's) and
    :data:`FLOW_NOISE_FACTOR` phase-noise deviations. A velocity ``(T, ny, nx)`` (cine) uses each voxel's
    largest ``|u|`` over the frames: a vessel flows at some time of the cycle, fat never.
    """
    far = beyond_flow(m, velocity, venc)
    labels, n = scipy.ndimage.label((m > 0.5) & ~far)
    if far.any():
        parts, n_parts = scipy.ndimage.label(far)
        labels[far] = parts[far] + n
        n += n_parts
    speed_img = _speed_image(velocity)
    speeds, sizes = {}, {}
    for j in range(1, n + 1):
        reg = labels == j
        sizes[j] = int(reg.sum())
        if sizes[j] < pp.MIN_LUMEN_VOXELS:
            continue
        core = scipy.ndimage.binary_erosion(reg)
        core = core if core.sum() >= 4 else reg
        speeds[j] = float(np.median(speed_img[core]))
    if not speeds:
        return Regions(labels, [], [], speeds)
    scale = venc if venc is not None else max(speeds.values())
    flowing: list[int] = []
    static: list[int] = []
    for j, s in speeds.items():
        mag = float(np.median(raw[labels == j]))
        noise = (scale if venc is not None else 1.0) * sigma / (np.pi * max(mag, 1e-300)) if np.isfinite(sigma) else 0
        (flowing if s > FLOW_FRACTION_OF_VENC * scale and s > FLOW_NOISE_FACTOR * noise else static).append(j)
    return Regions(labels, flowing, static, speeds)


def _static_summary(regions: Regions, grid: VoxelGrid) -> list:
    xc, yc = grid.centers()
    out = []
    for j in regions.static:
        reg = regions.labels == j
        out.append(
            {
                "center_mm": [float(xc[reg].mean()), float(yc[reg].mean())],
                "voxels": int(reg.sum()),
                "median_speed_m_s": regions.speeds[j],
            }
        )
    return out


def flow_aware_lumen(
    m: np.ndarray, raw: np.ndarray, velocity, grid: VoxelGrid, source: str, vessel, venc, sigma
) -> tuple[pp.Lumen, Regions]:
    """:func:`wss_nlp.models.preprocess.find_lumen` among the bright regions that flow (fat is never a vessel).

    Static bright regions are taken out of ``m`` before the search, so they are neither chosen nor reported as
    other vessels. Where no region flows (a frame without flow, velocity data of noise) the search is Appendix
    B's among all regions.
    """
    regions = flowing_regions(m, raw, velocity, venc, sigma)
    if not regions.static or not regions.flowing:
        return pp.find_lumen(m, grid, source, vessel), regions
    masked = np.where(regions.mask(regions.static), 0.0, m)
    return pp.find_lumen(masked, grid, source, vessel), regions


# ------------------------------------------------------------------ the surround model
def _poly_fit(x, y, values, order: int, robust: bool):
    """Least-squares polynomial of total degree ``order`` in (x, y) (scaled), with 3-MAD trimming if robust.
    Returns ``(coefficients, rss, n, kept)``."""
    a = off.design(np.stack([x, y], axis=1), order)
    keep = np.ones(values.size, bool)
    for _ in range(3 if robust else 1):
        c = np.linalg.lstsq(a[keep], values[keep], rcond=None)[0]
        r = values - a @ c
        if not robust:
            break
        s = pp.robust_std(r[keep])
        new = np.abs(r) < 3 * max(s, 1e-3 * float(np.median(np.abs(values))))  # noise-free: rounding is no outlier
        if new.sum() < a.shape[1] + 3 or np.array_equal(new, keep):
            break
        keep = new
    c = np.linalg.lstsq(a[keep], values[keep], rcond=None)[0]
    rss = float(np.sum((values[keep] - a[keep] @ c) ** 2))
    return c, rss, int(keep.sum()), keep


def _bic_order(x, y, values, max_order: int, robust: bool):
    """Order by BIC (``n ln(RSS/n) + k ln n`` on the voxels every order keeps) and its fit."""
    best = None
    table = {}
    _, _, _, keep = _poly_fit(x, y, values, max_order, robust)  # the most flexible fit sets the outliers
    for p in range(max_order + 1):
        k = len(off.monomials(2, p))
        if keep.sum() < 3 * k:
            break
        c, rss, n, _ = _poly_fit(x[keep], y[keep], values[keep], p, False)
        bic = n * np.log(max(rss / n, 1e-300)) + k * np.log(n)
        table[p] = float(bic)
        if best is None or bic < best[0]:
            best = (bic, p, c)
    assert best is not None
    return best[1], best[2], table, keep


@dataclass
class SurroundModel:
    """The fitted model of the signal in and around the lumen (raw units), or the two-level decision."""

    kind: str  # "two-level" or "tissue"
    reason: str
    sigma: float  # complex noise per channel from the lumen plateau (NaN without one)
    ring_mean: float = float("nan")  # mean raw magnitude of the outside ring
    ring_spread: float = float("nan")  # its robust deviation about the best constant
    lumen_order: int = -1
    lumen_coefficients: list = field(default_factory=list)
    inflow: float = 0.0  # raw units per (m/s) of through-plane speed (0: the lumen level does not follow the speed)
    outside_order: int = -1
    outside_coefficients: list = field(default_factory=list)
    wall_level: float = float("nan")  # raw level of the wall ring (NaN: no wall ring in the model)
    wall_mm: float = 0.0  # its thickness, mm
    wall_bic: dict = field(default_factory=dict)  # thickness (mm) -> BIC of the near voxels (0: no wall ring)
    centre_mm: tuple = (0.0, 0.0)
    scale_mm: float = 1.0
    outside_bic: dict = field(default_factory=dict)
    ring_voxels: int = 0
    ring_outliers: float = 0.0  # fraction of the ring trimmed as outliers of the outside polynomial

    def ambiguity(self) -> str:
        """Why the choice or the fit of this model is uncertain, or ``""`` (:data:`AMBIGUOUS_OUTLIERS`,
        :data:`AMBIGUOUS_BAND`)."""
        why = []
        s = self.sigma
        if np.isfinite(self.ring_mean) and abs(self.ring_mean / s / NOISE_FLOOR - 1) < AMBIGUOUS_BAND:
            why.append(f"the outside ring's mean ({self.ring_mean / s:.2g} sigma) is at the noise floor's threshold")
        if self.kind == "tissue" and self.ring_outliers > AMBIGUOUS_OUTLIERS:
            why.append(
                f"{100 * self.ring_outliers:.0f} % of the outside ring does not follow a smooth level (bright or "
                "dark structures touch the vessel)"
            )
        return "; ".join(why)

    def as_dict(self) -> dict:
        return asdict(self)

    def _xy(self, grid: VoxelGrid):
        xc, yc = grid.centers()
        return (xc - self.centre_mm[0]) / self.scale_mm, (yc - self.centre_mm[1]) / self.scale_mm

    def levels(self, grid: VoxelGrid, speed=None) -> tuple[np.ndarray, np.ndarray]:
        """``(l, b_far)``: the lumen level (``speed``: the lumen's |u| per voxel for the inflow term) and the
        outside polynomial on the grid (raw units)."""
        x, y = self._xy(grid)
        pts = np.stack([x.ravel(), y.ravel()], axis=1)
        lum = (off.design(pts, self.lumen_order) @ np.asarray(self.lumen_coefficients)).reshape(x.shape)
        if self.inflow and speed is not None:
            lum = lum + self.inflow * np.asarray(speed)
        out = off.design(pts, self.outside_order) @ np.asarray(self.outside_coefficients)
        return lum, out.reshape(x.shape)


def _distances(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (voxels) of each voxel centre to the nearest lumen voxel (outside) and non-lumen voxel (inside)."""
    return scipy.ndimage.distance_transform_edt(~mask), scipy.ndimage.distance_transform_edt(mask)


#: Voxel distance to the nearest lumen voxel from which a voxel is fully outside (beyond the 8-neighbours).
OUTSIDE_FROM = 1.9
#: The outside ring starts at least this far (mm) from the lumen: a vessel wall is thinner.
WALL_MAX_MM = 2.5


def ring_start(h: float) -> float:
    """Voxel distance from the lumen at which the outside ring begins (past the partial-volume voxels and wall)."""
    return max(OUTSIDE_FROM, WALL_MAX_MM / h)


def _lumen_level(x, y, raw, speed):
    """Lumen level by BIC over the polynomial degree (<= :data:`LEVEL_ORDER`) and, with degree <= 1 (coil
    shading), an inflow term ``kappa |u|``: ``(order, coefficients, kappa)``."""
    best = None
    for p in range(LEVEL_ORDER + 1):
        base = off.design(np.stack([x, y], axis=1), p)
        # with the speed only shading's degrees (<= 1): a parabolic profile's speed is itself of degree 2
        for with_speed in (False, True) if speed is not None and p <= 1 else (False,):
            a = np.column_stack([base, speed]) if with_speed else base
            if raw.size < 3 * a.shape[1]:
                continue
            c = np.linalg.lstsq(a, raw, rcond=None)[0]
            r = raw - a @ c
            floor = 1e-3 * float(np.median(np.abs(raw)))  # noise-free data: no trimming of rounding
            keep = np.abs(r) < 3 * max(pp.robust_std(r), floor)  # trimmed once: a misregistered voxel
            c = np.linalg.lstsq(a[keep], raw[keep], rcond=None)[0]
            n = int(keep.sum())
            rss = float(np.sum((raw[keep] - a[keep] @ c) ** 2))
            bic = n * np.log(max(rss / n, floor**2 * 1e-6)) + a.shape[1] * np.log(n)
            if best is None or bic < best[0]:
                best = (bic, p, c[: base.shape[1]], float(c[-1]) if with_speed else 0.0)
    assert best is not None
    return best[1], best[2], best[3]


def fit_surround(
    raw: np.ndarray, lumen: pp.Lumen, grid: VoxelGrid, sigma: float, exclude: np.ndarray, speed=None
) -> SurroundModel:
    """Choose and fit the model of what surrounds the lumen (see the module notes).

    The outside ring: voxels between :func:`ring_start` voxels (past the partial-volume voxels and a wall of
    up to :data:`WALL_MAX_MM`) and that plus ``max(3, RING_MM / h)`` voxels from the lumen, less ``exclude``
    (other vessels, dilated). Two-level when the ring's mean is below :data:`NOISE_FLOOR` sigma (air).
    Otherwise, be the ring one level (a bath, tissue without texture) or many: the lumen level ``l`` on the
    voxels at least two voxels inside (:func:`_lumen_level`: degree and inflow term ``kappa |u|`` by BIC,
    ``speed`` the measured ``|u|``), the outside polynomial ``b_far`` on the ring (outliers beyond 3 MAD
    trimmed: fat, texture), of total degree <= :data:`LEVEL_ORDER` by BIC. The wall ring is fitted later
    (:func:`fit_wall`), once a preliminary wall is known.
    """
    h = grid.h
    d_out, d_in = _distances(lumen.mask)
    start, width = ring_start(h), max(3.0, RING_MM / h)
    ring = (d_out >= start) & (d_out < start + width) & ~exclude
    # the outermost voxels of the view carry edge artefacts on scanners: left out
    ring[0, :] = ring[-1, :] = ring[:, 0] = ring[:, -1] = False
    model = SurroundModel("two-level", "", sigma, ring_voxels=int(ring.sum()))
    if ring.sum() < 20 or not np.isfinite(sigma):
        model.reason = "no outside ring or no lumen plateau to judge the background by: two-level (Appendix B)"
        return model
    vals = raw[ring]
    model.ring_mean = float(np.mean(vals))
    model.ring_spread = pp.robust_std(vals)
    if model.ring_mean < NOISE_FLOOR * sigma:
        model.reason = (
            f"the background is noise (mean {model.ring_mean / sigma:.2g} sigma < {NOISE_FLOOR:g}): two-level"
        )
        return model
    xc, yc = grid.centers()
    centre = (float(lumen.center[0]), float(lumen.center[1]))
    scale = float(max(3 * lumen.r_area, 4 * h))
    x, y = (xc - centre[0]) / scale, (yc - centre[1]) / scale
    order, c_out, table, keep = _bic_order(x[ring], y[ring], vals, LEVEL_ORDER, robust=True)
    model.outside_bic = {str(k): v for k, v in table.items()}
    model.ring_outliers = float(1.0 - keep.mean())
    # a uniform outside (one level within the noise: a bath, or tissue without texture) is no reason for Appendix
    # B's model either: its histogram peaks need not be the ring's level (air and fat elsewhere in the view), a
    # wall ring or a varying lumen level may lie within, and the partial-volume voxels' phase mixes the lumen's with
    # the outside signal's (lumen_velocity); the fitted model with constant levels holds the bath exactly
    inner = d_in >= 2
    if inner.sum() < 6:
        model.reason = "the lumen has too few voxels fully inside for its level: two-level"
        return model
    l_order, c_lum, kappa = _lumen_level(x[inner], y[inner], raw[inner], None if speed is None else speed[inner])
    return replace(
        model,
        kind="tissue",
        reason=(
            f"tissue around the lumen (outside ring mean {model.ring_mean / sigma:.2g} sigma, spread "
            f"{model.ring_spread / sigma:.2g} sigma): lumen level of degree {l_order}, outside level of degree {order}"
        ),
        lumen_order=l_order,
        lumen_coefficients=[float(v) for v in c_lum],
        inflow=kappa,
        outside_order=order,
        outside_coefficients=[float(v) for v in c_out],
        centre_mm=centre,
        scale_mm=scale,
    )


#: Wall thicknesses tried (mm) by :func:`fit_wall`.
WALL_GRID_MM = (0.3, 0.45, 0.6, 0.8, 1.0, 1.2, 1.5, 1.8, 2.2)
#: Quadrature points per voxel axis of the wall model's volume fractions.
WALL_QUAD = 12
#: Most geometry solves of the wall model's fixed-point iteration (:func:`preprocess`), and the change of the
#: mean radius (in voxels) that ends it. More rounds drift (a thinner, darker ring and a larger lumen explain the
#: partial-volume voxels about equally: 8 rounds moved the noise-free laminar wall of a development seed from
#: -0.01 to +0.03 mm at h = 1.5 mm); three were nearest the truth on the development seeds.
WALL_ROUNDS, WALL_TOL = 3, 2e-3
#: Voxels next to bright static tissue (fat) left out of the wall ring's fit: voxels whose outside part is fat reach
#: beyond the fat region the flow splits off (:func:`beyond_flow`) by its partial-volume rim. Measured with four fat
#: deposits against the wall at h = 1.5 mm (seeds 101-108 and 301-306): a margin of one voxel left the wall unfound
#: on 1 of the 14 slices (WSS 37 % off), two on none.
WALL_FAT_MARGIN = 2


def fraction_image(grid: VoxelGrid, center, coefficients, order: int = WALL_QUAD) -> np.ndarray:
    """Volume fraction of the star-shaped region ``r < R(phi)`` in every voxel (midpoint rule, ``order^2``)."""
    from .measurement import lumen_voxels

    out = np.zeros(grid.shape[0] * grid.shape[1])
    lv = lumen_voxels(grid, center, coefficients, order)
    out[lv.index] = lv.fraction
    return out.reshape(grid.shape)


def fit_wall(
    raw, lum, b_far, f, center, coefficients, grid: VoxelGrid, near: np.ndarray, force: bool = False
) -> tuple[float, float, dict]:
    """Level ``w`` and thickness ``t`` of a wall ring about the lumen ``R`` from the voxels ``near`` it.

    Notes
    -----
    A voxel holds lumen (fraction ``f``), wall (``F_t - f``, ``F_t`` the fraction within ``R + t``) and the
    outside beyond (``1 - F_t``): ``raw = l f + w (F_t - f) + b (1 - F_t)``. For each ``t`` of
    :data:`WALL_GRID_MM` the level ``w`` is linear least squares; the thickness with the smallest BIC
    (``n ln(RSS/n) + k ln n``, ``k = 2``) is taken if it beats the model without a wall ring (``k = 0``), or
    in any case with ``force`` (the first rounds: a wall misplaced by the model without one hides the ring).
    Returns ``(w, t, table)``; ``(nan, 0, table)`` without a wall.
    """
    sel = near.ravel()
    y = (raw - lum * f - b_far * (1 - f)).ravel()[sel]  # what the lumen and the far outside leave
    n = int(sel.sum())
    table = {"0": float(n * np.log(max(np.mean(y**2), 1e-300)))}
    best = (np.inf if force else table["0"], float("nan"), 0.0)
    c = np.array(coefficients, dtype=float)
    for t in WALL_GRID_MM:
        ct = c.copy()
        ct[0] += t
        g = (fraction_image(grid, center, ct) - f).ravel()[sel]  # the wall's fraction
        den = float(np.sum(g * g))
        if den <= 0:
            continue
        bg = b_far.ravel()[sel]
        w = float(np.sum(g * (y + bg * g)) / den)  # y = (w - b) g
        rss = float(np.sum((y - (w - bg) * g) ** 2))
        bic = n * np.log(max(rss / n, 1e-300)) + 2 * np.log(n)
        table[f"{t:g}"] = float(bic)
        if bic < best[0]:
            best = (bic, w, t)
    return best[1], best[2], table


def fractions(
    raw: np.ndarray,
    model: SurroundModel,
    lumen_mask: np.ndarray,
    grid: VoxelGrid,
    wall_fraction=None,
    speed=None,
    theta=None,
    outside=None,
):
    """``(f, static)``: the data's lumen fraction near the lumen and the static signal in each voxel (raw units).

    Without a wall ring ``f = (raw - b) / (l - b)``; with one (``wall_fraction``, ``F_t``: the fraction within
    ``R + t`` of the current wall) ``f = (raw - w F_t - b (1 - F_t)) / (l - w)``, the static signal being
    ``w (F_t - f) + b (1 - F_t)``. ``f`` is 0 beyond the outside ring (no voxel there is fitted) and is
    truncated only to [-0.5, 1.5] (a truncation at 0 would turn texture into a positive bias).

    ``theta`` (rad, per voxel: the lumen part's phase relative to the static tissue's) corrects the mixing
    for the phase: the voxel's magnitude is ``|l f e^{i theta} + s|``, not ``l f + s``, so the magnitude the
    linear forms use is ``raw + (l f + s) - |l f e^{i theta} + s|`` at the current ``f`` (two fixed-point
    steps). Near-wall speeds of a flat (turbulent) profile reach a radian of phase in the partial-volume voxels.

    ``outside`` (bool): voxels known to hold no lumen (bright static tissue, :func:`beyond_flow`): ``f = 0`` and
    their whole signal static there.
    """
    lum, b = model.levels(grid, speed)
    d_out, _ = _distances(lumen_mask)
    data = np.asarray(raw, float)
    for _ in range(1 if theta is None else 3):
        if wall_fraction is None or not np.isfinite(model.wall_level):
            lum = np.maximum(lum, b + 1e-6)
            f = (data - b) / (lum - b)
            static = b * (1 - np.clip(f, 0.0, 1.0))
        else:
            w, ft = model.wall_level, wall_fraction
            lw = np.maximum(lum - w, 1e-6)
            f = (data - w * ft - b * (1 - ft)) / lw
            fc = np.clip(f, 0.0, 1.0)
            static = w * np.clip(ft - fc, 0.0, None) + b * (1 - ft)
        if theta is not None:
            part = lum * np.clip(f, 0.0, 1.0)
            data = raw + (part + static) - np.abs(part * np.exp(1j * theta) + static)
    f = np.where(d_out < ring_start(grid.h) + max(3.0, RING_MM / grid.h), f, 0.0)
    if outside is not None:
        f = np.where(outside, 0.0, f)
        static = np.where(outside, np.asarray(raw, float), static)
    return np.clip(f, -0.5, 1.5), static


#: Partial-volume voxels whose lumen fraction is below this keep their measured velocity (mostly tissue's phase).
PV_MIN_FRACTION = 0.25
#: Largest factor by which a partial-volume voxel's velocity is raised (its noise grows by the same factor).
PV_MAX_GAIN = 3.0


def lumen_velocity(raw, velocity, f, static, near: np.ndarray, venc: float | None = None, static_u=None):
    """The lumen's own velocity in the partial-volume voxels ``near``: the measured one undiluted.

    Notes
    -----
    The voxel's complex signal is ``d = l f e^{i theta} + s e^{i pi o / venc}`` with ``s`` the static signal
    (``static``, :func:`fractions`) at the static tissue's velocity ``o`` (``static_u``: the offset where it was
    not subtracted, else 0), so the lumen's phase is ``theta = arg(d - s e^{i pi o / venc})``,
    ``d = raw e^{i pi u / venc}``; without a venc, the first-order form
    ``u |d| / (|d| - s)``. Applied where ``f`` >= :data:`PV_MIN_FRACTION`, the result limited to
    :data:`PV_MAX_GAIN` times the measured value (where the lumen's part is small, ``d - s`` is mostly noise).

    Returns ``(u, carrier)``: the velocity and the magnitude that carries its phase, ``|d - s|`` (at least
    ``|d| / PV_MAX_GAIN``), which sets the phase noise ``venc sigma / (pi carrier)``
    (:func:`wss_nlp.parameters.noise.phase_noise_std`).
    """
    u = np.array(velocity, dtype=float, copy=True)
    carrier = np.array(raw, dtype=float, copy=True)
    sel = near & (f >= PV_MIN_FRACTION) & (f < 1.0)
    s = np.clip(static, 0.0, None)[sel]
    if venc is not None:
        rot = 1.0 if static_u is None else np.exp(1j * np.pi * np.asarray(static_u)[sel] / venc)
        d = raw[sel] * np.exp(1j * np.pi * u[sel] / venc) - s * rot
        new = venc * np.angle(d) / np.pi
        part = np.abs(d)
    else:
        part = np.maximum(raw[sel] - s, 1e-12)
        new = u[sel] * raw[sel] / part
    cap = PV_MAX_GAIN * np.abs(u[sel])
    u[sel] = np.clip(new, -cap, cap)
    carrier[sel] = np.maximum(part, raw[sel] / PV_MAX_GAIN)
    return u, carrier


# ------------------------------------------------------------------ the hooks
def _peaks(raw: np.ndarray, velocity: np.ndarray, venc, source: str) -> pp.Normalization:
    """Appendix B's histogram peaks; where only the contrast-to-noise check refuses them (textured tissue
    widens the background class) the peaks stand if a bright region flows."""
    try:
        return pp.histogram_peaks(raw, source)
    except NoVesselError as exc:
        if "contrast-to-noise" not in str(exc):
            raise
        vals = raw.ravel()
        bins = int(np.clip(np.sqrt(vals.size), 32, 256))
        thr = pp._otsu(vals, bins)
        low, high = vals[vals <= thr], vals[vals > thr]
        norm = pp.Normalization(pp._peak(low, bins), pp._peak(high, bins), thr, pp.robust_std(low))
        m = pp.normalize_magnitude(raw, norm)
        regions = flowing_regions(m, raw, velocity, venc, float("nan"))
        # a vessel's velocity is smooth: its 4-neighbour high-pass is small against its speed (pure noise's
        # phases give a high-pass as large as the speeds themselves)
        hp = np.abs(_highpass(velocity)) if velocity.ndim == 2 else None
        coherent = [
            j for j in regions.flowing
            if hp is not None and np.median(hp[regions.labels == j]) < COHERENCE * regions.speeds[j]
        ]  # fmt: skip
        if not norm.m1 > norm.m0 or venc is None or not coherent:
            raise
        return norm


def screen_preprocess(raw, velocity, grid: VoxelGrid, source: str = "", vessel=None, venc=None, clip_upper=True):
    """Appendix B's preprocessing with the flow-aware lumen (the plausibility screen's call): ``(norm, m, lumen)``.

    ``lumen.tissue["static_bright"]`` lists the bright regions that do not flow (fat), which are not
    "other vessels". ``velocity`` may be a cine series' ``(T, ny, nx)`` of one slice: a region flows if it
    flows in some frame (:func:`flowing_regions`).
    """
    norm = _peaks(np.asarray(raw, float), np.asarray(velocity, float), venc, source)
    m = pp.normalize_magnitude(raw, norm, clip_upper)
    # the plateau's lumen among the regions that flow (before the noise is known: by the venc fraction alone):
    # fat is static, be it larger than the lumen, touching it or reaching the border of the view
    lumen0 = flow_aware_lumen(m, np.asarray(raw, float), velocity, grid, source, vessel, venc, float("nan"))[0]
    v2 = velocity if np.ndim(velocity) == 2 else None  # a cine series' (T, ny, nx): no plateau high-pass of it
    sigma = lumen_noise_sigma(np.asarray(raw, float), lumen0.mask, v2, venc)
    lumen, regions = flow_aware_lumen(m, np.asarray(raw, float), velocity, grid, source, vessel, venc, sigma)
    return norm, m, replace(lumen, tissue={"static_bright": _static_summary(regions, grid)})


def series_offset(
    raw,
    velocity,
    grid: VoxelGrid,
    source: str = "",
    vessel=None,
    venc: float | None = None,
    measurement: acq_model.MeasurementModel | None = None,
) -> off.SeriesOffset:
    """One background offset for a cine series of one slice: magnitudes and velocities ``(T, ny, nx)``.

    The eddy currents repeat in every frame, so the offset is fitted once (:func:`wss_nlp.models.offset.
    correct_series`: to the frames' mean velocity, on static tissue that is also still in time) and each frame
    subtracts the same field (:func:`preprocess` with ``series_offset``). What flows is judged over the series
    (:func:`flowing_regions` on each voxel's largest speed over the frames: a vein whose time-mean speed is small
    still flows at some time of the cycle), on the frames' mean magnitude; ``vessel`` (x, y in mm, e.g. the
    series' shared box centre) picks the vessel the offset is reported at. The complex noise per channel is the
    median over the frames of the lumen plateau's (:func:`lumen_noise_sigma`).
    """
    measurement = measurement or acq_model.VoxelMeans()
    raw = np.asarray(raw, float)
    u = np.asarray(velocity, float)
    mean_raw = raw.mean(axis=0)
    norm = _peaks(mean_raw, u, venc, source)
    m = pp.normalize_magnitude(mean_raw, norm, measurement.clip_upper)
    lumen0 = flow_aware_lumen(m, mean_raw, u, grid, source, vessel, venc, float("nan"))[0]
    hp = measurement.highpass_noise_variance(grid.shape)
    sigma = float(np.nanmedian([lumen_noise_sigma(raw[k], lumen0.mask, u[k], venc, hp) for k in range(len(raw))]))
    lumen, regions = flow_aware_lumen(m, mean_raw, u, grid, source, vessel, venc, sigma)
    flowing = regions.mask(regions.flowing) | lumen.mask
    fixed, rec, static = off.correct_series(
        u, raw, (grid.dy, grid.dx), (grid.origin_mm[1], grid.origin_mm[0]), sigma, flowing,
        (lumen.center[1], lumen.center[0]), lumen.r_area, venc,
        margin=int(np.ceil(off.FLOW_MARGIN * measurement.blur_voxels)),
    )  # fmt: skip
    return off.SeriesOffset(u[0] - fixed[0], rec, static)


def preprocess(
    raw,
    velocity,
    grid: VoxelGrid,
    source: str,
    vessel=None,
    venc: float | None = None,
    measurement: acq_model.MeasurementModel | None = None,
    options: TissueOptions | None = None,
    near=None,
    series_offset: off.SeriesOffset | None = None,
):
    """The preprocessing of one slice with the surround model and the offset correction.

    Returns ``(norm, m, lumen, velocity, raw)``: as :func:`wss_nlp.models.preprocess.preprocess`, the velocity
    the fits should use and the magnitude that carries its phase (the measured one but in partial-volume
    voxels in tissue: :func:`lumen_velocity`), which the noise estimates use. With ``options.off``
    (``--surround two-level --no-offset-correction``) exactly Appendix B's. Otherwise:

    1. Appendix B's normalization; the lumen among the bright regions that flow (:func:`flow_aware_lumen`);
    2. the offset correction (:func:`wss_nlp.models.offset.correct`) on static tissue, if enabled;
    3. the surround model (:func:`fit_surround`): two-level leaves ``m`` as it is; tissue replaces it near the
       lumen by :func:`fractions`, re-finds the lumen in it, takes the lumen's own velocity in the
       partial-volume voxels (:func:`lumen_velocity`) and gives the noise estimates the outside's noise-free
       magnitude (``lumen.signal``, :func:`wss_nlp.parameters.noise.complex_noise_sigma`), so their
       complex noise is the lumen plateau's.

    ``near`` (x, y in mm; a cine series' shared box centre): without ``vessel``, the flowing region there is the
    lumen (a frame of slow flow need not find its vessel among the fast ones). ``series_offset`` (a cine series'
    one offset, :func:`series_offset`) replaces the slice's own fit in step 2. ``lumen.tissue`` records all of it
    (``tissue_json`` in the result file, ``wss-nlp analyze``).
    ``measurement``: the acquisition's measurement model (:mod:`wss_nlp.models.acquisition`; None: voxel
    means); one whose :attr:`~wss_nlp.models.acquisition.MeasurementModel.two_level_only` says why (a k-space
    acquisition: its PSF tails are modelled with two levels) keeps the two-level model.
    """
    options = options or TissueOptions()
    measurement = measurement or acq_model.VoxelMeans()
    clip_upper = measurement.clip_upper
    if options.off:
        norm, m, lumen = pp.preprocess(raw, grid, source, vessel, clip_upper)
        return norm, m, lumen, np.asarray(velocity, float), np.asarray(raw, float)
    raw = np.asarray(raw, float)
    u = np.asarray(velocity, float)
    norm = _peaks(raw, u, venc, source)
    m = pp.normalize_magnitude(raw, norm, clip_upper)
    # the plateau's lumen among the regions that flow (before the noise is known: by the venc fraction alone):
    # fat is static, be it larger than the lumen, touching it or reaching the border of the view
    lumen0 = flow_aware_lumen(m, raw, u, grid, source, vessel, venc, float("nan"))[0]
    sigma = lumen_noise_sigma(raw, lumen0.mask, u, venc, measurement.highpass_noise_variance(grid.shape))
    lumen, regions = flow_aware_lumen(m, raw, u, grid, source, vessel, venc, sigma)
    if vessel is None and near is not None:
        try:
            lumen = replace(flow_aware_lumen(m, raw, u, grid, source, near, venc, sigma)[0], chosen_by=lumen.chosen_by)
        except NoVesselError:  # nothing bright at the box centre: the frame's own choice stands
            pass
    record: dict = {"static_bright": _static_summary(regions, grid), "sigma_lumen_plateau": sigma}
    # bright static tissue (fat) within two voxels of the lumen: the partial-volume voxels against it mix lumen, wall
    # and fat, which the surround model reads with the smooth outside level (a note: notes())
    near_lumen = scipy.ndimage.binary_dilation(lumen.mask, iterations=2)
    record["static_bright_touching_voxels"] = int(np.sum(near_lumen & regions.mask(regions.static)))
    flowing = regions.mask(regions.flowing) | lumen.mask
    # the offset is fitted in any case: with --no-offset-correction it is not subtracted, but the static tissue's
    # phase is still what the partial-volume voxels' lumen phase is measured against (lumen_velocity)
    if series_offset is not None:  # the series' one offset (the eddy currents repeat in every frame)
        fitted, rec = u - series_offset.image, replace(series_offset.record)
    else:
        fitted, rec, _ = off.correct(
            u, raw, (grid.dy, grid.dx), (grid.origin_mm[1], grid.origin_mm[0]), sigma, flowing,
            (lumen.center[1], lumen.center[0]), lumen.r_area, venc,
            margin=int(np.ceil(off.FLOW_MARGIN * measurement.blur_voxels)),
        )  # fmt: skip
    static_u = u - fitted  # the static tissue's velocity offset (0 where not fitted)
    if options.offset_correction:
        u, static_u = fitted, np.zeros_like(u)
    else:
        rec.applied, rec.uncertain, rec.reason = False, False, "switched off (--no-offset-correction)"
    record["offset"] = rec.as_dict()
    if options.surround == "two-level" or measurement.two_level_only:
        why = measurement.two_level_only or "--surround two-level"
        record["surround"] = SurroundModel("two-level", why, sigma).as_dict()
        return norm, m, replace(lumen, tissue=record), u, raw
    # bright static tissue (fat) is no part of the smooth outside level, and no part of the lumen: its voxels and
    # their partial-volume rim stay out of the outside ring, its voxels' lumen fraction is 0 (it does not flow)
    bright_static = regions.mask(regions.static)
    exclude = scipy.ndimage.binary_dilation(flowing & ~lumen.mask, iterations=2)
    exclude |= scipy.ndimage.binary_dilation(bright_static, iterations=1) & ~lumen.mask
    model = fit_surround(raw, lumen, grid, sigma, exclude, np.abs(u))
    record["surround"] = model.as_dict()
    if model.kind == "two-level":
        return norm, m, replace(lumen, tissue=record), u, raw
    speed = np.abs(u)  # the lumen's speed for the inflow term: the measured one, undiluted below as f is known
    f, static = fractions(raw, model, lumen.mask, grid, speed=speed, outside=bright_static)
    d_out, d_in = _distances(lumen.mask)
    reach = ring_start(grid.h) + max(3.0, RING_MM / grid.h)
    try:
        new = pp.find_lumen(np.where(d_out < reach, f, 0.0), grid, source)
    except NoVesselError as exc:  # the surround model lost the lumen: keep Appendix B's, say so
        record["surround"]["kind"] = "two-level"
        record["surround"]["reason"] = f"the surround model lost the lumen ({exc}): two-level"
        return norm, m, replace(lumen, tissue=record), u, raw
    # the wall ring: a preliminary geometry (default options) gives the voxels' fractions, they the wall's
    # level and thickness, those the data of the next geometry (a fixed point of at most WALL_ROUNDS solves; the
    # first rounds always take a ring, a misplaced wall hides it; the last fit decides whether it stays)
    # partial-volume voxels and the first outside layer (without static bright tissue: no wall level there)
    ring = (d_out < ring_start(grid.h)) & ~(d_in >= 2) & ~bright_static
    # the wall's level and thickness from the voxels whose outside part is the smooth outside level: next to bright
    # static tissue (fat) it is not, and a few such voxels hide the wall ring from BIC (then the lumen takes the
    # wall's place: the in-vivo phantom with fat against the wall, WSS 25-55 % off at h = 1.5 mm)
    wall_voxels = ring & ~scipy.ndimage.binary_dilation(bright_static, iterations=WALL_FAT_MARGIN)
    u_l = lumen_velocity(raw, u, f, static, ring, venc, static_u)[0]
    speed = np.abs(u_l)
    theta = None if venc is None else np.where(ring, np.pi * (u_l - static_u) / venc, 0.0)  # lumen vs static
    lum, b_far = model.levels(grid, speed)
    from . import geometry as geo  # here: the geometry module is heavy and only this branch needs it

    gopt = geo.GeometryOptions()
    problem = geo.GeometryProblem(grid, f, new.center, new.r0, new.r1, new.r_area)
    try:
        coef = geo.solve(problem, gopt).coefficients
        for _ in range(WALL_ROUNDS):
            w, t, table = fit_wall(raw, lum, b_far, fraction_image(grid, new.center, coef), new.center, coef, grid,
                                   wall_voxels, force=True)  # fmt: skip
            model = replace(model, wall_level=w, wall_mm=t, wall_bic=table)
            ct = np.array(coef, dtype=float)
            ct[0] += t
            f, static = fractions(
                raw, model, lumen.mask, grid, fraction_image(grid, new.center, ct), speed, theta, bright_static
            )
            u_l = lumen_velocity(raw, u, f, static, ring, venc, static_u)[0]
            speed = np.abs(u_l)
            theta = None if venc is None else np.where(ring, np.pi * (u_l - static_u) / venc, 0.0)
            lum, b_far = model.levels(grid, speed)
            before, coef = coef, geo.solve(replace(problem, magnitude=f), gopt, x0=coef).coefficients
            if abs(coef[0] - before[0]) < WALL_TOL * grid.h:
                break
        # the decision: does a ring at the final wall beat none (BIC)? If not, the data without one
        w, t, table = fit_wall(
            raw, lum, b_far, fraction_image(grid, new.center, coef), new.center, coef, grid, wall_voxels
        )
        if not np.isfinite(w):
            model = replace(model, wall_level=float("nan"), wall_mm=0.0, wall_bic=table)
            f, static = fractions(raw, model, lumen.mask, grid, None, speed, theta, bright_static)
    except Exception as exc:  # noqa: BLE001 - a failed preliminary solve leaves the model without a wall ring
        logger.info(f"{source}: no wall ring fitted ({exc})")
    record["surround"] = model.as_dict()
    u, carrier = lumen_velocity(raw, u, f, static, ring, venc, static_u)
    signal = np.where(raw > NOISE_FLOOR * sigma, np.sqrt(np.maximum(raw**2 - 2 * sigma**2, 0.0)), 0.0)
    lumen = replace(
        new, others=lumen.others, others_mask=lumen.others_mask, chosen_by=lumen.chosen_by, signal=signal,
        tissue=record,
    )  # fmt: skip
    return norm, f, lumen, u, carrier


def correct_inplane(
    inplane,
    raw,
    grid: VoxelGrid,
    lumen: pp.Lumen,
    venc: float | None,
    measurement: acq_model.MeasurementModel | None = None,
) -> tuple[np.ndarray, list]:
    """The background offset of the in-plane velocity components (4D flow): ``(inplane, records)``.

    Each encoding direction has its own eddy currents, so each in-plane component ``(2, ny, nx)`` gets its own
    polynomial (:func:`wss_nlp.models.offset.correct`) on the static tissue of the through-plane fit (signal,
    away from the lumen and the other vessels ``lumen.noise_mask``), with the noise of the lumen plateau
    (``lumen.tissue["sigma_lumen_plateau"]``) and the same venc. ``raw`` is the measured magnitude. The records
    (one per component, x then y) go to ``lumen.tissue["offset_inplane"]``. A cine series fits them per frame
    (only the through-plane offset is fitted once over the series).
    """
    measurement = measurement or acq_model.VoxelMeans()
    comps = np.array(inplane, dtype=float, copy=True)
    sigma = float((lumen.tissue or {}).get("sigma_lumen_plateau", float("nan")))
    records = []
    for c in range(comps.shape[0]):
        if not np.isfinite(sigma):
            records.append(off.OffsetRecord(False, "no lumen plateau to measure the noise by").as_dict())
            continue
        comps[c], rec, _ = off.correct(
            comps[c], raw, (grid.dy, grid.dx), (grid.origin_mm[1], grid.origin_mm[0]), sigma, lumen.noise_mask,
            (lumen.center[1], lumen.center[0]), lumen.r_area, venc,
            margin=int(np.ceil(off.FLOW_MARGIN * measurement.blur_voxels)),
        )  # fmt: skip
        records.append(rec.as_dict())
    return comps, records


# ------------------------------------------------------------------ flags and reports
#: Offset records that need no note: nothing to correct, or the user said so.
_QUIET = ("no static tissue in view", "switched off")


def notes(record: dict | None) -> list[str]:
    """The notes a slice carries for its surround model and offset correction (``lumen.tissue``)."""
    if not record:
        return []
    out = []
    o = record.get("offset")
    if o and not o["applied"] and not o["reason"].startswith(_QUIET):
        out.append(f"background phase offset not corrected: {o['reason']}")
    if o and o["applied"] and o.get("uncertain"):
        venc = o["at_vessel_m_s"] / o["at_vessel_fraction_of_venc"]
        std = 100 * o["at_vessel_std_m_s"] / venc
        spread = 100 * o.get("at_vessel_order_spread_m_s", 0.0) / venc
        why = (
            f"by {std:.2g} % of the venc (1 std, > {100 * off.MAX_STD_FRACTION:g} %: too little or too noisy static "
            "tissue to pin it down)"
            if std >= spread
            else f"by {spread:.2g} % of the venc (its change with the polynomial's order, > "
            f"{100 * off.MAX_STD_FRACTION:g} %: the static tissue does not tell the offset under the vessel)"
        )
        out.append(
            f"background phase offset removed, but its value at the vessel is uncertain {why}; the WSS may carry a "
            "residual offset"
        )
    if record.get("static_bright_touching_voxels", 0) > 0:
        out.append(
            f"bright static tissue (fat?) touches the vessel ({record['static_bright_touching_voxels']} voxels within "
            "two voxels of the lumen): it is split off by the flow, but the partial-volume voxels against it are "
            "read with the smooth outside level; the wall there, the near-wall velocity and the WSS may be biased "
            "(by about half a point at 1.5 mm voxels on the in-vivo phantom: scripts/results/invivo_touching.md)"
        )
    sm = record.get("surround")
    if sm:
        model = SurroundModel(**{k: (tuple(v) if k == "centre_mm" else v) for k, v in sm.items()})  # type: ignore[arg-type]
        why = model.ambiguity()
        if why:
            out.append(
                f"the model of the signal around the lumen is ambiguous ({model.kind} chosen): {why}; the wall "
                "position, and the WSS with it, may be biased (docs, 'Input checks': vessels in tissue)"
            )
    return out


def read_tissue(path) -> dict:
    """``{slice name: record}``: each slice's ``tissue_json`` (surround model, offset correction) of a result file."""
    import json

    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        for name in sorted(k for k in f if k.startswith("slice_")):
            if "tissue_json" in f[name].attrs:
                out[name] = json.loads(f[name].attrs["tissue_json"])
    return out


def report_lines(record: dict) -> list[str]:
    """What ``wss-nlp analyze`` says about one slice's surround model and offset correction."""
    lines = []
    sm = record.get("surround") or {}
    if sm:
        text = f"surround model: {sm['kind']} ({sm['reason']})"
        if sm["kind"] == "tissue" and np.isfinite(sm.get("wall_level", float("nan"))):
            text += f"; wall ring {sm['wall_mm']:g} mm at level {sm['wall_level']:.3g} (raw units)"
        lines.append(text)
    o = record.get("offset") or {}
    if o:
        if o["applied"]:
            lines.append(
                f"background phase offset: removed, polynomial of degree {o['order']} fitted to "
                f"{o['inlier_voxels']} of {o['static_voxels']} static voxels (MSAC inliers); at the vessel "
                f"{1000 * o['at_vessel_m_s']:.3g} mm/s = {100 * o['at_vessel_fraction_of_venc']:.2f} % of the venc"
            )
        else:
            lines.append(f"background phase offset: not corrected ({o['reason']})")
        if o.get("frames", 1) > 1:
            lines.append(f"  (one offset for the cine series, fitted to the mean of its {o['frames']} frames)")
    for axis, oi in zip("xy", record.get("offset_inplane") or []):
        if oi["applied"]:
            lines.append(
                f"in-plane {axis} velocity offset: removed, degree {oi['order']}; at the vessel "
                f"{1000 * oi['at_vessel_m_s']:.3g} mm/s = {100 * oi['at_vessel_fraction_of_venc']:.2f} % of the venc"
            )
        else:
            lines.append(f"in-plane {axis} velocity offset: not corrected ({oi['reason']})")
    for j in record.get("static_bright", []):
        c = j["center_mm"]
        lines.append(
            f"static bright region at ({c[0]:.1f}, {c[1]:.1f}) mm, {j['voxels']} voxels, median speed "
            f"{1000 * j['median_speed_m_s']:.3g} mm/s: not a vessel (fat?)"
        )
    return lines


def model_images(record: dict, grid: VoxelGrid) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(outside level, offset)`` images of a slice's record (raw units, m/s); None where not fitted."""
    outside = offset = None
    sm = record.get("surround") or {}
    if sm.get("kind") == "tissue":
        model = SurroundModel(**{k: (tuple(v) if k == "centre_mm" else v) for k, v in sm.items()})  # type: ignore[arg-type]
        outside = model.levels(grid)[1]
    o = record.get("offset") or {}
    if o.get("applied"):
        fit = off.OffsetFit(o["order"], np.asarray(o["coefficients"]), np.asarray(o["centre_mm"]), o["scale_mm"],
                            np.zeros(0, bool))  # fmt: skip
        yy, xx = off.coordinates(grid.shape, (grid.dy, grid.dx), (grid.origin_mm[1], grid.origin_mm[0]))
        offset = fit(np.stack([yy.ravel(), xx.ravel()], axis=1)).reshape(grid.shape)
    return outside, offset


def model_reach(lumen_mask: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """The voxels the surround model describes: up to the outer edge of the outside ring."""
    d_out, _ = _distances(lumen_mask)
    return d_out < ring_start(grid.h) + max(3.0, RING_MM / grid.h)
