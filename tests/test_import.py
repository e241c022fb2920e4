"""``wss-nlp import``: DICOM (Siemens, Philips, GE, enhanced multi-frame) and NIfTI written by pydicom and nibabel
from our phantoms during the test, read back to the phantom's images and WSS (to the stored integers' quantization).

Quantization bounds: Siemens 12-bit phase: a step of 2 in ``value = 2 stored - 4096`` over 4096 per venc, so
``|v - v_true| <= venc / 4096`` after rounding; Philips/enhanced: 4095 steps over 2 venc, ``<= venc / 4095``;
GE: integer mm/s, ``<= 0.5 mm/s``. The WSS tolerance (0.5 %) is far above what such errors move (they are about
1/100 of the SNR-25 noise) and far below the errors a wrong geometry or scaling gives (a swapped axis, a wrong
venc or voxel size moves the WSS by tens of percent).
"""

import json
import os

import h5py
import numpy as np
import pytest

pytest.importorskip("pydicom")
pytest.importorskip("nibabel")

from wss_nlp.io import files, importing
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms  # noqa: E402
from wss_nlp.synthetic import scanner_exports as se  # noqa: E402
from wss_nlp.app.cli import main  # noqa: E402
from wss_nlp.errors import InputError  # noqa: E402
from wss_nlp.pipeline import reconstruct  # noqa: E402
from wss_nlp.io.scanner import ImportOptions, write_import  # noqa: E402

OBLIQUE = {"row_dir": (0.0, 0.6, 0.8), "col_dir": (1.0, 0.0, 0.0)}  # a double-oblique plane, normal (0, 0.8, -0.6)
QUANT = {"siemens": 1 / 4096, "philips": 1 / 4095, "enhanced": 1 / 4095, "nifti": 1 / 4096}


def _bound(kind: str, venc: float) -> float:
    return 5e-4 + 1e-9 if kind == "ge" else venc * QUANT[kind] * (1 + 1e-6)


@pytest.fixture(scope="module")
def phantom():
    acq, truth = phantoms.make_phantom("laminar", h_mm=1.0, snr=25, seed=31)
    return acq, truth, reconstruct(acq)[0]


def _scan(acq, **kw):
    args = {"venc_m_s": acq.venc_m_s, "voxel_size_mm": acq.voxel_size_mm, "origin_mm": acq.origin_mm, **OBLIQUE}
    args.update(kw)
    return se.Scan(acq.magnitude, acq.velocity_images(), **args)


def _write(kind, folder, scan, **kw):
    if kind == "nifti":
        return se.write_nifti(str(folder), scan, **kw)
    se.write_dicom(str(folder), scan, kind)
    return [str(folder)]


@pytest.mark.parametrize("kind", [*se.VENDORS, "nifti"])
def test_single_frame_imports_to_the_phantom_and_its_wss(kind, phantom, tmp_path):
    acq, truth, direct = phantom
    fluid = ImportOptions(viscosity_pa_s=acq.viscosity_pa_s, density_kg_m3=acq.density_kg_m3)
    imp = importing.import_paths(_write(kind, tmp_path, _scan(acq)), fluid)
    frame = imp.frame(0, "imported")
    assert imp.trigger_times_ms is None and imp.magnitude.shape == (1, *acq.magnitude.shape)
    assert np.allclose(frame.voxel_size_mm, acq.voxel_size_mm) and np.allclose(
        frame.origin_mm, acq.origin_mm, atol=1e-5
    )
    assert np.abs(frame.velocity_images() - acq.velocity_images()).max() <= _bound(kind, acq.venc_m_s)
    scale = se.MAGNITUDE_FULL_SCALE / acq.magnitude.max()
    assert np.abs(frame.magnitude / scale - acq.magnitude).max() <= 0.5 / scale * (1 + 1e-9)
    assert imp.venc_m_s == pytest.approx(acq.venc_m_s, rel=1e-9)
    res = reconstruct(frame)[0]
    assert res.wss.mean == pytest.approx(direct.wss.mean, rel=5e-3)
    assert res.geometry.center == pytest.approx(direct.geometry.center, abs=0.01 * acq.voxel_size_mm[0])
    assert metrics.compare_slice(res, truth).radius_rel_l2 <= 0.005


