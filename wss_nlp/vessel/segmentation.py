"""The lumen of a vessel in a 4D flow volume, from the data: what flows is vessel, what is static is not.

Notes
-----
PC-MRA (phase-contrast angiogram), the mean over the ``nt`` frames of magnitude times speed,

.. math:: P(x) = \\frac{1}{n_t} \\sum_t M_t(x) \\, |v_t(x)|,

is large where blood flows and small elsewhere: in air and background the magnitude is noise (and the phase,
hence the speed, random), in static tissue the speed is the phase noise only, ``|v| ~ venc sigma / (pi M)``, so
that ``M |v| ~ venc sigma / pi`` whatever the tissue's brightness. Bright static tissue is therefore as dark in
``P`` as background: speed decides what flows. The time mean keeps every frame's information (a systolic frame
alone would lose vessels with little flow then) at the price of diluting ``P`` by diastole, which the threshold
below absorbs.

Threshold: Otsu's (maximum between-class variance of the histogram of ``P``), chosen from the data; or given.
In the background the phase is random, so its speeds are of the order of the venc and ``P`` there is noise
magnitude times venc: with a thin vessel at low SNR that noise's tail overlaps the vessel's ``P`` (at SNR 10 with
2 mm voxels on 4 mm tubes the background's 99.9th percentile exceeded the lumen's median, and Otsu's threshold
on all voxels fell inside the noise, taking 15 times the lumen's voxel count). So the background is left out
first by the magnitude (the voxels below Otsu's threshold of the time-mean magnitude: air and noise against
tissue and blood), and Otsu's threshold of ``P`` is taken over the rest, where it separates static tissue from
flowing blood.
Then an opening by reconstruction (the parts that survive one 6-neighbour erosion and dilation, restored whole
within the thresholded set) removes noise speckles without thinning thin vessels (a plain opening split a
PC-MRA core two voxels across into pieces on ``scripts/vessel_segmentation.py``'s 4 mm tubes at 2 mm voxels;
a core two voxels across and aligned with the grid has no voxel that survives the erosion: when nothing survives,
the thresholded voxels are kept unopened and the record says so);
hole filling closes voids in the lumen (flow voids of dephasing), and the voxels are grouped in face-connected
components. The
vessel is the largest component, or the one containing (or nearest, within two voxels) a seed point in world mm.

The no-slip condition makes ``P`` vanish at the wall, so a threshold of ``P`` puts the lumen boundary inside
the true wall (for Poiseuille flow a threshold at a fraction ``f`` of the centre value at ``r = R sqrt(1 - f)``).
Where the magnitude shows the lumen (blood brighter than its surroundings, as with inflow or contrast), the mask
is grown, one voxel layer at a time and by at most ``grow_voxels`` layers, into voxels whose time-mean magnitude
exceeds the midpoint between the lumen's (the chosen component's median) and the surroundings' (the median in a
shell two to four voxels outside): the midpoint is where a wall voxel holds half lumen, the partial-volume
boundary. The default bound is the PC-MRA mask's largest inscribed radius (at least two voxels): a threshold at
up to ``f = 0.75`` of the centre value leaves a deficit ``R (1 - sqrt(1 - f)) <= R sqrt(1 - f)`` (the PC-MRA
radius being ``R sqrt(1 - f)``); the bound also caps how far bright static tissue touching the lumen can be taken
in. On ``make_flow_volume`` phantoms (radius 6 mm at 1 x 1.1 x 0.9 mm voxels and 4 mm at 2 x 2.2 x 1.8 mm; SNR 25
and 10; seeds 0-4) Otsu's PC-MRA mask missed 51-56 % of the lumen's voxels on average, the grown mask 0.9-7.4 %,
adding at most 0.7 %; the radius of its centreline's cross-sections was 0.05-0.19 mm short
(``scripts/results/vessel_segmentation.md``, made by ``scripts/vessel_segmentation.py``). Without that
contrast (below :data:`MIN_CONTRAST`) the mask stays the PC-MRA mask, smaller than the lumen; the record says
which.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError, NoVesselError
from ..io.volume import VolumeAcquisition

log = logging.getLogger(__name__)

#: Relative magnitude contrast ``(m_in - m_out) / m_in`` below which the mask is not grown by the magnitude.
MIN_CONTRAST = 0.3
#: A seed point farther than this many voxels from every component selects none.
SEED_REACH_VOXELS = 2.0
#: How many of the other components the record lists (largest first).
LISTED_COMPONENTS = 10


@dataclass
class Segmentation:
    """The vessel's lumen on the volume grid and how it was found.

    ``mask[i, j, k]`` is True in the lumen; ``pcmra`` the PC-MRA ``P`` (magnitude units x m/s); ``record`` a
    JSON-able account: ``threshold`` and how it was chosen, ``components`` (the chosen one's and the others'
    voxel count, volume in mm^3 and centroid in world mm), ``selected_by`` (largest or seed), ``grown`` (the
    magnitude step's levels and how many voxels it added, or why it did not run).
    """

    mask: np.ndarray
    pcmra: np.ndarray
    record: dict = field(default_factory=dict)


def pcmra(vol: VolumeAcquisition) -> np.ndarray:
    """PC-MRA ``P = mean_t M_t |v_t|`` on the volume grid ``(ni, nj, nk)`` (see the module notes)."""
    speed = np.sqrt(np.sum(np.asarray(vol.velocity, float) ** 2, axis=1))
    return np.mean(np.asarray(vol.magnitude, float) * speed, axis=0)


def otsu_threshold(values: np.ndarray, bins: int = 1024) -> float:
    """Otsu's threshold of ``values``: the bin edge maximizing the between-class variance ``w0 w1 (mu0 - mu1)^2``."""
    v = np.asarray(values, float).ravel()
    lo, hi = float(v.min()), float(v.max())
    if not hi > lo:
        raise NoVesselError("the PC-MRA is constant: nothing flows in the volume (check the velocity files)")
    counts, edges = np.histogram(v, bins=bins, range=(lo, hi))
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(counts)[:-1].astype(float)
    w1 = v.size - w0
    m0 = np.cumsum(counts * centres)[:-1]
    total = float(np.sum(counts * centres))
    with np.errstate(divide="ignore", invalid="ignore"):
        between = w0 * w1 * (m0 / w0 - (total - m0) / w1) ** 2
    between[~np.isfinite(between)] = -1.0
    return float(edges[1 + int(np.argmax(between))])


def _structure(connectivity: int = 1) -> np.ndarray:
    import scipy.ndimage as ndi

    return ndi.generate_binary_structure(3, connectivity)


def _components(mask: np.ndarray, vol: VolumeAcquisition) -> tuple[np.ndarray, list[dict]]:
    """Face-connected components: labels and, largest first, each one's label, voxels, volume and centroid."""
    import scipy.ndimage as ndi

    labels, n = ndi.label(mask, structure=_structure(1))
    if n == 0:
        return labels, []
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    centroids = np.asarray(ndi.center_of_mass(mask, labels, index=np.arange(1, n + 1)), float).reshape(n, 3)
    voxel_volume = abs(float(np.linalg.det(np.asarray(vol.affine_mm, float)[:3, :3])))
    order = np.argsort(-sizes, kind="stable")
    comps = [
        {
            "label": int(i + 1),
            "voxels": int(sizes[i]),
            "volume_mm3": round(float(sizes[i]) * voxel_volume, 3),
            "centroid_mm": [round(float(c), 3) for c in vol.world(centroids[i])],
        }
        for i in order
    ]
    return labels, comps


def _select(labels: np.ndarray, comps: list[dict], vol: VolumeAcquisition, vessel) -> tuple[dict, str]:
    """The chosen component and how: the largest, or the one holding (or nearest to) the seed ``vessel`` (mm)."""
    if vessel is None:
        return comps[0], "largest component"
    seed = np.asarray(vessel, float)
    if seed.shape != (3,) or not np.all(np.isfinite(seed)):
        raise InputError(f"--vessel {np.asarray(vessel).tolist()}: give a point as three finite numbers X Y Z (mm)")
    index = vol.index(seed)
    upper = np.asarray(vol.shape) - 0.5
    if np.any(index < -0.5) or np.any(index > upper):
        raise InputError(
            f"--vessel {seed.tolist()} mm lies outside the volume {vol.source} (voxel index "
            f"{np.round(index, 1).tolist()}, shape {list(vol.shape)}); give a point inside the field of view"
        )
    i, j, k = np.clip(np.rint(index).astype(int), 0, np.asarray(vol.shape) - 1)
    by_label = {c["label"]: c for c in comps}
    if labels[i, j, k] > 0:
        return by_label[int(labels[i, j, k])], f"component containing the seed {seed.tolist()} mm"
    inside = np.argwhere(labels > 0)
    d = np.linalg.norm((inside - index) * vol.voxel_size_mm, axis=1)
    nearest = int(np.argmin(d))
    reach = SEED_REACH_VOXELS * float(vol.voxel_size_mm.max())
    if d[nearest] <= reach:
        label = int(labels[tuple(inside[nearest])])
        return by_label[label], f"component nearest ({d[nearest]:.2g} mm) to the seed {seed.tolist()} mm"
    listed = "; ".join(f"{c['voxels']} voxels at {c['centroid_mm']} mm" for c in comps[:3])
    raise NoVesselError(
        f"--vessel {seed.tolist()} mm: no flowing component within {reach:.3g} mm of the seed in {vol.source} "
        f"(largest: {listed}); move the seed into the vessel"
    )


def _grow(core: np.ndarray, mean_magnitude: np.ndarray, grow_voxels: int) -> tuple[np.ndarray, dict]:
    """Grow ``core`` by up to ``grow_voxels`` voxels into voxels brighter than the lumen/surroundings midpoint."""
    import scipy.ndimage as ndi

    face = _structure(1)
    m_in = float(np.median(mean_magnitude[core]))
    shell = ndi.binary_dilation(core, face, iterations=4) & ~ndi.binary_dilation(core, face, iterations=2)
    if grow_voxels <= 0 or not shell.any() or not m_in > 0:
        return core, {"done": False, "why": "not asked" if grow_voxels <= 0 else "no surroundings to compare"}
    m_out = float(np.median(mean_magnitude[shell]))
    contrast = (m_in - m_out) / m_in
    info: dict = {"lumen_magnitude": m_in, "surroundings_magnitude": m_out, "contrast": round(contrast, 4)}
    if contrast < MIN_CONTRAST:
        info.update(done=False, why=f"magnitude contrast {contrast:.2f} < {MIN_CONTRAST}: the lumen is the PC-MRA mask")
        return core, info
    level = 0.5 * (m_in + m_out)
    bright = mean_magnitude > level
    mask = core.copy()
    layers = 0
    for layers in range(1, grow_voxels + 1):
        new = ndi.binary_dilation(mask, face) & bright & ~mask
        if not new.any():
            layers -= 1
            break
        mask |= new
    info.update(done=True, level=level, layers=layers, bound=grow_voxels, added_voxels=int(mask.sum() - core.sum()))
    return mask, info


def segment_vessel(
    vol: VolumeAcquisition,
    vessel: tuple[float, float, float] | None = None,
    threshold: float | None = None,
    opening: int = 1,
    grow_voxels: int | None = None,
    magnitude_floor: bool = True,
) -> Segmentation:
    """The vessel's lumen mask from the data (module notes): PC-MRA, Otsu threshold, clean-up, one component.

    Parameters
    ----------
    vol : VolumeAcquisition
    vessel : (x, y, z), optional
        A point in world mm in (or within two voxels of) the wanted vessel; default the largest component.
    threshold : float, optional
        PC-MRA threshold (magnitude units x m/s) instead of Otsu's.
    opening : int
        Iterations of the opening by reconstruction (0: none).
    magnitude_floor : bool
        Leave out the voxels whose time-mean magnitude is below Otsu's threshold of the magnitude (background)
        before thresholding the PC-MRA (module notes).
    grow_voxels : int, optional
        Most voxel layers the magnitude step adds outwards (0: keep the PC-MRA mask; default the PC-MRA mask's
        largest inscribed radius in voxels, at least 2).

    Returns
    -------
    Segmentation

    Raises
    ------
    NoVesselError
        Nothing flows above the threshold, or no component near the seed.
    """
    import scipy.ndimage as ndi

    p = pcmra(vol)
    mean_magnitude = np.mean(np.asarray(vol.magnitude, float), axis=0)
    signal = np.ones(p.shape, bool)
    floor = None
    if magnitude_floor:  # background (noise, random phase) out by the magnitude first
        floor = otsu_threshold(mean_magnitude)
        signal = mean_magnitude > floor
    chosen_by = "given" if threshold is not None else "Otsu on the PC-MRA of the voxels above the magnitude floor"
    level = float(threshold) if threshold is not None else otsu_threshold(p[signal] if signal.sum() > 1 else p)
    raw = (p > level) & signal
    mask = raw
    opened = int(opening)
    if opening > 0:  # opening by reconstruction: what survives the opening, restored whole within ``raw``
        mask = ndi.binary_propagation(ndi.binary_opening(raw, _structure(1), iterations=opening), _structure(1), raw)
        if not mask.any() and raw.any():
            # a vessel two voxels across, aligned with the grid, has no voxel with all four in-plane neighbours:
            # the erosion removes all of it (a radius-6 mm tube at 2.5 mm voxels did). Nothing survived, so no
            # speckle is told from a vessel by the opening: keep what was thresholded, largest component first
            mask, opened = raw, 0
            log.info("vessel: nothing survived the opening (a vessel about two voxels across); no opening")
    mask = ndi.binary_fill_holes(mask)
    labels, comps = _components(mask, vol)
    if not comps:
        raise NoVesselError(
            f"{vol.source}: no voxel's PC-MRA exceeds the threshold {level:.4g} after the opening; nothing flows "
            "(check the velocity components and their units, or give a lower threshold)"
        )
    chosen, how = _select(labels, comps, vol, vessel)
    core = labels == chosen["label"]
    if grow_voxels is None:
        inscribed = float(ndi.distance_transform_edt(core).max())  # voxels (index units)
        grow_voxels = max(2, int(np.ceil(inscribed)))
    lumen, grown = _grow(core, mean_magnitude, grow_voxels)
    voxel_volume = abs(float(np.linalg.det(np.asarray(vol.affine_mm, float)[:3, :3])))
    record = {
        "pcmra": "mean over frames of magnitude x speed",
        "threshold": level,
        "threshold_from": chosen_by,
        "magnitude_floor": floor,
        "above_floor_voxels": int(signal.sum()),
        "above_threshold_voxels": int(raw.sum()),
        "opening_iterations": opened,
        **({"opening_skipped": "nothing survived it (a vessel about two voxels across)"} if opened < opening else {}),
        "selected_by": how,
        "vessel": chosen,
        "others": [c for c in comps if c is not chosen][:LISTED_COMPONENTS],
        "components": len(comps),
        "grown": grown,
        "voxels": int(lumen.sum()),
        "volume_mm3": round(float(lumen.sum()) * voxel_volume, 3),
    }
    log.info(
        "vessel: %d voxels (%s), PC-MRA threshold %.4g (%s), %d other components",
        record["voxels"], how, level, chosen_by, len(comps) - 1,
    )  # fmt: skip
    return Segmentation(mask=lumen, pcmra=p, record=record)


def read_mask(path, vol: VolumeAcquisition) -> np.ndarray:
    """A lumen mask from a NIfTI file (``--mask FILE``): nonzero voxels are lumen, on the volume's grid.

    The file must hold ``(ni, nj, nk)`` (or one frame of it) with the volume's affine (within 1e-4 mm);
    anything else is refused with the reason, as are NaN values and an empty mask.
    """
    from ..io.nifti import require_nibabel

    nibabel = require_nibabel()
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(f"{path}: no such file (--mask)")
    try:
        img = nibabel.load(path)
        data = np.asarray(img.get_fdata(), dtype=float)
    except Exception as exc:  # nibabel raises several types for unreadable files
        raise InputError(f"{path}: not a readable NIfTI mask ({type(exc).__name__}: {exc})") from None
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    if data.shape != vol.shape:
        raise InputError(
            f"{path}: the mask's grid {list(data.shape)} is not the volume's {list(vol.shape)}; resample the mask "
            "onto the volume's grid (same voxels and affine)"
        )
    affine = np.asarray(img.affine, float)
    if not np.allclose(affine, np.asarray(vol.affine_mm, float), atol=1e-4):
        worst = float(np.abs(affine - np.asarray(vol.affine_mm, float)).max())
        raise InputError(
            f"{path}: the mask's affine differs from the volume's by up to {worst:.3g} mm; resample the mask onto "
            "the volume's grid (same voxels and affine)"
        )
    if not np.all(np.isfinite(data)):
        raise InputError(f"{path}: the mask holds NaN or Inf values; store 0 outside and 1 inside the lumen")
    mask = data != 0
    if not mask.any():
        raise InputError(f"{path}: the mask is empty (no nonzero voxel); it must mark the lumen")
    return mask
