"""The surround model (wss_nlp.models.surround): two-level data give today's results exactly, the lumen fraction
is recovered in tissue, fat is not a vessel, the noise comes from the lumen plateau."""

import functools

import numpy as np
import pytest

from wss_nlp.core import radius as rad
from wss_nlp.models import geometry as geo
from wss_nlp.models import surround
from wss_nlp.models.measurement import VoxelGrid
from wss_nlp.pipeline import plausibility as plaus
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
from wss_nlp.synthetic import invivo, phantoms

OFF = surround.TissueOptions(surround="two-level", offset_correction=False)


def _same(a, b):
    # the same computation; the pipeline's solver and basis caches make the first run of a process differ from
    # later ones in the last bits (1e-17 mm, seen with the new code off in both runs), hence 1e-12, not ==
    for x, y in ((a.geometry.coefficients, b.geometry.coefficients), (a.velocity.coefficients, b.velocity.coefficients),
                 (a.wss.tau, b.wss.tau)):  # fmt: skip
        assert np.allclose(x, y, rtol=1e-12, atol=1e-12)
    assert a.notes == b.notes and a.beta_choice.chosen == b.beta_choice.chosen


@pytest.mark.parametrize("make", [lambda: phantoms.make_phantom("laminar", 1.5, seed=7),
                                  lambda: phantoms.make_two_vessels(1.5, seed=7)])  # fmt: skip
def test_two_level_data_reproduce_appendix_b_exactly(make):
    # tubes in air: the outside ring is noise, no static tissue: the new code must change nothing, bit for bit
    acq, _ = make()
    geo.clear_solvers()
    new = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    geo.clear_solvers()
    old = reconstruct(acq, ReconstructionOptions(uncertainty=False, tissue=OFF))[0]
    _same(new, old)
    rec = new.lumen.tissue
    assert rec["surround"]["kind"] == "two-level" and "noise" in rec["surround"]["reason"]
    assert not rec["offset"]["applied"] and rec["offset"]["static_voxels"] == 0


def test_off_is_appendix_b():
    acq, _ = phantoms.make_phantom("laminar", 1.5, seed=8)
    from wss_nlp.models import preprocess as pp

    norm, m, lumen = pp.preprocess(acq.magnitude[0], acq.grid, "x")
    n2, m2, l2, u2, raw2 = surround.preprocess(acq.magnitude[0], acq.velocity_images()[0], acq.grid, "x", options=OFF)
    assert n2 == norm and np.array_equal(m, m2) and np.array_equal(lumen.mask, l2.mask) and l2.tissue is None
    assert np.array_equal(u2, acq.velocity_images()[0]) and np.array_equal(raw2, acq.magnitude[0])


@functools.lru_cache(maxsize=1)
def _noise_free_tissue():
    """The laminar vessel in tissue without noise (built once for the tests that share it)."""
    return invivo.make_invivo("laminar", 1.0, snr=None, seed=invivo.DEV_SEEDS[1], max_points=12)


def test_noise_free_lumen_fraction_and_wall_in_tissue():
    # the laminar vessel in tissue without noise (wall 1.2 mm, texture, shading, inflow, offset): the normalized
    # magnitude must follow the true lumen fraction where Appendix B's is biased by the wall and the tissue
    acq, truth = _noise_free_tissue()
    raw, u = acq.magnitude[0], acq.velocity_images()[0]
    _, m, lumen, _, _ = surround.preprocess(raw, u, acq.grid, "x", None, acq.venc_m_s)
    _, m_old, _, _, _ = surround.preprocess(raw, u, acq.grid, "x", None, acq.venc_m_s, options=OFF)
    f = truth.flowing_fraction
    xc, yc = acq.grid.centers()
    pv = (f > 0.02) & (f < 0.98) & (np.hypot(xc - truth.center[0], yc - truth.center[1]) < 16)  # not the vein
    err_new, err_old = (m - f)[pv], (np.clip(m_old, 0, 1) - f)[pv]
    assert lumen.tissue["surround"]["kind"] == "tissue"
    # measured (dev seed 102): mean -0.005, rms 0.03 (texture beyond the wall, which no smooth model holds);
    # Appendix B's: mean -0.1. Bounds: a mean bias of 0.02 moves the wall by 0.02 h = 0.02 mm
    assert abs(err_new.mean()) < 0.02 and np.sqrt(np.mean(err_new**2)) < 0.06
    assert abs(err_old.mean()) > 3 * abs(err_new.mean())


