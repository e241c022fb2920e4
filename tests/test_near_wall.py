"""Near-wall enrichment (issue 13): profiles, exact cell means, the enriched basis, the model choice and the CLI."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.integrate

import casadi as ca

from wss_nlp.pipeline import driver
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.app import cli
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.io import files as wio
from wss_nlp.models import measurement as meas
from wss_nlp.models import near_wall as nw
from wss_nlp.models import velocity as vel
from wss_nlp.models import wss as wss_mod
from wss_nlp.errors import InputError
from wss_nlp.core.mapping import DiskMap
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
from wss_nlp.core.velocity_basis import make_basis

BASE = make_basis("zernike", 20, 400.0, 6)


@pytest.mark.parametrize("family", nw.FAMILIES)
def test_profiles_vanish_at_the_wall_with_unit_slope_and_antiderivatives_integrate_them(family):
    y = ca.SX.sym("y")
    f = ca.Function("f", [y], [nw.profile(family, y), ca.jacobian(nw.profile(family, y), y)])
    value, slope = (float(v) for v in f(0.0))
    assert value == 0.0 and slope == pytest.approx(1.0, abs=1e-12)
    for x in (0.01, 1.0, 7.0, 50.0, 400.0):
        f1, f2 = nw.antiderivatives(family, x)
        ref1 = scipy.integrate.quad(lambda s: nw.profile(family, s), 0, x, epsabs=1e-13, epsrel=1e-13)[0]
        ref2 = scipy.integrate.quad(lambda s: nw.antiderivatives(family, s)[0], 0, x, epsabs=1e-12, epsrel=1e-13)[0]
        assert f1 == pytest.approx(ref1, rel=1e-11, abs=1e-13)
        assert f2 == pytest.approx(ref2, rel=1e-10, abs=1e-12)


@pytest.mark.parametrize("family", nw.FAMILIES)
def test_cell_mean_is_the_trapezoid_mean_of_the_truncated_profile(family):
    """Against a 4000^2-point midpoint rule over the cell's two box directions (its error is ~1e-7 relative)."""
    n = 4000
    s = (np.arange(n) + 0.5) / n - 0.5
    for y, a, b in ((3.0, 2.0, 0.7), (0.4, 1.5, 1.0), (25.0, 4.0, 1e-5), (-0.5, 1.2, 0.3), (2.0, 0.01, 0.005)):
        pts = y + 2 * a * s[:, None] + 2 * b * s[None, :]
        ref = np.mean(np.where(pts > 0, nw.profile(family, np.maximum(pts, 0)), 0.0))
        # cells narrower than 0.02 l take the midpoint value: relative error <= a^2 |f''| / (6 f), 1e-4 promised
        rel = 1e-4 if a < 0.02 or y > 3 * (a + b) else 2e-6  # the midpoint and curvature-corrected branches
        assert nw.cell_mean(family, y, a, b) == pytest.approx(ref, rel=rel, abs=1e-9)


def test_enriched_basis_numpy_casadi_polar_forms_agree_and_layer_is_not_penalized():
    basis = nw.EnrichedBasis(BASE, "wall_law", 0.004)
    rng = np.random.default_rng(4)
    x, y = rng.uniform(-0.7, 0.7, (2, 7))
    xi = ca.SX.sym("xi", 2)
    sym = ca.Function("v", [xi], [basis.symbolic(xi)])
    values = basis.evaluate(x, y)
    np.testing.assert_allclose(np.hstack([np.asarray(sym([a, b])) for a, b in zip(x, y)]).T, values, atol=1e-12)
    polar = (basis.radial_raw(np.hypot(x, y)) * basis.angular_raw(np.arctan2(y, x))).T @ basis.transform
    np.testing.assert_allclose(polar, values, atol=1e-12)
    assert np.all(basis.evaluate(np.cos([0.3, 2.0]), np.sin([0.3, 2.0]))[:, BASE.size :] == 0)  # vanish on the wall
    gram = basis.laplacian_gram(2)
    assert np.all(gram[BASE.size :] == 0) and np.all(gram[:, BASE.size :] == 0)
    np.testing.assert_array_equal(gram[: BASE.size, : BASE.size], BASE.laplacian_gram(2))


