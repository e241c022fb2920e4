"""``wss-nlp import`` and ``export``: scanner exports in, VTK out."""

from __future__ import annotations

import os
import sys
from ...io import outputs, ranges
from ...errors import InputError


def cmd_export(args) -> int:
    from ...io import export

    if not args.vtk.endswith((".vtu", ".vtk")):
        raise InputError(f"--vtk {args.vtk}: name a .vtu (VTK XML) or .vtk (legacy VTK) file")
    outputs.check_outputs(files={"--vtk": args.vtk}, inputs=[args.result])
    if args.slice_spacing is not None:
        ranges.check("slice_spacing", args.slice_spacing, "--slice-spacing", ranges.parse_allow(args.allow_unphysical)
                     if args.allow_unphysical else ())  # fmt: skip
    print(f"wrote {export.write_vtk(args.result, args.vtk, args.slice_spacing)}")
    return 0


def cmd_import(args) -> int:
    from ...io import importing, scanner

    outputs.check_outputs(files={"-o": args.output}, inputs=[p for p in args.paths if os.path.isfile(p)])
    if not args.output.endswith((".h5", ".hdf5")):
        raise InputError(f"-o {args.output}: name an HDF5 file (.h5)")
    allow = ranges.parse_allow(args.allow_unphysical) if args.allow_unphysical else ()
    for name, value, flag in (
        ("venc", args.venc, "--venc"),
        ("viscosity", args.viscosity, "--viscosity"),
        ("density", args.density, "--density"),
        ("frame_spacing", args.frame_interval, "--frame-interval"),
        ("fov", args.plane_fov if args.plane is not None else None, "--plane-fov"),
        ("voxel_size", args.plane_voxel, "--plane-voxel"),
        ("slice_spacing", args.plane_spacing, "--plane-spacing"),
    ):
        if value is not None and (note := ranges.check(name, value, flag, allow)):
            print(f"wss-nlp: warning: {note}", file=sys.stderr)
    if args.plane is not None and not 1 <= args.plane_slices <= 500:
        raise InputError(f"--plane-slices {args.plane_slices}: must be a whole number in 1-500")
    options = scanner.ImportOptions(
        venc_m_s=args.venc,
        viscosity_pa_s=args.viscosity,
        density_kg_m3=args.density,
        flip_through_plane=args.flip_through_plane,
        allow_unphysical=allow,
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