def test_siemens_import_equals_the_dequantized_phantom_exactly(phantom, tmp_path):
    """The importer adds nothing but the stored integers: reconstructing the Siemens import equals reconstructing
    the phantom's images rounded by hand to the same integers (to solver round-off)."""
    acq, _, _ = phantom
    scan = _scan(acq)
    se.write_dicom(str(tmp_path), scan, "siemens")
    fluid = ImportOptions(viscosity_pa_s=acq.viscosity_pa_s, density_kg_m3=acq.density_kg_m3)
    imported = importing.import_paths([str(tmp_path)], fluid).frame(0, "imported")
    stored = np.clip(np.round((4096 * acq.velocity_images() / acq.venc_m_s + 4096) / 2), 0, 4095)
    by_hand = files.Acquisition(
        magnitude=np.round(acq.magnitude * se.MAGNITUDE_FULL_SCALE / acq.magnitude.max()),
        phase=np.pi * (2 * stored - 4096) / 4096,
        voxel_size_mm=acq.voxel_size_mm,
        origin_mm=acq.origin_mm,
        venc_m_s=acq.venc_m_s,
        viscosity_pa_s=acq.viscosity_pa_s,
        density_kg_m3=acq.density_kg_m3,
    )
    assert np.array_equal(imported.phase, by_hand.phase) and np.array_equal(imported.magnitude, by_hand.magnitude)
    a, b = reconstruct(imported)[0], reconstruct(by_hand)[0]
    assert np.allclose(a.wss.tau, b.wss.tau, rtol=1e-9, atol=1e-12)


def _cine(acq, nt=4, nz=2, spacing=2.5, **kw):
    factors = np.array([0.2, 1.0, 0.6, -0.1, 0.4][:nt])
    vel = factors[:, None, None, None] * np.concatenate([acq.velocity_images()] * nz)[None]
    mag = np.broadcast_to(np.concatenate([acq.magnitude] * nz)[None], vel.shape)
    args = {
        "venc_m_s": acq.venc_m_s,
        "voxel_size_mm": acq.voxel_size_mm,
        "origin_mm": acq.origin_mm,
        "slice_spacing_mm": spacing,
        "trigger_times_ms": tuple(10.0 + 50.0 * np.arange(nt)),
        "cardiac_period_ms": 800.0,
        **OBLIQUE,
    }
    args.update(kw)
    return se.Scan(mag, vel, **args)


@pytest.mark.parametrize("kind", [*se.VENDORS, "nifti"])
def test_cine_stack_round_trip_in_the_time_resolved_layout(kind, phantom, tmp_path):
    acq = phantom[0]
    scan = _cine(acq)
    paths = _write(kind, tmp_path / "scan", scan, **({"frame_interval_ms": 50.0} if kind == "nifti" else {}))
    imp = importing.import_paths(paths, ImportOptions(viscosity_pa_s=4e-3))
    out = str(tmp_path / "in.h5")
    write_import(out, imp)
    frames, times, period = files.read_frames(out)
    assert len(frames) == 4 and frames[0].magnitude.shape == (2, *acq.magnitude.shape[1:])
    expected = np.arange(4) * 50.0 + (0.0 if kind == "nifti" else 10.0)
    assert np.allclose(times, expected)
    # NIfTI carries no R-R interval: the format's default (last trigger + mean spacing)
    assert period == pytest.approx(200.0 if kind == "nifti" else 800.0)
    for it, fr in enumerate(frames):
        assert np.abs(fr.velocity_images() - scan.velocity[it]).max() <= _bound(kind, acq.venc_m_s)
        assert fr.slice_spacing_mm == pytest.approx(2.5) and fr.viscosity_pa_s == 4e-3
    with h5py.File(out) as f:
        assert f["magnitude"].shape == (4, 2, *acq.magnitude.shape[1:])
        assert json.loads(f.attrs["import_json"])["slice_normal"] == pytest.approx([0.0, 0.8, -0.6])
    with pytest.raises(InputError, match="time-resolved"):
        files.read_acquisition(out)  # single-frame readers refuse it clearly
    # frame 1 holds the phantom's own velocity (factor 1): its first slice reconstructs to the phantom's WSS
    one = frames[1]
    one = files.Acquisition(
        magnitude=one.magnitude[:1],
        phase=None if one.phase is None else one.phase[:1],
        velocity=None if one.velocity is None else one.velocity[:1],
        voxel_size_mm=one.voxel_size_mm,
        origin_mm=one.origin_mm,
        venc_m_s=one.venc_m_s,
        viscosity_pa_s=acq.viscosity_pa_s,
        density_kg_m3=acq.density_kg_m3,
    )
    assert reconstruct(one)[0].wss.mean == pytest.approx(phantom[2].wss.mean, rel=5e-3)