def test_layer_column_wss_is_mu_times_its_wall_slope():
    """On a circle of radius R (map r_in R rho + (1 - r_in) R rho^2), column m = 0 has wall gradient S/l."""
    big_r, r_in, scale = 10.0, 5.0, 0.003
    dm = DiskMap(np.array([big_r, 0, 0, 0, 0, 0, 0, 0, 0]), (0.0, 0.0), r_in, 2.0)
    basis = nw.EnrichedBasis(BASE, "exponential", scale)
    smat, _ = wss_mod.wss_matrix(basis, dm, 1e-3, 36)
    stretch = nw.stretch(dm)
    assert stretch == pytest.approx(r_in + 2 * (big_r - r_in))
    # d/d(distance) of f((1 - rho)/scale) at the wall is 1 / (scale * stretch) per mm; tau in Pa = mu * 1000 * that
    expected = 1e-3 * 1000 * basis.column_scale / (scale * stretch)
    np.testing.assert_allclose(smat[:, BASE.size], expected, rtol=1e-12)


def test_wss_graph_with_the_scale_as_parameter_equals_the_basis_own_graph():
    """One WSS graph per layer family serves every scale (the scale a parameter, wss.velocity_template): tau and
    d tau / d c equal those of a graph built on the basis itself (its scale and column scale as constants), on an
    off-centre elliptic wall, for two scales and both families; the second scale reuses the cached graph."""
    coef = np.array([10.0, 0.8, -0.3, 0, 0, 0.5, 0.2, 0, 0])
    dm = DiskMap(coef, (0.4, -0.2), 5.0, 2.0)
    rng = np.random.default_rng(21)
    for family in nw.FAMILIES:
        for scale in (0.004, 0.03):
            basis = nw.EnrichedBasis(BASE, family, scale)
            c = rng.normal(size=basis.size)
            direct = wss_mod.wss_expression(wss_mod._BasisVelocity(basis), 4, dm.r_in, 2.0).map(36)
            phi = np.linspace(0, 2 * np.pi, 36, endpoint=False)
            tau_direct = np.asarray(direct(phi[None, :], coef, np.array(dm.center), c, 3.5e-3)[0]).ravel()
            smat, _ = wss_mod.wss_matrix(basis, dm, 3.5e-3, 36)
            assert np.max(np.abs(smat @ c - tau_direct)) <= 1e-10 * np.max(np.abs(tau_direct))
    assert wss_mod._basis_wss_jacobian_map.cache_info().hits >= 2


@pytest.fixture(scope="module")
def turbulent550():
    acq, truth = phantoms.make_phantom("turbulent550", h_mm=1.5, snr=None, seed=11)
    res = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    return acq, truth, res


def _midpoint_layer_means(problem, basis):
    """The layer columns' voxel means by the problem's own midpoint rule (its points inside the lumen)."""
    vox = problem.voxels
    rho, t = problem.disk_map.inverse(vox.px[vox.inside], vox.py[vox.inside])
    rho = np.minimum(rho, 1.0)  # as velocity.assemble does
    values = basis.layer_radial(rho)[0] * basis.angular_raw(t)[-basis.n_layer :] * basis.column_scale
    return np.asarray(vox.mean_matrix() @ values.T)


@pytest.mark.slow  # CI budget: 52 s; the cell-mean trapezoid tests of every family stay in CI
def test_layer_quadrature_matches_a_fine_midpoint_rule(turbulent550):
    """Exact cell means on the 6 x 6 rule vs a 100 x 100 rule (the layer is 23 um, cells 250 um): 0.3 %."""
    acq, truth, res = turbulent550
    g, opts = res.geometry, ReconstructionOptions().velocity
    vp = vel.assemble(acq.grid, truth.velocity_image, g.coefficients, g.center, opts)
    fine = vel.assemble(acq.grid, truth.velocity_image, g.coefficients, g.center, replace(opts, quad_order=100))
    where = {v: i for i, v in enumerate(fine.voxels.index)}
    rows = [i for i, v in enumerate(vp.voxels.index) if v in where]
    for ratio in (1 / 549, 0.01):
        basis = nw.EnrichedBasis(vp.basis, "wall_law", ratio * g.coefficients[0] / nw.stretch(vp.disk_map))
        exact = nw.LayerQuadrature(vp).columns(basis)[rows]
        ref = _midpoint_layer_means(fine, basis)[[where[v] for v in vp.voxels.index[rows]]]
        coarse = _midpoint_layer_means(vp, basis)[rows]
        scale = np.max(np.abs(ref))
        assert np.max(np.abs(exact - ref)) < 3e-3 * scale
        assert np.max(np.abs(exact - ref)) < 0.2 * np.max(np.abs(coarse - ref))  # what the exact means buy


