"""4D flow NIfTI files in: a magnitude file and three velocity-component files to a :class:`VolumeAcquisition`.

The files are told apart as ``wss-nlp import --plane`` tells them apart (:func:`wss_nlp.io.nifti.flow_files`): a
component by its sidecar's Siemens ``SequenceName`` encoding direction (``rl``/``lr`` x, ``ap``/``pa`` y,
``fh``/``hf`` z) or a name ending ``_vx``, ``_vy``, ``_vz``; the magnitude by its sidecar ``ImageType`` or its
name (``mag``). Each file holds ``data[i, j, k(, t)]`` with the affine ``A`` (mm) mapping voxel ``(i, j, k)`` to
world ``(x, y, z)``; the component files hold the velocity along the world axes x, y, z of ``A`` (not along the
voxel axes), which is the layout's convention (:mod:`wss_nlp.io.volume`). A converter that writes components
along the voxel axes, or with the vendor's sign, needs a rotation by the user first (see Notes).

Phase values become velocities as on the 2D route (:func:`wss_nlp.io.nifti._component_velocity`): values in m/s,
cm/s, mm/s are scaled; radians or Siemens integers become ``v = venc phase / pi`` with the venc from
``venc_m_s`` (one value for all three components or one per component) or the sidecar's ``SequenceName``.
Frame times: ``frame_interval_ms`` or the header's fourth pixel dimension in ms or s, frame ``k`` at
``k dt`` (:func:`wss_nlp.io.nifti._frame_times`).

Notes
-----
4D flow DICOM is not read; convert with dcm2niix and pass the NIfTI files. Why, from the vendors' conventions as
the DICOM standard, the converters and their issue trackers describe them:

* What :mod:`wss_nlp.io.dicom` reads are 2D through-plane series: one phase image per slice and frame, its venc and
  direction from Siemens's ``SequenceName`` (``_v150in``, and it refuses the in-plane codes), Philips's private
  PC Velocity (2001,101A) (it refuses more than one non-zero direction) or GE's private (0019,10CC). A 4D flow
  export holds three phase series (Siemens: one series per direction, ``_vrl``/``_vap``/``_vfh``; Philips: one
  series with the three directions interleaved, told apart only by private tags; GE: vendor-specific ordering
  and private scale factors), and :func:`wss_nlp.io.scanner.assemble` has no notion of a component.
* The sign and axis of each component. The encoding direction of a classic image is stated in patient
  coordinates only by the Siemens sequence name (an axis code, not a validated sign convention); Philips and GE
  give no public direction per image, and tools that read their 4D flow (e.g. the vendors' own and research
  pipelines) apply per-vendor, per-software-version sign flips that the headers do not state. The enhanced MR
  image's MR Velocity Encoding Sequence (0018,9197) with Velocity Encoding Direction (0018,9090) states the
  direction per frame in the standard, but whether a vendor fills it correctly for 4D flow cannot be checked
  from the file, and a wrong sign or axis would give a plausible but wrong velocity field: the package never
  guesses a convention (see :mod:`wss_nlp.io.dicom`).
* Phase-encoding polarity, the one other per-axis sign, is missing from Philips DICOM (dcm2niix's documentation
  and issues say so), so not even the acquisition frame's orientation can be fully recovered there.

Converters (dcm2niix) write one NIfTI file per series with the geometry in RAS world coordinates; the velocity
values are left as the scanner stored them. The user names the files ``*_vx``/``*_vy``/``*_vz`` after checking
that each holds the velocity along that world axis with positive values pointing to increasing x, y, z (a
flowing vessel of known direction, e.g. the descending aorta flowing towards the feet, tells the sign).
"""

from __future__ import annotations

import json
import logging
import os

import numpy as np

from . import nifti
from .dicom import PHASE_UNITS, siemens_venc
from ..errors import InputError
from .volume import VolumeAcquisition

log = logging.getLogger(__name__)

#: The refusal of DICOM input on the volume route (see the module's notes).
DICOM_REFUSAL = "4D flow DICOM is not read; convert with dcm2niix and pass the NIfTI files"


def _vencs(venc_m_s) -> dict[str, float | None]:
    """``venc_m_s`` (None, one value or three) as a venc per world axis."""
    if venc_m_s is None:
        return dict.fromkeys("xyz")
    values = np.atleast_1d(np.asarray(venc_m_s, dtype=float)).ravel()
    if values.size not in (1, 3) or not np.all(np.isfinite(values)) or not np.all(values > 0):
        raise InputError(f"--venc {np.asarray(venc_m_s).tolist()}: give one positive value (m/s) or three (x, y, z)")
    if values.size == 1:
        values = np.repeat(values, 3)
    return {a: float(v) for a, v in zip("xyz", values)}


def _refuse_non_nifti(path: str) -> None:
    if nifti.is_nifti(path):
        return
    if os.path.isdir(path) or str(path).lower().endswith((".dcm", ".ima")) or _is_dicom_file(path):
        raise InputError(f"{path}: {DICOM_REFUSAL} (see wss_nlp.io.volume_import's notes for why)")
    raise InputError(f"{path}: not a NIfTI file (.nii or .nii.gz); pass a magnitude and three velocity-component files")


