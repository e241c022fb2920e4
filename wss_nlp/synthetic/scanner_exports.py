"""Phantom images written the way scanners export them (DICOM by vendor convention, NIfTI with a sidecar).

For trying ``wss-nlp import`` without scanner data and for its tests:
``wss-nlp phantom --dicom FOLDER --vendor siemens`` writes one phantom as a
scanner would, so that import followed by reconstruct can be checked against
the phantom's truth. Each writer follows the convention its reader
(:mod:`wss_nlp.io.dicom`, :mod:`wss_nlp.io.nifti`) documents, storing integers as the
scanners do (12-bit phase, velocity in cm/s or mm/s), so the imported images
differ from the phantom's by the quantization only.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np

from ..io.dicom import require_pydicom
from ..errors import InputError
from ..io.nifti import require_nibabel

VENDORS = ("siemens", "philips", "ge", "enhanced")
MR_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.4"
ENHANCED_MR_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.4.1"
#: Magnitude images are stored as integers up to this value.
MAGNITUDE_FULL_SCALE = 4000.0


@dataclass
class Scan:
    """Images ``(nt, nz, ny, nx)`` (magnitude, velocity in m/s) and where they lie in patient coordinates."""

    magnitude: np.ndarray
    velocity: np.ndarray
    venc_m_s: float
    voxel_size_mm: tuple[float, float]
    origin_mm: tuple[float, float] = (0.0, 0.0)
    slice_spacing_mm: float = 1.0
    row_dir: tuple[float, float, float] = (1.0, 0.0, 0.0)
    col_dir: tuple[float, float, float] = (0.0, 1.0, 0.0)
    trigger_times_ms: tuple[float, ...] | None = None
    cardiac_period_ms: float | None = None
    acquired_matrix: tuple[int, int] | None = None  # (ny, nx) k-space samples (phase encoding down the columns)

    def __post_init__(self):
        self.magnitude = np.asarray(self.magnitude, dtype=float)
        self.velocity = np.asarray(self.velocity, dtype=float)
        for name in ("magnitude", "velocity"):
            arr = getattr(self, name)
            if arr.ndim == 3:
                setattr(self, name, arr[None])
        if self.magnitude.shape != self.velocity.shape or self.magnitude.ndim != 4:
            raise InputError(f"Scan: magnitude {self.magnitude.shape} and velocity {self.velocity.shape} differ")

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.row_dir, self.col_dir)

    def position(self, iz: int) -> np.ndarray:
        """Patient coordinates of voxel (0, 0) of slice ``iz`` (mm)."""
        r, c = np.asarray(self.row_dir), np.asarray(self.col_dir)
        return self.origin_mm[0] * r + self.origin_mm[1] * c + iz * self.slice_spacing_mm * self.normal

    def trigger(self, it: int) -> float | None:
        return None if self.trigger_times_ms is None else float(self.trigger_times_ms[it])


def _base(sop_class: str, series_uid: str, number: int, description: str, manufacturer: str):
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import UID, ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(sop_class)
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset(f"{description}.dcm", {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "MR"
    ds.Manufacturer = manufacturer
    ds.SeriesInstanceUID = series_uid
    ds.SeriesNumber = number
    ds.SeriesDescription = description
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = 16
    return ds


def _pixels(ds, stored: np.ndarray, bits: int, signed: bool) -> None:
    ds.Rows, ds.Columns = stored.shape[-2:]
    ds.BitsStored, ds.HighBit, ds.PixelRepresentation = bits, bits - 1, int(signed)
    ds.PixelData = stored.astype(np.int16 if signed else np.uint16).tobytes()


def _plane(ds, scan: Scan, iz: int) -> None:
    ds.ImagePositionPatient = [float(v) for v in scan.position(iz)]
    ds.ImageOrientationPatient = [float(v) for v in (*scan.row_dir, *scan.col_dir)]
    ds.PixelSpacing = [float(scan.voxel_size_mm[0]), float(scan.voxel_size_mm[1])]
    ds.SliceThickness = float(scan.slice_spacing_mm)
    if scan.acquired_matrix is not None:  # [frequency rows, frequency columns, phase rows, phase columns]
        ds.AcquisitionMatrix = [int(scan.acquired_matrix[1]), 0, 0, int(scan.acquired_matrix[0])]
        ds.InPlanePhaseEncodingDirection = "COL"


def stored_magnitude(scan: Scan) -> tuple[np.ndarray, float]:
    """Magnitude as unsigned integers and the factor that made them."""
    scale = MAGNITUDE_FULL_SCALE / max(float(scan.magnitude.max()), 1e-300)
    return np.round(scan.magnitude * scale).astype(np.int64), scale


def stored_phase(scan: Scan, vendor: str) -> tuple[np.ndarray, float, float]:
    """``(stored integers, RescaleSlope, RescaleIntercept)`` of the phase images in the vendor's convention."""
    v = scan.velocity
    if vendor == "siemens":  # 12 bits, value = 2 stored - 4096 spans [-4096, 4094] for [-pi, pi)
        value = 4096.0 * v / scan.venc_m_s
        return np.clip(np.round((value + 4096.0) / 2.0), 0, 4095).astype(np.int64), 2.0, -4096.0
    if vendor in ("philips", "enhanced"):  # velocity in cm/s over 12 bits
        venc_cm = 100.0 * scan.venc_m_s
        slope = 2.0 * venc_cm / 4095.0
        return np.clip(np.round((100.0 * v + venc_cm) / slope), 0, 4095).astype(np.int64), slope, -venc_cm
    if vendor == "ge":  # signed velocity in mm/s
        return np.round(1000.0 * v).astype(np.int64), 1.0, 0.0
    raise InputError(f"unknown vendor {vendor!r}; choose from {', '.join(VENDORS)}")


