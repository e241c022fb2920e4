"""The in-vivo-like phantoms (wss_nlp.synthetic.invivo) and the offset correction on them end to end."""

import functools

import numpy as np

from wss_nlp.models import surround
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
from wss_nlp.synthetic import invivo

OFF = surround.TissueOptions(surround="two-level", offset_correction=False)
FAST = 12  # midpoint points per voxel axis: enough for these checks, 10x faster than the tables' 40


def test_phantom_is_seeded_and_its_truth_analytic():
    a1, t1 = invivo.make_invivo("laminar", 1.5, seed=invivo.DEV_SEEDS[0], max_points=FAST)
    a2, _ = invivo.make_invivo("laminar", 1.5, seed=invivo.DEV_SEEDS[0], max_points=FAST)
    assert np.array_equal(a1.magnitude, a2.magnitude) and np.array_equal(a1.phase, a2.phase)
    assert a1.magnitude.shape == (1, 43, 43)  # ceil(64 / 1.5) voxels: a 64 x 64 mm view
    venc = a1.venc_m_s
    cx, cy = t1.center
    # the offset is 2 % of the venc at the vessel's centre by construction (g(0, 0) = 1)
    assert abs(t1.offset_at(np.array([cx]), np.array([cy]))[0] / venc - 0.02) < 1e-12
    assert np.all(t1.static_fraction + t1.flowing_fraction <= 1 + 1e-12)
    assert set(invivo.DEV_SEEDS).isdisjoint(invivo.REPORTED_SEEDS)


def test_air_twin_is_the_same_vessel_alone():
    a, t = invivo.make_invivo("laminar", 1.5, seed=invivo.DEV_SEEDS[2], max_points=FAST, snr=None)
    b, u = invivo.make_invivo("laminar", 1.5, seed=invivo.DEV_SEEDS[2], max_points=FAST, snr=None, surround=False)
    assert t.center == u.center and a.grid == b.grid and a.venc_m_s == b.venc_m_s
    assert np.array_equal(t.velocity_image, u.velocity_image)
    outside = u.flowing_fraction == 0
    assert np.all(b.magnitude[0][outside] == 0)  # air: no signal at all away from the lumen


def test_surroundings_change_the_look_only():
    # the looks draw nothing from the seed: the same vessel, offset and noise draw in each; TEXTURED is the default;
    # in a BATH every point of tissue and wall has the one level TISSUE_LEVEL and every lumen point 1 (no
    # texture, no wall contrast, no shading, no inflow), where UNIFORM keeps the wall ring's own level
    seed = invivo.DEV_SEEDS[0]
    default, t0 = invivo.make_invivo("laminar", 1.5, seed=seed, max_points=FAST)
    textured, _ = invivo.make_invivo("laminar", 1.5, seed=seed, max_points=FAST, surroundings=invivo.TEXTURED)
    assert np.array_equal(default.magnitude, textured.magnitude)
    _, tb = invivo.make_invivo("laminar", 1.5, seed=seed, max_points=FAST, surroundings=invivo.BATH)
    _, tu = invivo.make_invivo("laminar", 1.5, seed=seed, max_points=FAST, surroundings=invivo.UNIFORM)
    assert tb.center == t0.center and tb.parameters["surroundings"]["texture"] == 0.0
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-31, 31, 20000), rng.uniform(-31, 31, 20000)
    reg = tb.scene.regions(x, y)
    rho_b, rho_u = np.abs(tb.scene.signal(x, y)), np.abs(tu.scene.signal(x, y))
    assert np.allclose(rho_b[reg["tissue"] | reg["wall"]], invivo.TISSUE_LEVEL, rtol=1e-12)
    assert np.allclose(rho_b[reg["lumen"]], 1.0, rtol=1e-12)
    shading = tu.scene.coil(x, y)
    assert np.allclose((rho_u / shading)[reg["tissue"]], invivo.TISSUE_LEVEL, rtol=1e-12)
    assert np.allclose((rho_u / shading)[reg["wall"]], invivo.WALL_LEVEL, rtol=1e-12)


