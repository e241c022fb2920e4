"""``wss-nlp phantom``: synthetic acquisitions (and their truth) written as input files or scanner exports."""

from __future__ import annotations

import logging
import dataclasses
import os
import numpy as np
from ...io import files as wio
from ...analysis import metrics
from ...io import outputs, ranges
from ...pipeline import limits
from ...synthetic import invivo, phantoms
from ...core import schema
from ...errors import InputError
from ...models.kspace import AcquisitionOptions

log = logging.getLogger(__name__)  # warnings: the command line shows them once per kind (main)


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
def _scanner_exports(args, frames, dicom_folder, nifti_folder, peak: float, times_ms=None, period_ms=None):
    """The images of ``frames`` (one acquisition, or a cine series' frames) as a scanner exports them.

    DICOM in ``args.vendor``'s convention into ``dicom_folder`` and NIfTI with dcm2niix-style sidecars into
    ``nifti_folder`` (either may be None); returns the two lists of files written.
    """
    if not (dicom_folder or nifti_folder):
        return [], []
    from ...synthetic import scanner_exports

    acq = frames[0]
    scan = scanner_exports.Scan(
        np.stack([a.magnitude for a in frames]),
        np.stack([a.velocity_images() for a in frames]),
        float(acq.venc_m_s or 1.25 * peak),
        acq.voxel_size_mm,
        acq.origin_mm,
        slice_spacing_mm=acq.slice_spacing_mm or 1.0,
        trigger_times_ms=None if times_ms is None else tuple(float(t) for t in times_ms),
        cardiac_period_ms=period_ms,
        acquired_matrix=None
        if acq.acquired_voxel_size_mm is None
        else tuple(  # type: ignore[arg-type]
            int(round(n * v / a))
            for n, v, a in zip(acq.magnitude.shape[1:], acq.voxel_size_mm, acq.acquired_voxel_size_mm)
        ),
    )
    dicom = scanner_exports.write_dicom(dicom_folder, scan, args.vendor) if dicom_folder else []
    interval = None if times_ms is None or len(times_ms) < 2 else float(np.median(np.diff(times_ms)))
    nifti = scanner_exports.write_nifti(nifti_folder, scan, interval) if nifti_folder else []
    return dicom, nifti


def _report_exports(args, written_dicom, written_nifti) -> None:
    """One line per scanner export: what was written and how to read it back."""
    if args.dicom:
        kind = "one enhanced multi-frame file" if args.vendor == "enhanced" else f"{len(written_dicom)} files"
        print(
            f"wrote {args.dicom}: the same images as DICOM, {args.vendor} convention, {kind} "
            f"(read back: wss-nlp import {args.dicom} -o FILE.h5)"
        )
    if args.nifti:
        names = ", ".join(os.path.basename(p) for p in written_nifti)
        print(f"wrote {args.nifti}: the same images as NIfTI with JSON sidecars: {names} "
              f"(read back: wss-nlp import {args.nifti} -o FILE.h5)")  # fmt: skip


def _phantom_volume(args) -> int:
    """A 4D-flow volume (a tilted tube, three velocity components, two frames) as NIfTI files, and its truth."""
    from ...synthetic import scanner_exports

    if not args.nifti or args.dicom or args.stack or args.case != "laminar":
        raise InputError("--volume writes NIfTI files only: give --nifti FOLDER (no --dicom, --stack or --case)")
    snr = None if args.snr <= 0 else args.snr
    volume = scanner_exports.make_flow_volume(seed=args.seed, snr=snr)
    with outputs.StagedFolder(args.nifti) as nii:
        written = scanner_exports.write_flow_volume(str(nii.path), volume)
        nii.commit()
    p, a = volume.center, volume.axis
    fov = round(4.4 * volume.radius_mm)  # the lumen and a margin of 1.2 radii each side, inside the volume
    n = volume.magnitude.shape
    print(
        f"wrote {args.nifti}: a 4D-flow volume as NIfTI ({', '.join(os.path.basename(f) for f in written)}): "
        f"{n[0]} x {n[1]} x {n[2]} voxels, {n[3]} frames, a tube of radius {volume.radius_mm:g} mm, SNR {args.snr:g}, "
        f"seed {args.seed}; exact WSS per frame " + ", ".join(f"{volume.wss_pa(it):.4g}" for it in range(n[3])) + " Pa"
    )
    print(
        "cut it perpendicular to the tube: wss-nlp import "
        f"{args.nifti} -o plane.h5 --plane {p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {a[0]:.5f} {a[1]:.5f} {a[2]:.5f} "
        f"--plane-fov {fov:g} --phase-units m/s --viscosity {volume.viscosity_pa_s:g}"
    )
    return 0


