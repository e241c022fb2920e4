"""Units, aliasing and several vessels (wss_nlp.pipeline.plausibility): checked against known answers.

Seeds here were not used to choose any threshold of the screen.
"""

from dataclasses import replace

import numpy as np
import pytest

from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.pipeline import plausibility as pl
from wss_nlp.errors import InputError
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

FAST = ReconstructionOptions(uncertainty=False)


def _disk(n=40, r=15.0):
    y, x = np.mgrid[:n, :n] - (n - 1) / 2
    return x, y, np.hypot(x, y) < r


def test_unwrap_recovers_a_smooth_field_exactly():
    # Poiseuille-like field up to 3.6 venc: two wraps, neighbour differences below venc, zero on the rim
    venc = 1.0
    x, y, inside = _disk()
    true = np.where(inside, 3.6 * venc * (1 - (x**2 + y**2) / 15.0**2), 0.0)
    wrapped = pl._wrap(true, venc)
    assert np.abs(wrapped - true).max() > 3 * venc  # the data really are wrapped twice
    rim = inside & ~np.roll(inside, 1, 0) | inside & ~np.roll(inside, -1, 0)
    out = pl.unwrap_velocity(wrapped, inside, venc, rim)
    assert np.abs(out - true)[inside].max() < 1e-12
    assert np.array_equal(out[~inside], wrapped[~inside])  # nothing outside the region changes


def test_residual_jumps_counts_a_branch_cut():
    # a phase vortex cannot be unwrapped consistently: its branch cut leaves jumps of 2 venc
    venc = 1.0
    x, y, inside = _disk()
    vortex = venc * np.arctan2(y, x) / np.pi
    out = pl.unwrap_velocity(vortex, inside, venc, inside & (np.hypot(x, y) > 13))
    assert pl.residual_jumps(out, inside, venc) >= 10  # about one per voxel along a radius
    assert pl.residual_jumps(np.zeros_like(x), inside, venc) == 0


@pytest.mark.parametrize(
    "case, h, venc_fraction, seed",
    [("laminar", 1.0, 0.6, 41), ("manufactured", 0.6, 0.45, 42), ("circle", 1.5, 0.7, 43)],
)
def test_aliased_phantom_reconstructs_as_well_as_unaliased(case, h, venc_fraction, seed):
    """The issue's criterion: WSS error within 1.5x that of the same phantom without aliasing."""
    acq0, truth = phantoms.make_phantom(case, h_mm=h, snr=25, seed=seed)
    peak = phantoms.peak_velocity(truth.flow)
    acq1, _ = phantoms.make_phantom(case, h_mm=h, snr=25, seed=seed, venc=venc_fraction * peak)
    r0, r1 = reconstruct(acq0, FAST)[0], reconstruct(acq1, FAST)[0]
    e0, e1 = (metrics.compare_slice(r, truth).wss_rel_l2 for r in (r0, r1))
    assert r1.screen["unwrapped"] and r1.screen["aliased_voxels"] > 0
    assert any("velocity aliasing" in w for w in r1.warnings)
    assert e1 <= 1.5 * e0, (e0, e1)
    assert not r0.screen["unwrapped"] and not any("aliasing" in w for w in r0.warnings)


def test_no_unwrap_keeps_the_data_and_warns():
    acq, truth = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=44, venc=0.25)
    screened, found = pl.screen(acq, pl.ScreenOptions(unwrap=False))
    assert screened is acq
    assert "suspected" in found[0].notes[0] and not found[0].record["unwrapped"]


def test_unresolvable_aliasing_is_refused():
    acq, _ = phantoms.make_phantom("circle", h_mm=1.0, snr=25, seed=45)
    _, _, inside = _disk(acq.magnitude.shape[1], 1.0)
    ny, nx = acq.magnitude.shape[1:]
    y, x = np.mgrid[:ny, :nx] - (ny - 1) / 2
    vortex = np.arctan2(y, x)[None]  # a phase singularity in the lumen: no consistent unwrapping exists
    with pytest.raises(InputError, match="cannot be unwrapped consistently.*venc"):
        pl.screen(replace(acq, phase=vortex))


