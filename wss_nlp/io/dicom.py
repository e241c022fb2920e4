"""DICOM phase-contrast series in (``wss-nlp import``): images, geometry, trigger times and each vendor's venc.

Reads classic single-frame MR images and enhanced multi-frame MR images
(pydicom, an optional dependency: ``pip install 'wss-nlp[dicom]'``) into
:class:`~wss_nlp.io.scanner.Image2D` records; :func:`wss_nlp.io.scanner.assemble`
makes the acquisition.

Notes
-----
Standard attributes (DICOM PS3.3): Image Position (Patient) (0020,0032),
Image Orientation (Patient) (0020,0037) and Pixel Spacing (0028,0030) of the
Image Plane module (C.7.6.2) or, in enhanced images, the Plane Position,
Plane Orientation and Pixel Measures functional groups (C.7.6.16.2); Trigger
Time (0018,1060) or Nominal Cardiac Trigger Delay Time (0020,9153) of the
Cardiac Synchronization functional group; Nominal Interval (0018,1062) as the
R-R interval; Rescale Slope/Intercept (0028,1053/1052) (C.11.1) and the Real
World Value Mapping (0040,9096) (C.7.6.16.2.11) with its measurement units
(UCUM ``cm/s``, ``mm/s``, ``m/s``, ``rad``); Complex Image Component
(0008,9208) (MAGNITUDE, PHASE) and the MR Velocity Encoding Sequence
(0018,9197) with Velocity Encoding Maximum Value (0018,9217, cm/s) (C.8.13.5).

Vendor conventions for classic images, as the vendors' DICOM conformance
statements and the converters that implement them (dcm2niix) describe them:

* Siemens: Image Type value 3 ``M`` (magnitude) or ``P`` (phase); phase
  stored as ``BitsStored``-bit integers whose rescaled value ``v = s RS + RI``
  spans ``[-F, F)`` with ``F = RS 2^(BitsStored - 1)`` (12 bits, RS 2,
  RI -4096: F = 4096) for ``[-pi, pi)``: ``phase = pi v / F``. Venc from the
  Sequence Name (0018,0024), e.g. ``fl2d1_v150in``: 150 cm/s, ``in`` =
  through-plane (``rl``, ``ap``, ``fh`` are in-plane directions).
* Philips: Image Type with ``P`` (or ``PHASE``, ``VELOCITY MAP``) for the
  velocity image; the rescaled value is the velocity in cm/s (Rescale Type
  or the real-world value mapping's units say so when present). Venc from
  the private PC Velocity (2001,101A, cm/s, one value per direction) or the
  standard (0018,9217).
* GE: the private image type (0043,102F): 0 magnitude, 1 phase; the phase
  image holds velocity in mm/s; venc from the private (0019,10CC) in mm/s.
  Phase-difference images (VAS collapse flags (0043,1032) with bit 2 set)
  need a further private scale and are refused with a message.

A convention that cannot be confirmed from the headers is never guessed:
``--phase-units`` states it, or the error names the tag that is missing.
"""

from __future__ import annotations

import logging
import os
import re
import types

import numpy as np

from ..errors import InputError
from .scanner import Image2D

log = logging.getLogger(__name__)

#: Units a user may state for the phase images (``--phase-units``): their meaning for the stored values.
PHASE_UNITS = {
    "rad": "radians in [-pi, pi)",
    "siemens": "integers with Siemens's full scale F = RescaleSlope 2^(BitsStored - 1) for pi",
    "cm/s": "velocity in cm/s",
    "mm/s": "velocity in mm/s",
    "m/s": "velocity in m/s",
}
_VELOCITY_FACTOR = {"cm/s": 1e-2, "mm/s": 1e-3, "m/s": 1.0, "cm.s-1": 1e-2, "mm.s-1": 1e-3, "m.s-1": 1.0}

_SIEMENS_VENC = re.compile(r"_v(\d+(?:\.\d+)?)(in|rl|lr|ap|pa|fh|hf|through)\b", re.IGNORECASE)
_PHASE_TYPES = {"P", "PHASE", "PHASE MAP", "VELOCITY", "VELOCITY MAP", "PHASE CONTRAST P"}
_MAGNITUDE_TYPES = {"M", "MAG", "MAGNITUDE", "M_PCA", "M_FFE", "FFE_M", "M_SE", "NORM"}


def require_pydicom(what: str = "reading"):
    """The pydicom module, or an :class:`InputError` saying how to install it."""
    try:
        import pydicom
    except ImportError:
        raise InputError(f"{what} DICOM needs pydicom, an optional dependency: pip install 'wss-nlp[dicom]'") from None
    return pydicom


