"""The vessel wall as a surface mesh for ParaView (meshio, VTK XML unstructured grid ``.vtu``).

:func:`wall_mesh` turns a :class:`wss_nlp.vessel.reconstruct.VesselResult` into quads over its ``(s, phi)`` grid
(closed around the vessel), points in world mm (the volume's affine's frame), with the point arrays

* ``wss_vector_pa`` (3-vector, Pa, world frame), ``tau_pa`` (its part along the centreline's direction, signed),
  ``circumferential_pa``, ``tau_std_pa`` (the band of ``tau_pa``: its standard deviation from the velocity noise,
  :mod:`wss_nlp.vessel.band3d`; NaN without the venc; absent for results without a band): one frame (``frame``);
* ``tawss_pa``, ``osi`` (cines), ``radius_mm``, ``flags`` (the bits of :mod:`wss_nlp.vessel.reconstruct`),
  ``covered`` (1 where no flag), ``s_mm``, ``phi_rad``.

:func:`write_wall` writes one ``.vtu`` (one frame), or for a cine one ``.vtu`` per frame and a ``.pvd`` collection
ParaView opens as a time series (``timestep`` in ms), plus the centreline as a legacy VTK polyline and the
per-plane table as CSV next to it. meshio is an optional dependency (``pip install 'wss-nlp[vtk]'``).
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import InputError


def _meshio():
    try:
        import meshio
    except ImportError:
        raise InputError("writing VTK needs meshio, an optional dependency: pip install 'wss-nlp[vtk]'") from None
    return meshio


def wall_mesh(result, frame: int = 0):
    """The wall of ``result`` as a ``meshio.Mesh`` of quads (module notes) for frame ``frame``."""
    meshio = _meshio()
    ns, nph = result.radius_mm.shape
    if not 0 <= frame < result.nt:
        raise InputError(f"frame {frame} does not exist; the result has {result.nt}")
    i, j = np.meshgrid(np.arange(ns - 1), np.arange(nph), indexing="ij")
    jn = (j + 1) % nph
    quads = np.stack([i * nph + j, (i + 1) * nph + j, (i + 1) * nph + jn, i * nph + jn], axis=-1).reshape(-1, 4)
    ss, pp = np.meshgrid(result.s_mm, result.phi, indexing="ij")
    data = {
        "wss_vector_pa": result.wss_pa[frame].reshape(-1, 3),
        "tau_pa": result.axial_pa[frame].ravel(),
        "circumferential_pa": result.circumferential_pa[frame].ravel(),
        "radius_mm": result.radius_mm.ravel(),
        "flags": result.flags.ravel().astype(np.int32),
        "covered": (result.flags.ravel() == 0).astype(np.int32),
        "s_mm": ss.ravel(),
        "phi_rad": pp.ravel(),
    }
    if result.axial_std_pa is not None:
        data["tau_std_pa"] = result.axial_std_pa[frame].ravel()
    if result.tawss_pa is not None:
        data["tawss_pa"] = result.tawss_pa.ravel()
        data["osi"] = result.osi.ravel()
    return meshio.Mesh(result.wall_mm.reshape(-1, 3), [("quad", quads)], point_data=data)


def write_wall(result, path) -> list[str]:
    """Write the wall (``path`` ending in ``.vtu``), per frame with a ``.pvd`` for cines, the centreline
    (``<stem>_centerline.vtk``) and the per-plane table (``<stem>_planes.csv``); returns the files written."""
    path = os.fspath(path)
    if not path.lower().endswith(".vtu"):
        raise InputError(f"{path}: write the wall as .vtu (VTK XML unstructured grid; meshio cannot write .vtp)")
    stem = path[:-4]
    written = []
    if result.nt == 1:
        wall_mesh(result, 0).write(path)
        written.append(path)
    else:
        entries = []
        for k in range(result.nt):
            name = f"{stem}_{k:03d}.vtu"
            wall_mesh(result, k).write(name)
            written.append(name)
            entries.append(f'    <DataSet timestep="{float(result.time_ms[k]):.6g}" file="{os.path.basename(name)}"/>')
        pvd = stem + ".pvd"
        with open(pvd, "w") as fh:
            fh.write('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n')
            fh.write("\n".join(entries) + "\n  </Collection>\n</VTKFile>\n")
        written.append(pvd)
    written.append(result.centerline.save(stem + "_centerline.vtk"))
    with open(stem + "_planes.csv", "w") as fh:
        fh.write(result.plane_table())
    written.append(stem + "_planes.csv")
    return written