def test_slices_are_ordered_along_the_normal_whatever_the_file_order(phantom, tmp_path):
    acq = phantom[0]
    scan = _cine(acq, nt=1, nz=3, spacing=-2.0, trigger_times_ms=None)  # written with decreasing position
    scan.velocity = scan.velocity * np.array([1.0, 2.0, 3.0])[None, :, None, None] / 3.0
    se.write_dicom(str(tmp_path), scan, "siemens")
    frame = importing.import_paths([str(tmp_path)]).frame(0, "x")
    assert frame.slice_spacing_mm == pytest.approx(2.0)
    assert np.allclose(frame.velocity_images(), scan.velocity[0][::-1], atol=_bound("siemens", acq.venc_m_s))
    assert np.allclose(frame.origin_mm, acq.origin_mm)  # the slices share the in-plane origin


def test_flip_through_plane_negates_the_velocity(phantom, tmp_path):
    acq = phantom[0]
    se.write_dicom(str(tmp_path), _scan(acq), "philips")
    a = importing.import_paths([str(tmp_path)]).frame(0, "a").velocity_images()
    b = importing.import_paths([str(tmp_path)], ImportOptions(flip_through_plane=True)).frame(0, "b").velocity_images()
    assert np.array_equal(a, -b)


def test_cli_import_then_reconstruct(phantom, tmp_path, capsys):
    acq, truth, direct = phantom
    se.write_dicom(str(tmp_path / "dicom"), _scan(acq), "siemens")
    inp, out = tmp_path / "in.h5", tmp_path / "out.h5"
    assert main(["import", str(tmp_path / "dicom"), "-o", str(inp), "--viscosity", str(acq.viscosity_pa_s)]) == 0
    text = capsys.readouterr().out
    assert "Siemens" in text and "fl2d1_v" in text and "39 x 39" in text
    assert main(["reconstruct", str(inp), "-o", str(out)]) == 0
    mean = files.read_result(str(out))[0]["mean_tau"]
    assert mean == pytest.approx(direct.wss.mean, rel=5e-3)


# ------------------------------------------------------------------ bad input: one line, exit 2, nothing written
def _fails(capsys, argv, *words):
    out = argv[argv.index("-o") + 1]
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    err = lines[-1]  # warnings may come before; the error is one line, the last
    assert err.startswith("wss-nlp: error:") and not any(x.startswith("wss-nlp: error") for x in lines[:-1])
    for w in words:
        assert w in err, err
    assert not os.path.exists(out)
    return err


def _siemens(tmp_path, acq, name="dicom", **kw):
    folder = tmp_path / name
    se.write_dicom(str(folder), _cine(acq, **kw) if kw else _scan(acq), "siemens")
    return folder


def test_missing_venc_names_the_tag_and_the_option(phantom, tmp_path, capsys):
    import pydicom

    folder = _siemens(tmp_path, phantom[0])
    for f in folder.glob("pha_*.dcm"):
        ds = pydicom.dcmread(f)
        del ds.SequenceName
        ds.save_as(f)
    out = str(tmp_path / "in.h5")
    _fails(capsys, ["import", str(folder), "-o", out], "pha_000_000.dcm", "no velocity encoding", "--venc")
    assert main(["import", str(folder), "-o", out, "--venc", str(phantom[0].venc_m_s)]) == 0


def test_only_magnitude_images(phantom, tmp_path, capsys):
    folder = _siemens(tmp_path, phantom[0])
    for f in folder.glob("pha_*.dcm"):
        f.unlink()
    _fails(capsys, ["import", str(folder), "-o", str(tmp_path / "in.h5")], "no phase image")


def test_two_phase_series_are_ambiguous(phantom, tmp_path, capsys):
    acq = phantom[0]
    folder = _siemens(tmp_path, acq)
    se.write_dicom(str(tmp_path / "again"), _scan(acq), "siemens")
    (tmp_path / "again" / "pha_000_000.dcm").rename(folder / "second_phase.dcm")
    _fails(capsys, ["import", str(folder), "-o", str(tmp_path / "in.h5")], "two phase images", "one phase series")