def find_files(paths) -> list[str]:
    """Files under ``paths`` (folders are searched recursively), sorted; a missing path is an error."""
    files = []
    for p in paths:
        p = os.fspath(p)
        if os.path.isdir(p):
            for root, dirs, names in os.walk(p):
                dirs.sort()
                files += [os.path.join(root, n) for n in sorted(names) if not n.startswith(".")]
        elif os.path.isfile(p):
            files.append(p)
        else:
            raise InputError(f"{p}: no such file or folder")
    return files


def vendor_of(ds) -> str:
    text = str(getattr(ds, "Manufacturer", "")).upper()
    for name in ("SIEMENS", "PHILIPS", "GE"):
        if name in text:
            return name.title() if name != "GE" else "GE"
    return text.strip().title()


def _private(ds, group: int, element: int):
    tag = (group << 16) | element
    return ds[tag].value if tag in ds else None


def _number(value, where: str, tag: str) -> float:
    try:
        return float(np.ravel(np.asarray(value, dtype=float))[0])
    except (TypeError, ValueError, IndexError):
        raise InputError(f"{where}: tag {tag} holds {value!r}, not a number") from None


def siemens_venc(sequence_name: str) -> tuple[float, str] | None:
    """``(venc in m/s, direction)`` from a Siemens sequence name like ``fl2d1_v150in``, or None."""
    m = _SIEMENS_VENC.search(sequence_name or "")
    if not m:
        return None
    return float(m.group(1)) / 100.0, m.group(2).lower()


def _role(ds, item, vendor: str, where: str) -> str | None:
    """``"magnitude"``, ``"phase"`` or None (neither: a localizer, a speed image, ...)."""
    component = getattr(item, "ComplexImageComponent", None) or getattr(ds, "ComplexImageComponent", None)
    if component:
        component = str(component).upper()
        return {"MAGNITUDE": "magnitude", "PHASE": "phase"}.get(component)
    if vendor == "GE":
        kind = _private(ds, 0x0043, 0x102F)
        if kind is not None:
            return {0: "magnitude", 1: "phase"}.get(int(_number(kind, where, "(0043,102F)")))
    types = getattr(item, "FrameType", None) or getattr(ds, "ImageType", None) or []
    tokens = {str(t).strip().upper() for t in types}
    if tokens & _PHASE_TYPES or any(t.startswith("P_") for t in tokens):
        return "phase"
    if tokens & _MAGNITUDE_TYPES:
        return "magnitude"
    return None


def _units_from_mapping(item) -> tuple[float, float, str] | None:
    """``(slope, intercept, units)`` of the first real-world value mapping with units we know."""
    for m in getattr(item, "RealWorldValueMappingSequence", None) or []:
        units = ""
        for code in getattr(m, "MeasurementUnitsCodeSequence", None) or []:
            units = str(getattr(code, "CodeValue", "")).strip()
        if units in _VELOCITY_FACTOR or units == "rad":
            slope = float(getattr(m, "RealWorldValueSlope", 1.0))
            intercept = float(getattr(m, "RealWorldValueIntercept", 0.0))
            return slope, intercept, units
    return None


def _phase_pixels(ds, item, stored: np.ndarray, vendor: str, where: str, units: str | None):
    """Pixels of a phase image in ``("rad" | "m/s")`` units, by the stated units or the vendor's convention."""
    slope = float(getattr(item, "RescaleSlope", getattr(ds, "RescaleSlope", 1.0)) or 1.0)
    intercept = float(getattr(item, "RescaleIntercept", getattr(ds, "RescaleIntercept", 0.0)) or 0.0)
    value = stored * slope + intercept
    if units is None:
        mapped = _units_from_mapping(item) or _units_from_mapping(ds)
        if mapped is not None:
            s, i, u = mapped
            value, units = stored * s + i, u
        elif vendor == "Siemens":
            units = "siemens"
        elif vendor == "Philips":
            rescale_type = str(getattr(item, "RescaleType", getattr(ds, "RescaleType", ""))).strip().lower()
            if rescale_type not in ("", "us", "cm/s", "cms", "cm/sec"):
                raise InputError(
                    f"{where}: Philips phase image with Rescale Type {rescale_type!r}, not a velocity in cm/s; "
                    "pass --phase-units to state what the rescaled values are"
                )
            units = "cm/s"
        elif vendor == "GE":
            flags = _private(ds, 0x0043, 0x1032)
            if flags is not None and int(_number(flags, where, "(0043,1032)")) & 2:
                raise InputError(
                    f"{where}: GE phase-difference image (VAS collapse flags (0043,1032) bit 2); export the "
                    "velocity images (or pass --phase-units for these values)"
                )
            units = "mm/s"
        else:
            raise InputError(
                f"{where}: no convention known for phase images of manufacturer {vendor or '(not stated)'!r} "
                "and no real-world value mapping; pass --phase-units (" + ", ".join(PHASE_UNITS) + ")"
            )
    if units == "siemens":
        bits = int(getattr(ds, "BitsStored", 12))
        full = slope * 2 ** (bits - 1)
        if not np.isclose(intercept, -full, rtol=1e-6):
            raise InputError(
                f"{where}: phase rescale intercept {intercept:g} (0028,1052) is not -{full:g} = -RescaleSlope "
                f"2^(BitsStored - 1) of Siemens's convention; pass --phase-units to state the units"
            )
        return to_physical(value, units, full, where)
    return to_physical(value, units, None, where)


