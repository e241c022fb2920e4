"""NIfTI phase-contrast images in (``wss-nlp import``): a magnitude and a phase (or velocity) file.

Reads ``.nii`` / ``.nii.gz`` files (nibabel, an optional dependency:
``pip install 'wss-nlp[nifti]'``) with their JSON sidecars where a converter
(dcm2niix) wrote them, into :class:`~wss_nlp.scanner.Image2D` records.

Notes
-----
A file holds ``data[i, j, k, t]``; the affine ``A`` maps voxel ``(i, j, k)``
to millimetres. Image ``k`` of frame ``t`` is ``data[:, :, k, t].T`` (rows
``j``, columns ``i``, as DICOM converters write them): its row direction is
``A[:3, 0] / |A[:3, 0]|``, its column direction ``A[:3, 1] / |A[:3, 1]|``, its
pixel spacing ``[|A[:3, 1]|, |A[:3, 0]|]`` and its first voxel lies at
``A (0, 0, k, 1)``. Values are scaled by the header's ``scl_slope`` and
``scl_inter`` (nibabel applies them).

The role of a file comes from its sidecar's ``ImageType`` (``P``/``PHASE``
against ``M``/``MAGNITUDE``), else from its name (``_ph``, ``phase``, ``vel``
against ``mag``). The phase values' units come from ``--phase-units``, else
from the sidecar: Siemens (``Manufacturer``) phase as dcm2niix writes it,
``[-4096, 4096)`` for ``[-pi, pi)``, or radians when all values lie in
``[-pi, pi]``. The venc comes from ``--venc`` or the sidecar's Siemens
``SequenceName`` (``fl2d1_v150in``). Frame times: ``--frame-interval`` or the
header's fourth pixel dimension when its time unit is ms or s.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any

import numpy as np

import logging

from .dicom import PHASE_UNITS, siemens_venc, to_physical
from ..errors import InputError
from .plane import TILT_THRESHOLD_DEG, Plane, sample, tilt, voxel_index
from .scanner import Image2D

log = logging.getLogger(__name__)

#: Siemens phase as converters store it: this value stands for pi.
SIEMENS_FULL_SCALE = 4096.0


def is_nifti(path: str) -> bool:
    return str(path).lower().endswith((".nii", ".nii.gz"))


def sidecar(path: str) -> dict:
    """The JSON sidecar next to a NIfTI file (``name.json`` for ``name.nii[.gz]``), or ``{}``."""
    stem = re.sub(r"\.nii(\.gz)?$", "", str(path), flags=re.IGNORECASE)
    side = stem + ".json"
    if not os.path.exists(side):
        return {}
    try:
        with open(side) as fh:
            data = json.load(fh)
    except (OSError, ValueError) as exc:
        raise InputError(f"{side}: not a readable JSON sidecar ({exc}); fix or remove it") from None
    if not isinstance(data, dict):
        raise InputError(f"{side}: a JSON sidecar must hold an object, got {type(data).__name__}")
    return data


def role_of(path: str, meta: dict) -> str:
    """``"magnitude"`` or ``"phase"`` from the sidecar's ImageType, else the file name; an error if neither says."""
    tokens = {str(t).strip().upper() for t in meta.get("ImageType", [])}
    if tokens & {"P", "PHASE", "VELOCITY"}:
        return "phase"
    if tokens & {"M", "MAGNITUDE", "MAG"}:
        return "magnitude"
    name = os.path.basename(str(path)).lower()
    if re.search(r"(_ph\b|_ph\.|phase|vel)", name):
        return "phase"
    if re.search(r"(mag|_m\.|_m\b)", name):
        return "magnitude"
    raise InputError(
        f"{path}: cannot tell whether this is the magnitude or the phase image: no 'ImageType' in a JSON sidecar; "
        "put 'mag' or 'phase' in the file name"
    )


def _units(path: str, meta: dict, values: np.ndarray, phase_units: str | None) -> tuple[np.ndarray, str]:
    units = phase_units
    peak = float(np.nanmax(np.abs(values))) if values.size else 0.0
    if units is None:
        if peak <= np.pi * (1 + 1e-6) and "siemens" in str(meta.get("Manufacturer", "")).lower():
            units = "rad"
        elif "siemens" in str(meta.get("Manufacturer", "")).lower():
            units = "siemens"
        else:
            raise InputError(
                f"{path}: the units of the phase values (up to {peak:.4g}) are not stated (no Siemens sidecar); "
                "pass --phase-units (" + ", ".join(PHASE_UNITS) + ")"
            )
    return to_physical(values, units, SIEMENS_FULL_SCALE, path)