def test_a_missing_frame_is_named(phantom, tmp_path, capsys):
    folder = _siemens(tmp_path, phantom[0], nt=3, nz=2)
    (folder / "pha_001_002.dcm").unlink()
    _fails(capsys, ["import", str(folder), "-o", str(tmp_path / "in.h5")], "slice 1", "frames are missing")


def test_mixed_matrix_sizes(phantom, tmp_path, capsys):
    acq = phantom[0]
    folder = _siemens(tmp_path, acq)
    small = files.Acquisition(magnitude=acq.magnitude[:, :-2], velocity=acq.velocity_images()[:, :-2])
    se.write_dicom(str(tmp_path / "small"), _scan(small, venc_m_s=acq.venc_m_s), "siemens")
    (tmp_path / "small" / "mag_000_000.dcm").rename(folder / "small_mag.dcm")
    _fails(capsys, ["import", str(folder), "-o", str(tmp_path / "in.h5")], "image size")


def test_unequal_slice_spacing(phantom, tmp_path, capsys):
    acq = phantom[0]
    folder = _siemens(tmp_path, acq, nt=1, nz=2, trigger_times_ms=None)
    se.write_dicom(str(tmp_path / "far"), _cine(acq, nt=1, nz=4, spacing=2.5, trigger_times_ms=None), "siemens")
    for role in ("mag", "pha"):
        (tmp_path / "far" / f"{role}_003_000.dcm").rename(folder / f"{role}_far.dcm")
    _fails(capsys, ["import", str(folder), "-o", str(tmp_path / "in.h5")], "not equally spaced")


def test_too_small_venc_is_refused(phantom, tmp_path, capsys):
    acq = phantom[0]
    folder = _siemens(tmp_path, acq)
    # Siemens phase is in radians whatever the venc; a Philips velocity image is not
    se.write_dicom(str(tmp_path / "philips"), _scan(acq), "philips")
    philips = ["import", str(tmp_path / "philips"), "-o", str(tmp_path / "in.h5"), "--venc", str(acq.venc_m_s / 3)]
    # a --venc that disagrees with the header's scales every velocity by the ratio (issue 42: -80 % went unflagged)
    _fails(capsys, philips, "disagrees with the venc", "--allow-unphysical venc")
    _fails(capsys, [*philips, "--allow-unphysical", "venc"], "beyond the venc")
    siemens = ["import", str(folder), "-o", str(tmp_path / "in.h5"), "--venc", str(acq.venc_m_s / 3)]
    _fails(capsys, siemens, "disagrees with the venc")
    assert main([*siemens, "--allow-unphysical", "venc"]) == 0  # a header known to be wrong: overridden, and said
    assert "overrides the venc" in capsys.readouterr().err


def test_in_plane_encoding_and_ge_phase_difference_are_refused(phantom, tmp_path, capsys):
    import pydicom

    acq = phantom[0]
    folder = _siemens(tmp_path, acq)
    for f in folder.glob("pha_*.dcm"):
        ds = pydicom.dcmread(f)
        ds.SequenceName = "fl2d1_v150rl"
        ds.save_as(f)
    _fails(capsys, ["import", str(folder), "-o", str(tmp_path / "a.h5")], "in-plane direction 'rl'")
    se.write_dicom(str(tmp_path / "ge"), _scan(acq), "ge")
    for f in (tmp_path / "ge").glob("pha_*.dcm"):
        ds = pydicom.dcmread(f)
        ds.private_block(0x0043, "GEMS_PARM_01").add_new(0x32, "SS", 2)
        ds.save_as(f)
    _fails(capsys, ["import", str(tmp_path / "ge"), "-o", str(tmp_path / "b.h5")], "phase-difference", "(0043,1032)")


def test_unknown_vendor_needs_phase_units(phantom, tmp_path, capsys):
    import pydicom

    acq = phantom[0]
    se.write_dicom(str(tmp_path / "d"), _scan(acq), "philips")
    for f in (tmp_path / "d").glob("*.dcm"):
        ds = pydicom.dcmread(f)
        ds.Manufacturer = "ACME"
        ds.save_as(f)
    out = str(tmp_path / "in.h5")
    venc = str(acq.venc_m_s)
    _fails(capsys, ["import", str(tmp_path / "d"), "-o", out, "--venc", venc], "'Acme'", "--phase-units")
    assert main(["import", str(tmp_path / "d"), "-o", out, "--venc", venc, "--phase-units", "cm/s"]) == 0
    v = files.read_acquisition(out).velocity_images()
    assert np.abs(v - acq.velocity_images()).max() <= _bound("philips", acq.venc_m_s)


