"""Export a result file for ParaView and other VTK readers (``wss-nlp export RESULT.h5 --vtk OUT``).

A single slice becomes a closed polyline through its wall points; a stack
becomes the wall surface, quadrilaterals between the wall rings of
neighbouring slices (the same angles ``phi`` on every slice), at
``z = k * slice_spacing_mm``. Point data: ``tau_pa`` (WSS, Pa), and where the
result has them ``tau_std_pa`` (its linearized standard deviation) and
``wss_vector_pa`` (the WSS vector of three-component stacks). Coordinates in
mm. Failed slices (NaN) leave a gap: no cell touches them. Written with
meshio (optional dependency: ``pip install 'wss-nlp[vtk]'``); the format
follows the file name (``.vtu`` XML, ``.vtk`` legacy).
"""

from __future__ import annotations

import os

import numpy as np

from .errors import InputError
from .files import read_result


def wall_mesh(path: str, slice_spacing_mm: float | None = None):
    """``(points (n, 3), cells [(type, connectivity)], point_data dict)`` of a result file's wall."""
    import h5py

    slices = read_result(path)
    with h5py.File(path, "r") as f:
        stored = f.attrs.get("slice_spacing_mm")
    dz = slice_spacing_mm if slice_spacing_mm is not None else (None if stored is None else float(stored))
    missing = [d["name"] for d in slices if "wall_x" not in d and not d.get("failed")]
    if missing:
        raise InputError(f"{path}: {missing[0]} has no wss/wall_x_mm; export needs a result written by wss-nlp")
    if len(slices) > 1 and dz is None:
        raise InputError(f"{path}: a stack without 'slice_spacing_mm'; pass --slice-spacing MM")
    n_phi = slices[0]["phi"].size
    if any(d["phi"].size != n_phi for d in slices):
        raise InputError(f"{path}: the slices have different numbers of wall angles; cannot join them as a surface")
    points, tau, std, vec = [], [], [], []
    for k, d in enumerate(slices):
        nan = np.full(n_phi, np.nan)
        x = d.get("wall_x", nan)
        y = d.get("wall_y", nan)
        points.append(np.column_stack([x, y, np.full(n_phi, k * (dz or 0.0))]))
        tau.append(d["tau"])
        std.append(d.get("tau_std", nan))
        vec.append(d.get("tau_vector", np.full((n_phi, 3), np.nan)))
    ok = [bool(np.all(np.isfinite(p))) for p in points]
    j = np.arange(n_phi)
    if len(slices) == 1:
        cells = [("line", np.column_stack([j, (j + 1) % n_phi]))] if ok[0] else []
    else:
        quads = [
            np.column_stack([k * n_phi + j, k * n_phi + (j + 1) % n_phi, (k + 1) * n_phi + (j + 1) % n_phi,
                             (k + 1) * n_phi + j])
            for k in range(len(slices) - 1)
            if ok[k] and ok[k + 1]
        ]  # fmt: skip
        cells = [("quad", np.vstack(quads))] if quads else []
    if not cells:
        raise InputError(f"{path}: no reconstructed wall to export (every slice failed)")
    data = {"tau_pa": np.concatenate(tau)}
    if any(np.isfinite(s).any() for s in std):
        data["tau_std_pa"] = np.concatenate(std)
    if any(np.isfinite(v).any() for v in vec):
        data["wss_vector_pa"] = np.vstack(vec)
    return np.nan_to_num(np.vstack(points)), cells, data


def write_vtk(result_path: str, out_path: str, slice_spacing_mm: float | None = None) -> str:
    """Write the wall of ``result_path`` (see module notes) to ``out_path``; returns ``out_path``."""
    try:
        import meshio
    except ImportError:
        raise InputError("VTK export needs meshio: pip install 'wss-nlp[vtk]'") from None
    points, cells, data = wall_mesh(result_path, slice_spacing_mm)
    folder, name = os.path.split(os.path.abspath(out_path))
    tmp = os.path.join(folder, ".part-" + name)  # same extension: meshio picks the format from it
    try:
        meshio.write(tmp, meshio.Mesh(points, cells, point_data=data))
        os.replace(tmp, out_path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return out_path