def _frame_times(img, path: str, nt: int, frame_interval_ms: float | None) -> list[float | None]:
    if nt == 1:
        return [None]
    if frame_interval_ms is not None:
        if not frame_interval_ms > 0:
            raise InputError(f"--frame-interval {frame_interval_ms}: must be > 0 ms")
        return [k * frame_interval_ms for k in range(nt)]
    zooms = img.header.get_zooms()
    unit = img.header.get_xyzt_units()[1]
    if len(zooms) > 3 and zooms[3] > 0 and unit in ("msec", "sec"):
        step = float(zooms[3]) * (1000.0 if unit == "sec" else 1.0)
        return [k * step for k in range(nt)]
    raise InputError(
        f"{path}: {nt} frames but the header states no frame interval (pixdim[4] in ms or s); pass --frame-interval MS"
    )


def require_nibabel(what: str = "reading"):
    """The nibabel module, or an :class:`InputError` saying how to install it."""
    try:
        import nibabel
    except ImportError:
        raise InputError(f"{what} NIfTI needs nibabel, an optional dependency: pip install 'wss-nlp[nifti]'") from None
    return nibabel


def _load(path: str, data: bool = True):
    """``(image, data (x, y, z, t), sidecar)`` of one NIfTI file; ``data=False``: the header alone (a placeholder
    of the data's shape that holds no memory)."""
    nibabel = require_nibabel()
    if not os.path.isfile(path):
        raise InputError(f"{path}: no such file")
    try:
        img: Any = nibabel.load(path)
        values = np.asarray(img.get_fdata(), dtype=np.float64) if data else np.broadcast_to(np.float64(0), img.shape)
    except Exception as exc:  # nibabel raises several types for unreadable files
        raise InputError(f"{path}: not a readable NIfTI file ({type(exc).__name__}: {exc})") from None
    return _as_4d(path, img, values)


def _as_4d(path: str, img, data: np.ndarray):
    if data.ndim == 2:
        data = data[:, :, None]
    if data.ndim == 3:
        data = data[..., None]
    if data.ndim != 4:
        raise InputError(
            f"{path}: {data.ndim}D data {data.shape}; expected (x, y, z) or (x, y, z, t) of one image or one "
            "velocity component (a 4D-flow file per component; see --plane)"
        )
    return img, data, sidecar(path)


def images_from_file(
    path: str, phase_units: str | None = None, frame_interval_ms: float | None = None
) -> list[Image2D]:
    """The 2D images of one NIfTI file (every slice of every frame)."""
    img, data, meta = _load(path)
    role = role_of(path, meta)
    affine = np.asarray(img.affine, dtype=np.float64)
    di, dj = (float(np.linalg.norm(affine[:3, c])) for c in (0, 1))
    if not (di > 0 and dj > 0):
        raise InputError(f"{path}: the affine has a zero voxel size ({di}, {dj}); fix the header")
    row_dir, col_dir = affine[:3, 0] / di, affine[:3, 1] / dj
    values, units = (data, "") if role == "magnitude" else _units(path, meta, data, phase_units)
    venc = None
    venc_source = ""
    if role == "phase" and meta.get("SequenceName"):
        found = siemens_venc(str(meta["SequenceName"]))
        if found is not None:
            if found[1] not in ("in", "through"):
                raise InputError(
                    f"{path}: SequenceName {meta['SequenceName']!r} encodes the in-plane direction {found[1]!r}; "
                    "wss-nlp needs the through-plane velocity, or --venc for this one"
                )
            venc, venc_source = found[0], f"sidecar SequenceName {meta['SequenceName']!r}"
    nt = data.shape[3]
    times = _frame_times(img, path, nt, frame_interval_ms)
    series = str(meta.get("SeriesDescription", os.path.basename(path)))
    out = []
    for k in range(data.shape[2]):
        position = (affine @ np.array([0.0, 0.0, k, 1.0]))[:3]
        for t in range(nt):
            out.append(
                Image2D(
                    where=f"{path} (slice {k}, frame {t})" if nt > 1 or data.shape[2] > 1 else path,
                    role=role,
                    pixels=values[:, :, k, t].T.copy(),
                    units=units,
                    position=position,
                    row_dir=row_dir,
                    col_dir=col_dir,
                    spacing=(dj, di),
                    trigger_ms=times[t],
                    venc_m_s=venc,
                    venc_source=venc_source,
                    series=series,
                    series_uid=str(path),
                    vendor=str(meta.get("Manufacturer", "")).strip().title(),
                )
            )
    return out


_DIRECTION_AXIS = {"rl": "x", "lr": "x", "ap": "y", "pa": "y", "fh": "z", "hf": "z"}


