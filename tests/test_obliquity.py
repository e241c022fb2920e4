"""Planes off the vessel's axis (wss_nlp.pipeline.obliquity, wss_nlp.io.plane.tilt): the tilt from the in-plane
velocity, the WSS correction against the closed form of an oblique cut, the flag on a plane cut from a 4D-flow
volume, and the single-component shape check."""

import numpy as np
import pytest

from wss_nlp.io.plane import tilt
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
from wss_nlp.pipeline.obliquity import MAX_ASPECT_MISMATCH, correct, shape_check
from wss_nlp.synthetic import phantoms


def _oblique_poiseuille(theta, psi, n=720, radius=6.0, u=0.8, mu=3.5e-3):
    """Wall points and the 2D WSS of a circular Poiseuille tube (radius mm, peak m/s) cut at tilt ``theta`` along
    the image direction at angle ``psi``: the plane sees the ellipse ``(s cos theta)^2 + t^2 = R^2`` and
    ``w = u cos(theta) (1 - ((s cos theta)^2 + t^2) / R^2)``, whose gradient at the wall is taken in closed form."""
    t_par = 2 * np.pi * np.arange(n) / n
    s, t = radius / np.cos(theta) * np.cos(t_par), radius * np.sin(t_par)
    ws = u * np.cos(theta) * (-2 * s * np.cos(theta) ** 2 / radius**2)  # dw/ds, (m/s)/mm
    wt = u * np.cos(theta) * (-2 * t / radius**2)
    tau2d = mu * np.hypot(ws, wt) * 1000.0  # Pa
    e = np.array([np.cos(psi), np.sin(psi)])
    x, y = s * e[0] - t * e[1], s * e[1] + t * e[0]
    return x + 3.0, y - 2.0, tau2d, tuple(e), 2 * mu * u / radius * 1000.0


@pytest.mark.parametrize("theta_deg, psi", [(20.0, 0.0), (35.0, 1.1), (8.0, -2.4)])
def test_the_correction_recovers_the_cross_sections_wss_exactly(theta_deg, psi):
    theta = np.radians(theta_deg)
    x, y, tau2d, e, exact = _oblique_poiseuille(theta, psi)
    assert tau2d.min() == pytest.approx(exact * np.cos(theta) ** 2, rel=1e-9)  # the 2D WSS is low by cos^2 ...
    assert tau2d.max() == pytest.approx(exact * np.cos(theta), rel=1e-9)  # ... to cos of the tilt
    corrected, mean = correct(tau2d, x, y, theta, e)
    # exact but for the wall normals, taken from central differences of 720 wall points: O(1/n^2) ~ 1e-5
    np.testing.assert_allclose(corrected, exact, rtol=2e-5)
    assert mean == pytest.approx(exact, rel=2e-5)


def test_the_tilt_is_read_from_the_in_plane_velocity_despite_swirl_and_noise():
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[-20:21, -20:21] * 0.5
    r2 = (xx / 1.1) ** 2 + yy**2
    mask = r2 < 64
    w = np.where(mask, 0.6 * (1 - r2 / 64), 0.0)
    theta, psi = np.radians(20.0), 0.7
    lean = np.tan(theta) * np.array([np.cos(psi), np.sin(psi)])
    swirl = 0.05 * np.exp(-r2 / 30)  # a rotation about the centre: it averages out of the fit
    ux = lean[0] * w - swirl * yy + rng.normal(0, 0.01, w.shape)
    uy = lean[1] * w + swirl * xx + rng.normal(0, 0.01, w.shape)
    found, e, residual = tilt(w + rng.normal(0, 0.01, w.shape), ux, uy, mask)
    # 0.3 degrees: noise 0.01 m/s against a mean |w| of 0.3 m/s over about 600 voxels
    assert np.degrees(found) == pytest.approx(20.0, abs=0.3)
    assert np.arctan2(e[1], e[0]) == pytest.approx(psi, abs=0.01)
    # the residual is the part of the in-plane velocity that is not axial (the swirl and the noise) relative to
    # all of it; computed from the construction, it agrees up to what the fit's small error in the lean moves
    # between the two (5 %)
    rest_x, rest_y = ux - lean[0] * w, uy - lean[1] * w
    expected = np.sqrt(np.sum(rest_x[mask] ** 2 + rest_y[mask] ** 2) / np.sum(ux[mask] ** 2 + uy[mask] ** 2))
    assert residual == pytest.approx(expected, rel=0.05)
    assert tilt(np.zeros_like(w), ux, uy, mask) is None  # no flow, no tilt


