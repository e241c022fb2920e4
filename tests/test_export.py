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


def test_imported_oblique_slice_is_exported_in_the_scanners_world_frame(tmp_path):
    """A laminar phantom written as DICOM in an oblique plane (rows along (0.6, 0, 0.8), columns along y), imported,
    reconstructed and exported: every wall point lies in that plane, and its coordinates along the row and column
    directions lie on the phantom's true (elliptic, 13 x 10 mm) wall about its true centre. Tolerance 0.2 mm, a
    tenth of the 2 mm voxel: the noise-free reconstruction's wall error is below it, while swapped or unrotated
    axes are off by millimetres (the ellipse's semi-axes differ by 3 mm)."""
    pytest.importorskip("pydicom")
    from wss_nlp.synthetic import scanner_exports

    acq, truth = phantoms.make_phantom("laminar", h_mm=2.0, snr=None, seed=97)
    e_r, e_c = np.array([0.6, 0.0, 0.8]), np.array([0.0, 1.0, 0.0])
    scan = scanner_exports.Scan(
        acq.magnitude, acq.velocity_images(), 1.0, acq.voxel_size_mm, acq.origin_mm, 2.0, tuple(e_r), tuple(e_c)
    )
    scanner_exports.write_dicom(str(tmp_path / "dcm"), scan, "siemens")
    inp, res, vtu = tmp_path / "in.h5", tmp_path / "r.h5", tmp_path / "wall.vtu"
    assert main(["import", str(tmp_path / "dcm"), "-o", str(inp)]) == 0
    fast = [
        "--viscosity",
        "3.5e-3",
        "--beta",
        "5e-8",
        "--no-uncertainty",
        "--near-wall",
        "off",
        "-q",
    ]  # the frame is under test, not the fit
    assert main(["reconstruct", str(inp), "-o", str(res), *fast]) == 0
    assert main(["export", str(res), "--vtk", str(vtu)]) == 0
    mesh = meshio.read(vtu)
    normal = np.cross(e_r, e_c)
    assert np.max(np.abs(mesh.points @ normal)) < 1e-9  # in the plane through the origin (Scan.position(0))
    x, y = mesh.points @ e_r, mesh.points @ e_c
    cx, cy = truth.center
    dist = np.hypot(x - cx, y - cy)
    assert np.max(np.abs(dist - truth.radius_about(truth.center, np.arctan2(y - cy, x - cx)))) < 0.2
    assert mesh.field_data["world_frame"][0] == 1 and mesh.field_data["length_unit_mm"][0] == 1.0


def test_phantom_result_says_its_frame_is_its_own(results, tmp_path):
    out = tmp_path / "slice.vtu"
    assert main(["export", str(results / "slice_r.h5"), "--vtk", str(out)]) == 0
    assert meshio.read(out).field_data["world_frame"][0] == 0  # no import record: the input's own (x, y, z)