@pytest.mark.parametrize("factor, unit", [(100.0, "cm/s"), (1000.0, "mm/s")])
def test_velocity_in_wrong_units_is_refused(factor, unit):
    acq, _ = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=46, as_phase=False)
    bad = replace(acq, velocity=acq.velocity * factor)
    with pytest.raises(InputError, match=f"'velocity'.*venc_m_s.*{unit}"):
        pl.screen(bad)
    with pytest.raises(InputError, match=f"implausible for blood flow.*{unit}"):
        pl.screen(replace(bad, venc_m_s=None))  # without venc: the speed bound catches it


def test_venc_in_cm_s_is_refused():
    acq, _ = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=47)
    with pytest.raises(InputError, match="implausible.*venc_m_s = 50: is it in cm/s"):
        pl.screen(replace(acq, venc_m_s=acq.venc_m_s * 100))


def test_two_vessels_largest_taken_others_reported_and_selectable():
    acq, truth = phantoms.make_two_vessels(h_mm=1.0, snr=25, seed=48)
    res = reconstruct(acq)[0]
    others = res.screen["other_vessels"]
    assert len(others) == 1 and others[0]["center_mm"] == pytest.approx([9, 5], abs=0.8)
    assert others[0]["equal_area_radius_mm"] == pytest.approx(5.0, rel=0.1)
    assert any("1 other vessel(s) in view" in w for w in res.warnings)
    # the artery, with the vein kept out of the noise background: accurate, with a band of the usual size
    err = metrics.compare_slice(res, truth)
    assert err.wss_rel_l2 < 0.05 and err.radius_rel_l2 < 0.01
    assert res.wss.mean_std < 0.02 * abs(res.wss.mean)
    vein = reconstruct(acq, replace(FAST, screen=pl.ScreenOptions(vessel=(9.0, 5.0))))[0]
    exact = -2 * 3.5e-3 * 0.25 / 5e-3  # Poiseuille: tau = -2 mu U / R, reverse flow
    assert vein.wss.mean == pytest.approx(exact, rel=0.06)
    assert vein.geometry.coefficients[0] == pytest.approx(5.0, rel=0.02)
    assert "(-8" in vein.warnings[0] or "(-7" in vein.warnings[0]


def test_hidden_aliasing_is_flagged_not_passed_off():
    # a plug-like turbulent profile at coarse voxels with venc 0.45 x peak: the velocity rises by more than venc
    # within one voxel all around the wall, so no spatial unwrapping can see the wrap; the fit cannot follow the data
    # and the slice is flagged (threshold measured on seeds 300-301 in scripts/aliasing.py; seed 49 here)
    acq0, truth = phantoms.make_phantom("turbulent", h_mm=1.5, snr=25, seed=49)
    acq, _ = phantoms.make_phantom(
        "turbulent", h_mm=1.5, snr=25, seed=49, venc=0.45 * phantoms.peak_velocity(truth.flow)
    )
    bad = reconstruct(acq, FAST)[0]
    assert bad.screen["suspect"] and bad.screen["velocity_residual_to_noise"] > pl.MAX_RESIDUAL_TO_NOISE
    assert any("SUSPECT" in w and "venc_m_s" in w for w in bad.warnings)
    good = reconstruct(acq0, FAST)[0]
    assert not good.screen["suspect"] and good.screen["velocity_residual_to_noise"] < 1.5
    assert not any("SUSPECT" in w for w in good.warnings)


def test_a_velocity_fit_that_interpolates_the_noise_is_flagged():
    """A lumen three voxels in radius (the 3 mm Womersley pipe at h = 1 mm, a frame at flow reversal, seed 4)
    fitted with a fixed beta of 1e-13: the fit spends about as many effective parameters as there are voxels
    and its WSS is off by several times the peak, so the slice is SUSPECT; the same frame at beta 1e-6
    is not (the built-in phantoms at their chosen beta: at most 0.11 of the voxels, checked on seven cases at
    h 0.6-1.5 mm and SNR 10/25)."""
    from wss_nlp.synthetic import pulsatile
    from wss_nlp.pipeline.results import DOF_LIMIT

    frames, _ = pulsatile.make_cine(h_mm=1.0, snr=25, seed=4, frames=20, radius_mm=3.0)
    base = ReconstructionOptions(uncertainty=False, choice=ChoiceOptions(beta_rule="fixed"))
    loose = reconstruct(frames[13], replace(base, velocity=replace(base.velocity, beta=1e-13, near_wall="off")))[0]
    n_vox = np.count_nonzero(loose.velocity.voxel_fraction)
    assert loose.velocity.dof > DOF_LIMIT * n_vox
    assert any("effective parameters" in w and "SUSPECT" in w for w in loose.warnings)
    firm = reconstruct(frames[13], replace(base, velocity=replace(base.velocity, beta=1e-6, near_wall="off")))[0]
    assert firm.velocity.dof < 0.5 * n_vox and not any("effective parameters" in w for w in firm.warnings)