def _phantom_cine(args) -> int:
    from ...synthetic import pulsatile

    if args.stack:
        raise InputError("--case cine is one time-resolved slice; --stack does not apply")
    if args.pipe_radius is not None and not args.pipe_radius > 0:
        raise InputError(f"--pipe-radius must be > 0 mm, got {args.pipe_radius}")
    snr = None if args.snr <= 0 else args.snr
    radius = {} if args.pipe_radius is None else {"radius_mm": args.pipe_radius}
    frames, truth = pulsatile.make_cine(
        h_mm=args.h, snr=snr, seed=args.seed, frames=args.frames, venc=args.venc, psf=_phantom_psf(args),
        distension=args.distension or 0.0, shape=args.shape or "circle", **radius,
    )  # fmt: skip
    with outputs.StagedFolder(args.dicom) as dcm, outputs.StagedFolder(args.nifti) as nii:
        written_dicom, written_nifti = _scanner_exports(  # the frames carry their venc: no peak needed
            args, frames, dcm.path, nii.path, 1.0, truth.times_ms, truth.period_ms
        )
        wio.write_frames(args.output, frames, truth.times_ms, truth.period_ms)
        if args.truth:
            try:
                pulsatile.write_truth(args.truth, truth)
            except BaseException:
                os.remove(args.output)  # the pair is written whole or not at all
                raise
        dcm.commit()
        nii.commit()
    acq = frames[0]
    print(
        f"wrote {args.output}: {truth.frames[0].name} (Womersley number {truth.flow.womersley(1):.1f}), "
        f"{args.frames} frames over {truth.period_ms:g} ms, h = {args.h} mm, SNR {args.snr:g}, seed {args.seed}, "
        f"{acq.magnitude.shape[2]} x {acq.magnitude.shape[1]} voxels"
    )
    if args.truth:
        tau = truth.tau()
        print(f"wrote {args.truth}: exact WSS over the cycle ({tau.min():.3g} to {tau.max():.3g} Pa)")
    _report_exports(args, written_dicom, written_nifti)
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


def _allowed(args) -> tuple[str, ...]:
    return ranges.parse_allow(args.allow_unphysical) if args.allow_unphysical else ()


def _voxel_and_noise_notes(args, allow) -> list:
    """``--h`` and ``--snr`` in their plausible ranges (every phantom has both): the range notes; ``--snr`` 0 or
    below means noise-free, a value that is not a finite number is refused."""
    notes = [ranges.check("voxel_size", args.h, "--h", allow)]
    if not np.isfinite(args.snr):
        raise InputError(f"--snr {args.snr}: must be a finite number (0 or below: no noise)")
    if args.snr > 0:
        notes.append(ranges.check("snr", args.snr, "--snr", allow))
    return notes


def _check_phantom_options(args) -> None:
    """Every physical option in its plausible range (:mod:`wss_nlp.io.ranges`), counts in theirs, and the images'
    memory, before anything is built; ``--snr`` 0 or below means noise-free."""
    allow = _allowed(args)
    notes = _voxel_and_noise_notes(args, allow)
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
    images = args.frames if args.case == "cine" else (args.nz if args.stack else 1)
    half_fov = 2.0 * (args.pipe_radius or 10.0) if args.case == "cine" else 25.0  # every case: 15-21 mm
    limits.check_phantom(half_fov, args.h, images, "--h")
    for note in notes:
        if note:
            log.warning(note)