def test_static_tissue_phase_is_the_offset():
    # noise-free: away from every vessel the velocity read from the phase is the offset field itself
    acq, t = invivo.make_invivo("laminar", 1.0, seed=invivo.DEV_SEEDS[1], snr=None, max_points=FAST)
    u = acq.velocity_images()[0]
    xc, yc = acq.grid.centers()
    static = (t.static_fraction == 1) & (acq.magnitude[0] > 0.1)
    # the phase of a voxel mean of rho e^{i pi o / venc} is o averaged with the weights rho: it differs from o at
    # the centre by |grad o| h times the texture's first moment in the voxel (3e-4 m/s/mm x 1 mm x ~0.1), 1e-4 bounds
    # it with a margin of ~3 (0.02 % of the venc)
    assert np.max(np.abs(u[static] - t.offset_at(xc[static], yc[static]))) < 1e-4


def test_offset_removed_at_the_vessel_end_to_end():
    # a quadratic field: within the model's span, so the target must hold; the smooth non-polynomial family
    # leaves more on some seeds at h = 1.5 mm (scripts/results/invivo.md, the offset table)
    acq, t = invivo.make_invivo("laminar", 1.5, seed=invivo.DEV_SEEDS[0], max_points=FAST, offset_family="quadratic")
    res = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    rec = res.lumen.tissue["offset"]
    assert rec["applied"] and rec["sectors"] == 8
    true = t.offset_at(np.array([t.center[0]]), np.array([t.center[1]]))[0]
    # issue 39: a 2 % venc offset removed to <= 0.3 % of the venc at the vessel
    assert abs(true - rec["at_vessel_m_s"]) / acq.venc_m_s < 0.003
    assert res.lumen.tissue["surround"]["kind"] == "tissue"
    from wss_nlp.app import plotting

    fig = plotting.figure_offset(res, acq.magnitude[0])  # the static mask and the removed offset in % of venc
    img = fig.axes[1].images[0].get_array()
    xc, yc = acq.grid.centers()
    # the image is the record's polynomial: at the voxel nearest the vessel centre it is the recorded value, in %
    iy, ix = np.unravel_index(np.argmin(np.hypot(xc - res.lumen.center[0], yc - res.lumen.center[1])), xc.shape)
    assert abs(img[iy, ix] - 100 * rec["at_vessel_fraction_of_venc"]) < 0.05  # within a voxel of the centre
    assert len(plotting.figure_surround(res, acq.magnitude[0]).axes) >= 2
    # --no-offset-correction: recorded as switched off, no note
    off = reconstruct(
        acq, ReconstructionOptions(uncertainty=False, tissue=surround.TissueOptions(offset_correction=False))
    )
    assert not off[0].lumen.tissue["offset"]["applied"] and not any("offset" in n for n in off[0].notes)


def test_make_case_names():
    assert set(invivo.INVIVO_CASES) == {"invivo", "invivo-turbulent"}
    acq, t = invivo.make_case("invivo", h_mm=1.5, seed=invivo.DEV_SEEDS[0], max_points=FAST)
    assert acq.source == "phantom:invivo" and t.parameters["case"] == "invivo"