def write_dicom(folder: str, scan: Scan, vendor: str = "siemens") -> list[str]:
    """Write ``scan`` as DICOM files of one vendor's convention into ``folder``; returns the files."""
    require_pydicom("writing")
    from pydicom.uid import generate_uid

    if vendor not in VENDORS:
        raise InputError(f"unknown vendor {vendor!r}; choose from {', '.join(VENDORS)}")
    os.makedirs(folder, exist_ok=True)
    mag, _ = stored_magnitude(scan)
    phase, slope, intercept = stored_phase(scan, vendor)
    if vendor == "enhanced":
        return [_write_enhanced(folder, scan, mag, phase, slope, intercept)]
    files = []
    nt, nz = scan.magnitude.shape[:2]
    manufacturer = {"siemens": "SIEMENS", "philips": "Philips Medical Systems", "ge": "GE MEDICAL SYSTEMS"}[vendor]
    venc_cm = 100.0 * scan.venc_m_s
    for role, number in (("magnitude", 1), ("phase", 2)):
        uid = generate_uid()
        for iz in range(nz):
            for it in range(nt):
                ds = _base(MR_IMAGE_STORAGE, uid, number, f"pc {role}", manufacturer)
                ds.InstanceNumber = 1 + it + nt * iz
                _plane(ds, scan, iz)
                if scan.trigger_times_ms is not None:
                    ds.TriggerTime = scan.trigger(it)
                if scan.cardiac_period_ms is not None:
                    ds.NominalInterval = int(round(scan.cardiac_period_ms))
                if role == "magnitude":
                    _pixels(ds, mag[it, iz], 16, False)
                    kind = {"siemens": "M", "philips": "M", "ge": "OTHER"}[vendor]
                else:
                    _pixels(ds, phase[it, iz], 12 if vendor != "ge" else 16, vendor == "ge")
                    ds.RescaleSlope, ds.RescaleIntercept = f"{slope:.10g}", f"{intercept:.10g}"
                    kind = {"siemens": "P", "philips": "P", "ge": "OTHER"}[vendor]
                ds.ImageType = ["ORIGINAL", "PRIMARY", kind, "ND"]
                if vendor == "siemens":
                    ds.SequenceName = f"fl2d1_v{venc_cm:g}in"
                elif vendor == "philips":
                    ds.ImageType = ["ORIGINAL", "PRIMARY", "M_PCA" if role == "magnitude" else "VELOCITY MAP", kind]
                    block = ds.private_block(0x2001, "Philips Imaging DD 001", create=True)
                    block.add_new(0x1A, "FL", [0.0, 0.0, float(venc_cm)])
                elif vendor == "ge":
                    block = ds.private_block(0x0043, "GEMS_PARM_01", create=True)
                    block.add_new(0x2F, "SS", 0 if role == "magnitude" else 1)
                    acq = ds.private_block(0x0019, "GEMS_ACQU_01", create=True)
                    acq.add_new(0xCC, "DS", f"{1000.0 * scan.venc_m_s:g}")
                name = os.path.join(folder, f"{role[:3]}_{iz:03d}_{it:03d}.dcm")
                ds.save_as(name, enforce_file_format=True)
                files.append(name)
    return files


