"""Every bad input gives a clear error naming the file and the problem, exit code 2, no output."""

import os

import h5py
import numpy as np
import pytest

from wss_nlp.io import files as wio
from wss_nlp.synthetic import phantoms
from wss_nlp.app.cli import main
from wss_nlp.errors import InputError


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    acq, _ = phantoms.make_phantom("circle", h_mm=1.0, snr=25, seed=2)
    path = tmp_path_factory.mktemp("io") / "good.h5"
    wio.write_acquisition(path, acq)
    return path, acq


def _copy_with(src, dst, drop=(), attrs=None, drop_attrs=(), replace=None):
    with h5py.File(src, "r") as f, h5py.File(dst, "w") as g:
        for k in f:
            if k not in drop:
                g[k] = (replace or {}).get(k, f[k][()])
        for k, v in f.attrs.items():
            if k not in drop_attrs:
                g.attrs[k] = v
        for k, v in (attrs or {}).items():
            g.attrs[k] = v
    return dst


def test_roundtrip(good):
    path, acq = good
    back = wio.read_acquisition(path)
    assert np.array_equal(back.magnitude, acq.magnitude)
    assert np.array_equal(back.phase, acq.phase)
    assert back.venc_m_s == acq.venc_m_s and back.voxel_size_mm == acq.voxel_size_mm


def _nan_phase(f):
    p = f["phase"][()].copy()
    p[0, 3, 4] = np.nan
    return {"phase": p}


CASES = {
    "missing magnitude": (dict(drop=("magnitude",)), "missing dataset 'magnitude'"),
    "missing velocity and phase": (dict(drop=("phase",)), "missing dataset 'velocity'"),
    "missing voxel size": (dict(drop_attrs=("voxel_size_mm",)), "missing attribute 'voxel_size_mm'"),
    "missing origin": (dict(drop_attrs=("origin_mm",)), "missing attribute 'origin_mm'"),
    "missing venc": (dict(drop_attrs=("venc_m_s",)), "'venc_m_s'"),
    "negative voxel size": (dict(attrs={"voxel_size_mm": [1.0, -1.0]}), "two positive numbers"),
    "zero voxel size": (dict(attrs={"voxel_size_mm": [0.0, 1.0]}), "two positive numbers"),
    "voxel size wrong length": (dict(attrs={"voxel_size_mm": [1.0]}), "must have 2 values"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_malformed_files(good, tmp_path, name):
    src, _ = good
    kw, message = CASES[name]
    bad = _copy_with(src, tmp_path / "bad.h5", **kw)
    with pytest.raises(InputError) as exc:
        wio.read_acquisition(bad)
    assert str(bad) in str(exc.value) and message in str(exc.value)


def test_nan_shape_and_phase_range(good, tmp_path):
    src, acq = good
    p = acq.phase.copy()
    p[0, 3, 4] = np.nan
    for replace, message in (
        ({"phase": p}, "NaN or Inf"),
        ({"phase": acq.phase[:, :-1]}, "shape mismatch"),
        ({"phase": acq.phase * 2}, "(-pi, pi]"),
    ):
        bad = _copy_with(src, tmp_path / "bad.h5", replace=replace)
        with pytest.raises(InputError, match=message.replace("(", r"\(").replace("]", r"\]")):
            wio.read_acquisition(bad)


def test_both_velocity_and_phase_is_an_error(good, tmp_path):
    src, acq = good
    with h5py.File(src, "r") as f:
        phase = f["phase"][()]
    bad = _copy_with(src, tmp_path / "both.h5")
    with h5py.File(bad, "a") as f:
        f["velocity"] = phase
    with pytest.raises(InputError, match="exactly one"):
        wio.read_acquisition(bad)


def test_multislice_needs_spacing(good, tmp_path):
    src, acq = good
    two = {"magnitude": np.concatenate([acq.magnitude] * 2), "phase": np.concatenate([acq.phase] * 2)}
    bad = _copy_with(src, tmp_path / "two.h5", replace=two)
    with pytest.raises(InputError, match="slice_spacing_mm"):
        wio.read_acquisition(bad)


def test_not_hdf5_and_missing(tmp_path):
    txt = tmp_path / "notes.h5"
    txt.write_text("hello")
    with pytest.raises(InputError, match="not an HDF5 file"):
        wio.read_acquisition(txt)
    with pytest.raises(InputError, match="no such file"):
        wio.read_acquisition(tmp_path / "nothing.h5")


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.h5"
    with pytest.raises(RuntimeError):
        with wio.atomic_h5(target) as f:
            f["x"] = np.arange(3)
            raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("name", ["missing magnitude", "negative voxel size"])
def test_cli_exit_code_and_no_output(good, tmp_path, capsys, name):
    src, _ = good
    kw, message = CASES[name]
    bad = _copy_with(src, tmp_path / "bad.h5", **kw)
    out = tmp_path / "result.h5"
    assert main(["reconstruct", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and message in err
    assert not out.exists() and not list(tmp_path.glob("*.part"))


def test_written_file_has_umask_permissions(tmp_path):
    target = tmp_path / "perm.h5"
    old = os.umask(0o022)
    try:
        with wio.atomic_h5(target) as f:
            f["x"] = np.arange(3)
    finally:
        os.umask(old)
    assert (target.stat().st_mode & 0o777) == 0o644
