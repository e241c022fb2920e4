"""Planes that cut the vessel off its axis: the tilt measured, the WSS corrected for it, and what cannot be told.

A plane tilted by ``theta`` from the vessel's cross-section sees the lumen stretched by ``1 / cos(theta)`` along
the tilt and only the through-plane component ``w = w_3 cos(theta)`` of the axial flow ``w_3``; the 2D WSS is then
low by ``cos(theta)`` to ``cos^2(theta)`` around the wall (-12 % to -6 % at 20 degrees).

* **With in-plane velocity** (4D flow, a plane cut from a volume) the tilt is measured
  (:func:`wss_nlp.io.plane.tilt`); above :data:`~wss_nlp.io.plane.TILT_THRESHOLD_DEG` the slice's WSS is
  corrected and the slice flagged with the angle (:func:`correct`).
* **Single-component data** cannot show a tilt: an oblique cut of a circular vessel and an elliptic vessel look
  alike. What can be checked is that the through-plane flow follows the lumen's shape, as developed flow in a
  straight vessel does whether it is cut straight or obliquely: the velocity-weighted second moments of the
  lumen have the lumen's own aspect and axes. An elliptic lumen whose flow does not
  (:data:`MAX_ASPECT_MISMATCH`, :data:`MAX_AXES_ANGLE_DEG`) is flagged SUSPECT (:func:`shape_check`).

Notes
-----
Correction. In the plane, take ``s`` along the tilt direction ``e`` and ``t`` across it; the cross-section
perpendicular to the axis has coordinates ``(s cos(theta), t)`` and the axial velocity
``w_3 = w / cos(theta)``. At the wall ``grad w = |grad w| (n_s, n_t)`` (no slip), so the wall shear stress of the
cross-section is

.. math:: \\tau = \\frac{\\tau_{2D}}{\\cos\\theta} \\sqrt{\\frac{n_s^2}{\\cos^2\\theta} + n_t^2},

exact for a straight vessel with axial flow whatever its cross-section. The mean is taken over the cross-section's
arc length, ``dl_perp = dl sqrt(n_s^2 + cos^2(theta) n_t^2)``. The WSS vector of a single slice (4D flow) is left
as computed (it takes the wall along the plane's normal).
"""

from __future__ import annotations

import numpy as np

from ..io.plane import TILT_THRESHOLD_DEG, tilt
from .results import SliceResult

#: Lumen aspect above which the single-component shape check runs (a circle's fit reads 1.0-1.1 with noise).
MIN_ASPECT = 1.2
#: The velocity-weighted aspect may differ from the lumen's by this factor (voxels and noise: at most 1.008, the axes
#: within 1.2 degrees, on the laminar and turbulent-ellipse phantoms at h 1 and 1.5 mm, SNR 10 and 25, seeds 300-301;
#: scripts/results/obliquity.md, made by scripts/obliquity.py).
MAX_ASPECT_MISMATCH = 1.25
#: The velocity's principal axes may turn from the lumen's by this much (degrees) when both are elliptic.
MAX_AXES_ANGLE_DEG = 25.0


def _wall_frame(wall_x: np.ndarray, wall_y: np.ndarray):
    """Arc-length weights and outward unit normals of a closed wall sampled at uniform angles."""
    tx = (np.roll(wall_x, -1) - np.roll(wall_x, 1)) / 2
    ty = (np.roll(wall_y, -1) - np.roll(wall_y, 1)) / 2
    dl = np.hypot(tx, ty)
    nx, ny = ty / np.maximum(dl, 1e-300), -tx / np.maximum(dl, 1e-300)
    cx, cy = float(np.mean(wall_x)), float(np.mean(wall_y))
    sign = np.sign(np.sum(nx * (wall_x - cx) + ny * (wall_y - cy))) or 1.0
    return dl, sign * nx, sign * ny


def correct(tau: np.ndarray, wall_x: np.ndarray, wall_y: np.ndarray, theta: float, e) -> tuple[np.ndarray, float]:
    """``(tau of the cross-section at the same wall points, its arc-length mean)`` (module notes)."""
    dl, nx, ny = _wall_frame(np.asarray(wall_x, float), np.asarray(wall_y, float))
    ns = nx * e[0] + ny * e[1]
    nt = -nx * e[1] + ny * e[0]
    c = np.cos(theta)
    factor = np.sqrt(ns**2 / c**2 + nt**2) / c
    weight = dl * np.sqrt(ns**2 + c**2 * nt**2)
    corrected = np.asarray(tau, float) * factor
    return corrected, float(np.sum(corrected * weight) / np.sum(weight))