def test_noise_free_turbulent_recovery_with_the_wall_law(turbulent550):
    """Re_tau 549 DNS, exact viscous length given: WSS within 2 % (0.6 % measured); the plain basis misses by 79 %."""
    acq, truth, _ = turbulent550
    ell = 25.885 / 2 / phantoms.dns_profile("re550")[2]
    opts = ReconstructionOptions(
        uncertainty=False, velocity=vel.VelocityOptions(near_wall="wall_law", layer_scale_mm=ell)
    )
    res = reconstruct(acq, opts)[0]
    assert metrics.compare_slice(res, truth).wss_rel_l2 < 0.02
    assert res.near_wall.model == "wall_law" and res.near_wall.criterion.startswith("given")
    from wss_nlp.app import plotting

    fig = plotting.figure_near_wall(res, truth)
    assert fig.axes[0].get_title().startswith("near-wall model: wall_law, l = ")
    assert len(fig.axes[0].lines) >= 3  # fitted and true profiles, the layer scale, the wall
    off = ReconstructionOptions(uncertainty=False, velocity=vel.VelocityOptions(near_wall="off"))
    assert plotting.figure_near_wall(reconstruct(acq, off)[0]) is None


def test_noise_free_entrance_flow_with_the_exponential_layer():
    """Langhaar's profile (not exactly exponential), l = R/a given: within 4 % (1.1-2.8 % measured)."""
    acq, truth = phantoms.make_phantom("entrance", h_mm=1.0, snr=None, seed=12)
    opts = ReconstructionOptions(
        uncertainty=False, velocity=vel.VelocityOptions(near_wall="exponential", layer_scale_mm=10.0 / 30.0)
    )
    assert metrics.compare_slice(reconstruct(acq, opts)[0], truth).wss_rel_l2 < 0.04


def test_plain_model_kept_on_laminar_data():
    """20 seeded draws (4 laminar-type phantoms x seeds 300-304, not used in development), h = 1.5 mm, SNR 25.

    The laminar Reynolds numbers (about 1200-1400) offer the exponential
    layer, which must not beat the plain basis by the required evidence.
    """
    opts = ReconstructionOptions(uncertainty=False, velocity=vel.VelocityOptions(near_wall="auto"))
    picked = []
    for case in ("laminar", "circle", "manufactured", "fourier"):
        for seed in range(300, 305):
            acq, _ = phantoms.make_phantom(case, h_mm=1.5, snr=25.0, seed=seed)
            picked.append((case, seed, reconstruct(acq, opts)[0].near_wall.model))
    assert all(model == "plain" for _, _, model in picked), picked


@pytest.mark.parametrize(
    "case, h, seed, limit",
    [
        # limits: the measured report-seed means (scripts/results/near_wall.md) plus about 3 noise standard deviations
        ("turbulent550", 1.0, 310, 0.04),
        ("turbulent1000", 1.5, 311, 0.07),
        ("turbulent", 0.6, 312, 0.10),  # Reichardt's law vs the low-Re DNS: +4 % even noise-free
        ("turbulent-ellipse", 1.0, 313, 0.10),
    ],
)
def test_turbulent_wss_with_the_law_of_the_wall(case, h, seed, limit):
    """--near-wall auto on unseen seeds: the wall law at its self-consistent scale (the plain basis: 15-45 % off)."""
    acq, truth = phantoms.make_phantom(case, h_mm=h, snr=25.0, seed=seed)
    opts = ReconstructionOptions(uncertainty=False, velocity=vel.VelocityOptions(near_wall="auto"))
    res = reconstruct(acq, opts)[0]
    assert res.near_wall.model == "low_re" and "u_tau l = nu" in res.near_wall.criterion
    assert metrics.compare_slice(res, truth).wss_rel_l2 < limit
    if case != "turbulent-ellipse":  # a pipe: the scale is the DNS's viscous length nu/u_tau = R/Re_tau
        true_ratio = 1 / phantoms.dns_profile(truth.flow.dns)[2]
        assert res.near_wall.scale_ratio == pytest.approx(true_ratio, rel=0.06)