def component_of(path: str, meta: dict) -> str | None:
    """World axis (``x``, ``y``, ``z``) of a velocity component file, from the sidecar or the name, or None."""
    found = siemens_venc(str(meta.get("SequenceName", "")))
    if found is not None and found[1] in _DIRECTION_AXIS:
        return _DIRECTION_AXIS[found[1]]
    stem = re.sub(r"\.nii(\.gz)?$", "", os.path.basename(str(path)), flags=re.IGNORECASE).lower()
    m = re.search(r"(?:^|[_\-.])v?([xyz])$", stem)
    return m.group(1) if m else None


def _component_velocity(path: str, meta: dict, data: np.ndarray, phase_units: str | None, venc: float | None):
    values, units = _units(path, meta, data, phase_units)
    if units == "m/s":
        return values
    found = siemens_venc(str(meta.get("SequenceName", "")))
    venc = venc if venc is not None else (found[0] if found else None)
    if venc is None:
        raise InputError(f"{path}: phase values need the venc to become velocities: pass --venc M_S")
    return venc * values / np.pi


def flow_files(loaded: dict, what: str) -> tuple[str, dict[str, str]]:
    """The magnitude file and the x, y, z velocity-component files of 4D flow among ``loaded`` (path: :func:`_load`).

    A file is a component when :func:`component_of` names its axis, else the magnitude when :func:`role_of` says so;
    two magnitude files, a component missing, doubled or not told apart, and grids or affines that differ from the
    magnitude's are each an :class:`InputError` naming the file (``what`` names the route in the message).
    """
    magnitude: str | None = None
    components: dict[str, str] = {}
    for path, (_, _, meta) in loaded.items():
        axis = component_of(path, meta)
        if axis is None and role_of(path, meta) == "magnitude":
            if magnitude is not None:
                raise InputError(f"{magnitude} and {path}: two magnitude files; pass one")
            magnitude = path
        elif axis is None:
            raise InputError(
                f"{path}: which velocity component is this? Name it *_vx, *_vy or *_vz (world axes of the "
                "affine), or give a sidecar SequenceName with the encoding direction (rl, ap, fh)"
            )
        elif axis in components:
            raise InputError(f"{components[axis]} and {path}: two files for the {axis} component")
        else:
            components[axis] = path
    missing = [a for a in "xyz" if a not in components]
    if magnitude is None or missing:
        absent = "a magnitude file" if magnitude is None else f"the {', '.join(missing)} component(s)"
        raise InputError(f"{what} needs a magnitude file and three velocity components; {absent} missing")
    img, mag, _ = loaded[magnitude]
    affine = np.asarray(img.affine, dtype=np.float64)
    for path in components.values():
        other = loaded[path]
        if other[1].shape != mag.shape or not np.allclose(np.asarray(other[0].affine), affine, atol=1e-4):
            raise InputError(f"{path}: its grid {other[1].shape} or affine differs from {magnitude}'s; resample first")
    return magnitude, components


def plane_images(
    paths, plane: Plane, phase_units: str | None, frame_interval_ms: float | None, venc_m_s: float | None
) -> list[Image2D]:
    """A magnitude file and three velocity-component files (4D flow), resampled on ``plane`` (see wss_nlp.plane)."""
    plane.check()
    # the headers alone first: which file is which, and a plane that leaves the volume, before any voxel is read
    magnitude, components = flow_files({str(p): _load(str(p), data=False) for p in paths}, "--plane")
    header = _load(magnitude, data=False)
    plane.check_inside(np.asarray(header[0].affine, dtype=np.float64), header[1].shape, magnitude)
    loaded = {str(p): _load(str(p)) for p in paths}
    img, mag, meta = loaded[magnitude]
    affine = np.asarray(img.affine, dtype=np.float64)
    velocity = {
        a: _component_velocity(p, loaded[p][2], loaded[p][1], phase_units, venc_m_s) for a, p in components.items()
    }
    nt = mag.shape[3]
    times = _frame_times(img, magnitude, nt, frame_interval_ms)
    centres = plane.centres(affine)
    e1, e2, n = plane.axes()
    h = plane.sampling(affine)[0]
    vendor = str(meta.get("Manufacturer", "")).strip().title()
    index = voxel_index(affine, centres, mag.shape, magnitude)  # the same points for every frame and component
    grid_shape = centres.shape[:-1]
    out = []
    for t in range(nt):
        mag_t = sample(mag[..., t], index, plane.order).reshape(grid_shape)
        u = np.stack([sample(velocity[a][..., t], index, plane.order).reshape(grid_shape) for a in "xyz"], axis=-1)
        parts = {"magnitude": mag_t, "velocity": u @ n, "velocity_x": u @ e1, "velocity_y": u @ e2}
        for k in range(centres.shape[0]):
            for role, values in parts.items():
                out.append(
                    Image2D(
                        where=f"{magnitude} (plane slice {k}, frame {t})",
                        role=role,
                        pixels=values[k],
                        units="" if role == "magnitude" else "m/s",
                        position=centres[k, 0, 0],
                        row_dir=e1,
                        col_dir=e2,
                        spacing=(h, h),
                        trigger_ms=times[t],
                        series=f"{role} on the plane",
                        series_uid=role,
                        vendor=vendor,
                    )
                )
    return out


