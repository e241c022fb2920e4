"""The wall-normal fit most 4D flow tools use, on the same segmentation (issue 38, item 5).

Petersson, Dyverfeldt, Ebbers, "Assessment of the accuracy of MRI wall shear stress estimation using numerical
simulations", JMRI 36 (2012) and the calculators built on it (e.g. Ferdian's wss_mri_calculator) estimate the WSS
from a segmentation: at points of the segmentation's surface, along the inward normal, the velocity is sampled
and its tangential part fitted against the distance from the wall; the WSS is the viscosity times the fitted
slope at the wall. Here, written from that description:

* surface: the zero level of the mask's signed distance (``+`` outside, world mm, the voxel faces between lumen
  and background at zero: the Euclidean distance transforms of the mask and of its complement, each shifted by
  half a voxel), smoothed by a Gaussian of one voxel; the wall point at ``(s_i, phi_j)`` is where the ray from
  the centreline point ``c(s_i)`` in the direction ``cos phi n1 + sin phi n2`` first crosses it (sampled every
  ``h / 20``, trilinear, the crossing interpolated linearly); the outward normal is the smoothed distance's
  gradient there;
* samples: the velocity (trilinear in each world component) at ``d_k = k h / 2``, ``k = 1 .. 4`` along the inward
  normal, its tangential part ``(I - n n^T) u``;
* fit: ``u_t(d) = a d + b d^2`` (no-slip at the wall point: no constant), least squares per component;
  ``tau = mu a`` (a vector in the wall's tangent plane, Pa), ``tau . t`` its axial part.

The result is a :class:`wss_nlp.vessel.reconstruct.VesselResult` on the same ``(s, phi)`` grid as the
reconstruction's, with the same flags (plus :data:`FLAG_UNRESOLVED` where no crossing is found), so tables show
both side by side.
"""

from __future__ import annotations

import time

import numpy as np

from . import reconstruct as rec
from . import wss3d

#: Distances of the samples along the inward normal, in voxels (the largest edge).
SAMPLES_VOXELS = (0.5, 1.0, 1.5, 2.0)


def signed_distance(mask: np.ndarray, vol, smooth_voxels: float = 1.0) -> np.ndarray:
    """The mask's signed distance (mm, positive outside, zero on the faces between lumen and background voxels),
    smoothed by a Gaussian of ``smooth_voxels`` voxels."""
    import scipy.ndimage as ndi

    spacing = np.asarray(vol.voxel_size_mm, float)
    m = np.asarray(mask, bool)
    outside = ndi.distance_transform_edt(~m, sampling=spacing)  # lumen voxels: 0; outside: distance to the lumen
    inside = ndi.distance_transform_edt(m, sampling=spacing)
    half = 0.5 * float(np.exp(np.mean(np.log(spacing))))
    sdf = np.where(m, -(inside - half), outside - half)
    return ndi.gaussian_filter(sdf, sigma=smooth_voxels)


def _sample(field: np.ndarray, vol, points: np.ndarray) -> np.ndarray:
    """Trilinear values of ``field (ni, nj, nk)`` at world points ``(m, 3)`` (edge values beyond the grid)."""
    import scipy.ndimage as ndi

    idx = vol.index(points.reshape(-1, 3))
    return ndi.map_coordinates(field, idx.T, order=1, mode="nearest")


def wall_normal_fit(vol, mask: np.ndarray, centerline, record: dict, s, phi, mu: float,
                    smooth_voxels: float = 1.0) -> dict:  # fmt: skip
    """Wall points, normals and WSS vectors of the wall-normal fit on the grid ``(s, phi)`` (module notes)."""
    h = float(np.max(vol.voxel_size_mm))
    sdf = signed_distance(mask, vol, smooth_voxels)
    grads = np.gradient(sdf, *np.asarray(vol.voxel_size_mm, float))  # d/d(index axis) per mm along each axis
    a = np.asarray(vol.affine_mm, float)[:3, :3]
    unit_axes = a / np.linalg.norm(a, axis=0)  # world directions of the index axes
    ns, nph = s.size, phi.size
    ss, pp = (v.ravel() for v in np.meshgrid(s, phi, indexing="ij"))
    c = centerline.position(ss)
    _, n1, n2 = centerline.frame(ss)
    e = np.cos(pp)[:, None] * n1 + np.sin(pp)[:, None] * n2
    r_max = 2.5 * float(np.max(record.get("radius", {}).get("radius_mm", [h * 10])))
    radii = np.arange(0.0, r_max, h / 20)
    values = _sample(sdf, vol, (c[:, None, :] + radii[None, :, None] * e[:, None, :]).reshape(-1, 3))
    values = values.reshape(ss.size, radii.size)
    found = np.zeros(ss.size, bool)
    r_wall = np.full(ss.size, np.nan)
    for i in range(ss.size):
        cross = np.flatnonzero((values[i, :-1] < 0) & (values[i, 1:] >= 0))
        if cross.size:
            k = cross[0]
            f0, f1 = values[i, k], values[i, k + 1]
            r_wall[i] = radii[k] + (radii[k + 1] - radii[k]) * (-f0) / (f1 - f0)
            found[i] = True
    r_wall = np.where(found, r_wall, 0.0)
    wall = c + r_wall[:, None] * e
    # the gradient in world coordinates: along index axis j the derivative is grads[j] (per mm along that axis)
    g_idx = np.stack([_sample(g, vol, wall) for g in grads], axis=1)
    normal = g_idx @ unit_axes.T
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    d = np.asarray(SAMPLES_VOXELS) * h
    pts = wall[:, None, :] - d[None, :, None] * normal[:, None, :]
    design = np.stack([d, d**2], axis=1)
    pinv = np.linalg.pinv(design)[0]  # the slope's row of the least-squares solution
    nt = vol.nt
    vel = np.asarray(vol.velocity, float)
    taus = np.empty((nt, ss.size, 3))
    for k in range(nt):
        u = np.stack([_sample(vel[k, comp], vol, pts.reshape(-1, 3)) for comp in range(3)], axis=1)
        u = u.reshape(ss.size, d.size, 3)
        ut = u - np.sum(u * normal[:, None, :], axis=2, keepdims=True) * normal[:, None, :]
        slope = np.einsum("k,mkc->mc", pinv, ut)  # (m/s)/mm
        taus[k] = mu * slope * wss3d.PER_MM
    return {"wall": wall.reshape(ns, nph, 3), "normal": normal.reshape(ns, nph, 3), "radius": r_wall.reshape(ns, nph),
            "found": found.reshape(ns, nph), "tau": taus.reshape(nt, ns, nph, 3)}  # fmt: skip


