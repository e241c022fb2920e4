"""VTK export: the file read back with meshio holds the wall points and the WSS of the result."""

import numpy as np
import pytest

from wss_nlp.io import files
from wss_nlp.synthetic import phantoms
from wss_nlp.app.cli import main

meshio = pytest.importorskip("meshio")


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    acq, _ = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=95)
    files.write_acquisition(d / "slice.h5", acq)
    stack, _ = phantoms.make_stack("tapered", nz=3, h_mm=1.5, spacing_mm=2.0, snr=25, seed=96)
    files.write_acquisition(d / "stack.h5", stack)
    for name in ("slice", "stack"):
        assert main(["reconstruct", str(d / f"{name}.h5"), "-o", str(d / f"{name}_r.h5"), "--no-uncertainty"]) == 0
    return d


def test_slice_is_a_closed_polyline(results):
    out = results / "slice.vtu"
    assert main(["export", str(results / "slice_r.h5"), "--vtk", str(out)]) == 0
    mesh = meshio.read(out)
    rec = files.read_result(results / "slice_r.h5")[0]
    assert np.allclose(mesh.points[:, 0], rec["wall_x"]) and np.allclose(mesh.points[:, 1], rec["wall_y"])
    assert np.all(mesh.points[:, 2] == 0)
    lines = mesh.cells_dict["line"]
    assert lines.shape == (rec["phi"].size, 2) and lines[-1].tolist() == [rec["phi"].size - 1, 0]
    assert np.allclose(mesh.point_data["tau_pa"], rec["tau"])


def test_stack_is_a_surface_at_the_slice_positions(results):
    out = results / "stack.vtk"
    assert main(["export", str(results / "stack_r.h5"), "--vtk", str(out)]) == 0
    mesh = meshio.read(out)
    rec = files.read_result(results / "stack_r.h5")
    n = rec[0]["phi"].size
    assert mesh.cells_dict["quad"].shape == (2 * n, 4)  # two bands between three rings
    assert np.allclose(mesh.points[:, 2], np.repeat([0.0, 2.0, 4.0], n))  # slice_spacing_mm stored by reconstruct
    assert np.allclose(mesh.point_data["tau_pa"], np.concatenate([r["tau"] for r in rec]))


def test_bad_export_requests(results, capsys):
    assert main(["export", str(results / "slice_r.h5"), "--vtk", str(results / "x.txt")]) == 2
    assert main(["export", str(results / "slice_r.h5"), "--vtk", str(results / "nofolder" / "z.vtu")]) == 2
    assert main(["export", str(results / "slice.h5"), "--vtk", str(results / "y.vtu")]) == 2  # an input file
    err = capsys.readouterr().err
    assert ".vtu (VTK XML)" in err and "does not exist" in err and "slice_NNN" in err
    assert not (results / "x.txt").exists() and not (results / "y.vtu").exists()