def to_physical(value: np.ndarray, units: str, full_scale: float | None, where: str) -> tuple[np.ndarray, str]:
    """Phase values in ``units`` (one of :data:`PHASE_UNITS`) as ``(radians, "rad")`` or ``(m/s, "m/s")``.

    ``full_scale`` is the stored value that stands for pi (``siemens`` units only).
    """
    if units == "siemens" and full_scale:
        return np.pi * value / full_scale, "rad"
    if units == "rad":
        return value, "rad"
    if units in _VELOCITY_FACTOR:
        return value * _VELOCITY_FACTOR[units], "m/s"
    raise InputError(f"{where}: unknown phase units {units!r}; choose from {', '.join(PHASE_UNITS)}")


def _venc(ds, item, vendor: str, where: str) -> tuple[float | None, str]:
    """``(venc in m/s or None, which tag said so)`` from the standard sequence or the vendor's tag."""
    for holder in (item, ds):
        for enc in getattr(holder, "MRVelocityEncodingSequence", None) or []:
            vmax = getattr(enc, "VelocityEncodingMaximumValue", None)
            if vmax is not None:
                return abs(float(vmax)) / 100.0, "Velocity Encoding Maximum Value (0018,9217)"
    if vendor == "Siemens":
        found = siemens_venc(str(getattr(ds, "SequenceName", "")))
        if found is not None:
            venc, direction = found
            if direction not in ("in", "through"):
                raise InputError(
                    f"{where}: Sequence Name {ds.SequenceName!r} encodes the in-plane direction {direction!r}; "
                    "wss-nlp needs the through-plane velocity (an '_in' series), or --venc for this one"
                )
            return venc, f"Sequence Name (0018,0024) {str(ds.SequenceName)!r}"
    if vendor == "Philips":
        pc = _private(ds, 0x2001, 0x101A)
        if pc is not None:
            values = [abs(float(v)) for v in np.ravel(np.asarray(pc, dtype=float)) if float(v) != 0]
            if len(values) > 1:
                raise InputError(
                    f"{where}: PC Velocity (2001,101A) {list(values)} cm/s encodes several directions; import "
                    "one through-plane series or pass --venc"
                )
            if values:
                return values[0] / 100.0, "Philips PC Velocity (2001,101A)"
    if vendor == "GE":
        venc = _private(ds, 0x0019, 0x10CC)
        if venc is not None:
            return abs(_number(venc, where, "(0019,10CC)")) / 1000.0, "GE velocity encoding (0019,10CC)"
    return None, ""


def _plane(item, ds, where: str):
    """``(position, row_dir, col_dir, (dy, dx))`` from a functional-group item or the classic attributes."""

    def first(seq_name, attr):
        seq = getattr(item, seq_name, None) if item is not None else None
        if seq:
            return getattr(seq[0], attr, None)
        return None

    position = first("PlanePositionSequence", "ImagePositionPatient") or getattr(ds, "ImagePositionPatient", None)
    orientation = first("PlaneOrientationSequence", "ImageOrientationPatient") or getattr(
        ds, "ImageOrientationPatient", None
    )
    spacing = first("PixelMeasuresSequence", "PixelSpacing") or getattr(ds, "PixelSpacing", None)
    for name, tag, value in (
        ("Image Position (Patient)", "(0020,0032)", position),
        ("Image Orientation (Patient)", "(0020,0037)", orientation),
        ("Pixel Spacing", "(0028,0030)", spacing),
    ):
        if value is None:
            raise InputError(f"{where}: missing {name} {tag}; cannot place the image in space")
    assert orientation is not None and spacing is not None  # checked above
    o = np.asarray(orientation, dtype=float)
    dy, dx = (float(v) for v in spacing)
    if not (dy > 0 and dx > 0):
        raise InputError(f"{where}: Pixel Spacing (0028,0030) must be positive, got {list(spacing)}")
    return np.asarray(position, dtype=float), o[:3], o[3:6], (dy, dx)


