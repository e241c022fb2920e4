r"""Export a result file for ParaView and other VTK readers (``wss-nlp export RESULT.h5 --vtk OUT``).

A single slice becomes a closed polyline through its wall points; a stack
becomes the wall surface, quadrilaterals between the wall rings of
neighbouring slices (the same angles ``phi`` on every slice), at
``z = k * slice_spacing_mm``. Point data: ``tau_pa`` (WSS, Pa), and where the
result has them ``tau_std_pa`` (its linearized standard deviation) and
``wss_vector_pa`` (the WSS vector of three-component stacks). Coordinates in
mm. Failed slices (NaN) leave a gap: no cell touches them. Written with
meshio (optional dependency: ``pip install 'wss-nlp[vtk]'``); the format
follows the file name (``.vtu`` XML, ``.vtk`` legacy).

World coordinates: a result reconstructed from imported data (``wss-nlp
import``: DICOM, NIfTI, or a plane cut from a 4D-flow volume) carries the
import record (``import_json``: the row, column and slice-normal directions
``e_r``, ``e_c``, ``n`` and the first slice's position ``P_0``, all in the
scanner's patient/world frame, mm). A wall point at in-plane coordinates
``(x, y)`` of slice ``k`` is then written at

.. math:: X = x e_r + y e_c + (P_0 \cdot n + k \Delta z) n,

which is where the voxel grid of the input lies in that frame (the input's
``origin_mm`` is ``(P_0 \cdot e_r, P_0 \cdot e_c)``), so the wall overlays the
volume or the DICOM series in ParaView. Without the record (a phantom) the
frame is the input's own: ``(x, y, k \Delta z)``. The field data name the
frame (``world_frame``: 1 scanner frame, 0 the input's own) and the units
(``length_unit_mm`` = 1; the point data's units are in their names) in
``.vtu`` files (the legacy ``.vtk`` writer has no field data).

A time-resolved (cine) result written to a ``.pvd`` file becomes a time
series: one ``.vtu`` per frame (the frame's wall and its ``tau_pa``; its time
in ms after the trigger as the field ``TimeValue``) in the folder ``NAME_frames/`` beside it, listed by the
ParaView collection file; ``.vtu``/``.vtk`` give the cycle average as before.
"""

from __future__ import annotations

import json
import os
from xml.sax.saxutils import quoteattr

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


