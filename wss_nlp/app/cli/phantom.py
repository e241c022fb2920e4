"""``wss-nlp phantom``: synthetic acquisitions (and their truth) written as input files or scanner exports."""

from __future__ import annotations

import dataclasses
import os
import sys
import numpy as np
from ...io import files as wio
from ...analysis import metrics
from ...io import outputs, ranges
from ...pipeline import limits
from ...synthetic import invivo, phantoms
from ...core import schema
from ...errors import InputError
from ...models.kspace import AcquisitionOptions


def _write_truth(path, truth) -> None:
    """Exact geometry and WSS of a phantom (one group per slice for a stack phantom)."""
    from ...core import radius as rad

    stack = isinstance(truth, phantoms.StackTruth)
    slices = truth.slices if stack else [truth]
    cases = phantoms.STACK_CASES if stack else {**phantoms.CASES, **invivo.INVIVO_CASES}
    with wio.atomic_h5(path) as f:
        for k, v in wio.provenance({"truth": truth.parameters}).items():
            f.attrs[k] = v
        f.attrs["case"] = truth.name
        f.attrs["description"] = cases[truth.name][1]
        for i, sl in enumerate(slices):
            s = metrics.truth_samples(sl)
            g = f.create_group(f"slice_{i:03d}")
            g["geometry/center_mm"] = s["center"]
            g["geometry/phi"] = s["phi"]
            g["geometry/radius_mm"] = s["radius"]
            g["geometry/coefficients"] = rad.fit(s["phi"], s["radius"], 32)
            g["geometry"].attrs["note"] = "coefficients: least-squares projection onto V_32 of the exact radius"
            g["wss/phi"] = s["phi"]
            g["wss/tau_pa"] = s["tau"]
            g["wss"].attrs["mean_pa"] = s["mean_tau"]
            g["velocity_true_m_s"] = sl.velocity_image
            g.attrs["alpha"] = np.nan
            g.attrs["beta"] = np.nan


# ------------------------------------------------------------------ commands
def _phantom_cine(args) -> int:
    from ...synthetic import pulsatile

    if args.dicom or args.nifti or args.stack:
        raise InputError("--case womersley writes a time-resolved HDF5 input only (no --dicom, --nifti, --stack)")
    if args.pipe_radius is not None and not args.pipe_radius > 0:
        raise InputError(f"--pipe-radius must be > 0 mm, got {args.pipe_radius}")
    snr = None if args.snr <= 0 else args.snr
    radius = {} if args.pipe_radius is None else {"radius_mm": args.pipe_radius}
    frames, truth = pulsatile.make_cine(
        h_mm=args.h, snr=snr, seed=args.seed, frames=args.frames, venc=args.venc, psf=_phantom_psf(args),
        distension=args.distension or 0.0, shape=args.shape or "circle", **radius,
    )  # fmt: skip
    wio.write_frames(args.output, frames, truth.times_ms, truth.period_ms)
    if args.truth:
        try:
            pulsatile.write_truth(args.truth, truth)
        except BaseException:
            os.remove(args.output)  # the pair is written whole or not at all
            raise
    acq = frames[0]
    print(
        f"wrote {args.output}: {truth.frames[0].name} (Womersley number {truth.flow.womersley(1):.1f}), "
        f"{args.frames} frames over {truth.period_ms:g} ms, h = {args.h} mm, SNR {args.snr:g}, seed {args.seed}, "
        f"{acq.magnitude.shape[2]} x {acq.magnitude.shape[1]} voxels"
    )
    if args.truth:
        tau = truth.tau()
        print(f"wrote {args.truth}: exact WSS over the cycle ({tau.min():.3g} to {tau.max():.3g} Pa)")
    return 0


def _phantom_psf(args):
    """The k-space acquisition a phantom asks for (``--acquisition kspace``), or None for voxel means.

    A phantom has no data to choose a filter from: ``--kspace-filter auto`` acquires without one.
    """
    how = schema.from_args(AcquisitionOptions, args)
    psf = how.psf((args.h, args.h))
    return psf if psf is None or psf.filter != "auto" else dataclasses.replace(psf, filter="none")


def _acquired_text(psf) -> str:
    if psf is None:
        return "voxel means"
    return f"k-space acquisition, {psf.filter} filter, zero-filling {psf.zero_fill[1]:g} x {psf.zero_fill[0]:g}"


