"""``wss-nlp import``: scanner exports (DICOM folders or files, NIfTI files) to an input file of the contract.

The readers live in :mod:`wss_nlp.io.dicom` and :mod:`wss_nlp.io.nifti`; the
assembly into slices and frames and the writing in :mod:`wss_nlp.io.scanner`.
"""

from __future__ import annotations

import os

from . import dicom, nifti
from ..errors import InputError
from .plane import Plane
from .scanner import Imported, ImportOptions, assemble


def import_paths(
    paths,
    options: ImportOptions | None = None,
    phase_units: str | None = None,
    frame_interval_ms: float | None = None,
    plane: Plane | None = None,
) -> Imported:
    """Read DICOM (folders or files) or NIfTI files and assemble one acquisition.

    Parameters
    ----------
    paths : list of str
        DICOM files or folders (searched recursively), or NIfTI files
        (``.nii``, ``.nii.gz``) or folders holding them (a dcm2niix output
        folder: its NIfTI files are read, the JSON sidecars beside them), not both.
    options : ImportOptions
        Venc, viscosity, density and the through-plane sign the user supplies.
    phase_units : str, optional
        Units of the phase images' values when the headers do not state them
        (one of :data:`wss_nlp.io.dicom.PHASE_UNITS`).
    frame_interval_ms : float, optional
        Time between NIfTI frames when the header does not state it.
    plane : Plane, optional
        Cut 4D-flow NIfTI volumes (a magnitude and three velocity components)
        by this plane (:mod:`wss_nlp.io.plane`).
    """
    options = options or ImportOptions()
    paths = [q for p in paths for q in _nifti_folder(str(p))]
    if not paths:
        raise InputError("import: name the DICOM folder(s)/files or the NIfTI files to read")
    if phase_units is not None and phase_units not in dicom.PHASE_UNITS:
        raise InputError(f"--phase-units {phase_units}: choose from {', '.join(dicom.PHASE_UNITS)}")
    kinds = {nifti.is_nifti(p) for p in paths}
    if kinds == {True, False}:
        raise InputError(f"{', '.join(paths)}: mixes NIfTI and DICOM; import one kind at a time")
    if True in kinds:
        images, record = nifti.read_images(paths, phase_units, frame_interval_ms, plane, options.venc_m_s)
    else:
        if plane is not None:
            raise InputError("--plane cuts NIfTI 4D-flow volumes; DICOM 4D flow: convert to NIfTI first (dcm2niix)")
        if frame_interval_ms is not None:
            raise InputError("--frame-interval applies to NIfTI only; DICOM states the trigger times (0018,1060)")
        images, record = dicom.read_images(paths, phase_units)
    return assemble(images, options, record)


def _nifti_folder(path: str) -> list[str]:
    """The NIfTI files directly inside folder ``path`` (sorted), or ``[path]`` for a file or a folder without any.

    A folder without NIfTI files stays a DICOM folder (searched recursively by the DICOM reader).
    """
    if not os.path.isdir(path):
        return [path]
    found = sorted(os.path.join(path, n) for n in os.listdir(path) if n.lower().endswith((".nii", ".nii.gz")))
    return found or [path]