def _is_dicom_file(path: str) -> bool:
    """Whether ``path`` is a file with the DICOM preamble's ``DICM`` marker at byte 128."""
    try:
        with open(path, "rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def is_flow_volume(paths) -> bool:
    """Whether ``paths`` look like a 4D flow volume (the volume route of ``wss-nlp import`` without ``--plane``).

    True when every path is NIfTI and either at least two of them are velocity components of different world axes
    (:func:`wss_nlp.io.nifti.component_of`: sidecar encoding direction or a name ending ``_vx``, ``_vy``, ``_vz``),
    or there are four files of which one is a magnitude and three are phase/velocity images (then
    :func:`read_nifti_volume` asks the user to tell the components apart). A 2D through-plane series has one phase
    image per slice and no component axis, so it keeps the slice route.
    """
    paths = [os.fspath(p) for p in paths]
    if not paths or not all(nifti.is_nifti(p) for p in paths):
        return False
    axes = {nifti.component_of(p, nifti.sidecar(p)) for p in paths} - {None}
    if len(axes) >= 2:
        return True
    if len(paths) != 4:
        return False
    roles = []
    for p in paths:
        try:
            roles.append(nifti.role_of(p, nifti.sidecar(p)))
        except InputError:
            return False  # the slice route names the file whose role is unknown
    return roles.count("magnitude") == 1 and roles.count("phase") == 3


def read_nifti_volume(
    paths,
    venc_m_s: float | tuple[float, float, float] | None = None,
    phase_units: str | None = None,
    frame_interval_ms: float | None = None,
    viscosity_pa_s: float | None = None,
) -> VolumeAcquisition:
    """Read a magnitude NIfTI file and three velocity-component files into a :class:`VolumeAcquisition`.

    Parameters
    ----------
    paths : list of str
        Four files, in any order: the magnitude and the x, y, z velocity components (world axes of the affine),
        each ``(x, y, z)`` or ``(x, y, z, t)`` on one grid with one affine (mm).
    venc_m_s : float or three floats, optional
        Velocity encoding (m/s), for all components or per component x, y, z; needed for phase data (radians,
        Siemens integers) unless the sidecar's ``SequenceName`` states it; stored in the result when given or found.
    phase_units : str, optional
        Units of the component files' values (:data:`wss_nlp.io.dicom.PHASE_UNITS`) when no sidecar states them.
    frame_interval_ms : float, optional
        Time between frames (ms) when the header's pixdim[4] does not state it; frame ``k`` is at ``k dt``.
    viscosity_pa_s : float, optional
        Dynamic viscosity (Pa*s) stored in the result.

    Returns
    -------
    VolumeAcquisition
        ``magnitude (nt, ni, nj, nk)`` as stored (scaled by the header's slope and intercept), ``velocity
        (nt, 3, ni, nj, nk)`` in m/s along the world axes, ``affine_mm`` the magnitude file's affine, frame times
        ``trigger_times_ms`` (None for one frame), ``source`` the magnitude file; ``extra_attrs["import"]`` a JSON
        record of which file gave which component, the units and the venc's origin.

    Raises
    ------
    InputError
        One line naming the file and the fix: DICOM given (:data:`DICOM_REFUSAL`), a file that is not NIfTI, two
        magnitude files, a component missing, doubled or not told apart, grids or affines that differ, phase
        data without a venc, NaN or Inf values, unknown phase units.
    """
    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise InputError("volume import: name a magnitude file and three velocity-component NIfTI files")
    for p in paths:
        _refuse_non_nifti(p)
    if phase_units is not None and phase_units not in PHASE_UNITS:
        raise InputError(f"--phase-units {phase_units}: choose from {', '.join(PHASE_UNITS)}")
    vencs = _vencs(venc_m_s)
    if viscosity_pa_s is not None and not viscosity_pa_s > 0:
        raise InputError(f"--viscosity {viscosity_pa_s}: must be > 0 Pa*s (e.g. 3.5e-3 for blood)")
    loaded = {p: nifti._load(p) for p in paths}
    for p, (_, data, _) in loaded.items():
        bad = ~np.isfinite(data)
        if bad.any():
            raise InputError(
                f"{p}: {int(bad.sum())} NaN or Inf values; replace them in the converter's output (e.g. by 0 "
                "outside the field of view) before importing"
            )
    magnitude, components = nifti.flow_files(loaded, "a 4D flow volume")
    img, mag, meta = loaded[magnitude]
    velocity = []
    record: dict = {"magnitude": magnitude, "components": {}}
    found_vencs: dict[str, float | None] = {}
    for axis in "xyz":
        path = components[axis]
        _, data, cmeta = loaded[path]
        velocity.append(nifti._component_velocity(path, cmeta, data, phase_units, vencs[axis]))
        from_sidecar = siemens_venc(str(cmeta.get("SequenceName", "")))
        if vencs[axis] is not None:
            found_vencs[axis], origin = vencs[axis], "--venc"
        elif from_sidecar is not None:
            found_vencs[axis], origin = from_sidecar[0], f"sidecar SequenceName {cmeta['SequenceName']!r}"
        else:
            found_vencs[axis], origin = None, "not stated"
        record["components"][axis] = {"file": path, "venc_m_s": found_vencs[axis], "venc_from": origin}
    nt = mag.shape[3]
    times = nifti._frame_times(img, magnitude, nt, frame_interval_ms)
    venc = tuple(found_vencs[a] for a in "xyz")
    vol = VolumeAcquisition(
        magnitude=np.ascontiguousarray(np.moveaxis(mag, 3, 0)),
        velocity=np.ascontiguousarray(np.stack([np.moveaxis(v, 3, 0) for v in velocity], axis=1)),
        affine_mm=np.asarray(img.affine, dtype=np.float64),
        venc_m_s=None if any(v is None for v in venc) else venc,  # type: ignore[arg-type]
        viscosity_pa_s=viscosity_pa_s,
        trigger_times_ms=None if nt == 1 else np.asarray(times, dtype=float),
        source=magnitude,
        extra_attrs={"import": json.dumps(record)},
    )
    vol.validate()
    log.info("read a %d-frame 4D flow volume %s from %s", nt, vol.shape, ", ".join(paths))
    return vol