def test_noise_free_radius_in_tissue():
    acq, truth = _noise_free_tissue()
    res = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    phi = rad.uniform_angles(180)
    dr = res.geometry.radius(phi) - truth.radius_about(res.geometry.center, phi)
    old = reconstruct(acq, ReconstructionOptions(uncertainty=False, tissue=OFF))[0]
    dr_old = old.geometry.radius(phi) - truth.radius_about(old.geometry.center, phi)
    # measured: mean +0.006 mm (Appendix B's: -0.11 mm); 0.03 mm = 3 % of a voxel
    assert abs(dr.mean()) < 0.03 and abs(dr_old.mean()) > 3 * abs(dr.mean())


def _fat_and_vessel(n=60, h=1.0, seed=0):
    """A bright static blob (fat, larger than the vessel) beside a flowing vessel, in tissue."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n] * h - (n - 1) * h / 2
    mag = np.full((n, n), 0.3)
    fat = np.hypot(x + 12, y - 10) < 10
    vessel = np.hypot(x - 12, y + 8) < 7
    mag[fat], mag[vessel] = 0.85, 1.0
    venc = 0.5
    u = np.where(vessel, 0.35 * (1 - ((x - 12) ** 2 + (y + 8) ** 2) / 49), 0.0)
    d = mag * np.exp(1j * np.pi * u / venc) + 0.03 * (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n)))
    grid = VoxelGrid((n, n), (h, h), (-(n - 1) * h / 2, -(n - 1) * h / 2))
    return np.abs(d), venc * np.angle(d) / np.pi, grid, venc


def test_fat_is_not_a_vessel():
    raw, u, grid, venc = _fat_and_vessel()
    from wss_nlp.models import preprocess as pp

    old = pp.preprocess(raw, grid, "x")[2]
    assert old.center[0] < 0  # Appendix B takes the larger bright region: the fat
    _, _, lumen = surround.screen_preprocess(raw, u, grid, "x", None, venc)
    assert abs(lumen.center[0] - 12) < 1 and abs(lumen.center[1] + 8) < 1
    assert lumen.others == []  # fat is not "another vessel in view"
    (fat,) = lumen.tissue["static_bright"]
    assert abs(fat["center_mm"][0] + 12) < 1.5


def test_screen_reports_only_flowing_vessels():
    acq, _ = invivo.make_invivo("laminar", 1.5, seed=invivo.DEV_SEEDS[0], max_points=12)
    _, found = plaus.screen(acq)
    rec = found[0].record
    centres = sorted(tuple(round(c) for c in o["center_mm"]) for o in rec["other_vessels"])
    assert len(centres) == 2  # the artery and the vein; the fat layer and deposits are static bright regions
    assert len(rec["static_bright_regions"]) >= 1


def test_lumen_noise_sigma_from_the_plateau():
    rng = np.random.default_rng(1)
    n, sigma = 50, 0.04
    y, x = np.mgrid[0:n, 0:n] - (n - 1) / 2
    mask = np.hypot(x, y) < 18
    # smooth inflow-like level and shading: a constant Laplacian and a slow trend do not count as noise
    level = (1 + 0.2 * (1 - (x**2 + y**2) / 18**2)) * np.exp(0.005 * x)
    raw = np.abs(level + sigma * (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))))
    # ~700 plateau voxels: the trimmed deviation's relative error is ~3 %; 10 % is the test's margin
    assert abs(surround.lumen_noise_sigma(raw, mask) / sigma - 1) < 0.1


def _highpass_ratio(seeds) -> tuple[float, float]:
    """``(measured, predicted)`` variance of ``a - (mean of 4 neighbours)`` per unit noise variance, k-space noise."""
    from wss_nlp.models import acquisition as am
    from wss_nlp.models import kspace

    psf = kspace.PSF("hamming", (2.0, 2.0))
    ratios = []
    for seed in seeds:  # the same seed draws the same sub-voxel shift: the difference is the noise alone
        noisy = phantoms.make_phantom("laminar", 1.0, 25, seed, psf=psf)[0]
        clean = phantoms.make_phantom("laminar", 1.0, None, seed, psf=psf)[0]
        n = noisy.magnitude[0] * np.exp(1j * noisy.phase[0]) - clean.magnitude[0] * np.exp(1j * clean.phase[0])
        hp = n - 0.25 * (np.roll(n, 1, 0) + np.roll(n, -1, 0) + np.roll(n, 1, 1) + np.roll(n, -1, 1))
        inner = (slice(2, -2), slice(2, -2))
        ratios.append(np.var(hp.real[inner]) / np.var(n.real[inner]))
    return float(np.mean(ratios)), am.KSpace(psf).highpass_noise_variance(n.shape)


def test_highpass_noise_variance_of_kspace_noise_matches_the_phantoms_noise():
    # the noise estimate from the lumen plateau divides by the variance of a - (mean of 4 neighbours) per unit
    # noise variance: 1.25 for independent voxels; a Hamming-filtered, twice zero-filled acquisition correlates
    # neighbours and leaves about 0.024. Checked against the noise the k-space phantom adds (white k-space noise
    # filtered and zero-filled by FFT, an independent computation) on one image of ~1300 voxels, about 1/13 of
    # them effectively independent: the ratio's sampling error is ~15 %, hence 25 % (the slow test: 3 seeds, 15 %)
    from wss_nlp.models import acquisition as am

    measured, predicted = _highpass_ratio((3,))
    assert abs(measured / predicted - 1) < 0.25
    assert am.VoxelMeans().highpass_noise_variance((39, 39)) == 1.25


@pytest.mark.slow
def test_highpass_noise_variance_of_kspace_noise_over_seeds():
    measured, predicted = _highpass_ratio((3, 4, 5))  # ~9 % sampling error over three images: 15 %
    assert abs(measured / predicted - 1) < 0.15


def test_an_ambiguous_surround_is_noted_with_its_reason():
    # each of the two ambiguity tests of SurroundModel reaches the slice's notes with its reason, and a model
    # clear of every threshold gives no note: a ring mean at the noise floor's threshold, a tissue ring with more
    # outliers than AMBIGUOUS_OUTLIERS
    sigma = 2.0
    clear = dict(kind="tissue", reason="", sigma=sigma, ring_mean=5 * surround.NOISE_FLOOR * sigma,
                 ring_spread=sigma, ring_outliers=0.0)  # fmt: skip
    assert surround.notes({"surround": clear}) == []
    cases = {
        "at the noise floor's threshold": dict(ring_mean=1.05 * surround.NOISE_FLOOR * sigma),
        "does not follow a smooth level": dict(ring_outliers=surround.AMBIGUOUS_OUTLIERS + 0.05),
    }
    for reason, change in cases.items():
        (note,) = surround.notes({"surround": {**clear, **change}})
        assert "ambiguous (tissue chosen)" in note and reason in note, note
    # the outliers test is about fitted tissue: a two-level model has no outside polynomial to be off
    assert surround.notes({"surround": {**clear, "kind": "two-level", "ring_outliers": 0.5}}) == []


def _lumen_detection(acq, venc=True):
    """The preliminary (Appendix B) and the flow-aware lumen of a slice: ``(Appendix B's or its error, flow-aware)``."""
    from wss_nlp.errors import WssNlpError
    from wss_nlp.models import preprocess as pp

    raw, u = acq.magnitude[0], acq.velocity_images()[0]
    m = pp.normalize_magnitude(raw, surround._peaks(raw, u, acq.venc_m_s, "x"))
    try:
        plain = pp.find_lumen(m, acq.grid, "x")
    except WssNlpError as exc:
        plain = exc
    flow = surround.flow_aware_lumen(m, raw, u, acq.grid, "x", None, acq.venc_m_s if venc else None, float("nan"))
    return plain, flow[0]


def test_fat_touching_the_vessel_is_split_off_by_the_flow():
    # four fat deposits pressed against the wall (h = 1.5 mm: partial volume joins them to the lumen, and one to
    # the subcutaneous fat layer, which reaches the border). The magnitude alone takes fat for lumen (the
    # configuration is a real test: Appendix B's lumen fails or is too large); the flow-aware lumen is the untouched
    # twin's (same seed and noise) but for partial-volume rim voxels where a deposit touches, at most 2 per deposit
    # (of ~180), its centre within 0.05 voxel of the twin's (the fat deposits would pull it by several mm)
    seed = invivo.DEV_SEEDS[1]
    touched, touched_truth = invivo.make_invivo("laminar", 1.5, seed=seed, max_points=6, touching_fat=4)
    twin, truth = invivo.make_invivo("laminar", 1.5, seed=seed, max_points=6)
    # the deposits draw nothing from the seed: the slice is the twin's bit for bit away from them
    xc, yc = twin.grid.centers()
    blobs = touched_truth.scene.fat_blobs[-4:]
    away = np.all([np.hypot(xc - bx, yc - by) > br + 2.0 for bx, by, br in blobs], axis=0)
    assert np.array_equal(touched.magnitude[0][away], twin.magnitude[0][away])
    assert touched_truth.scene.regions(np.array([blobs[0][0]]), np.array([blobs[0][1]]))["fat"][0]
    plain, lumen = _lumen_detection(touched)
    _, ref = _lumen_detection(twin)
    assert isinstance(plain, Exception) or plain.mask.sum() > 1.1 * truth.lumen_mask().sum()
    assert np.sum(lumen.mask ^ ref.mask) <= 2 * 4
    assert np.hypot(lumen.center[0] - ref.center[0], lumen.center[1] - ref.center[1]) < 0.05 * 1.5
    # the slice says so: the partial-volume voxels against the fat are read with the smooth outside level
    assert any("touches the vessel (3 voxels" in n for n in surround.notes({"static_bright_touching_voxels": 3}))
    assert not surround.notes({"static_bright_touching_voxels": 0})
    # without a venc the fastest region's speed sets the flow threshold: the same split
    _, no_venc = _lumen_detection(touched, venc=False)
    assert np.sum(no_venc.mask ^ ref.mask) <= 2 * 4


def test_beyond_flow_keeps_a_slow_lumen_whole():
    # a core barely faster than the flow threshold reaches its whole radius: a slowly flowing lumen (a frame of
    # diastole) is never cut into "lumen" and "static tissue". A disk of radius 8 voxels, Poiseuille with a peak
    # of 1.5 x the threshold; and the same disk at a peak of 10 x the threshold (a lumen in its own region, no
    # static part: the band reaches its rim)
    n = 40
    yy, xx = np.mgrid[:n, :n] - n / 2 + 0.5
    r = np.hypot(xx, yy) / 8.0
    m = (r < 1).astype(float)
    for peak in (1.5, 10.0):
        u = np.where(r < 1, peak * surround.FLOW_FRACTION_OF_VENC * (1 - r**2), 0.0)
        assert not surround.beyond_flow(m, u, 1.0).any()


@pytest.mark.parametrize("h, seed", [(1.0, invivo.DEV_SEEDS[0]), (1.5, 401), (1.5, 402)])
def test_fat_touching_the_vessel_leaves_radius_and_wss_near_the_untouched_twins(h, seed):
    # the end-to-end claim (about 2 s each): with four fat deposits pressed against the wall the default
    # reconstruction is as accurate as on the untouched twin (same seed, noise and scene otherwise), within issue
    # 39's allowance for tissue against air (WSS 1.3 x + 1 point, radius 1.5 x + 0.1 point). At h = 1.5 mm the
    # voxels next to the fat used to hide the wall ring from its fit (WALL_FAT_MARGIN): the lumen took the wall's
    # place and the WSS was 25-55 % off; the wall ring must be found. Seeds 401-402 were never used to tune.
    from wss_nlp.analysis import metrics

    errors, walls = {}, {}
    for n in (0, 4):
        acq, truth = invivo.make_invivo("laminar", h, seed=seed, max_points=8, touching_fat=n)
        res = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
        e = metrics.compare_slice(res, truth)
        errors[n] = (100 * e.radius_rel_l2, 100 * e.wss_rel_l2)
        walls[n] = res.lumen.tissue["surround"]["wall_mm"]
    assert walls[4] > 0 and walls[0] > 0  # the phantom's wall ring is 1.2 mm
    assert errors[4][0] <= 1.5 * errors[0][0] + 0.1
    assert errors[4][1] <= 1.3 * errors[0][1] + 1.0


@pytest.mark.parametrize("look", ["UNIFORM", "BATH"])
def test_a_uniform_outside_takes_the_fitted_model_not_appendix_b(look):
    # tissue without texture: its outside ring is one level within the noise, which used to mean Appendix B's
    # two-level model. That is wrong twice: the histogram's background peak need not be the ring's level (air and
    # fat are in the view) and a wall ring or a shaded, inflow-enhanced lumen may lie within (UNIFORM); and even in
    # a bath of exactly two levels (BATH) the partial-volume voxels' phase mixes the lumen's with the bath's, which
    # only the fitted model takes back. h = 1.5 mm, SNR 25, seeds 301-302 (never used to tune): the default stays
    # within issue 39's allowance against the same vessel in air (WSS 1.3 x + 1 point, radius 1.5 x + 0.1 point),
    # and Appendix B's model on the same data misses by more (measured: UNIFORM 10-11 % against 4.8-5.1 %, BATH
    # 7.7-8.4 % against 4.7-5.4 %; 1.3 x leaves room for a seed)
    from wss_nlp.analysis import metrics

    def errors(acq, truth, tissue=None):
        opts = ReconstructionOptions(uncertainty=False, **({} if tissue is None else {"tissue": tissue}))
        res = reconstruct(acq, opts)[0]
        e = metrics.compare_slice(res, truth)
        return 100 * e.radius_rel_l2, 100 * e.wss_rel_l2, res.lumen.tissue["surround"]

    for seed in (301, 302):
        air = errors(*invivo.make_invivo("laminar", 1.5, seed=seed, surround=False))
        acq, truth = invivo.make_invivo("laminar", 1.5, seed=seed, surroundings=getattr(invivo, look))
        radius, wss, model = errors(acq, truth)
        two = errors(acq, truth, surround.TissueOptions(surround="two-level"))
        assert model["kind"] == "tissue", model["reason"]
        if look == "BATH":  # one level outside and in the wall, a uniform lumen, no shading: nothing more is found
            assert model["outside_order"] == model["lumen_order"] == 0 and model["inflow"] == 0.0
            assert model["wall_mm"] == 0.0
        else:  # the wall ring (1.2 mm, level 0.22 against the tissue's 0.32) is found, within a step of its grid
            assert 0.8 <= model["wall_mm"] <= 1.8
        assert radius <= 1.5 * air[0] + 0.1 and wss <= 1.3 * air[1] + 1.0, (radius, wss, air)
        assert two[1] > 1.3 * wss, (two[1], wss)


def test_flowing_regions_are_kept_for_the_same_images_and_each_caller_gets_a_copy():
    """The kept answer equals a fresh computation (labels, flowing, static, speeds), a change of any input (the
    velocity by one voxel, the venc) is a new question, and a caller's changes to its copy reach nobody else."""
    acq, _ = invivo.make_invivo("laminar", 1.5, seed=invivo.DEV_SEEDS[1], max_points=6, touching_fat=4)
    raw, u = acq.magnitude[0], acq.velocity_images()[0]
    m = np.clip(raw / np.percentile(raw, 99), 0, 2)
    fresh = surround._flowing_regions(m, raw, u, acq.venc_m_s, 1.0)
    first = surround.flowing_regions(m, raw, u, acq.venc_m_s, 1.0)
    first.labels[:] = -1
    first.flowing.append(99)
    again = surround.flowing_regions(m, raw, u, acq.venc_m_s, 1.0)
    assert np.array_equal(again.labels, fresh.labels) and again.flowing == fresh.flowing
    assert again.static == fresh.static and again.speeds == fresh.speeds
    v = u.copy()
    v.flat[np.argmax(np.abs(v))] = 0.0
    assert surround._digest(m, raw, v, extra=(acq.venc_m_s, 1.0)) != surround._digest(
        m, raw, u, extra=(acq.venc_m_s, 1.0)
    )
    assert surround._digest(m, raw, u, extra=(None, 1.0)) != surround._digest(m, raw, u, extra=(acq.venc_m_s, 1.0))