def baseline_vessel(vol, mask: np.ndarray, centerline, record: dict, options: rec.VesselOptions | None = None,
                    s=None, phi=None) -> rec.VesselResult:  # fmt: skip
    """The wall-normal fit as a :class:`wss_nlp.vessel.reconstruct.VesselResult` (``method`` "wall-normal fit").

    ``s, phi``: the grid (default: the reconstruction's, over the visible part extended as it does).
    """
    options = options or rec.VesselOptions()
    t0 = time.perf_counter()
    mu = rec.check_volume(vol, options)
    h = float(np.max(vol.voxel_size_mm))
    visible = record.get("visible", [])
    if s is None or phi is None:
        ext = 4 * h if options.extend_mm is None else float(options.extend_mm)
        s_range = (
            max(0.0, min(v[0] for v in visible) - ext),
            min(centerline.length_mm, max(v[1] for v in visible) + ext),
        )
        s, phi = wss3d.wall_grid(s_range, h, options.n_phi, options.s_spacing_mm)
    fit = wall_normal_fit(vol, mask, centerline, record, s, phi, mu)
    ns, nph = s.size, phi.size
    t = centerline.frame(s)[0]
    tau = fit["tau"]
    axial = np.einsum("tijc,ic->tij", tau, t)
    e_a = t[:, None, :] - np.sum(t[:, None, :] * fit["normal"], axis=2, keepdims=True) * fit["normal"]
    e_a /= np.maximum(np.linalg.norm(e_a, axis=2, keepdims=True), 1e-300)
    e_c = np.cross(e_a, fit["normal"])
    circ = np.einsum("tijc,ijc->tij", tau, e_c)
    wall = fit["wall"]
    d_s = np.gradient(wall, s, axis=0) if ns > 1 else np.zeros_like(wall)
    d_phi = (np.roll(wall, -1, axis=1) - np.roll(wall, 1, axis=1)) / (2 * (2 * np.pi / nph))
    area = np.linalg.norm(np.cross(d_phi, d_s), axis=2) * (float(s[1] - s[0]) if ns > 1 else h) * (2 * np.pi / nph)
    flags = np.zeros((ns, nph), np.uint8)
    exclude = rec._branch_test(record.get("branches", []))
    if exclude is not None:
        ss, pp = np.meshgrid(s, phi, indexing="ij")
        flags[exclude(ss, pp)] |= rec.FLAG_BRANCH
    vis = np.zeros(ns, bool)
    for a0, b0 in visible:
        vis |= (s >= a0) & (s <= b0)
    flags[~vis] |= rec.FLAG_NOT_VISIBLE
    border = h if options.border_mm is None else float(options.border_mm)
    dist = rec.distance_to_border(wall.reshape(-1, 3), vol.affine_mm, vol.shape).reshape(ns, nph)
    flags[dist < border] |= rec.FLAG_BORDER
    flags[~fit["found"]] |= rec.FLAG_UNRESOLVED
    times = np.zeros(1) if vol.trigger_times_ms is None else np.asarray(vol.trigger_times_ms, float)
    tawss = osi = None
    if vol.nt > 1:
        period = vol.cardiac_period_ms
        if period is None:  # as the reconstruction: the frames cover one cycle
            period = float(times[-1] - times[0] + np.mean(np.diff(times)))
        tawss, osi = rec.cycle_indices(tau, times, period)
    radius = fit["radius"]
    dphi = 2 * np.pi / nph
    mag = np.linalg.norm(tau, axis=-1)
    planes = {"s_mm": s, "area_mm2": 0.5 * np.sum(radius**2, axis=1) * dphi,
              "flow_ml_s": np.full((vol.nt, ns), np.nan), "mean_wss_pa": mag.mean(axis=2),
              "mean_axial_pa": axial.mean(axis=2), "flags": np.bitwise_or.reduce(flags, axis=1)}  # fmt: skip
    return rec.VesselResult(
        method="wall-normal fit", centerline=centerline, s_mm=s, phi=phi, time_ms=times, wall_mm=wall,
        normal=fit["normal"], radius_mm=radius, area_mm2=area, flags=flags, wss_pa=tau, axial_pa=axial,
        circumferential_pa=circ, planes=planes, viscosity_pa_s=mu, affine_mm=np.asarray(vol.affine_mm, float),
        source=vol.source, tawss_pa=tawss, osi=osi,
        parameters={"samples_mm": (np.asarray(SAMPLES_VOXELS) * h).tolist(), "fit": "a d + b d^2",
                    "surface": "zero level of the mask's signed distance, Gaussian 1 voxel"},
        seconds={"total": time.perf_counter() - t0}, notes=["Petersson 2012-style wall-normal fit on the mask"],
        record=record,
    )  # fmt: skip