def test_bulk_reynolds_number_and_regime():
    """Poiseuille flow in a 10 mm pipe: U = u_max/2 = 0.2 m/s, D = 20 mm, blood: Re = 1211 (partial volumes: 2 %)."""
    acq, _ = phantoms.make_phantom("circle", h_mm=0.6, snr=None, seed=2)
    res = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    g = res.geometry
    vp = vel.assemble(res.grid, res.velocity_image, g.coefficients, g.center, ReconstructionOptions().velocity)
    nu = 3.5e-3 / 1060.0
    assert nw.bulk_reynolds(vp, nu) == pytest.approx(0.2 * 0.02 / nu, rel=0.02)
    assert nw.regime_families(1211) == ("exponential",) and nw.regime_families(5300) == ("wall_law", "low_re")
    # the scan's starting point: Blasius's law at the DNS's bulk Reynolds number 5300 gives its Re_tau 180.9 (1 %)
    from wss_nlp.parameters.layer import blasius_scale

    assert 2.0 ** -blasius_scale(5300.0) == pytest.approx(180.9, rel=0.01)


def test_density_is_read_checked_and_overridable(tmp_path):
    acq, _ = phantoms.make_phantom("turbulent", h_mm=1.5, snr=25.0, seed=1)
    assert acq.density(None) == (997.8, "file attribute 'density_kg_m3'")
    path = str(tmp_path / "in.h5")
    wio.write_acquisition(path, acq)
    back = wio.read_acquisition(path)
    assert back.density_kg_m3 == 997.8 and back.density(1050.0)[0] == 1050.0
    assert replace(back, density_kg_m3=None).density(None)[0] == wio.DEFAULT_DENSITY
    with pytest.raises(InputError, match="g/cm"):
        replace(back, density_kg_m3=1.06).validate()
    with pytest.raises(InputError, match="--density"):
        ReconstructionOptions(density_kg_m3=-3.0)


def test_cli_records_the_choice_for_both_methods(tmp_path, capsys):
    acq, _ = phantoms.make_phantom("entrance", h_mm=1.0, snr=25.0, seed=13)
    src, out = str(tmp_path / "in.h5"), str(tmp_path / "r.h5")
    wio.write_acquisition(src, acq)
    assert cli.main(["reconstruct", src, "-o", out, "--near-wall", "auto", "--no-uncertainty"]) == 0
    rec = wio.read_near_wall(out)["slice_000"]
    assert rec["model"] == "exponential" and rec["margin"] > nw.AMBIGUOUS_MARGIN
    assert 0.3 / 10 / 2 < rec["scale_ratio"] < 2 * 0.33 / 10  # Langhaar's layer is about R/a = R/30
    capsys.readouterr()
    assert cli.main(["analyze", out]) == 0
    assert "near-wall model 'exponential'" in capsys.readouterr().out
    coupled = ["reconstruct", src, "-o", str(tmp_path / "c.h5"), "--method", "coupled", "--no-uncertainty"]
    assert cli.main(coupled + ["--near-wall", "auto"]) == 0  # the coupled method keeps the chosen layer
    assert wio.read_near_wall(str(tmp_path / "c.h5"))["slice_000"]["model"] == "exponential"
    with pytest.raises(InputError, match="layer-scale"):
        vel.VelocityOptions(near_wall="auto", layer_scale_mm=0.1)


def test_new_phantoms_wall_gradients_match_finite_differences_of_their_velocity():
    """Along the inward normal, one-sided differences at 1e-4 mm (the layers are >= 13 um thick)."""
    for case in ("turbulent550", "turbulent1000", "turbulent-ellipse", "entrance"):
        _, truth = phantoms.make_phantom(case, h_mm=1.0, snr=None, seed=0)
        lumen, flow = truth.lumen, truth.flow
        phi = np.array([0.2, 1.3, 2.9])
        r = lumen.radius(phi)
        dr = (lumen.radius(phi + 1e-7) - lumen.radius(phi - 1e-7)) / 2e-7
        wx, wy = lumen.center[0] + r * np.cos(phi), lumen.center[1] + r * np.sin(phi)
        nx, ny = r * np.cos(phi) + dr * np.sin(phi), r * np.sin(phi) - dr * np.cos(phi)
        norm = np.hypot(nx, ny)
        eps = 1e-4
        inner = flow.velocity(wx - eps * nx / norm, wy - eps * ny / norm)
        np.testing.assert_allclose(inner / eps, flow.wall_gradient(phi), rtol=2e-3, err_msg=case)