def _trigger(item, ds) -> float | None:
    if item is not None:
        for sync in getattr(item, "CardiacSynchronizationSequence", None) or []:
            t = getattr(sync, "NominalCardiacTriggerDelayTime", None)
            if t is not None:
                return float(t)
    t = getattr(ds, "TriggerTime", None)
    return None if t is None or t == "" else float(t)


def _group(ds, index: int, name: str):
    """The functional-group item holding ``name`` for frame ``index`` (per-frame first, then shared)."""
    per_frame = getattr(ds, "PerFrameFunctionalGroupsSequence", None)
    if per_frame and index < len(per_frame) and name in per_frame[index]:
        return per_frame[index]
    shared = getattr(ds, "SharedFunctionalGroupsSequence", None)
    if shared and name in shared[0]:
        return shared[0]
    return None


_FRAME_SEQUENCES = (
    "PlanePositionSequence",
    "PlaneOrientationSequence",
    "PixelMeasuresSequence",
    "CardiacSynchronizationSequence",
    "MRVelocityEncodingSequence",
    "RealWorldValueMappingSequence",
    "MRFOVGeometrySequence",
)
_FRAME_VALUES = {
    "MRImageFrameTypeSequence": ("FrameType", "ComplexImageComponent"),
    "PixelValueTransformationSequence": ("RescaleSlope", "RescaleIntercept", "RescaleType"),
}


def _frame_view(ds, index: int) -> types.SimpleNamespace:
    """Frame ``index`` of an enhanced image as one flat record of the attributes the readers use."""
    view = types.SimpleNamespace()
    for name in _FRAME_SEQUENCES:
        item = _group(ds, index, name)
        setattr(view, name, None if item is None else getattr(item, name))
    for name, attrs in _FRAME_VALUES.items():
        item = _group(ds, index, name)
        if item is not None:
            for attr in attrs:
                value = getattr(getattr(item, name)[0], attr, None)
                if value is not None:
                    setattr(view, attr, value)
    return view


def acquired_matrix(ds, item, where: str) -> tuple[int, int] | None:
    """``(ny, nx)`` k-space samples of the acquisition along the image's columns and rows, or None if not stated.

    Classic images: Acquisition Matrix (0018,1310) ``[frequency rows, frequency columns, phase rows, phase
    columns]``, of which one frequency and one phase value are non-zero: ``[Nf, 0, 0, Np]`` is phase encoding
    along the columns (In-plane Phase Encoding Direction COL: ``Np`` samples down a column, ``Nf`` along a
    row), ``[0, Nf, Np, 0]`` along the rows. Enhanced images: MR FOV/Geometry Sequence (0018,9107) with MR
    Acquisition Frequency Encoding Steps (0018,9058), MR Acquisition Phase Encoding Steps in-plane (0018,9231)
    and In-plane Phase Encoding Direction. Partial-Fourier and parallel-imaging details are not modelled.
    """
    fov = getattr(item, "MRFOVGeometrySequence", None) if item is not None else None
    if fov:
        geo = fov[0]
        nf = getattr(geo, "MRAcquisitionFrequencyEncodingSteps", None)
        npe = getattr(geo, "MRAcquisitionPhaseEncodingStepsInPlane", None)
        direction = str(getattr(geo, "InPlanePhaseEncodingDirection", "")).upper()
        if not nf or not npe or direction not in ("ROW", "COL", "COLUMN"):
            return None
        return (int(npe), int(nf)) if direction.startswith("COL") else (int(nf), int(npe))
    matrix = getattr(ds, "AcquisitionMatrix", None)
    if matrix is None or len(matrix) != 4:
        return None
    fr, fc, pr, pc = (int(v) for v in matrix)
    if fr and pc and not (fc or pr):
        return pc, fr  # phase encoding down the columns
    if fc and pr and not (fr or pc):
        return fc, pr
    log.info("%s: Acquisition Matrix %s has no one frequency and one phase value; acquired size unknown", where, matrix)
    return None


