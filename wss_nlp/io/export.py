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

from ..errors import InputError
from .files import read_result


def _cine_slices(f) -> list[dict]:
    """Per slice of a time-resolved result: the wall averaged over the frames, the cycle-mean WSS, TAWSS, OSI."""
    from ..core.periodic import cycle_weights

    out = []
    for name in sorted(k for k in f if k.startswith("slice_")):
        g = f[name]
        frames = g["frames"]
        walls = [
            (frames[k]["wss/wall_x_mm"][()], frames[k]["wss/wall_y_mm"][()])
            for k in sorted(frames)
            if "wss/wall_x_mm" in frames[k]
        ]
        n_phi = g["wss/phi"].size
        nan = np.full(n_phi, np.nan)
        tau = g["wss/tau_pa"][()]
        weights = cycle_weights(g["wss/time_ms"][()], float(f.attrs["cardiac_period_ms"]))
        d = {
            "name": name,
            "phi": g["wss/phi"][()],
            "wall_x": np.mean([w[0] for w in walls], axis=0) if walls else nan,
            "wall_y": np.mean([w[1] for w in walls], axis=0) if walls else nan,
            "tau": np.nansum(weights[:, None] * tau, axis=0) / np.sum(weights[np.isfinite(tau[:, 0])]),
            "tawss": g["wss/tawss_pa"][()],
            "osi": g["wss/osi"][()],
            "failed": not walls,
        }
        out.append(d)
    return out


def wall_mesh(path: str, slice_spacing_mm: float | None = None):
    """``(points (n, 3), cells [(type, connectivity)], point_data dict)`` of a result file's wall.

    A time-resolved result gives the wall averaged over the frames, ``tau_pa`` the WSS averaged over the
    cycle, and ``tawss_pa`` and ``osi``.
    """
    import h5py

    with h5py.File(path, "r") as f:
        stored = f.attrs.get("slice_spacing_mm")
        cine = "trigger_times_ms" in f.attrs and any("wss/tawss_pa" in f[k] for k in f if k.startswith("slice_"))
        slices = _cine_slices(f) if cine else None
    if slices is None:
        slices = read_result(path)
    dz = slice_spacing_mm if slice_spacing_mm is not None else (None if stored is None else float(stored))
    missing = [d["name"] for d in slices if "wall_x" not in d and not d.get("failed")]
    if missing:
        raise InputError(f"{path}: {missing[0]} has no wss/wall_x_mm; export needs a result written by wss-nlp")
    if len(slices) > 1 and dz is None:
        raise InputError(f"{path}: a stack without 'slice_spacing_mm'; pass --slice-spacing MM")
    n_phi = slices[0]["phi"].size
    if any(d["phi"].size != n_phi for d in slices):
        raise InputError(f"{path}: the slices have different numbers of wall angles; cannot join them as a surface")
    points, tau, std, vec, tawss, osi = [], [], [], [], [], []
    for k, d in enumerate(slices):
        nan = np.full(n_phi, np.nan)
        x = d.get("wall_x", nan)
        y = d.get("wall_y", nan)
        points.append(np.column_stack([x, y, np.full(n_phi, k * (dz or 0.0))]))
        tau.append(d["tau"])
        std.append(d.get("tau_std", nan))
        vec.append(d.get("tau_vector", np.full((n_phi, 3), np.nan)))
        tawss.append(d.get("tawss", nan))
        osi.append(d.get("osi", nan))
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
    if any(np.isfinite(v).any() for v in tawss):
        data["tawss_pa"] = np.concatenate(tawss)
        data["osi"] = np.concatenate(osi)
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