def test_an_elliptic_poiseuille_slice_with_a_leaning_in_plane_velocity_is_a_tilted_tube_and_is_corrected():
    """Poiseuille flow in the 13 x 10 mm elliptic lumen of the laminar phantom is exactly what a plane tilted by
    ``arccos(10/13)`` = 39.7 degrees (along the major axis) sees of a circular tube of radius 10 mm carrying a peak
    ``0.4 / cos`` m/s: its cross-section's WSS is uniform, ``2 mu u / R``. Given the in-plane velocity such a cut
    measures (``tan(theta) e w``, seeded noise 0.01 m/s), the slice is flagged and its WSS corrected to that."""
    from dataclasses import replace

    acq, truth = phantoms.make_phantom("laminar", h_mm=1.5, snr=25, seed=302)
    c, e = 10.0 / 13.0, np.array([np.cos(0.4), np.sin(0.4)])
    w = np.asarray(truth.velocity_image, float)
    noise = np.random.default_rng(11).normal(0, 0.01, (2, 1, *w.shape))
    inplane = np.tan(np.arccos(c)) * e[:, None, None, None] * w[None, None] + noise
    res = reconstruct(replace(acq, velocity_inplane=inplane), ReconstructionOptions(uncertainty=False))[0]
    rec = res.screen["obliquity"]
    exact = 2 * 3.5e-3 * (0.4 / c) / 10.0 * 1000.0  # Pa: mu 3.5 mPa s, u in m/s, R in mm
    # 1 degree: the lean is read over ~170 lumen voxels with noise 0.01 m/s against |w| up to 0.4 m/s
    assert rec["tilt_deg"] == pytest.approx(np.degrees(np.arccos(c)), abs=1.0)
    assert any("OBLIQUE PLANE" in n for n in res.warnings)
    # 3 % on the mean and 6 % pointwise (relative RMS; measured 0.05 % and 2.9 % here): the reconstruction's own
    # error on the laminar phantom at h 1.5 mm, SNR 25 (3 % median WSS error in scripts/results/soak.md) plus the
    # correction's, exact for this flow; uncorrected the mean is 31 % low (1 - 1/1.454)
    assert res.wss.mean == pytest.approx(exact, rel=0.03)
    assert np.sqrt(np.mean((np.asarray(res.wss.tau) - exact) ** 2)) / exact < 0.06
    assert res.wss.mean / rec["mean_factor"] < 0.75 * exact


@pytest.fixture(scope="module")
def oblique_plane(tmp_path_factory):
    """A plane 20 degrees off the axis of an unseen 4D-flow tube (seed 43; scripts/plane_extraction.py reports
    seeds 0-4), imported through the command line's path."""
    pytest.importorskip("nibabel")
    from wss_nlp.io import importing
    from wss_nlp.io.plane import Plane
    from wss_nlp.io.scanner import ImportOptions
    from wss_nlp.synthetic import scanner_exports as se

    vol = se.make_flow_volume(seed=43, snr=25, peaks_m_s=(0.8,))
    paths = se.write_flow_volume(str(tmp_path_factory.mktemp("oblique")), vol)
    a = np.cross(vol.axis, np.eye(3)[int(np.argmin(np.abs(vol.axis)))])
    a /= np.linalg.norm(a)
    normal = np.cos(np.radians(20)) * vol.axis + np.sin(np.radians(20)) * a
    plane = Plane(point=tuple(vol.center + 2 * vol.axis), normal=tuple(normal), fov_mm=30.0)
    fluid = ImportOptions(viscosity_pa_s=vol.viscosity_pa_s, venc_m_s=vol.venc_m_s)
    imp = importing.import_paths(paths, fluid, "m/s", None, plane)
    return vol, imp