def _write_enhanced(folder, scan: Scan, mag, phase, slope, intercept) -> str:
    """One enhanced MR multi-frame file holding both series (standard tags only)."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence
    from pydicom.uid import generate_uid

    def item(**kw):
        d = Dataset()
        for k, v in kw.items():
            setattr(d, k, v)
        return d

    ds = _base(ENHANCED_MR_IMAGE_STORAGE, generate_uid(), 1, "pc enhanced", "SIEMENS")
    ds.ImageType = ["ORIGINAL", "PRIMARY", "VELOCITY", "NONE"]
    units = item(CodeValue="cm/s", CodingSchemeDesignator="UCUM", CodeMeaning="centimeter per second")
    shared = item(
        PixelMeasuresSequence=Sequence(
            [item(PixelSpacing=[float(v) for v in scan.voxel_size_mm], SliceThickness=scan.slice_spacing_mm)]
        ),
        PlaneOrientationSequence=Sequence(
            [item(ImageOrientationPatient=[float(v) for v in (*scan.row_dir, *scan.col_dir)])]
        ),
        MRVelocityEncodingSequence=Sequence(
            [
                item(
                    VelocityEncodingDirection=[0.0, 0.0, 1.0],
                    VelocityEncodingMinimumValue=-100.0 * scan.venc_m_s,
                    VelocityEncodingMaximumValue=100.0 * scan.venc_m_s,
                )
            ]
        ),
    )
    frames, stored = [], []
    nt, nz = scan.magnitude.shape[:2]
    for role in ("magnitude", "phase"):
        for iz in range(nz):
            for it in range(nt):
                fg = item(
                    PlanePositionSequence=Sequence([item(ImagePositionPatient=[float(v) for v in scan.position(iz)])]),
                    MRImageFrameTypeSequence=Sequence(
                        [
                            item(
                                FrameType=["ORIGINAL", "PRIMARY", "VELOCITY", "NONE"],
                                ComplexImageComponent=role.upper(),
                            )
                        ]
                    ),
                )
                if scan.trigger_times_ms is not None:
                    sync = item(NominalCardiacTriggerDelayTime=scan.trigger(it))
                    if scan.cardiac_period_ms is not None:
                        sync.RRIntervalTimeNominal = float(scan.cardiac_period_ms)
                    fg.CardiacSynchronizationSequence = Sequence([sync])
                if role == "phase":
                    fg.RealWorldValueMappingSequence = Sequence(
                        [
                            item(
                                RealWorldValueSlope=float(slope),
                                RealWorldValueIntercept=float(intercept),
                                LUTLabel="velocity",
                                MeasurementUnitsCodeSequence=Sequence([units]),
                            )
                        ]
                    )
                    stored.append(phase[it, iz])
                else:
                    stored.append(mag[it, iz])
                frames.append(fg)
    if scan.acquired_matrix is not None:
        shared.MRFOVGeometrySequence = Sequence(
            [
                item(
                    InPlanePhaseEncodingDirection="COLUMN",
                    MRAcquisitionFrequencyEncodingSteps=int(scan.acquired_matrix[1]),
                    MRAcquisitionPhaseEncodingStepsInPlane=int(scan.acquired_matrix[0]),
                )
            ]
        )
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.NumberOfFrames = len(frames)
    _pixels(ds, np.stack(stored), 16, False)
    name = os.path.join(folder, "enhanced.dcm")
    ds.save_as(name, enforce_file_format=True)
    return name


def write_nifti(folder: str, scan: Scan, frame_interval_ms: float | None = None) -> list[str]:
    """Write ``scan`` as dcm2niix does for Siemens: ``mag.nii.gz`` and ``phase_ph.nii.gz`` with JSON sidecars."""
    os.makedirs(folder, exist_ok=True)
    dy, dx = scan.voxel_size_mm
    affine = np.eye(4)
    affine[:3, 0] = dx * np.asarray(scan.row_dir)
    affine[:3, 1] = dy * np.asarray(scan.col_dir)
    affine[:3, 2] = scan.slice_spacing_mm * scan.normal
    affine[:3, 3] = scan.position(0)
    mag, _ = stored_magnitude(scan)
    phase, slope, intercept = stored_phase(scan, "siemens")
    files = []
    for name, stored, image_type, scl in (
        ("mag", mag, ["ORIGINAL", "PRIMARY", "M", "ND"], (1.0, 0.0)),
        ("phase_ph", phase, ["ORIGINAL", "PRIMARY", "P", "ND"], (slope, intercept)),
    ):
        data = np.transpose(stored, (3, 2, 1, 0)).astype(np.int16)  # (nt, nz, ny, nx) -> (x, y, z, t)
        path = _save_nifti(os.path.join(folder, f"{name}.nii.gz"), data, affine, frame_interval_ms, scl)
        meta = {"Manufacturer": "Siemens", "ImageType": image_type, "SeriesDescription": f"pc {name}"}
        if name != "mag":
            meta["SequenceName"] = f"fl2d1_v{100.0 * scan.venc_m_s:g}in"
        with open(os.path.join(folder, f"{name}.json"), "w") as fh:
            json.dump(meta, fh, indent=1)
        files.append(path)
    return files


@dataclass
class FlowVolume:
    """A 4D-flow phantom: magnitude and three velocity components on a rotated, anisotropic voxel grid.

    ``magnitude``, ``velocity`` (3, ...) have shape ``(ni, nj, nk, nt)``; ``affine`` maps voxel indices
    to world mm; Poiseuille flow ``U(t) (1 - r^2 / R^2)`` along ``axis`` through ``center``.
    """

    magnitude: np.ndarray
    velocity: np.ndarray
    affine: np.ndarray
    axis: np.ndarray
    center: np.ndarray
    radius_mm: float
    peak_m_s: np.ndarray  # (nt,)
    venc_m_s: float
    viscosity_pa_s: float = 3.5e-3

    def wss_pa(self, it: int) -> float:
        """Exact WSS of frame ``it``: ``2 mu U / R``."""
        return 2.0 * self.viscosity_pa_s * float(self.peak_m_s[it]) / (1e-3 * self.radius_mm)


def make_flow_volume(
    seed: int = 0,
    snr: float | None = 25.0,
    n: int = 40,
    voxel_mm: tuple[float, float, float] = (1.0, 1.1, 0.9),
    radius_mm: float = 6.0,
    peaks_m_s: tuple[float, ...] = (0.8, 0.4),
    sub: int = 4,
) -> FlowVolume:
    """Seeded 4D-flow phantom: a straight tube at a random tilt through a rotated grid, phase-contrast signal.

    Notes
    -----
    Each velocity component ``c`` is measured as in :func:`wss_nlp.synthetic.phantoms.acquire`:
    ``d_c = (1/|V|) int_V chi exp(i pi u_c / venc) dx + n_c`` (``sub^3`` points a voxel), velocity
    ``venc arg(d_c) / pi``; the magnitude is ``|int_V chi dx / |V| + n_0|``; noise complex Gaussian with
    standard deviation ``1 / SNR`` per channel, independent between components and voxels.
    """
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3) * (0.35, 0.35, 0.0) + (0.0, 0.0, 1.0)  # tilted up to about 30 degrees from z
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0, np.pi / 2)
    c, s = np.cos(angle), np.sin(angle)
    affine = np.eye(4)
    affine[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag(voxel_mm)
    affine[:3, 3] = -affine[:3, :3] @ np.full(3, (n - 1) / 2)
    center = rng.uniform(-2.0, 2.0, size=3)
    venc = 1.25 * max(peaks_m_s)
    t = (np.arange(sub) + 0.5) / sub - 0.5
    idx = np.stack(np.meshgrid(*(np.arange(n, dtype=float),) * 3, indexing="ij"), -1).reshape(-1, 3)
    offsets = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    nt = len(peaks_m_s)
    fraction = np.zeros(idx.shape[0])
    signal = np.zeros((nt, 3, idx.shape[0]), dtype=complex)
    for o in offsets:
        d = (idx + o) @ affine[:3, :3].T + affine[:3, 3] - center
        r2 = np.sum(d**2, axis=1) - (d @ axis) ** 2
        inside = r2 < radius_mm**2
        fraction += inside
        profile = np.where(inside, 1.0 - r2 / radius_mm**2, 0.0)
        for it, peak in enumerate(peaks_m_s):
            for k in range(3):
                signal[it, k] += inside * np.exp(1j * np.pi * peak * profile * axis[k] / venc)
    fraction /= offsets.shape[0]
    signal /= offsets.shape[0]
    noise = 0.0 if snr is None else 1.0 / snr
    shape = (n, n, n)
    magnitude = np.empty((*shape, nt))
    velocity = np.empty((3, *shape, nt))
    for it in range(nt):
        m = fraction + noise * (rng.standard_normal(fraction.shape) + 1j * rng.standard_normal(fraction.shape))
        magnitude[..., it] = np.abs(m).reshape(shape)
        for k in range(3):
            d = signal[it, k] + noise * (rng.standard_normal(fraction.shape) + 1j * rng.standard_normal(fraction.shape))
            velocity[k, ..., it] = (venc * np.angle(d) / np.pi).reshape(shape)
    return FlowVolume(magnitude, velocity, affine, axis, center, radius_mm, np.asarray(peaks_m_s), venc)


def write_flow_volume(folder: str, volume: FlowVolume, frame_interval_ms: float = 40.0) -> list[str]:
    """``mag.nii.gz`` and ``flow_vx/vy/vz.nii.gz`` (velocity in m/s, float32), as a converter writes 4D flow."""
    os.makedirs(folder, exist_ok=True)
    pairs = [("mag", volume.magnitude)] + [(f"flow_v{c}", volume.velocity[k]) for k, c in enumerate("xyz")]
    return [
        _save_nifti(os.path.join(folder, f"{name}.nii.gz"), data.astype(np.float32), volume.affine, frame_interval_ms)
        for name, data in pairs
    ]


def _save_nifti(path: str, data: np.ndarray, affine, frame_interval_ms: float | None, scl=None) -> str:
    """One NIfTI file in mm and ms, with the frame interval in pixdim[4] and the scaling ``(slope, inter)``."""
    nibabel = require_nibabel("writing")
    img = nibabel.Nifti1Image(data, affine)
    if scl is not None:
        img.header.set_slope_inter(*scl)
    img.header.set_xyzt_units("mm", "msec")
    if frame_interval_ms is not None:
        zooms = list(img.header.get_zooms())
        zooms[3] = frame_interval_ms
        img.header.set_zooms(zooms)
    nibabel.save(img, path)
    return path
