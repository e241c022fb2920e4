"""4D flow NIfTI volumes in (``wss_nlp.io.volume_import``): the phantom's arrays come back exactly (components on
the world axes, affine, frame times), phase data become velocities by the venc, and every refusal is one InputError
naming the file."""

import json
import os
import shutil

import numpy as np
import pytest

nibabel = pytest.importorskip("nibabel")

from wss_nlp.synthetic import scanner_exports as se  # noqa: E402
from wss_nlp.errors import InputError  # noqa: E402
from wss_nlp.io.volume import read_volume, write_volume  # noqa: E402
from wss_nlp.io.volume_import import DICOM_REFUSAL, read_nifti_volume  # noqa: E402


@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    """A small noisy straight-tube phantom (seed 5) written as a converter writes 4D flow (float32, m/s)."""
    vol = se.make_flow_volume(seed=5, snr=25.0, n=16, radius_mm=4.0, sub=2)
    folder = str(tmp_path_factory.mktemp("flow"))
    return vol, se.write_flow_volume(folder, vol, frame_interval_ms=37.5), folder


def _copy(paths, folder, rename=None):
    """Copies of ``paths`` in ``folder``, renamed by ``rename`` (old base name -> new)."""
    os.makedirs(folder, exist_ok=True)
    out = []
    for p in paths:
        name = os.path.basename(p)
        out.append(shutil.copy(p, os.path.join(folder, (rename or {}).get(name, name))))
    return out


def test_the_phantom_round_trips_to_its_arrays(phantom, tmp_path):
    """Order of the files does not matter; the values are the phantom's rounded to float32 (what was written), the
    components along the world axes (make_flow_volume's velocity[c] is the world component c), the affine and the
    frame times (k * 37.5 ms from pixdim[4]) exact; and the HDF5 volume layout round-trips it."""
    vol, paths, _ = phantom
    got = read_nifti_volume(paths[::-1], phase_units="m/s", viscosity_pa_s=3.5e-3)
    assert got.shape == (16, 16, 16) and got.nt == 2
    assert np.array_equal(got.magnitude, np.moveaxis(vol.magnitude.astype(np.float32), -1, 0))
    assert np.array_equal(got.velocity, np.moveaxis(vol.velocity.astype(np.float32), -1, 0))
    assert np.allclose(got.affine_mm, vol.affine, rtol=0, atol=1e-6)  # NIfTI stores the affine in float32
    assert np.allclose(got.trigger_times_ms, [0.0, 37.5])
    assert got.viscosity_pa_s == 3.5e-3 and got.venc_m_s is None and got.source == paths[0]
    record = json.loads(got.extra_attrs["import"])
    assert {a: os.path.basename(record["components"][a]["file"]) for a in "xyz"} == {
        "x": "flow_vx.nii.gz", "y": "flow_vy.nii.gz", "z": "flow_vz.nii.gz"
    }  # fmt: skip
    write_volume(tmp_path / "v.h5", got)
    back = read_volume(tmp_path / "v.h5")
    assert np.array_equal(back.velocity, got.velocity) and np.array_equal(back.trigger_times_ms, got.trigger_times_ms)


def test_frame_interval_option_overrides_the_header(phantom):
    _, paths, _ = phantom
    got = read_nifti_volume(paths, phase_units="m/s", frame_interval_ms=50.0)
    assert np.array_equal(got.trigger_times_ms, [0.0, 50.0])


def test_phase_in_radians_becomes_velocity_by_the_per_component_venc(tmp_path):
    """Components stored as radians ``phi = pi v / venc_c`` with a different venc per component come back as
    ``v`` (float32 rounding of phi: relative 1e-7)."""
    vol = se.make_flow_volume(seed=6, snr=None, n=12, radius_mm=3.0, sub=2, peaks_m_s=(0.8,))
    venc = (1.0, 1.5, 2.0)
    folder = tmp_path / "rad"
    folder.mkdir()
    paths = [se._save_nifti(str(folder / "mag.nii.gz"), vol.magnitude.astype(np.float32), vol.affine, None)]
    for k, c in enumerate("xyz"):
        phase = (np.pi * vol.velocity[k] / venc[k]).astype(np.float32)
        paths.append(se._save_nifti(str(folder / f"ph_v{c}.nii.gz"), phase, vol.affine, None))
    got = read_nifti_volume(paths, venc_m_s=venc, phase_units="rad")
    assert got.nt == 1 and got.trigger_times_ms is None and got.venc_m_s == venc
    assert np.allclose(got.velocity[0], vol.velocity[..., 0], rtol=0, atol=2e-6 * max(venc))
    with pytest.raises(InputError, match=r"ph_vx.nii.gz: phase values need the venc"):
        read_nifti_volume(paths, phase_units="rad")