def test_nifti_without_role_or_units(phantom, tmp_path, capsys):
    acq = phantom[0]
    mag, pha = se.write_nifti(str(tmp_path), _scan(acq))
    os.rename(pha, tmp_path / "second.nii.gz")
    os.remove(tmp_path / "phase_ph.json")
    out = str(tmp_path / "in.h5")
    _fails(
        capsys, ["import", mag, str(tmp_path / "second.nii.gz"), "-o", out], "second.nii.gz", "magnitude or the phase"
    )
    os.rename(tmp_path / "second.nii.gz", tmp_path / "velocity.nii.gz")
    _fails(capsys, ["import", mag, str(tmp_path / "velocity.nii.gz"), "-o", out], "--phase-units")
    argv = ["import", mag, str(tmp_path / "velocity.nii.gz"), "-o", out, "--venc", str(acq.venc_m_s)]
    assert main([*argv, "--phase-units", "siemens"]) == 0


def test_inputs_that_are_not_scanner_exports(phantom, tmp_path, capsys):
    text = tmp_path / "notes.txt"
    text.write_text("not an image")
    out = str(tmp_path / "in.h5")
    _fails(capsys, ["import", str(text), "-o", out], "notes.txt", "not a DICOM file")
    _fails(capsys, ["import", str(tmp_path / "missing"), "-o", out], "no such file")
    mag, _ = se.write_nifti(str(tmp_path / "n"), _scan(phantom[0]))
    _fails(capsys, ["import", mag, str(text), "-o", out], "mixes NIfTI and DICOM")
    _fails(capsys, ["import", str(tmp_path / "n"), "-o", str(tmp_path / "in.txt")], ".h5")


def test_trigger_times_that_disagree_between_series(phantom, tmp_path, capsys):
    import pydicom

    folder = _siemens(tmp_path, phantom[0], nt=3, nz=1)
    for f in folder.glob("pha_*.dcm"):
        ds = pydicom.dcmread(f)
        ds.TriggerTime = float(ds.TriggerTime) + 30.0  # frames are 50 ms apart
        ds.save_as(f)
    _fails(capsys, ["import", str(folder), "-o", str(tmp_path / "in.h5")], "trigger times differ", "one cine")


# ------------------------------------------------------------------ header fuzz: no internal error, whatever is off
MUTATIONS = {
    "no_position": lambda ds: delattr(ds, "ImagePositionPatient"),
    "no_orientation": lambda ds: delattr(ds, "ImageOrientationPatient"),
    "no_spacing": lambda ds: delattr(ds, "PixelSpacing"),
    "zero_spacing": lambda ds: setattr(ds, "PixelSpacing", [0.0, 1.0]),
    "skew_orientation": lambda ds: setattr(ds, "ImageOrientationPatient", [1.0, 0, 0, 0.7, 0.7, 0]),
    "text_trigger": lambda ds: setattr(ds, "TriggerTime", "12.5"),
    "no_image_type": lambda ds: delattr(ds, "ImageType"),
    "no_pixels": lambda ds: delattr(ds, "PixelData"),
    "short_pixels": lambda ds: setattr(ds, "PixelData", ds.PixelData[:100]),
    "odd_intercept": lambda ds: setattr(ds, "RescaleIntercept", "-1000"),
    "no_manufacturer": lambda ds: delattr(ds, "Manufacturer"),
    "bad_sequence_name": lambda ds: setattr(ds, "SequenceName", "fl2d1_vXXin"),
}


@pytest.mark.parametrize("name", sorted(MUTATIONS))
def test_mutated_headers_give_one_line_or_a_file(name, phantom, tmp_path, capsys):
    """Every phase file of a Siemens export mutated one way: exit 0 with a readable input, or exit 2 with one
    line naming a file; never an internal error (exit 3) or a half-written output."""
    import pydicom

    folder = _siemens(tmp_path, phantom[0])
    for f in folder.glob("pha_*.dcm"):
        ds = pydicom.dcmread(f)
        MUTATIONS[name](ds)
        ds.save_as(f)
    out = tmp_path / "in.h5"
    rc = main(["import", str(folder), "-o", str(out), "--viscosity", "3.5e-3"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc in (0, 2), err
    if rc == 2:
        assert err[-1].startswith("wss-nlp: error:") and str(tmp_path) in err[-1]
        assert not out.exists()
    else:
        files.read_acquisition(str(out))