def _check_phantom_options(args) -> None:
    """Every physical option in its plausible range (:mod:`wss_nlp.io.ranges`), counts in theirs, and the images'
    memory, before anything is built; ``--snr`` 0 or below means noise-free."""
    allow = ranges.parse_allow(args.allow_unphysical) if args.allow_unphysical else ()
    notes = [ranges.check("voxel_size", args.h, "--h", allow)]
    if not np.isfinite(args.snr):
        raise InputError(f"--snr {args.snr}: must be a finite number (0 or below: no noise)")
    if args.snr > 0:
        notes.append(ranges.check("snr", args.snr, "--snr", allow))
    for name, value, flag in (("venc", args.venc, "--venc"), ("slice_spacing", args.spacing, "--spacing"),
                              ("radius", args.pipe_radius, "--pipe-radius")):  # fmt: skip
        if value is not None:
            notes.append(ranges.check(name, value, flag, allow))
    for flag, value, lo, hi in (("--nz", args.nz, 1, 500), ("--frames", args.frames, 1, 500)):
        if not lo <= value <= hi:
            raise InputError(f"{flag} {value}: must be a whole number in {lo}-{hi}")
    if args.swirl is not None and not (np.isfinite(args.swirl) and abs(args.swirl) <= 1000):
        raise InputError(f"--swirl {args.swirl}: must be a swirl rate in 1/s within +-1000")
    if args.distension is not None and not 0 <= args.distension < 0.3:
        raise InputError(f"--distension {args.distension}: must lie in [0, 0.3)")
    images = args.frames if args.case == "womersley" else (args.nz if args.stack else 1)
    half_fov = 2.0 * (args.pipe_radius or 10.0) if args.case == "womersley" else 25.0  # every case: 15-21 mm
    limits.check_phantom(half_fov, args.h, images, "--h")
    for note in notes:
        if note:
            print(f"wss-nlp: warning: {note}", file=sys.stderr)


def cmd_phantom(args) -> int:
    outputs.check_outputs(
        files={"-o": args.output, "--truth": args.truth}, folders={"--dicom": args.dicom, "--nifti": args.nifti}
    )
    _check_phantom_options(args)
    if args.case == "womersley":
        return _phantom_cine(args)
    cine_only = [f for f, v in (("--distension", args.distension), ("--shape", args.shape),
                                ("--pipe-radius", args.pipe_radius)) if v is not None]  # fmt: skip
    if cine_only:
        raise InputError(f"{', '.join(cine_only)}: only for --case womersley (the cine phantom)")
    snr = None if args.snr <= 0 else args.snr
    psf = _phantom_psf(args)
    truth: phantoms.Truth | phantoms.StackTruth
    if args.stack:
        acq, truth = phantoms.make_stack(
            args.stack,
            nz=args.nz,
            h_mm=args.h,
            spacing_mm=args.spacing,
            snr=snr,
            seed=args.seed,
            venc=args.venc,
            swirl_per_s=args.swirl,
            psf=psf,
        )
        args.case = f"{args.stack} stack ({args.nz} slices, {args.spacing:g} mm apart)"
    else:
        acq, truth = phantoms.make_phantom(
            args.case,
            h_mm=args.h,
            snr=snr,
            seed=args.seed,
            venc=args.venc,
            as_phase=not args.velocity,
            psf=psf,
        )
    peak = max(phantoms.peak_velocity(t.flow) for t in getattr(truth, "slices", [truth]))
    if acq.venc_m_s is not None and acq.venc_m_s < peak:
        print(
            f"wss-nlp: warning: venc {acq.venc_m_s:g} m/s is below the peak velocity {peak:.3g} m/s: the phase "
            "wraps (aliasing); 'reconstruct' unwraps it (or refuses it when it cannot)",
            file=sys.stderr,
        )
    with outputs.StagedFolder(args.dicom) as dcm, outputs.StagedFolder(args.nifti) as nii:
        if dcm.path or nii.path:  # the same images as a scanner exports them, for trying 'wss-nlp import'
            from ...synthetic import scanner_exports

            scan = scanner_exports.Scan(
                acq.magnitude,
                acq.velocity_images(),
                float(acq.venc_m_s or 1.25 * peak),
                acq.voxel_size_mm,
                acq.origin_mm,
                slice_spacing_mm=acq.slice_spacing_mm or 1.0,
                acquired_matrix=None
                if acq.acquired_voxel_size_mm is None
                else tuple(  # type: ignore[arg-type]
                    int(round(n * v / a))
                    for n, v, a in zip(acq.magnitude.shape[1:], acq.voxel_size_mm, acq.acquired_voxel_size_mm)
                ),
            )
            if dcm.path:
                scanner_exports.write_dicom(dcm.path, scan, args.vendor)
            if nii.path:
                scanner_exports.write_nifti(nii.path, scan)
        wio.write_acquisition(args.output, acq)
        if args.truth:
            try:
                _write_truth(args.truth, truth)
            except BaseException:
                os.remove(args.output)  # the pair is written whole or not at all
                raise
        dcm.commit()
        nii.commit()
    print(
        f"wrote {args.output}: {args.case}, h = {args.h} mm, SNR {args.snr:g}, seed {args.seed}, "
        f"{acq.magnitude.shape[2]} x {acq.magnitude.shape[1]} voxels ({_acquired_text(psf)})"
    )
    if args.truth:
        means = [t.mean_wss for t in getattr(truth, "slices", [truth])]
        print(f"wrote {args.truth}: exact radius and WSS (mean {min(means):.5g}-{max(means):.5g} Pa)")
    return 0