def world_frame(record: dict | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """``(e_r, e_c, n, P_0 . n)`` of an import record (``import_json``), or None when it lacks the frame."""
    keys = ("row_direction", "column_direction", "slice_normal", "first_slice_position")
    if not record or any(record.get(k) is None for k in keys):
        return None
    e_r, e_c, n, p0 = (np.asarray(record[k], dtype=float) for k in keys)
    if not all(v.shape == (3,) and np.all(np.isfinite(v)) for v in (e_r, e_c, n, p0)):
        return None
    return e_r, e_c, n, float(p0 @ n)


def _record(f) -> dict | None:
    text = f.attrs.get("import_json")
    if text is None:
        return None
    try:
        return json.loads(text.decode() if isinstance(text, bytes) else str(text))
    except ValueError:
        return None


def _place(x, y, k: int, dz: float, frame) -> np.ndarray:
    """Points ``(n, 3)`` of slice ``k``'s wall: in the scanner's world frame when known (module notes)."""
    if frame is None:
        return np.column_stack([x, y, np.full(np.shape(x), k * dz)])
    e_r, e_c, n, offset = frame
    return x[:, None] * e_r + y[:, None] * e_c + (offset + k * dz) * n


def wall_mesh(path: str, slice_spacing_mm: float | None = None):
    """``(points (n, 3), cells [(type, connectivity)], point_data dict)`` of a result file's wall.

    A time-resolved result gives the wall averaged over the frames, ``tau_pa`` the WSS averaged over the
    cycle, and ``tawss_pa`` and ``osi``. Points in the scanner's world frame when the result carries the
    import record (module notes); :func:`field_data` says which.
    """
    import h5py

    with h5py.File(path, "r") as f:
        stored = f.attrs.get("slice_spacing_mm")
        cine = "trigger_times_ms" in f.attrs and any("wss/tawss_pa" in f[k] for k in f if k.startswith("slice_"))
        slices = _cine_slices(f) if cine else None
        frame = world_frame(_record(f))
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
        points.append(_place(np.asarray(x, dtype=float), np.asarray(y, dtype=float), k, dz or 0.0, frame))
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


def field_data(path: str) -> dict[str, np.ndarray]:
    """The mesh's field data: ``world_frame`` (1: the scanner's frame, 0: the input's own) and ``length_unit_mm``."""
    import h5py

    with h5py.File(path, "r") as f:
        known = world_frame(_record(f)) is not None
    return {"world_frame": np.array([int(known)]), "length_unit_mm": np.array([1.0])}


def _meshio():
    try:
        import meshio
    except ImportError:
        raise InputError("VTK export needs meshio: pip install 'wss-nlp[vtk]'") from None
    return meshio


def _write_mesh(out_path: str, points, cells, point_data, fields) -> None:
    meshio = _meshio()
    folder, name = os.path.split(os.path.abspath(out_path))
    tmp = os.path.join(folder, ".part-" + name)  # same extension: meshio picks the format from it
    try:
        meshio.write(tmp, meshio.Mesh(points, cells, point_data=point_data))
        if tmp.lower().endswith(".vtu"):
            _add_field_data(tmp, fields)
        os.replace(tmp, out_path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _add_field_data(path: str, fields: dict[str, np.ndarray]) -> None:
    """Insert ``fields`` as the grid's FieldData into a VTU file (meshio 5 writes none; ParaView reads it).

    A field named ``TimeValue`` is the time ParaView shows for the mesh.
    """
    arrays = "".join(
        f'\n<DataArray type="{"Int32" if np.issubdtype(v.dtype, np.integer) else "Float64"}" Name={quoteattr(k)} '
        f'NumberOfTuples="{v.size}" format="ascii">{" ".join(repr(x.item()) for x in v.ravel())}</DataArray>'
        for k, v in fields.items()
    )
    with open(path) as fh:
        text = fh.read()
    tag = "<UnstructuredGrid>"
    if tag not in text:  # pragma: no cover - meshio's layout changed: the mesh itself is still right
        return
    with open(path, "w") as fh:
        fh.write(text.replace(tag, f"{tag}\n<FieldData>{arrays}\n</FieldData>", 1))


def write_vtk(result_path: str, out_path: str, slice_spacing_mm: float | None = None) -> str:
    """Write the wall of ``result_path`` (see module notes) to ``out_path``; returns ``out_path``.

    ``.vtu``/``.vtk``: one mesh (a cine result's cycle average); ``.pvd``: a cine result's frames as a time series.
    """
    if out_path.lower().endswith(".pvd"):
        return write_time_series(result_path, out_path)
    _meshio()
    points, cells, data = wall_mesh(result_path, slice_spacing_mm)
    _write_mesh(out_path, points, cells, data, field_data(result_path))
    return out_path


def frame_meshes(path: str):
    """``[(time_ms, points, cells, point_data)]``: each frame's wall (every slice a closed polyline) and WSS.

    For a time-resolved result; slices are placed as in :func:`wall_mesh`. A frame whose slice failed
    contributes no cell for that slice.
    """
    import h5py

    with h5py.File(path, "r") as f:
        if "trigger_times_ms" not in f.attrs:
            raise InputError(f"{path}: not a time-resolved result; a .pvd time series needs a cine result")
        frame = world_frame(_record(f))
        stored = f.attrs.get("slice_spacing_mm")
        dz = 0.0 if stored is None else float(stored)
        names = sorted(k for k in f if k.startswith("slice_"))
        times = np.asarray(f[names[0]]["wss/time_ms"][()], dtype=float)
        out = []
        for t, time_ms in enumerate(times):
            points: list[np.ndarray] = []
            lines: list[np.ndarray] = []
            tau: list[np.ndarray] = []
            for k, name in enumerate(names):
                g = f[name]
                wall = g["frames"].get(f"frame_{t:03d}")  # cine.write_result's name; absent: the frame failed
                n_phi = g["wss/phi"].size
                if wall is None or "wss/wall_x_mm" not in wall:
                    x = y = np.full(n_phi, np.nan)
                else:
                    x, y = wall["wss/wall_x_mm"][()], wall["wss/wall_y_mm"][()]
                start = sum(p.shape[0] for p in points)
                points.append(_place(np.asarray(x, float), np.asarray(y, float), k, dz, frame))
                tau.append(np.asarray(g["wss/tau_pa"][t], dtype=float))
                if np.all(np.isfinite(points[-1])):
                    j = np.arange(n_phi)
                    lines.append(np.column_stack([start + j, start + (j + 1) % n_phi]))
            cells = [("line", np.vstack(lines))] if lines else []
            out.append((float(time_ms), np.nan_to_num(np.vstack(points)), cells, {"tau_pa": np.concatenate(tau)}))
    return out


def write_time_series(result_path: str, out_path: str) -> str:
    """A cine result as a ParaView time series: ``out_path`` (.pvd) listing ``NAME_frames/frame_NNN.vtu``."""
    _meshio()
    frames = frame_meshes(result_path)
    fields = field_data(result_path)
    folder, name = os.path.split(os.path.abspath(out_path))
    stem = os.path.splitext(name)[0]
    sub = os.path.join(folder, f"{stem}_frames")
    os.makedirs(sub, exist_ok=True)
    rows = []
    for i, (time_ms, points, cells, data) in enumerate(frames):
        if not cells:
            continue  # every slice of this frame failed: ParaView shows the neighbours
        file = f"frame_{i:03d}.vtu"
        _write_mesh(os.path.join(sub, file), points, cells, data, fields | {"TimeValue": np.array([time_ms])})
        rows.append(f'    <DataSet timestep="{time_ms:.6g}" part="0" file={quoteattr(f"{stem}_frames/{file}")}/>')
    if not rows:
        raise InputError(f"{result_path}: no reconstructed wall in any frame to export")
    text = (
        '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
        + "\n".join(rows)
        + "\n  </Collection>\n</VTKFile>\n"
    )
    tmp = os.path.join(folder, ".part-" + name)
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, out_path)
    return out_path