def _moments(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """``(aspect, angle of the major axis)`` of the second moments of points ``(x, y)`` weighted by ``w``."""
    w = np.maximum(w, 0.0)
    s = float(np.sum(w))
    mx, my = float(np.sum(w * x)) / s, float(np.sum(w * y)) / s
    dx, dy = x - mx, y - my
    cov = np.array([[np.sum(w * dx * dx), np.sum(w * dx * dy)], [np.sum(w * dx * dy), np.sum(w * dy * dy)]]) / s
    vals, vecs = np.linalg.eigh(cov)
    aspect = float(np.sqrt(max(vals[1], 1e-300) / max(vals[0], 1e-300)))
    return aspect, float(np.arctan2(vecs[1, 1], vecs[0, 1]))


def shape_check(r) -> tuple[str, dict]:
    """``(SUSPECT note or "", record)``: does the through-plane flow follow an elliptic lumen's shape?

    The lumen's aspect and axes come from the second moments of its voxels' centres weighted by their lumen
    fractions; the flow's from the same voxels weighted also by the measured velocity (not the fit, which vanishes
    on the wall it was given), signed so that the mean flow is positive and floored at zero.
    """
    v = r.velocity
    index = np.asarray(v.voxel_index)
    frac = np.asarray(v.voxel_fraction, float)
    xc, yc = (np.asarray(a).ravel()[index] for a in r.grid.centers())
    lumen_aspect, lumen_angle = _moments(xc, yc, frac)
    record = {"lumen_aspect": lumen_aspect}
    if lumen_aspect < MIN_ASPECT:
        return "", record
    measured = np.asarray(r.velocity_image, float).ravel()[index]
    measured = np.where(np.isfinite(measured), measured, 0.0)
    measured = measured * (np.sign(np.sum(measured * frac)) or 1.0)
    flow_aspect, flow_angle = _moments(xc, yc, frac * measured)
    turn = abs((np.degrees(flow_angle - lumen_angle) + 90.0) % 180.0 - 90.0)
    record.update(flow_aspect=flow_aspect, axes_angle_deg=float(turn))
    ratio = max(flow_aspect, lumen_aspect) / min(flow_aspect, lumen_aspect)
    if ratio <= MAX_ASPECT_MISMATCH and (turn <= MAX_AXES_ANGLE_DEG or flow_aspect < MIN_ASPECT):
        return "", record
    implied = float(np.degrees(np.arccos(1.0 / lumen_aspect)))
    return (
        f"SUSPECT: the lumen is elliptic (aspect {lumen_aspect:.2f}) but the through-plane flow does not follow "
        f"its shape (aspect {flow_aspect:.2f}, axes {turn:.0f} degrees apart): developed flow in a straight "
        f"vessel would, cut straight or obliquely. If the vessel is circular the plane is about {implied:.0f} "
        "degrees off its axis, and single-component data cannot show the tilt or correct for it (its WSS is low "
        "by up to 1 - cos^2 of it); a wrong lumen or strongly non-axial flow do the same; this slice's WSS is not "
        "trustworthy"
    ), record


def apply(r, acq) -> None:
    """Measure a slice's tilt and correct its WSS (in-plane velocity), or check its shape (single component)."""
    if not isinstance(r, SliceResult):
        return
    if acq.velocity_inplane is None:
        note, record = shape_check(r)
        r.screen = {**(r.screen or {}), "obliquity": record}
        if note:
            r.notes.append(note)
            r.screen["suspect"] = True
        return
    ux, uy = (np.asarray(acq.velocity_inplane[c, r.index], float) for c in range(2))
    found = tilt(r.velocity_image, ux, uy, r.lumen.mask)
    if found is None:
        return
    theta, e, residual = found
    degrees = float(np.degrees(theta))
    record = {"tilt_deg": degrees, "tilt_direction": [float(e[0]), float(e[1])], "tilt_fit_residual": residual}
    r.screen = {**(r.screen or {}), "obliquity": record}
    if degrees <= TILT_THRESHOLD_DEG:
        return
    w = r.wss
    before = float(w.mean)
    scale, _ = correct(np.ones_like(w.tau), w.wall_x, w.wall_y, theta, e)
    w.tau, w.mean = correct(w.tau, w.wall_x, w.wall_y, theta, e)
    record["mean_factor"] = float(w.mean / before) if before else float("nan")
    if getattr(w, "tau_std", None) is not None:  # the band scales with the WSS, angle by angle
        w.tau_std = np.asarray(w.tau_std) * scale
        if np.isfinite(record["mean_factor"]):
            w.mean_std = float(w.mean_std) * record["mean_factor"]
    r.notes.append(
        f"OBLIQUE PLANE: the plane is {degrees:.1f} degrees off the vessel's axis (its in-plane velocity leans "
        f"along ({e[0]:.2f}, {e[1]:.2f}) in the image): the WSS was corrected to the vessel's cross-section (mean "
        f"x{record['mean_factor']:.3f}; exact for a straight vessel with axial flow, the in-plane fit's relative "
        f"residual is {residual:.2f}); cut perpendicular to the vessel for the best result"
    )
