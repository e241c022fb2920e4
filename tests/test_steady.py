"""Single frames of unsteady flow read as steady slices (issue 40): wss_nlp.models.steady and its use by the driver.

The full study (8 phases x 3 voxel sizes x reported seeds, 20 steady laminar and 20 steady turbulent slices) is
``scripts/unsteady_frames.py`` -> scripts/results/unsteady_frames.md; these tests check each side on one case.
"""

import numpy as np
import pytest

from wss_nlp.core import radius as rad
from wss_nlp.models import steady
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
from wss_nlp.synthetic import phantoms, pulsatile


def _voxels(profile, h=0.5, radius=10.0, noise=0.002, seed=50):
    """Voxel centres of a circular lumen (radius mm) on an h-grid, the profile's point values there plus seeded
    noise: ``(u, sigma, x, y, coefficients)``."""
    rng = np.random.default_rng(seed)
    g = np.arange(-radius, radius + h, h)
    x, y = (v.ravel() for v in np.meshgrid(g, g))
    rho = np.hypot(x, y) / radius
    keep = rho < 1
    x, y, rho = x[keep], y[keep], rho[keep]
    sigma = np.full(x.size, noise)
    coefficients = np.zeros(rad.n_coefficients(2))
    coefficients[0] = radius
    return profile(rho) + sigma * rng.standard_normal(x.size), sigma, x, y, coefficients


def _check(profile, **kw):
    u, sigma, x, y, c = _voxels(profile, **kw)
    return steady.check(u, sigma, x, y, c, (0.0, 0.0), kw.get("h", 0.5), reynolds=1000.0)


def test_steady_profiles_pass_and_each_unsteady_shape_is_named():
    """Point values of steady profiles (the parabola, Langhaar's entrance profile at epsilon 20, a turbulent-like
    1 - rho^8 core) with seeded noise of 0.2 % of the axis velocity per voxel: no reason given (the rings' noise,
    about 3e-4, is far below the profiles' ring-to-ring fall and curvature, so no shape constraint is active and
    each chi-square gain is about 0, against the threshold 25). Unsteady shapes, each named by its own reason: a
    near-wall reversal under a forward core, an overshoot near the wall, a core more peaked than the parabola
    (1 - rho, a cone)."""
    for profile in (lambda r: 1 - r**2, steady.langhaar(20.0), lambda r: 1 - r**8):
        found = _check(profile)
        assert not found.unsteady, found.reasons
    reversal = _check(lambda r: 1 - r**2 - 0.6 * np.exp(-(((1 - r) / 0.08) ** 2)))
    assert any(m.startswith("flow reversal") for m in reversal.reasons)
    overshoot = _check(lambda r: (1 - r**2) + 1.5 * r**6 * (1 - r) * 8)
    assert any(m.startswith("near-wall overshoot") for m in overshoot.reasons)
    cone = _check(lambda r: 1 - r)
    assert any("more peaked than the parabola" in m for m in cone.reasons), cone.reasons


def test_ring_drop_of_the_parabola_matches_the_closed_form_and_langhaar_tends_to_it():
    """The parabola's area-weighted ring means over [a, b] are 1 - (a^2 + b^2)/2 at the mean radius
    2 (b^3 - a^3) / (3 (b^2 - a^2)): ring_drop's midpoint rule (64 points a ring, error ~ (w/64)^2) matches the
    closed form to 1e-5; Langhaar's profile at epsilon 1e-2 differs from the parabola by O(epsilon^2) (drop
    within 1e-4); at epsilon 200 the core is flat (drop < 1e-6)."""
    rings = 9
    a, b = np.linspace(0, 1, rings + 1)[:-1], np.linspace(0, 1, rings + 1)[1:]
    means = 1 - (a**2 + b**2) / 2
    centres = 2 * (b**3 - a**3) / (3 * (b**2 - a**2))
    exact = 1 - np.interp(0.7, centres, means) / means[0]
    assert steady.ring_drop(steady.langhaar(0.0), rings) == pytest.approx(exact, abs=1e-5)
    assert steady.ring_drop(steady.langhaar(1e-2), rings) == pytest.approx(exact, abs=1e-4)
    assert steady.ring_drop(steady.langhaar(200.0), rings) < 1e-6


def test_shape_regressions_against_brute_force():
    """The antitonic fit of a known violator pools it (PAV: [3, 1, 2] -> [3, 1.5, 1.5]); a concave
    non-increasing sequence is its own concave fit (to 1e-9), and the concave fit of a convex sequence is no
    worse than the best straight line (a concave candidate) and never better than the data."""
    assert np.allclose(steady.antitonic(np.array([3.0, 1.0, 2.0]), np.ones(3)), [3.0, 1.5, 1.5])
    x = np.linspace(0.1, 0.9, 8)
    w = np.ones(8)
    concave = 1 - x**2
    assert np.allclose(steady.concave_decreasing(x, concave, w), concave, atol=1e-9)
    convex = (1 - x) ** 2
    fit = steady.concave_decreasing(x, convex, w)
    line = np.polyval(np.polyfit(x, convex, 1), x)
    assert np.sum((fit - convex) ** 2) <= np.sum((line - convex) ** 2) + 1e-12
    assert np.all(np.diff(fit) <= 1e-12)