def test_band_with_a_fixed_layer_matches_monte_carlo():
    """Linearized band of the mean WSS with the layer fixed (scale and beta) against 24 re-noised solves.

    24 draws estimate a standard deviation to about +-15 % (1 sigma), so a
    ratio within [0.6, 1.6] is a 3-sigma agreement; the band is conditional on
    the layer scale (the docs say what the scale's own spread adds).
    """
    acq0, _ = phantoms.make_phantom("turbulent550", h_mm=1.5, snr=None, seed=14)
    rng = np.random.default_rng(15)
    first = reconstruct(
        phantoms.noisy_copy(acq0, 25, rng), ReconstructionOptions(velocity=vel.VelocityOptions(near_wall="auto"))
    )[0]
    assert first.near_wall.model == "low_re" and np.isfinite(first.wss.mean_std)
    fixed = ReconstructionOptions(
        uncertainty=False,
        velocity=vel.VelocityOptions(
            near_wall="low_re", layer_scale_mm=first.near_wall.scale_mm, beta=first.beta_choice.chosen
        ),
        choice=ChoiceOptions(beta_rule="fixed"),
    )
    band = reconstruct(phantoms.noisy_copy(acq0, 25, rng), replace(fixed, uncertainty=True))[0].wss.mean_std
    means = [reconstruct(phantoms.noisy_copy(acq0, 25, rng), fixed)[0].wss.mean for _ in range(24)]
    assert 0.6 < np.std(means, ddof=1) / band < 1.6


def test_band_with_the_chosen_scale_includes_the_scales_spread():
    """--near-wall auto (scale from u_tau l = nu, re-chosen per draw): band vs 24 re-noised solves, Re_tau 180, h 1.5.

    The band adds the scale's response to the noise (implicit-function
    theorem); without it the band is about 0.6 x the Monte-Carlo spread here.
    Tolerance as in the fixed-layer test (24 draws: +-15 % per sigma). The
    beta choice's own spread is not in the band (docs, "Thin wall layers").
    """
    acq0, _ = phantoms.make_phantom("turbulent", h_mm=1.5, snr=None, seed=16)
    rng = np.random.default_rng(17)
    auto = vel.VelocityOptions(near_wall="auto")
    first = reconstruct(phantoms.noisy_copy(acq0, 25, rng), ReconstructionOptions(velocity=auto))[0]
    assert first.near_wall.consistent and first.near_wall.scale_std_log > 0
    opts = ReconstructionOptions(uncertainty=False, velocity=auto)
    means = [reconstruct(phantoms.noisy_copy(acq0, 25, rng), opts)[0].wss.mean for _ in range(24)]
    assert 0.6 < np.std(means, ddof=1) / first.wss.mean_std < 1.6


def test_exponential_scale_interval_and_the_ambiguity_flag():
    """An exponential layer's scale comes with the interval of scales whose criterion lies within
    AMBIGUOUS_MARGIN of the chosen one (the ends bracketed by evaluated scales inside and outside the margin)
    and the spread of their mean WSS; where that spread exceeds the band the slice is flagged (the entrance
    flow at h = 1 mm, SNR 10: spread 7-10 %, band about 1 % on development seeds 0-3), and without a band it is
    recorded but not judged. Seed 23 (not used in development)."""
    acq, _ = phantoms.make_phantom("entrance", h_mm=1.0, snr=10.0, seed=23)
    r = reconstruct(acq, ReconstructionOptions())[0]
    choice = r.near_wall
    assert choice.model == "exponential"
    lo, hi = choice.scale_interval
    assert lo < choice.scale_ratio < hi
    crit = {ratio: c for model, ratio, c in choice.tried if model == "exponential"}
    limit = crit[min(crit, key=lambda k: abs(k - choice.scale_ratio))] + nw.AMBIGUOUS_MARGIN
    assert all(c <= limit for ratio, c in crit.items() if lo <= ratio <= hi)
    assert any(c > limit for ratio, c in crit.items() if ratio < lo)
    assert any(c > limit for ratio, c in crit.items() if ratio > hi)
    assert choice.scale_wss_spread * abs(r.wss.mean) > r.wss.mean_std
    assert any("layer scale ambiguous" in n for n in r.notes)
    quiet = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    assert quiet.near_wall.scale_wss_spread == pytest.approx(choice.scale_wss_spread, rel=1e-9)
    assert not any("ambiguous" in n for n in quiet.notes)
    assert nw.scale_ambiguity_note(choice, r.wss.mean, float("nan")) == ""
    assert nw.scale_ambiguity_note(choice, r.wss.mean, 10 * abs(r.wss.mean)) == ""


