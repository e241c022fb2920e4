"""``wss-nlp import`` and ``export``: scanner exports in, VTK out."""

from __future__ import annotations

import os
from ...io import files as wio
from ...io import outputs
from ...errors import InputError


def cmd_export(args) -> int:
    from ...io import export

    if not args.vtk.endswith((".vtu", ".vtk")):
        raise InputError(f"--vtk {args.vtk}: name a .vtu (VTK XML) or .vtk (legacy VTK) file")
    outputs.check_outputs(files={"--vtk": args.vtk}, inputs=[args.result])
    print(f"wrote {export.write_vtk(args.result, args.vtk, args.slice_spacing)}")
    return 0


def cmd_import(args) -> int:
    from ...io import importing, scanner

    outputs.check_outputs(files={"-o": args.output}, inputs=[p for p in args.paths if os.path.isfile(p)])
    if not args.output.endswith((".h5", ".hdf5")):
        raise InputError(f"-o {args.output}: name an HDF5 file (.h5)")
    wio.check_density(args.density, "--density")
    if args.viscosity is not None and not args.viscosity > 0:
        raise InputError(f"--viscosity {args.viscosity}: must be > 0 Pa*s (e.g. 3.5e-3 for blood)")
    options = scanner.ImportOptions(
        venc_m_s=args.venc,
        viscosity_pa_s=args.viscosity,
        density_kg_m3=args.density,
        flip_through_plane=args.flip_through_plane,
    )
    plane = None
    if args.plane is not None:
        from ...io.plane import Plane

        plane = Plane(
            point=tuple(args.plane[:3]),
            normal=tuple(args.plane[3:]),
            fov_mm=args.plane_fov,
            voxel_mm=args.plane_voxel,
            slices=args.plane_slices,
            spacing_mm=args.plane_spacing,
        )
        plane.check()
    imp = importing.import_paths(args.paths, options, args.phase_units, args.frame_interval, plane)
    scanner.write_import(args.output, imp, argv=["wss-nlp", *args.argv])
    print(f"wrote {args.output}: {imp.summary()}")
    return 0