def _phantom_vessel(args) -> int:
    """A whole-vessel 4D-flow phantom (:func:`wss_nlp.synthetic.vessels.make_vessel_phantom`): the volume as an
    input file and/or NIfTI files, and its truth file."""
    from ...io.volume import write_volume
    from ...synthetic import vessels

    wrong = [f for f, given in (("--dicom", args.dicom), ("--stack", args.stack), ("--volume", args.volume),
                                ("--case", args.case != "laminar"), ("--venc", args.venc is not None),
                                ("--velocity", args.velocity)) if given]  # fmt: skip
    if wrong:
        raise InputError(f"{', '.join(wrong)}: not with --volume-case (a vessel phantom sets its own venc; write it "
                         "with -o FILE.h5 and/or --nifti FOLDER)")  # fmt: skip
    if not (args.output or args.nifti):
        raise InputError("--volume-case: name where the volume goes (-o FILE.h5 and/or --nifti FOLDER)")
    notes = _voxel_and_noise_notes(args, _allowed(args))
    frames = args.frames if args.volume_case == "pulsatile" else 1
    if not 1 <= frames <= 100:
        raise InputError(f"--frames {frames}: a vessel phantom takes 1-100 frames")
    for note in notes:
        if note:
            log.warning(note)
    snr = None if args.snr <= 0 else args.snr
    vol, truth = vessels.make_vessel_phantom(
        args.volume_case, h_mm=args.h, snr=snr, seed=args.seed, tissue=args.tissue, frames=frames
    )
    with outputs.StagedFolder(args.nifti) as nii:
        written = vessels.write_volume_nifti(str(nii.path), vol) if args.nifti else []
        try:
            if args.output:
                write_volume(args.output, vol)
            if args.truth:
                # the wall a reconstruction maps may reach past the visible part: sample the truth 20 mm beyond it
                lo, hi = min(v[0] for v in truth.visible), max(v[1] for v in truth.visible)
                lo, hi = lo - 20.0, hi + 20.0
                if truth.vessel.capped:  # the lumen ends with the centreline
                    lo, hi = max(lo, 0.0), min(hi, truth.vessel.centreline.length)
                s_mm = np.arange(lo, hi + 0.25, 0.5)
                truth.write_truth(args.truth, s_mm=s_mm)
        except BaseException:
            for path in (args.output, args.truth):
                if path and os.path.exists(path):
                    os.remove(path)  # written whole or not at all
            raise
        nii.commit()
    n = vol.shape
    print(f"wrote {args.output or args.nifti}: {args.volume_case} vessel ({vessels.CASES[args.volume_case][1]}), "
          f"{n[0]} x {n[1]} x {n[2]} voxels of {args.h:g} mm, {vol.nt} frame(s), SNR {args.snr:g}, seed {args.seed}"
          + (", tissue around the lumen" if args.tissue else ""))  # fmt: skip
    if written:
        print(f"wrote {args.nifti}: {', '.join(os.path.basename(f) for f in written if f.endswith('.gz'))} (read back: "
              f"wss-nlp import {' '.join(os.path.basename(f) for f in written if f.endswith('.gz'))} -o exam.h5 "
              f"--phase-units m/s --viscosity {truth.viscosity_pa_s:g})")  # fmt: skip
    if args.truth:
        print(f"wrote {args.truth}: the exact wall and WSS vectors (for wss-nlp compare RESULT {args.truth})")
    return 0


def cmd_phantom(args) -> int:
    outputs.check_outputs(
        files={"-o": args.output, "--truth": args.truth}, folders={"--dicom": args.dicom, "--nifti": args.nifti}
    )
    if args.h is None:
        args.h = 2.0 if args.volume_case else 1.0
    if args.volume_case:
        return _phantom_vessel(args)
    if args.tissue:
        raise InputError("--tissue: only for --volume-case (the in-vivo slices are --case invivo)")
    if args.volume:
        return _phantom_volume(args)
    if args.output is None:
        raise InputError("phantom: name the input file to write (-o FILE.h5)")
    _check_phantom_options(args)
    if args.case == "cine":
        return _phantom_cine(args)
    cine_only = [f for f, v in (("--distension", args.distension), ("--shape", args.shape),
                                ("--pipe-radius", args.pipe_radius)) if v is not None]  # fmt: skip
    if cine_only:
        raise InputError(f"{', '.join(cine_only)}: only for --case cine (the time-resolved phantom)")
    snr = None if args.snr <= 0 else args.snr
    tissue = args.case in invivo.INVIVO_CASES and not args.stack
    if tissue:  # the in-vivo scene sets its own venc (1.25 x its peak) and is sampled on the voxels (box model)
        kspace = schema.from_args(AcquisitionOptions, args).model == "kspace"
        fixed = [f for f, given in (("--venc", args.venc is not None), ("--velocity", args.velocity),
                                    ("--acquisition kspace", kspace)) if given]  # fmt: skip
        if fixed:
            raise InputError(f"{', '.join(fixed)}: not for the in-vivo cases ({args.case}), which set the venc and "
                             "the voxel model themselves; leave them out or choose a phantom in air")  # fmt: skip
    psf = None if tissue else _phantom_psf(args)
    truth: phantoms.Truth | phantoms.StackTruth
    if tissue:
        acq, truth = invivo.make_case(args.case, h_mm=args.h, snr=snr, seed=args.seed)
    elif args.stack:
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
        log.warning(
            f"venc {acq.venc_m_s:g} m/s is below the peak velocity {peak:.3g} m/s: the phase wraps (aliasing); "
            "'reconstruct' unwraps it (or refuses it when it cannot)"
        )
    with outputs.StagedFolder(args.dicom) as dcm, outputs.StagedFolder(args.nifti) as nii:
        written_dicom, written_nifti = _scanner_exports(args, [acq], dcm.path, nii.path, peak)
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
    _report_exports(args, written_dicom, written_nifti)
    return 0