def test_demo_records_the_offset_and_analyze_reports_it(tmp_path, capsys, monkeypatch):
    # the demo's in-vivo case end to end: its result records the offset and the surround model, it writes the
    # two tissue figures, analyze reports both and the fat (--no-offset-correction: test above, by the options)
    import functools
    import os

    from wss_nlp.app import cli

    monkeypatch.setattr(invivo, "make_case", functools.partial(invivo.make_case, max_points=FAST))
    out = tmp_path / "demo"
    args = ["demo", "--case", "invivo", "--h", "1.5", "--seed", str(invivo.DEV_SEEDS[3]), "--no-uncertainty"]
    assert cli.main([*args, "-o", str(out)]) == 0
    assert {"surround.png", "offset.png"} <= set(os.listdir(out))
    rec = surround.read_tissue(str(out / "result.h5"))["slice_000"]
    assert rec["offset"]["applied"] and rec["surround"]["kind"] == "tissue"
    capsys.readouterr()
    assert cli.main(["analyze", str(out / "result.h5")]) == 0
    text = capsys.readouterr().out
    assert "background phase offset: removed" in text and "surround model: tissue" in text
    assert "not a vessel (fat?)" in text
    # the flags reach the options (the reconstruction with the correction off: test above)
    parsed = cli.build_parser().parse_args(["reconstruct", "in.h5", "-o", "r.h5", "--no-offset-correction",
                                            "--surround", "two-level"])  # fmt: skip
    tissue = cli.options_from_args(parsed).tissue
    assert tissue.offset_correction is False and tissue.surround == "two-level"