def test_siemens_sidecars_tell_components_and_venc(tmp_path):
    """Sidecars with SequenceName ``..._v120rl/ap/fh`` name the component (rl x, ap y, fh z) and the venc, whatever
    the file names; Siemens integers [-4096, 4096) for [-pi, pi) become ``venc * value / 4096``. (Noise makes the
    integers span their range, as in scans: nifti's unit rule takes a Siemens file whose values all lie within
    [-pi, pi] for radians.)"""
    vol = se.make_flow_volume(seed=7, snr=25.0, n=12, radius_mm=3.0, sub=2, peaks_m_s=(0.9,))
    venc = 1.2
    paths = [se._save_nifti(str(tmp_path / "a.nii.gz"), vol.magnitude.astype(np.float32), vol.affine, None)]
    with open(tmp_path / "a.json", "w") as fh:
        json.dump({"Manufacturer": "Siemens", "ImageType": ["ORIGINAL", "PRIMARY", "M", "ND"]}, fh)
    for k, (name, code) in enumerate((("c", "rl"), ("b", "ap"), ("d", "fh"))):
        stored = np.round(4096.0 * vol.velocity[k] / venc).astype(np.int16)
        paths.append(se._save_nifti(str(tmp_path / f"{name}.nii.gz"), stored, vol.affine, None))
        with open(tmp_path / f"{name}.json", "w") as fh:
            meta = {"Manufacturer": "Siemens", "ImageType": ["ORIGINAL", "PRIMARY", "P", "ND"]}
            json.dump({**meta, "SequenceName": f"fl3d1_v{100 * venc:g}{code}"}, fh)
    got = read_nifti_volume(paths)
    assert got.venc_m_s == (venc, venc, venc)
    # one stored integer is venc / 4096 m/s: rounding leaves half of it
    assert np.abs(got.velocity[0] - vol.velocity[..., 0]).max() <= 0.5 * venc / 4096 + 1e-12


@pytest.mark.parametrize(
    "case, pattern",
    [
        ("two magnitudes", r"mag.nii.gz and .*mag2.nii.gz: two magnitude files"),
        ("component missing", r"needs a magnitude file and three velocity components; the z component\(s\) missing"),
        ("component doubled", r"flow_vx.nii.gz and .*flow2_vx.nii.gz: two files for the x component"),
        ("not told apart", r"vel_q.nii.gz: which velocity component is this\? Name it \*_vx"),
        ("grid differs", r"flow_vy.nii.gz: its grid .* or affine differs from .*mag.nii.gz's; resample first"),
        ("affine differs", r"flow_vy.nii.gz: its grid .* or affine differs from .*mag.nii.gz's; resample first"),
        ("venc missing", r"flow_v[xyz].nii.gz: phase values need the venc to become velocities: pass --venc"),
        ("NaN", r"flow_vz.nii.gz: 3 NaN or Inf values; replace them"),
        ("units unknown", r"flow_v[xyz].nii.gz: the units of the phase values .* pass --phase-units"),
        ("DICOM", DICOM_REFUSAL),
        ("not NIfTI", r"notes.txt: not a NIfTI file"),
        ("venc count", r"--venc \[1.0, 2.0\]: give one positive value \(m/s\) or three"),
    ],
)
def test_each_refusal_is_one_input_error_naming_the_file(phantom, tmp_path, case, pattern):
    vol, paths, _ = phantom
    mag, vx, vy, vz = paths
    kwargs = {"phase_units": "m/s"}
    files = list(paths)
    if case == "two magnitudes":
        files += _copy([mag], str(tmp_path), {"mag.nii.gz": "mag2.nii.gz"})
    elif case == "component missing":
        files = [mag, vx, vy]
    elif case == "component doubled":
        files += _copy([vx], str(tmp_path), {"flow_vx.nii.gz": "flow2_vx.nii.gz"})
    elif case == "not told apart":
        files = [mag, vx, vy] + _copy([vz], str(tmp_path), {"flow_vz.nii.gz": "vel_q.nii.gz"})
    elif case == "grid differs":
        data = np.asarray(nibabel.load(vy).get_fdata())[:-1]
        files[2] = se._save_nifti(str(tmp_path / "flow_vy.nii.gz"), data.astype(np.float32), vol.affine, 40.0)
    elif case == "affine differs":
        shifted = vol.affine.copy()
        shifted[0, 3] += 0.5
        data = np.asarray(nibabel.load(vy).get_fdata())
        files[2] = se._save_nifti(str(tmp_path / "flow_vy.nii.gz"), data.astype(np.float32), shifted, 40.0)
    elif case == "venc missing":
        kwargs = {"phase_units": "rad"}
    elif case == "NaN":
        data = np.asarray(nibabel.load(vz).get_fdata())
        data[1, 2, 3, :] = np.nan
        data[4, 4, 4, 0] = np.inf
        files[3] = se._save_nifti(str(tmp_path / "flow_vz.nii.gz"), data.astype(np.float32), vol.affine, 40.0)
    elif case == "units unknown":
        kwargs = {}
    elif case == "DICOM":
        dicom_file = tmp_path / "IM0001"
        dicom_file.write_bytes(b"\0" * 128 + b"DICM" + b"\0" * 16)
        files = [mag, vx, vy, str(dicom_file)]
    elif case == "not NIfTI":
        (tmp_path / "notes.txt").write_text("x")
        files = [mag, vx, vy, str(tmp_path / "notes.txt")]
    elif case == "venc count":
        kwargs = {"phase_units": "m/s", "venc_m_s": (1.0, 2.0)}
    with pytest.raises(InputError, match=pattern) as info:
        read_nifti_volume(files, **kwargs)
    assert "\n" not in str(info.value)


def test_a_dicom_folder_is_refused_with_the_conversion_hint(tmp_path):
    with pytest.raises(InputError, match=rf"{tmp_path}: {DICOM_REFUSAL}"):
        read_nifti_volume([str(tmp_path)])