def test_wall_law_roots_within_the_margin_give_the_scale_spread_and_the_flag(monkeypatch):
    """Several roots of u_tau l = nu: a rival root whose criterion lies within AMBIGUOUS_MARGIN of the chosen
    one's makes the record carry both scales' range and the spread of their fits' mean WSS (flagged where it
    exceeds the band, as for the exponential scale), kept through the dephasing pass, which follows the chosen
    root only; a rival outside the margin leaves both NaN. On the
    phantoms the other roots lie 300-450 above (Re_tau 180) or do not exist (Re_tau 549, 998), so the rival
    here is planted a quarter octave from the real root, its fit the real one at that scale."""
    from wss_nlp.parameters import layer as ch

    acq, _ = phantoms.make_phantom("turbulent", h_mm=1.5, snr=25.0, seed=24)
    real = ch._wall_law_scale

    passes = []

    def with_rival(gap):
        def planted(score, *args, **kwargs):
            x, how, rivals = real(score, *args, **kwargs)
            passes.append(args[-1])  # previous: None on the first pass, the root before a dephasing pass
            # a dephasing pass follows the chosen root only: the rival is planted where the scan would find it
            return x, how, ([(score(x)[0] + gap, x + 0.25)] if args[-1] is None else [])

        return planted

    monkeypatch.setattr(ch, "_wall_law_scale", with_rival(nw.AMBIGUOUS_MARGIN / 2))
    r = reconstruct(acq, ReconstructionOptions())[0]
    choice = r.near_wall
    assert choice.model == "low_re" and choice.consistent
    assert passes[0] is None and any(p is not None for p in passes)  # the record is the dephasing pass's
    lo, hi = choice.scale_interval
    # the first pass's range, kept: the pass moved the root by far less than the planted quarter octave
    assert hi == pytest.approx(2**0.25 * lo, rel=1e-12) and lo == pytest.approx(choice.scale_ratio, rel=0.05)
    assert choice.scale_wss_spread > 0
    flagged = any("layer scale ambiguous" in n for n in r.notes)
    assert flagged == (choice.scale_wss_spread * abs(r.wss.mean) > r.wss.mean_std)
    monkeypatch.setattr(ch, "_wall_law_scale", with_rival(2 * nw.AMBIGUOUS_MARGIN))
    far = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0].near_wall
    assert np.isnan(far.scale_wss_spread) and np.isnan(far.scale_interval[0])


def test_a_z_regularized_stack_flags_rival_wall_law_scales(monkeypatch):
    """The stack path (z-regularized, with its joint band) records and flags the scale spread as single slices
    do: a rival root planted half an octave from the real one, within the margin, on a two-slice Re_tau 549
    stack (h = 1.5 mm, SNR 25, seed 5): every slice carries the spread (measured 17-19 %, band about 1 % of the
    mean) and the warning."""
    from wss_nlp.parameters import layer as ch

    real = ch._wall_law_scale

    def planted(score, *args, **kwargs):
        x, how, rivals = real(score, *args, **kwargs)
        return x, how, ([(score(x)[0] + nw.AMBIGUOUS_MARGIN / 2, x + 0.5)] if args[-1] is None else [])

    monkeypatch.setattr(ch, "_wall_law_scale", planted)
    acq, _ = phantoms.make_stack("turbulent", nz=2, h_mm=1.5, snr=25.0, seed=5)
    slices, _ = driver.reconstruct_stack(acq, ReconstructionOptions())
    for r in slices:
        assert r.near_wall.consistent and r.near_wall.scale_wss_spread * abs(r.wss.mean) > r.wss.mean_std
        assert any("layer scale ambiguous" in n for n in r.notes)


def test_wall_law_without_a_root_takes_the_criterions_scale_as_a_fitted_one():
    """Where no scale satisfies u_tau l = nu (the wall law forced on developing laminar flow), the wall law falls
    back to the criterion's scale, which then counts as one more fitted parameter (+ ln n, as the exponential
    layer's), gets the same scale interval and WSS spread, and is not marked consistent (so the band does not
    take the consistency's implicit-function term for it). Seed 29 (not used in development)."""
    acq, _ = phantoms.make_phantom("entrance", h_mm=1.0, snr=25.0, seed=29)
    forced = ReconstructionOptions(uncertainty=False, velocity=vel.VelocityOptions(near_wall="wall_law"))
    choice = reconstruct(acq, forced)[0].near_wall
    assert choice.model == "wall_law" and "no scale satisfies" in choice.criterion
    assert "+ ln(n) for the fitted scale" in choice.criterion and not choice.consistent
    lo, hi = choice.scale_interval
    assert lo <= choice.scale_ratio <= hi and np.isfinite(choice.scale_wss_spread)
    crit = {ratio: c for model, ratio, c in choice.tried if model == "wall_law"}
    raw = crit[min(crit, key=lambda k: abs(k - choice.scale_ratio))]
    # the recorded criterion is the raw one plus ln n, n the number of velocity voxels (box data: all independent)
    n = np.exp(choice.values["wall_law"] - raw)
    assert 100 < n < 1e5 and n == pytest.approx(round(n), abs=1e-6 * n)