def images_from_dataset(ds, path: str, phase_units: str | None = None) -> list[Image2D]:
    """The magnitude and phase images of one DICOM dataset (one image, or every frame of an enhanced image)."""
    vendor = vendor_of(ds)
    series = f"{getattr(ds, 'SeriesNumber', '?')} {str(getattr(ds, 'SeriesDescription', '')).strip()}".strip()
    period = getattr(ds, "NominalInterval", None)
    if period in (None, "", 0) and "PerFrameFunctionalGroupsSequence" in ds:
        sync = _frame_view(ds, 0).CardiacSynchronizationSequence
        period = getattr(sync[0], "RRIntervalTimeNominal", None) if sync else None
    period_ms = float(period) if period not in (None, "", 0) else None
    try:
        pixels = np.asarray(ds.pixel_array, dtype=float)
    except Exception as exc:  # pydicom raises several types for missing/compressed pixel data
        raise InputError(f"{path}: cannot read the pixel data ({type(exc).__name__}: {exc})") from None
    enhanced = "PerFrameFunctionalGroupsSequence" in ds
    frames = pixels if enhanced and pixels.ndim == 3 else pixels[None]
    out = []
    for k, stored in enumerate(frames):
        where = f"{path} (frame {k + 1})" if enhanced else path
        item = _frame_view(ds, k) if enhanced else None
        role = _role(ds, item if item is not None else ds, vendor, where)
        if role is None:
            continue
        position, row_dir, col_dir, spacing = _plane(item, ds, where)
        image = Image2D(
            where=where,
            role=role,
            pixels=stored,
            units="",
            position=position,
            row_dir=row_dir,
            col_dir=col_dir,
            spacing=spacing,
            trigger_ms=_trigger(item, ds),
            series=series,
            series_uid=str(getattr(ds, "SeriesInstanceUID", series)),
            vendor=vendor,
            period_ms=period_ms,
            acquired_matrix=acquired_matrix(ds, item, where),
        )
        if role == "phase":
            holder = item if item is not None else ds
            image.pixels, image.units = _phase_pixels(ds, holder, stored, vendor, where, phase_units)
            image.venc_m_s, image.venc_source = _venc(ds, holder, vendor, where)
        else:
            slope = float(getattr(ds, "RescaleSlope", 1.0) or 1.0)
            image.pixels = stored * slope + float(getattr(ds, "RescaleIntercept", 0.0) or 0.0)
        out.append(image)
    return out


def read_images(paths, phase_units: str | None = None) -> tuple[list[Image2D], dict]:
    """Every magnitude and phase image under ``paths`` and a record of what was read and skipped."""
    pydicom = require_pydicom()
    files = find_files(paths)
    images: list[Image2D] = []
    skipped: list[str] = []
    not_dicom: list[str] = []
    enhanced = 0  # enhanced multi-frame files among them: the summary names the kind, not only the manufacturer
    for path in files:
        try:
            ds = pydicom.dcmread(path)
        except Exception:  # not DICOM (pydicom raises InvalidDicomError and others)
            if any(os.path.samefile(path, p) for p in paths if os.path.isfile(p)):
                raise InputError(f"{path}: not a DICOM file (give a DICOM file or a folder of them)") from None
            not_dicom.append(path)
            continue
        if "PixelData" not in ds:
            skipped.append(f"{path} (no image)")
            continue
        found = images_from_dataset(ds, path, phase_units)
        enhanced += bool(found) and "PerFrameFunctionalGroupsSequence" in ds
        if not found:
            skipped.append(f"{path} (Image Type {list(getattr(ds, 'ImageType', []))}: neither magnitude nor phase)")
        images += found
    if skipped:
        log.warning("skipped %d DICOM file(s) that hold no magnitude or phase image, e.g. %s", len(skipped), skipped[0])
    if not_dicom:
        log.info("ignored %d file(s) that are not DICOM, e.g. %s", len(not_dicom), not_dicom[0])
    if not images:
        raise InputError(
            f"{', '.join(map(str, paths))}: no DICOM magnitude or phase images found"
            + (f" ({len(files)} files; e.g. {skipped[0]})" if skipped else f" ({len(files)} files)")
        )
    kind = "DICOM" if not enhanced else "DICOM enhanced multi-frame" if enhanced == len(files) else "DICOM (mixed)"
    record = {"format": kind, "paths": [str(p) for p in paths], "files": len(files), "skipped": skipped[:20]}
    return images, record
