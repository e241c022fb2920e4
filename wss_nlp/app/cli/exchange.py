"""``wss-nlp import`` and ``export``: scanner exports in, VTK out."""

from __future__ import annotations

import logging
import argparse
import os

import numpy as np

from ...io import files as wio
from ...io import outputs, ranges
from ...errors import InputError

log = logging.getLogger(__name__)  # warnings: the command line shows them once per kind (main)


def cmd_export(args) -> int:
    from ...io import export
    from .vessel import export_volume, is_vessel_result

    if is_vessel_result(args.result):
        return export_volume(args)
    if not args.vtk.endswith((".vtu", ".vtk", ".pvd")):
        raise InputError(
            f"--vtk {args.vtk}: name a .vtu (VTK XML), .vtk (legacy VTK) or .pvd (a cine result's frames as a "
            "time series) file"
        )
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
    p.add_argument(
        "--venc",
        default=None,
        metavar="M_S",
        help="velocity encoding in m/s (overrides); a 4D flow volume takes one value or three X,Y,Z",
    )
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


def venc_values(text: str | None) -> tuple[float, ...] | None:
    """``--venc``: one value (m/s) or three, comma-separated (x, y, z of a 4D flow volume)."""
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in str(text).split(","))
    except ValueError:
        raise InputError(f"--venc {text}: give one number in m/s, or three X,Y,Z for a 4D flow volume") from None
    if len(values) not in (1, 3) or not all(np.isfinite(v) and v > 0 for v in values):
        raise InputError(f"--venc {text}: give one positive number in m/s, or three X,Y,Z for a 4D flow volume")
    return values


def cmd_import(args) -> int:
    from ...io import importing, scanner
    from ...io.volume_import import is_flow_volume

    outputs.check_outputs(files={"-o": args.output}, inputs=[p for p in args.paths if os.path.isfile(p)])
    if not args.output.endswith((".h5", ".hdf5")):
        raise InputError(f"-o {args.output}: name an HDF5 file (.h5)")
    if args.plane is None and is_flow_volume(args.paths):
        wio.check_density(args.density, "--density")
        if args.viscosity is not None and not args.viscosity > 0:
            raise InputError(f"--viscosity {args.viscosity}: must be > 0 Pa*s (e.g. 3.5e-3 for blood)")
        return _import_volume(args, venc_values(args.venc))
    imp = importing.import_paths(args.paths, **import_settings(args))
    scanner.write_import(args.output, imp, argv=["wss-nlp", *args.argv])
    print(f"wrote {args.output}: {imp.summary()}")
    return 0


def import_settings(args) -> dict:
    """The keywords of :func:`wss_nlp.io.importing.import_paths` from parsed import options (checked)."""
    from ...io import scanner

    wio.check_density(args.density, "--density")
    venc = venc_values(args.venc)
    if venc is not None and len(venc) != 1:
        raise InputError(f"--venc {args.venc}: three values are for a 4D flow volume; slices and planes take one")
    allow = ranges.parse_allow(args.allow_unphysical) if getattr(args, "allow_unphysical", "") else ()
    for name, value, flag in (  # the user's numbers in their ranges before any file is read (issue 42)
        ("venc", None if venc is None else venc[0], "--venc"),
        ("viscosity", args.viscosity, "--viscosity"),
        ("density", args.density, "--density"),
        ("frame_spacing", args.frame_interval, "--frame-interval"),
        ("fov", args.plane_fov if args.plane is not None else None, "--plane-fov"),
        ("voxel_size", args.plane_voxel, "--plane-voxel"),
        ("slice_spacing", args.plane_spacing, "--plane-spacing"),
    ):
        if value is not None and (note := ranges.check(name, value, flag, allow)):
            log.warning(note)
    if args.plane is not None and not 1 <= args.plane_slices <= 500:
        raise InputError(f"--plane-slices {args.plane_slices}: must be a whole number in 1-500")
    options = scanner.ImportOptions(
        venc_m_s=None if venc is None else venc[0],
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


def _import_volume(args, venc: tuple[float, ...] | None) -> int:
    """A magnitude and three velocity-component NIfTI files without ``--plane``: the volume layout
    (:mod:`wss_nlp.io.volume`)."""
    import dataclasses

    from ...io.volume import write_volume
    from ...io.volume_import import read_nifti_volume

    if args.flip_through_plane:
        raise InputError("--flip-through-plane: a 4D flow volume has no through-plane direction; the components "
                         "are along the affine's world axes (rename or negate the component file instead)")  # fmt: skip
    vol = read_nifti_volume(
        args.paths,
        venc_m_s=None if venc is None else (venc[0] if len(venc) == 1 else venc),  # type: ignore[arg-type]
        phase_units=args.phase_units,
        frame_interval_ms=args.frame_interval,
        viscosity_pa_s=args.viscosity,
    )
    if args.density is not None:
        vol = dataclasses.replace(vol, density_kg_m3=float(args.density))
    vol = dataclasses.replace(vol, extra_attrs={**vol.extra_attrs, "argv": " ".join(["wss-nlp", *args.argv])})
    write_volume(args.output, vol)
    size = " x ".join(f"{v:.3g}" for v in vol.voxel_size_mm)
    frames = "one frame" if vol.nt == 1 else f"{vol.nt} frames"
    print(f"wrote {args.output}: a 4D flow volume of {' x '.join(map(str, vol.shape))} voxels ({size} mm), {frames}")
    return 0