@pytest.mark.slow  # 30-40 s (the volume, its NIfTI files, the import): the test above checks the claim in 2D
def test_a_plane_cut_20_degrees_off_the_axis_is_flagged_and_corrected(oblique_plane):
    vol, imp = oblique_plane
    assert imp.record["plane"]["tilt_deg"] == pytest.approx(20.0, abs=1.5)  # the import measures and records it
    axis = np.asarray(imp.record["plane"]["axis_from_velocity"])
    assert abs(axis @ vol.axis) > np.cos(np.radians(1.5))  # the normal of a perpendicular plane, within 1.5 deg
    res = reconstruct(imp.frame(0, "plane"), ReconstructionOptions(uncertainty=False))[0]
    rec = res.screen["obliquity"]
    assert rec["tilt_deg"] == pytest.approx(20.0, abs=1.5) and any("OBLIQUE PLANE" in w for w in res.warnings)
    before = res.wss.mean / rec["mean_factor"]
    truth = vol.wss_pa(0)
    # uncorrected the mean is low by cos to cos^2 of the tilt (6-12 %) on top of the resampling's error; corrected
    # it is within the 15 % the docs claim for perpendicular planes (scripts/results/plane_extraction.md)
    assert 1.05 < rec["mean_factor"] < 1.13
    assert abs(res.wss.mean - truth) < abs(before - truth) and res.wss.mean == pytest.approx(truth, rel=0.15)


# the fourier phantom (seed 300, h 1.5 mm) reads aspect 1.17 < MIN_ASPECT: the check would not run, so it is not here
@pytest.mark.parametrize("case", ["laminar", pytest.param("turbulent-ellipse", marks=pytest.mark.slow)])
def test_elliptic_lumens_whose_flow_follows_their_shape_are_not_flagged(case):
    acq, _ = phantoms.make_phantom(case, h_mm=1.5, snr=25, seed=300)
    res = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    note, rec = shape_check(res)
    assert note == "" and rec["lumen_aspect"] > 1.2, rec
    assert max(rec["flow_aspect"], rec["lumen_aspect"]) / min(rec["flow_aspect"], rec["lumen_aspect"]) < 1.1


def test_an_elliptic_lumen_with_flow_across_its_shape_is_suspect():
    """A 13 x 8 mm elliptic lumen whose velocity is elongated across it (a profile squeezed along the major axis):
    no straight vessel, cut at any angle, has such flow."""
    from dataclasses import replace

    acq, truth = phantoms.make_phantom("laminar", h_mm=1.5, snr=25, seed=301)  # 13 x 10 mm, major axis at 0.4 rad
    xc, yc = (np.asarray(a) for a in acq.grid.centers())
    x, y = xc - truth.flow.lumen.center[0], yc - truth.flow.lumen.center[1]
    along, across = x * np.cos(0.4) + y * np.sin(0.4), -x * np.sin(0.4) + y * np.cos(0.4)
    inside = truth.flow.lumen.inside(xc, yc)
    flow = np.where(inside, np.clip(1 - (along / 6.0) ** 2 - (across / 13.0) ** 2, 0, None) * 0.5, 0.0)
    noise = np.random.default_rng(9).normal(0, 0.01, flow.shape)
    odd = replace(acq, phase=None, velocity=(flow + noise)[None], venc_m_s=None)
    res = reconstruct(odd, ReconstructionOptions(uncertainty=False))[0]
    note, rec = shape_check(res)
    assert note.startswith("SUSPECT") and res.screen["suspect"] and any(note in w for w in res.warnings)
    assert rec["axes_angle_deg"] > 45 or rec["flow_aspect"] / rec["lumen_aspect"] > MAX_ASPECT_MISMATCH