def test_z_regularized_stacks_choose_the_near_wall_model_per_slice():
    """A laminar tapered stack with --near-wall auto stays z-regularized and every slice records its choice
    (plain, as single laminar slices); a forced family is taken on every slice of a z-regularized stack (it
    was refused before stacks took layers; the turbulent case is tests/test_stack.py)."""
    acq, _ = phantoms.make_stack("tapered", nz=3, h_mm=1.5, spacing_mm=2.0, snr=25, seed=1)
    opts = ReconstructionOptions(uncertainty=False, velocity=vel.VelocityOptions(near_wall="auto"))
    results = reconstruct(acq, opts)
    assert results.stack is not None  # still z-regularized
    assert all(r.near_wall is not None and r.near_wall.model == "plain" for r in results)
    forced = replace(
        opts, velocity=vel.VelocityOptions(near_wall="exponential"), stack=replace(opts.stack, z_smoothing_mm=2.0)
    )
    results = reconstruct(acq, forced)
    assert results.stack is not None and all(r.near_wall.model == "exponential" for r in results)


@pytest.mark.parametrize("family", ["wall_law", "exponential", "inside"])
def test_casadi_cell_mean_equals_numpy_and_its_derivative_is_exact(family):
    """The coupled method's CasADi cell mean (every branch: midpoint, far inside, box, trapezoid) equals the fit's
    NumPy one to rounding (1e-8: NumPy's inside fraction far inside is the trapezoid's rounding of 1, CasADi's
    exactly 1), its continuous variant (the trapezoid also far inside) within the far branch's truncation
    (5e-4 relative at cells up to six layer scales wide; 3e-4 measured), and its y-derivative the central
    differences of its values."""
    rng = np.random.default_rng(17)
    n = 3000
    y, a = rng.uniform(-5, 40, n), rng.uniform(0, 6, n)
    b = rng.uniform(0, 6, n) * rng.choice([0.0, 1e-5, 1.0], n)
    a[:100] = 0.01  # cells small against the layer: the midpoint value
    exact = nw.cell_mean(family, y, a, b)
    value, slope = (np.asarray(v).ravel() for v in nw.cell_mean_function(family).map(n)(y, a, b))
    np.testing.assert_allclose(value, exact, rtol=0, atol=1e-8 * np.max(np.abs(exact)))
    smooth = nw.cell_mean_function(family, continuous=True).map(n)
    wide = a > 0.02
    sv, sd = (np.asarray(v).ravel() for v in smooth(y, a, b))
    np.testing.assert_allclose(sv[wide], exact[wide], rtol=5e-4, atol=1e-8)
    eps = 1e-5
    fd = (np.asarray(smooth(y + eps, a, b)[0]).ravel() - np.asarray(smooth(y - eps, a, b)[0]).ravel()) / (2 * eps)
    # away from the kinks of the truncated profile's antiderivatives (an argument y +- a +- b at the wall) and
    # from the trapezoid's cancellation in the differences (a b small but not zero: the box formula's domain)
    kinks = np.min(np.abs(np.stack([y + sa * a + sb * b for sa in (-1, 0, 1) for sb in (-1, 0, 1)])), axis=0)
    ok = (kinks > 1e-3) & ((b == 0) | (a * b > 1e-3))
    assert ok.mean() > 0.5
    # the differences' own error: truncation eps^2 f''' and rounding 1e-16 F_2 / (a b eps), about 1e-5
    np.testing.assert_allclose(sd[ok], fd[ok], rtol=0, atol=2e-5 * max(1.0, np.max(np.abs(sd))))