def test_phantom_command_writes_the_invivo_case_and_its_truth(tmp_path, monkeypatch, capsys):
    # `wss-nlp phantom --case invivo` writes what make_case builds (same images, same exact WSS, bit for bit), and
    # refuses the options the in-vivo scene sets itself (one line, exit 2) before writing anything
    import functools

    import h5py

    from wss_nlp.analysis import metrics
    from wss_nlp.app import cli
    from wss_nlp.io import files as wio

    monkeypatch.setattr(invivo, "make_case", functools.partial(invivo.make_case, max_points=FAST))
    seed = invivo.DEV_SEEDS[1]
    out, truth_path = tmp_path / "in.h5", tmp_path / "truth.h5"
    args = ["phantom", "--case", "invivo-turbulent", "--h", "2", "--seed", str(seed)]
    assert cli.main([*args, "-o", str(out), "--truth", str(truth_path)]) == 0
    acq, truth = invivo.make_case("invivo-turbulent", h_mm=2.0, seed=seed)
    read = wio.read_acquisition(str(out))
    assert np.array_equal(read.magnitude, acq.magnitude) and np.array_equal(read.phase, acq.phase)
    assert read.venc_m_s == acq.venc_m_s
    with h5py.File(truth_path, "r") as f:
        assert f.attrs["case"] == "invivo-turbulent"
        assert np.array_equal(f["slice_000/wss/tau_pa"][()], metrics.truth_samples(truth)["tau"])
    capsys.readouterr()
    for extra in (["--venc", "2"], ["--acquisition", "kspace"], ["--velocity"]):
        assert cli.main([*args, *extra, "-o", str(tmp_path / "no.h5")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not for the in-vivo cases" in err[0] and extra[0] in err[0]
        assert not (tmp_path / "no.h5").exists()


@functools.lru_cache(maxsize=1)
def _cine():
    """A 6-frame in-vivo-like cine series with a quadratic offset (2 % of the venc at the vessel), built once."""
    return invivo.make_invivo_cine(1.5, seed=invivo.DEV_SEEDS[0], n_frames=6, max_points=4, offset_family="quadratic")


def test_cine_frames_record_what_a_slice_records():
    # a frame's truth parameters are a slice's (one builder) plus its frame and time; a series without an offset
    # says so (offset_family "none") whatever family the seed would draw
    cine = _cine()
    _, truth = invivo.make_invivo("laminar", 1.5, seed=invivo.DEV_SEEDS[0], max_points=4, offset_family="quadratic")
    frame = cine.truths[2].parameters
    assert set(frame) == set(truth.parameters) | {"frame", "time_ms"} and frame["frame"] == 2
    for key in ("h_mm", "snr", "seed", "offset_family", "offset_pct_at_vessel", "touching_fat", "surroundings"):
        assert frame[key] == truth.parameters[key], key
    assert frame["time_ms"] == cine.times_ms[2]
    none = invivo.make_invivo_cine(1.5, seed=invivo.DEV_SEEDS[0], n_frames=2, max_points=2, offset_pct=0.0)
    assert none.truths[0].parameters["offset_family"] == "none"
    assert none.truths[0].parameters["offset_pct_at_vessel"] == 0.0


def _stacks(cine):
    raw = np.stack([f.magnitude[0] for f in cine.frames])
    return raw, np.stack([f.velocity_images()[0] for f in cine.frames])


def test_cine_offset_is_one_fit_over_the_series_and_a_pulsing_vein_is_not_static():
    from wss_nlp.models import offset as off

    cine = _cine()
    raw, u = _stacks(cine)
    grid, venc, truth = cine.frames[0].grid, cine.frames[0].venc_m_s, cine.truths[0]
    xc, yc = grid.centers()
    vein = truth.scene.regions(xc, yc)["neighbour1"]
    # the configuration is a real test: the vein's time-mean speed is zero, so in the frames' mean it looks static
    assert np.all(np.abs(np.mean([t.scene.velocity(xc, yc) for t in cine.truths], axis=0)[vein]) < 1e-12)
    assert np.all(off.static_mask(raw.mean(axis=0), 1 / 25, np.zeros_like(vein))[vein])
    fit = surround.series_offset(raw, u, grid, "x", None, venc)
    assert fit.record.applied and fit.record.frames == 6
    assert not np.any(fit.static & vein)  # it pulses: neither the flow over the series nor its std call it static
    # the known quadratic recovered under the vessel: the fitted order holds it exactly, so what is left is the
    # noise of the fit; 3 predicted deviations (the record's std at the centre, from the static voxels' noise)
    # bound its RMS over the lumen, which is within issue 39's 0.3 % of the venc
    lumen = truth.lumen_mask()
    left = np.sqrt(np.mean((truth.offset_at(xc, yc) - fit.image)[lumen] ** 2))
    assert fit.record.order == 2
    assert left < 3 * fit.record.at_vessel_std_m_s and left < 0.003 * venc


def test_cine_pipeline_attaches_the_series_offset_to_every_frames_box():
    from wss_nlp.pipeline import cine as cine_mod

    cine = _cine()
    opts = ReconstructionOptions(uncertainty=False)
    boxes = cine_mod.shared_boxes(cine.frames, opts)
    records = cine_mod.series_offsets(cine.frames, boxes, opts)
    assert set(records) == {0} and records[0]["frames"] == 6 and boxes[0].offset is not None
    # the same fit as the model's own call (the pipeline adds nothing to it), and nothing with the new code off
    raw, u = _stacks(cine)
    ref = surround.series_offset(raw, u, cine.frames[0].grid, "", boxes[0].center, cine.frames[0].venc_m_s)
    assert np.array_equal(boxes[0].offset.image, ref.image)
    off_opts = ReconstructionOptions(uncertainty=False, tissue=OFF)
    assert cine_mod.series_offsets(cine.frames, cine_mod.shared_boxes(cine.frames, off_opts), off_opts) == {}


def test_cine_reconstruction_records_the_series_offset(tmp_path):
    # end to end (about 3 s): every frame subtracts the one offset and says so, the result file holds it
    import json

    import h5py

    from wss_nlp.pipeline import cine as cine_mod

    cine = _cine()
    opts = ReconstructionOptions(uncertainty=False)
    res = cine_mod.reconstruct_cine(cine.frames, cine.times_ms, cine.period_ms, opts)
    rec = res.offsets[0]
    assert rec["applied"] and rec["frames"] == 6
    for frame in res.frames:
        assert frame[0].lumen.tissue["offset"]["coefficients"] == rec["coefficients"]
    path = str(tmp_path / "cine.h5")
    cine_mod.write_result(path, res, {})
    with h5py.File(path, "r") as f:
        assert json.loads(f["slice_000"].attrs["cine_offset_json"])["coefficients"] == rec["coefficients"]