@pytest.mark.parametrize("x", [0.1, 0.8, 1.5, 2.5])
def test_dephasing_spread_inverts_the_ramp_factor(x):
    # a linear ramp of width du across a voxel: D = |mean_t exp(i pi du t / venc)| = sin(x) / x, x = pi du / (2 venc);
    # the inversion interpolates on 2001 points of the first lobe: 1e-4 of venc is well above its error there
    assert pl.dephasing_spread(np.sin(x) / x) == pytest.approx(2 * x / np.pi, abs=1e-4)
    # the same factor by a second, independent computation: a 4001-point midpoint mean of the phases of the ramp
    t = (np.arange(4001) + 0.5) / 4001
    assert abs(np.mean(np.exp(1j * 2 * x * t))) == pytest.approx(np.sin(x) / x, abs=1e-6)


def test_dephasing_bounds_depend_on_unwrapping():
    between = (pl.MIN_DEPHASING_FACTOR + pl.MIN_DEPHASING_FACTOR_ALIASED) / 2
    assert pl.check_dephasing(between, 0.3, unwrapped=True).startswith("SUSPECT: intravoxel dephasing")
    assert pl.check_dephasing(between, 0.3, unwrapped=False) == ""  # unaliased flow can dephase this much
    assert "venc_m_s = 0.3" in pl.check_dephasing(0.5, 0.3, unwrapped=False)
    assert pl.check_dephasing(0.5, None, unwrapped=True) == ""  # no phase data, no dephasing model
    assert pl.check_dephasing(1.0, 0.3, unwrapped=True) == ""


def test_aliased_dephased_wall_is_flagged_and_the_same_flow_unaliased_is_not():
    """The soak's silent wrong results (issue 42): a plug-like entrance profile with venc 0.85 x its peak,
    unwrapped correctly, but its wall voxels hold velocities spanning about venc; the WSS is far off with a fit
    residual at the noise level. The dephasing check flags it; the same phantom and seed at the default venc is
    neither flagged nor far off. Seed 61 was not used to choose the thresholds (seeds 300-301 were)."""
    acq0, truth = phantoms.make_phantom("entrance", h_mm=1.0, snr=25, seed=61)
    peak = phantoms.peak_velocity(truth.flow)
    acq, _ = phantoms.make_phantom("entrance", h_mm=1.0, snr=25, seed=61, venc=0.85 * peak)
    bad, good = reconstruct(acq, FAST)[0], reconstruct(acq0, FAST)[0]
    e_bad, e_good = (metrics.compare_slice(r, truth).wss_rel_l2 for r in (bad, good))
    assert bad.screen["unwrapped"] and bad.screen["velocity_residual_to_noise"] < pl.MAX_RESIDUAL_TO_NOISE
    # what the flag is for: wrong by far more than the soak's 10 % (27 % here, 26-36 % in the soak's failures on this
    # profile at h 1 mm), with a residual the fit check accepts
    assert e_bad > 0.2
    assert bad.dephasing.min_factor < pl.MIN_DEPHASING_FACTOR_ALIASED
    assert bad.screen["dephasing_suspect"] and bad.screen["suspect"]
    assert any("SUSPECT: intravoxel dephasing" in w for w in bad.warnings)
    assert not good.screen["unwrapped"] and not good.screen["dephasing_suspect"]
    assert good.dephasing.min_factor > pl.MIN_DEPHASING_FACTOR_ALIASED  # the default venc keeps D >= 0.76
    # the unaliased entrance profile is the hardest phantom (its layer is thinner than a voxel): 9.6 % here, up to
    # 9.8 % unflagged in the soak; 15 % leaves room for the solver's rounding and is still half the aliased error
    assert not any("SUSPECT" in w for w in good.warnings) and e_good < 0.15
