"""Background phase correction of a 4D flow volume: each velocity component's offset fitted on static tissue.

Eddy currents add a smooth phase to every voxel, which reads as a velocity offset ``o_c(x)`` in each encoded
component ``c`` (Dyverfeldt et al. 2015, Bissell et al. 2023: a required step of 4D flow). Static tissue does not
move, so its measured velocity is the offset plus noise; a low-order polynomial in the world coordinates, fitted
robustly there (:func:`wss_nlp.models.offset.fit_offset`: MSAC, the order by an information criterion) and
subtracted from every voxel of every frame, removes the offset from the lumen too.

Static tissue: the voxels with signal (time-mean magnitude above Otsu's threshold of the magnitude: air and noise
below it), at least :data:`MARGIN_MM` from the lumen mask (partial volume, the wall's blur), whose time-mean
speed is below :data:`FLOW_SIGMAS` noise deviations (a neighbouring vessel flows: out) and, for a cine, whose
velocity varies over the cycle by less than 5 % of the venc (a vessel pulses, tissue does not). The noise of each
voxel's velocity is ``k / M`` (the phase noise of a complex signal of magnitude ``M``), ``k`` estimated from
the static voxels themselves: the median absolute difference between a voxel's velocity and the mean of its
six neighbours, ``v - mean_6 = n_0 - mean_6(n)`` having variance ``(1 + 1/6) sigma^2`` for white noise (the
smooth offset cancels in the difference).

Refused, with the reason in the record, when fewer than :data:`wss_nlp.models.offset.MIN_STATIC_VOXELS` static
voxels exist (a phantom in air: nothing to fit, nothing changes), or when the fitted offset in the lumen exceeds
:data:`wss_nlp.models.offset.MAX_OFFSET_FRACTION` of the venc (the static tissue may hold flow). The record
flags the correction as uncertain when the offset's standard deviation or its change with one polynomial order
more exceeds :data:`wss_nlp.models.offset.MAX_STD_FRACTION` of the venc somewhere in the lumen, as for slices.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field

import numpy as np

from ..io.volume import VolumeAcquisition
from ..models import offset as off

log = logging.getLogger(__name__)

#: Static tissue lies at least this far (mm) from the lumen mask, and at least two voxels.
MARGIN_MM = 4.0
#: Voxels whose time-mean speed exceeds this many noise deviations flow (another vessel): not static.
FLOW_SIGMAS = 5.0
#: MSAC's candidates are scored on this many static voxels (:func:`wss_nlp.models.offset.fit_offset`).
MSAC_POINTS = 4000
#: A cine voxel whose velocity's temporal standard deviation exceeds this fraction of the venc is not static.
TEMPORAL_STD_FRACTION = 0.05


@dataclass
class VolumeOffsetRecord:
    """What the volume's offset correction did (the result's notes and ``parameters['offset']``)."""

    applied: bool
    reason: str = ""
    static_voxels: int = 0
    noise_k: float = float("nan")  # velocity noise x magnitude (m/s x magnitude units)
    orders: list = field(default_factory=list)  # per component x, y, z
    coefficients: list = field(default_factory=list)  # per component, monomials of ((x - centre) / scale)
    centre_mm: list = field(default_factory=list)
    scale_mm: float = float("nan")
    lumen_offset_m_s: list = field(default_factory=list)  # per component: the fitted offset's mean over the lumen
    lumen_std_m_s: list = field(default_factory=list)  # per component: its std's RMS over the lumen
    lumen_spread_m_s: list = field(default_factory=list)  # per component: RMS change with one order more
    uncertain: bool = False

    def as_dict(self) -> dict:
        return asdict(self)

    def note(self) -> str | None:
        """A one-line note for the result, or None when nothing needs saying."""
        if not self.applied:
            quiet = self.reason.startswith("no static tissue")
            return None if quiet else f"background offset not corrected: {self.reason}"
        removed = ", ".join(f"{c} {1000 * o:+.1f} mm/s" for c, o in zip("xyz", self.lumen_offset_m_s))
        text = (
            f"background offset removed ({removed} in the lumen, polynomial orders {'/'.join(map(str, self.orders))})"
        )
        if self.uncertain:
            text += (
                "; its value in the lumen is uncertain beyond 0.1 % of the venc (too little static tissue near the "
                "vessel): the WSS may carry a residual offset"
            )
        return text


def _noise_scale(velocity_mean: np.ndarray, magnitude: np.ndarray, static: np.ndarray) -> float:
    """``k`` of the velocity noise ``k / M`` from the static voxels whose six neighbours are static too."""
    import scipy.ndimage as ndi

    inner = ndi.binary_erosion(static, ndi.generate_binary_structure(3, 1))
    if inner.sum() < 20:
        inner = static
    kernel = np.zeros((3, 3, 3))
    kernel[1, 1, 0] = kernel[1, 1, 2] = kernel[1, 0, 1] = kernel[1, 2, 1] = kernel[0, 1, 1] = kernel[2, 1, 1] = 1 / 6
    values = []
    for c in range(velocity_mean.shape[0]):
        hp = velocity_mean[c] - ndi.convolve(velocity_mean[c], kernel, mode="nearest")
        values.append(np.abs(hp[inner]) * magnitude[inner])
    mad = float(np.median(np.concatenate(values)))
    return mad / 0.6745 / np.sqrt(1.0 + 1.0 / 6.0)


def correct_volume(
    vol: VolumeAcquisition, mask: np.ndarray, seed: int = 0
) -> tuple[VolumeAcquisition, VolumeOffsetRecord]:
    """The volume with each velocity component's background offset removed, and the record (module notes).

    Parameters
    ----------
    vol : VolumeAcquisition
    mask : bool array ``(ni, nj, nk)``
        The lumen (the segmentation's or the user's), kept out of the fit with a margin.
    seed : int
        Seeds MSAC's random subsets (the fit is reproducible).
    """
    import dataclasses

    import scipy.ndimage as ndi

    from .segmentation import otsu_threshold

    mag_t = np.asarray(vol.magnitude, float)
    vel_t = np.asarray(vol.velocity, float)
    nt = vol.nt
    magnitude = mag_t.mean(axis=0)
    velocity = vel_t.mean(axis=0)  # (3, ni, nj, nk)
    spacing = np.asarray(vol.voxel_size_mm, float)
    venc = np.asarray(vol.venc_m_s, float) if vol.venc_m_s is not None else None
    lumen = np.asarray(mask, bool)
    scale_v = (
        venc if venc is not None else np.full(3, float(np.quantile(np.linalg.norm(velocity[:, lumen], axis=0), 0.99)))
    )

    far = ndi.distance_transform_edt(~lumen, sampling=spacing) >= max(MARGIN_MM, 2 * float(spacing.max()))
    far[[0, -1], :, :] = far[:, [0, -1], :] = far[:, :, [0, -1]] = False  # the view's faces: edge artefacts
    if far.sum() < off.MIN_STATIC_VOXELS:
        return vol, VolumeOffsetRecord(False, "no static tissue in view (the vessel fills the view)")
    # the noise scale k from the brighter part of what lies away from the lumen (Otsu's upper class: tissue
    # against air, or the brighter tissue when there is no air), then the signal test of the slices: magnitude
    # above SIGNAL_MIN complex-noise deviations, sigma = pi k / venc (the phase noise of a voxel is sigma / M)
    bright = far & (magnitude > otsu_threshold(magnitude[far])) if np.ptp(magnitude[far]) > 0 else far
    if bright.sum() < off.MIN_STATIC_VOXELS:
        return vol, VolumeOffsetRecord(False, "no static tissue in view")
    k = _noise_scale(velocity, magnitude, bright)
    sigma = np.pi * k / float(scale_v.max())
    static = far & (magnitude > off.SIGNAL_MIN * sigma)
    if static.sum() < off.MIN_STATIC_VOXELS:
        return vol, VolumeOffsetRecord(False, "no static tissue in view (the background is noise)")
    noise = k / np.maximum(magnitude, 1e-12)  # one frame's velocity noise per voxel
    speed = np.linalg.norm(velocity, axis=0)
    # a flowing voxel's speed stands far above its noise (the mean's noise is sqrt(nt) smaller; the offset itself
    # is a few noise deviations at most, hence a generous band)
    static &= speed <= FLOW_SIGMAS * noise * np.sqrt(3.0 / nt) + 0.05 * float(scale_v.max())
    if nt > 1:
        std_t = np.linalg.norm(vel_t.std(axis=0), axis=0)
        static &= std_t <= TEMPORAL_STD_FRACTION * float(scale_v.max())
    n_static = int(static.sum())
    rec = VolumeOffsetRecord(False, "", static_voxels=n_static, noise_k=k)
    if n_static < off.MIN_STATIC_VOXELS:
        rec.reason = f"static tissue too sparse for the offset fit: {n_static} voxels (< {off.MIN_STATIC_VOXELS})"
        return vol, rec
    affine = np.asarray(vol.affine_mm, float)
    idx = np.argwhere(static)
    pts = idx @ affine[:3, :3].T + affine[:3, 3]
    lumen_idx = np.argwhere(lumen)
    lumen_pts = lumen_idx @ affine[:3, :3].T + affine[:3, 3]
    sigma = noise[static] / np.sqrt(nt)
    fits = []
    for c in range(3):
        fit = off.fit_offset(pts, velocity[c][static], sigma, seed=seed + c, msac_points=MSAC_POINTS)
        fits.append(fit)
        at = fit(lumen_pts)
        rec.orders.append(fit.order)
        rec.coefficients.append([float(x) for x in fit.coefficients])
        rec.lumen_offset_m_s.append(float(np.mean(at)))
        # RMS over the lumen: the wall map's WSS, an average over the wall, carries the lumen's typical residual
        rec.lumen_std_m_s.append(float(np.sqrt(np.mean(fit.std(lumen_pts) ** 2))))
        rec.lumen_spread_m_s.append(float(np.sqrt(np.mean(fit.order_spread(lumen_pts) ** 2))))
        if np.max(np.abs(at)) > off.MAX_OFFSET_FRACTION * scale_v[c]:
            rec.reason = (
                f"the fitted {'xyz'[c]} offset in the lumen, {100 * np.max(np.abs(at)) / scale_v[c]:.1f} % of the "
                f"venc, is larger than any eddy current ({100 * off.MAX_OFFSET_FRACTION:g} %): the static tissue may "
                "hold flow; not corrected"
            )
            return vol, rec
    rec.centre_mm, rec.scale_mm = [float(x) for x in fits[0].centre], float(fits[0].scale)
    all_idx = np.indices(vol.shape).reshape(3, -1).T
    all_pts = all_idx @ affine[:3, :3].T + affine[:3, 3]
    field_c = np.stack([f(all_pts).reshape(vol.shape) for f in fits])  # (3, ni, nj, nk)
    rec.applied = True
    spread = max(max(rec.lumen_std_m_s[c], rec.lumen_spread_m_s[c]) / scale_v[c] for c in range(3))
    rec.uncertain = bool(spread > off.MAX_STD_FRACTION)
    log.info("volume offset: %d static voxels, orders %s, lumen offsets %s m/s", n_static, rec.orders,
             [round(o, 4) for o in rec.lumen_offset_m_s])  # fmt: skip
    return dataclasses.replace(vol, velocity=vel_t - field_c[None]), rec