def test_a_womersley_frame_read_as_a_steady_slice_is_flagged():
    """The 4-harmonic Womersley phantom at 250 ms (frame 1 of 4, phase 2 of the study's 8: after peak systole, a
    curved core under a Stokes layer thinner than a voxel), h = 1.5 mm, SNR 25, seed 50 (not a tuning or
    reported seed): the default reconstruction misses its mean WSS by more than twice its band (the study: 14-32
    % of the peak at this phase), and the result says the data contradict every steady family: the SUSPECT
    warning, the screen record's reasons."""
    frames, truth = pulsatile.make_cine(h_mm=1.5, snr=25, seed=50, frames=4)
    r = reconstruct(frames[1], ReconstructionOptions())[0]
    error = abs(r.wss.mean - truth.reference_tau()[1])
    assert error > 2 * r.wss.mean_std
    assert r.steady is not None and r.steady.unsteady
    assert r.screen["suspect"] and r.screen["steady"]["reasons"]
    assert any("contradict every steady family" in w for w in r.warnings)


@pytest.mark.parametrize("case", ["laminar", "turbulent"])
def test_steady_slices_are_not_flagged(case):
    """Steady laminar (elliptic Poiseuille) and turbulent (DNS pipe mean) slices, h = 1.0 mm, SNR 25, seed 51 (not
    a tuning or reported seed): tested (a record) and not flagged."""
    acq, _ = phantoms.make_phantom(case, h_mm=1.0, snr=25, seed=51)
    r = reconstruct(acq, ReconstructionOptions())[0]
    assert r.steady is not None and not r.steady.unsteady, r.steady.reasons
    assert "steady" in r.screen and not any("steady family" in w for w in r.warnings)


class _Turbulent:
    """A near-wall choice as the driver passes it: the law of the wall chosen, its data viscosity ratio given."""

    model, unresolved_mm, scale_ratio = "wall_law", float("nan"), float("nan")

    def __init__(self, ratio):
        self.viscosity_ratio = ratio


def test_turbulent_regime_reasons_name_the_stated_viscosity():
    """A flat steady core (1 - rho^8, seeded noise 0.2 %) at Re 10000 whose law of the wall implies 2.0 x the
    stated viscosity (the ratio outside the factor 1.6): the only reason is the viscosity's, so the note asks
    whether the stated viscosity is off rather than calling the slice unsteady; a ratio of 1.2 gives no reason;
    with an unsteady shape besides (a near-wall reversal), the note stays the unsteady-flow one."""
    u, sigma, x, y, c = _voxels(lambda r: 1 - r**8)
    off = steady.check(u, sigma, x, y, c, (0.0, 0.0), 0.5, reynolds=1e4, near=_Turbulent(2.0))
    assert off.unsteady and off.viscosity_reasons == len(off.reasons) == 1
    assert "true viscosity is 2 x the stated one" in off.reasons[0]
    assert off.note().startswith("SUSPECT: unsteady flow, or the stated viscosity off?")
    fine = steady.check(u, sigma, x, y, c, (0.0, 0.0), 0.5, reynolds=1e4, near=_Turbulent(1.2))
    assert not fine.unsteady
    u, sigma, x, y, c = _voxels(lambda r: 1 - r**8 - 0.6 * np.exp(-(((1 - r) / 0.08) ** 2)))
    both = steady.check(u, sigma, x, y, c, (0.0, 0.0), 0.5, reynolds=1e4, near=_Turbulent(2.0))
    assert both.viscosity_reasons == 1 < len(both.reasons)
    assert both.note().startswith("SUSPECT: unsteady flow? the near-wall data")


def test_a_steady_turbulent_slice_with_its_viscosity_stated_half_says_so():
    """The steady turbulent slice (DNS pipe mean), h = 1.0 mm, SNR 25, seed 52 (not a tuning or reported seed),
    its viscosity stated at half the true one: flagged (the law of the wall's layer implies about twice the
    stated viscosity; scripts/results/unsteady_viscosity.md), and the warning names the stated viscosity."""
    acq, _ = phantoms.make_phantom("turbulent", h_mm=1.0, snr=25, seed=52)
    r = reconstruct(acq, ReconstructionOptions(viscosity_pa_s=0.5 * acq.viscosity(None)))[0]
    assert r.steady is not None and r.steady.unsteady and r.steady.viscosity_reasons == len(r.steady.reasons)
    assert any("or the stated viscosity off?" in w for w in r.warnings)