@pytest.mark.parametrize("kind", ["erf", "arctan"])
def test_smoothed_inside_fraction_is_the_trapezoid_mean_of_the_smoothed_indicator(kind):
    """The coupled layer's inside fraction (every branch: point value, box, trapezoid) equals the mean of H_g over
    the cell's projection by brute force (a 400 x 400 midpoint rule over the cell: error (1/400)^2 (a^2 + b^2)
    max|H''| / 24 < 1e-6 for these widths), its y-derivative the central differences of its values (smooth
    everywhere, no kinks to avoid), and as g -> 0 (1e-9) the decoupled fit's sharp fraction away from the kinks
    of its piecewise-linear box mean."""
    rng = np.random.default_rng(23)
    n = 60
    y, a, g = rng.uniform(-6, 6, n), rng.uniform(0, 4, n), rng.uniform(0.5, 3, n)
    b = rng.uniform(0, 4, n) * rng.choice([0.0, 1e-5, 1.0], n)
    a[:5], b[:5] = 1e-7, 0.0  # narrower than NARROW_INSIDE: the point value
    fun = nw.smoothed_inside_function(kind).map(n)
    value, slope = (np.asarray(v).ravel() for v in fun(y, a, b, g))
    u = (np.arange(400) + 0.5) / 400 * 2 - 1  # midpoints on (-1, 1)
    brute = [np.mean(meas.smoothed_heaviside(yk + ak * u[:, None] + bk * u[None, :], gk, kind))
             for yk, ak, bk, gk in zip(y, a, b, g)]  # fmt: skip
    np.testing.assert_allclose(value, brute, rtol=0, atol=1e-6)
    eps = 1e-5
    fd = (np.asarray(fun(y + eps, a, b, g)[0]).ravel() - np.asarray(fun(y - eps, a, b, g)[0]).ravel()) / (2 * eps)
    # the differences' own error: truncation eps^2 H''' and rounding 1e-16 G_2 / (a b eps) where the trapezoid
    # formula takes a b down to 1e-3 a^2 (b = 1e-5 falls to the box formula): 1e-5
    np.testing.assert_allclose(slope, fd, rtol=0, atol=1e-5)
    sharp = np.asarray(nw.smoothed_inside_function("erf").map(n)(y, a, b, 1e-9)[0]).ravel()
    kinks = np.min(np.abs(np.stack([y + sa * a + sb * b for sa in (-1, 1) for sb in (-1, 0, 1)])), axis=0)
    ok = (kinks > 1e-3) & (a > 1e-3)
    assert ok.mean() > 0.5
    np.testing.assert_allclose(sharp[ok], nw.cell_mean("inside", y, a, b)[ok], rtol=0, atol=1e-9)


def test_branch_functions_equal_the_all_branch_cell_means_on_their_cells():
    """The coupled method builds each cell's own formula (cells grouped by spread_branch: point, box, trapezoid)
    instead of every branch under if_else: same expressions, so values and y-derivatives agree to rounding (1e-14
    relative to the largest), for the profiles' continuous means and the smoothed inside fraction."""
    rng = np.random.default_rng(29)
    n = 400
    y, a = rng.uniform(-8, 30, n), rng.uniform(0, 5, n)
    b = rng.uniform(0, 5, n) * rng.choice([0.0, 1e-5, 1.0], n)
    a[:20] = rng.uniform(0, 0.02, 20)  # narrow against a profile
    a[20:25], b[20:25] = 1e-7, 0.0  # narrow even against the inside fraction's cancellation
    cases = [(nw.cell_mean_function(f, continuous=True), nw.NARROW_PROFILE, (), f) for f in nw.FAMILIES]
    cases.append((nw.smoothed_inside_function("erf"), nw.NARROW_INSIDE, (1.7,), "inside"))
    for full, narrow, extra, name in cases:
        branch = nw.spread_branch(a, b, narrow)
        assert set(branch) == {0, 1, 2}, name  # every branch exercised
        want = [np.asarray(v).ravel() for v in full.map(n)(y, a, b, *extra)]
        for k, label in enumerate(nw.BRANCHES):
            sel = branch == k
            fun = (nw.cell_mean_function(name, True, label) if name != "inside"
                   else nw.smoothed_inside_function("erf", label))  # fmt: skip
            got = [np.asarray(v).ravel() for v in fun.map(int(sel.sum()))(y[sel], a[sel], b[sel], *extra)]
            for g, w in zip(got, want):
                np.testing.assert_allclose(g, w[sel], rtol=0, atol=1e-14 * max(1.0, np.max(np.abs(w))))
