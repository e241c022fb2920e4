import json

import h5py
import numpy as np
import pytest

from wss_nlp.models import geometry as geo
from wss_nlp.io import files as wio
from wss_nlp.synthetic import phantoms
from wss_nlp.app.cli import main
from wss_nlp.errors import SolverError


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    inp, truth = d / "in.h5", d / "truth.h5"
    assert (
        main(["phantom", "--case", "laminar", "--h", "1.0", "--seed", "4", "-o", str(inp), "--truth", str(truth)]) == 0
    )
    return d, inp, truth


def test_phantom_writes_valid_input(files):
    _, inp, truth = files
    acq = wio.read_acquisition(inp)
    assert acq.phase is not None and acq.venc_m_s > 0 and acq.viscosity_pa_s == pytest.approx(3.5e-3)
    t = wio.read_result(truth)[0]
    assert t["mean_tau"] > 0 and t["phi"].size >= 360


def test_reconstruct_and_compare(files, capsys):
    d, inp, truth = files
    out = d / "out.h5"
    assert main(["reconstruct", str(inp), "-o", str(out), "--figures", str(d / "figs")]) == 0
    with h5py.File(out) as f:
        s = f["slice_000"]
        assert s["geometry/coefficients"].shape == (2 * geo.GeometryOptions().n_fourier + 1,)
        assert s["geometry/phi"].shape[0] >= 360
        assert s["wss/tau_pa"].shape == s["wss/phi"].shape
        assert np.isfinite(s["wss"].attrs["mean_pa"])
        assert {"alpha", "beta", "converged"} <= set(s.attrs)
        for key in (
            "wss_nlp_version",
            "casadi_version",
            "ipopt_version",
            "command_line",
            "created_utc",
            "options_json",
        ):
            assert key in f.attrs
        recorded = json.loads(f.attrs["options_json"])
        assert recorded["geometry"]["alpha"] == geo.GeometryOptions().alpha
        assert recorded["dephasing_beta_rule"] == "gcv"
    assert len(list((d / "figs").glob("*.png"))) == 5  # figures 1-5 of the paper and the near-wall data
    capsys.readouterr()
    assert main(["compare", str(out), str(truth)]) == 0
    text = capsys.readouterr().out
    assert "WSS rel. L2 error" in text


def test_viscosity_override_scales_wss(files):
    d, inp, _ = files
    a, b = d / "a.h5", d / "b.h5"
    assert main(["reconstruct", str(inp), "-o", str(a)]) == 0
    assert main(["reconstruct", str(inp), "-o", str(b), "--viscosity", "7e-3"]) == 0
    ta, tb = (wio.read_result(p)[0]["tau"] for p in (a, b))
    assert np.allclose(tb, 2 * ta, rtol=1e-12)  # tau is linear in mu; the file has 3.5e-3


def test_missing_viscosity_is_an_input_error(files, tmp_path, capsys):
    _, inp, _ = files
    acq = wio.read_acquisition(inp)
    acq.viscosity_pa_s = None
    path = tmp_path / "novisc.h5"
    wio.write_acquisition(path, acq)
    assert main(["reconstruct", str(path), "-o", str(tmp_path / "o.h5")]) == 2
    assert "--viscosity" in capsys.readouterr().err


def test_solver_failure_exit_1_no_output(files, tmp_path, monkeypatch, capsys):
    _, inp, _ = files

    def fail(*a, **k):
        raise SolverError("geometry (IPOPT): IPOPT failed with status Restoration_Failed")

    monkeypatch.setattr(geo, "solve", fail)
    out = tmp_path / "o.h5"
    assert main(["reconstruct", str(inp), "-o", str(out)]) == 1
    assert "Restoration_Failed" in capsys.readouterr().err
    assert not out.exists()


def test_not_converged_is_flagged(files, tmp_path, monkeypatch, capsys):
    _, inp, _ = files
    real = geo.solve
    monkeypatch.setattr(geo, "solve", lambda p, o, x0=None: real(p, geo.with_options(o, max_iter=2), x0))
    out = tmp_path / "o.h5"
    assert main(["reconstruct", str(inp), "-o", str(out)]) == 0
    assert "did not converge" in capsys.readouterr().err
    with h5py.File(out) as f:
        assert not f["slice_000"].attrs["converged"] and not f.attrs["all_converged"]
        assert f["slice_000/geometry"].attrs["solver_status"] == "Maximum_Iterations_Exceeded"


def test_no_vessel_cli(tmp_path, capsys):
    rng = np.random.default_rng(0)
    noise = np.abs(rng.normal(size=(1, 40, 40)) + 1j * rng.normal(size=(1, 40, 40)))
    acq = wio.Acquisition(magnitude=noise, velocity=rng.normal(size=(1, 40, 40)), viscosity_pa_s=1e-3)
    path = tmp_path / "empty.h5"
    wio.write_acquisition(path, acq)
    assert main(["reconstruct", str(path), "-o", str(tmp_path / "o.h5")]) == 2
    assert "no vessel in view" in capsys.readouterr().err


def test_lumen_touching_border_cli(tmp_path, capsys):
    acq, _ = phantoms.make_phantom("circle", h_mm=1.0, snr=25, seed=1)
    acq.magnitude, acq.phase = acq.magnitude[:, :, 8:], acq.phase[:, :, 8:]  # cut the left side of the lumen
    path = tmp_path / "cut.h5"
    wio.write_acquisition(path, acq)
    assert main(["reconstruct", str(path), "-o", str(tmp_path / "o.h5")]) == 2
    assert "touches the border" in capsys.readouterr().err


def test_help_and_usage_errors(capsys):
    assert main(["--help"]) == 0
    assert main(["reconstruct"]) == 2
    assert main(["demo", "--case", "nonsense"]) == 2


def test_demo(tmp_path, capsys):
    assert main(["demo", "--h", "1.5", "-o", str(tmp_path / "demo")]) == 0
    text = capsys.readouterr().out
    assert "radius rel. L2 error" in text and "WSS rel. L2 error" in text
    assert "alpha (fixed)" in text and "beta (balance)" in text  # the defaults, and the chosen value
    assert (tmp_path / "demo" / "result.h5").exists()
    assert len(list((tmp_path / "demo").glob("*.png"))) == 5


def test_multislice_file_is_reconstructed_slice_by_slice(tmp_path):
    a, _ = phantoms.make_phantom("circle", h_mm=1.0, snr=25, seed=1)
    b, _ = phantoms.make_phantom("circle", h_mm=1.0, snr=25, seed=2)
    assert a.magnitude.shape == b.magnitude.shape and a.origin_mm == b.origin_mm
    b.phase = b.venc_m_s / a.venc_m_s * b.phase  # express slice 1 in slice 0's venc
    a.magnitude = np.concatenate([a.magnitude, b.magnitude])
    a.phase = np.concatenate([a.phase, b.phase])
    a.slice_spacing_mm = 2.0
    inp, out = tmp_path / "stack.h5", tmp_path / "out.h5"
    wio.write_acquisition(inp, a)
    assert main(["reconstruct", str(inp), "-o", str(out)]) == 0
    res = wio.read_result(out)
    assert [r["name"] for r in res] == ["slice_000", "slice_001"]
    # independent noise: different numbers, both close to the 10 mm circle
    assert not np.allclose(res[0]["radius"], res[1]["radius"])
    assert all(abs(r["coefficients"][0] - 10.0) < 0.05 for r in res)
