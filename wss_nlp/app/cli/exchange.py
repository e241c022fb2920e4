"""``wss-nlp import`` and ``export``: scanner exports in, VTK out."""

from __future__ import annotations

import argparse
import os
import sys
from ...io import files as wio
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


def add_allow(p: argparse.ArgumentParser) -> None:
    """``--allow-unphysical [QUANTITY,...]`` for commands whose options are physical quantities
    (:mod:`wss_nlp.io.ranges`; reconstruct has it from its options' declaration)."""
    p.add_argument(
        "--allow-unphysical",
        nargs="?",
        const="all",
        default="",
        metavar="QUANTITY,...",
        help="use values outside the plausible ranges of the docs page 'Input checks' as given (all, or those named)",
    )


def add_import_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``wss-nlp import`` (not its paths and output): the import subcommand's, and the columns a
    batch manifest may set per exam (:mod:`wss_nlp.app.batch.manifest`)."""
    p.add_argument("--venc", type=float, default=None, metavar="M_S", help="velocity encoding in m/s (overrides)")
    p.add_argument("--viscosity", type=float, default=None, metavar="PA_S", help="dynamic viscosity to store")
    p.add_argument("--density", type=float, default=None, metavar="KG_M3", help="fluid density to store")
    p.add_argument(
        "--flip-through-plane", action="store_true", help="negate the through-plane velocity (forward flow negative)"
    )
    p.add_argument(
        "--phase-units",
        default=None,
        choices=["rad", "siemens", "cm/s", "mm/s", "m/s"],
        help="units of the phase images' values when the headers do not state them",
    )
    p.add_argument(
        "--frame-interval", type=float, default=None, metavar="MS", help="ms between NIfTI frames (if not in header)"
    )
    p.add_argument(
        "--plane",
        type=float,
        nargs=6,
        default=None,
        metavar=("X", "Y", "Z", "NX", "NY", "NZ"),
        help="4D flow (NIfTI magnitude + *_vx/_vy/_vz files): cut the volume by the plane through (X, Y, Z) mm "
        "with normal (NX, NY, NZ), in the affine's world frame",
    )
    p.add_argument("--plane-fov", type=float, default=40.0, metavar="MM", help="side of the plane (default 40)")
    p.add_argument(
        "--plane-voxel", type=float, default=None, metavar="MM", help="plane voxel (default: the volume's largest)"
    )
    p.add_argument("--plane-slices", type=int, default=1, metavar="N", help="parallel slices (a stack; default 1)")
    p.add_argument(
        "--plane-spacing", type=float, default=None, metavar="MM", help="between those slices (default: the voxel)"
    )
    add_allow(p)


def cmd_import(args) -> int:
    from ...io import importing, scanner

    outputs.check_outputs(files={"-o": args.output}, inputs=[p for p in args.paths if os.path.isfile(p)])
    if not args.output.endswith((".h5", ".hdf5")):
        raise InputError(f"-o {args.output}: name an HDF5 file (.h5)")
    imp = importing.import_paths(args.paths, **import_settings(args))
    scanner.write_import(args.output, imp, argv=["wss-nlp", *args.argv])
    print(f"wrote {args.output}: {imp.summary()}")
    return 0


def import_settings(args) -> dict:
    """The keywords of :func:`wss_nlp.io.importing.import_paths` from parsed import options (checked)."""
    from ...io import scanner

    wio.check_density(args.density, "--density")
    allow = ranges.parse_allow(args.allow_unphysical) if getattr(args, "allow_unphysical", "") else ()
    for name, value, flag in (  # the user's numbers in their ranges before any file is read (issue 42)
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
    return {
        "options": options,
        "phase_units": args.phase_units,
        "frame_interval_ms": args.frame_interval,
        "plane": plane,
    }