def _check_perpendicular(images: list[Image2D]) -> dict:
    """How far the plane is off the vessel's axis, from the in-plane velocity (:func:`wss_nlp.io.plane.tilt`).

    Returns the record (``tilt_deg``, the axis it implies in the world frame, the fit's residual); warns above
    :data:`~wss_nlp.io.plane.TILT_THRESHOLD_DEG` with the angle and the normal of a perpendicular plane, and when
    the in-plane velocity exceeds the through-plane one (a plane far off the vessel, or component files whose
    axes or signs are not the affine's world axes).
    """
    by: dict[str, dict[str, np.ndarray]] = {}
    frame_of: dict[str, Image2D] = {}
    for im in images:
        by.setdefault(im.where, {})[im.role] = im.pixels
        if im.role == "magnitude":
            frame_of[im.where] = im
    where = max(by, key=lambda k: float(np.abs(by[k]["velocity"]).mean()))
    peak = by[where]
    mag = peak["magnitude"]
    lumen = mag > 0.5 * (np.percentile(mag, 10) + np.percentile(mag, 99))
    if lumen.sum() < 4:
        return {}
    through = float(np.median(np.abs(peak["velocity"][lumen])))
    inplane = float(np.median(np.hypot(peak["velocity_x"][lumen], peak["velocity_y"][lumen])))
    if inplane > through:
        log.warning(
            "in the vessel the in-plane velocity (median %.3g m/s) exceeds the through-plane one (%.3g m/s): the "
            "plane is not perpendicular to the vessel, or the component files' axes or signs are not the "
            "affine's world axes; check --plane",
            inplane,
            through,
        )
    found = tilt(peak["velocity"], peak["velocity_x"], peak["velocity_y"], lumen)
    if found is None:
        return {}
    theta, e, residual = found
    im = frame_of[where]
    n = np.cross(im.row_dir, im.col_dir)
    d = np.cos(theta) * n + np.sin(theta) * (e[0] * np.asarray(im.row_dir) + e[1] * np.asarray(im.col_dir))
    d = d * np.sign(float(np.sum(peak["velocity"][lumen])) or 1.0)
    record = {"tilt_deg": float(np.degrees(theta)), "axis_from_velocity": [round(float(v), 6) for v in d],
              "tilt_fit_residual": residual}  # fmt: skip
    if np.degrees(theta) > TILT_THRESHOLD_DEG:
        log.warning(
            "the plane is %.1f degrees off the vessel's axis (its in-plane velocity leans that way); 'reconstruct' "
            "corrects the WSS for it and flags it; a plane perpendicular to the vessel has the normal %s",
            np.degrees(theta),
            " ".join(f"{v:.4f}" for v in d),
        )
    return record


def read_images(
    paths,
    phase_units: str | None = None,
    frame_interval_ms: float | None = None,
    plane: Plane | None = None,
    venc_m_s: float | None = None,
):
    """Every image of the NIfTI files ``paths`` (or the 4D-flow volumes cut by ``plane``) and a record."""
    record: dict = {"format": "NIfTI", "paths": [str(p) for p in paths], "files": len(paths)}
    images: list[Image2D] = []
    if plane is not None:
        images = plane_images(paths, plane, phase_units, frame_interval_ms, venc_m_s)
        tilt_record = _check_perpendicular(images)
        record["plane"] = {
            "point": [float(v) for v in plane.point],
            "normal": [round(float(v), 6) for v in np.cross(images[0].row_dir, images[0].col_dir)],
            "fov_mm": plane.fov_mm,
            "voxel_mm": images[0].spacing[0],
            "slices": plane.slices,
            "interpolation": "nearest voxel" if plane.order == 0 else "trilinear",
            **tilt_record,
        }
        return images, record
    for path in paths:
        if not os.path.isfile(path):
            raise InputError(f"{path}: no such file")
        images += images_from_file(path, phase_units, frame_interval_ms)
    return images, record
