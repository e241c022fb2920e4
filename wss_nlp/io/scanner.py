"""Scanner exports in, the input contract out: the part of ``wss-nlp import`` common to DICOM and NIfTI.

The readers (:mod:`wss_nlp.io.dicom`, :mod:`wss_nlp.io.nifti`) turn every 2D image
they find into an :class:`Image2D`: its pixels in physical units (magnitude as
stored; phase in radians or velocity in m/s), where it lies in the scanner's
patient coordinates and when it was acquired. :func:`assemble` sorts them
into slices and frames and checks that they form one acquisition; the result
is written by :func:`write_import` in the layout of
``shared/spec/data-format.md`` (single frames as before; several frames in the
time-resolved layout with ``trigger_times_ms``).

Notes
-----
Geometry. A 2D image with position ``p`` of its first voxel's centre (DICOM
Image Position (Patient)), unit row and column directions ``e_r, e_c``
(Image Orientation (Patient)) and spacing ``[dy, dx]`` (Pixel Spacing: the
distance between rows, then between columns) puts voxel ``(iy, ix)`` at
``p + ix dx e_r + iy dy e_c``. The file's in-plane frame is ``x`` along
``e_r`` and ``y`` along ``e_c``, so ``voxel_size_mm = [dy, dx]`` and
``origin_mm = [p . e_r, p . e_c]``; slices are ordered by ``s = p . n`` with
``n = e_r x e_c`` and must be equally spaced, parallel and unshifted in-plane.
The polar angle of the results is counter-clockwise about ``n``.

Velocity sign. Through-plane velocity is stored as the scanner encodes it
(positive along the vendor's encoding direction, which is not always ``n``);
``--flip-through-plane`` negates it when forward flow comes out negative.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from . import ranges
from .files import Acquisition, write_acquisition, write_frames

log = logging.getLogger(__name__)

#: Slices closer than this along the normal (mm) are the same slice.
SAME_POSITION_MM = 1e-3
#: Relative tolerance on equal slice spacing, voxel sizes and directions.
RELATIVE_TOLERANCE = 1e-3
#: A phase (or velocity / venc) beyond 1 + this is not a phase of this venc.
VENC_SLACK = 2e-3


@dataclass
class Image2D:
    """One 2D image of a scanner export, in physical units.

    ``pixels[iy, ix]``; ``units`` is ``""`` for magnitude, ``"rad"`` for phase,
    ``"m/s"`` for velocity. ``where`` names the file (and frame) in messages.
    """

    where: str
    role: str  # "magnitude", "phase"; resampled volumes: "velocity" (through-plane), "velocity_x", "velocity_y"
    pixels: np.ndarray
    units: str
    position: np.ndarray  # (3,) mm, centre of voxel (0, 0)
    row_dir: np.ndarray  # (3,) unit vector along a row (increasing ix)
    col_dir: np.ndarray  # (3,) unit vector along a column (increasing iy)
    spacing: tuple[float, float]  # (dy, dx) mm
    trigger_ms: float | None = None
    venc_m_s: float | None = None
    venc_source: str = ""
    series: str = ""  # number and description, for messages
    series_uid: str = ""  # what tells two series apart
    vendor: str = ""
    period_ms: float | None = None
    acquired_matrix: tuple[int, int] | None = None  # (ny, nx) k-space samples, from the header if it says


@dataclass
class ImportOptions:
    """What the user supplies or overrides (``wss-nlp import`` options)."""

    venc_m_s: float | None = None
    viscosity_pa_s: float | None = None
    density_kg_m3: float | None = None
    flip_through_plane: bool = False
    allow_unphysical: tuple = ()  # quantities whose values are used as given (wss_nlp.io.ranges)


@dataclass
class Imported:
    """An assembled acquisition: images ``(nt, nz, ny, nx)`` and where every number came from."""

    magnitude: np.ndarray
    phase: np.ndarray | None  # radians, from phase images
    velocity: np.ndarray | None  # m/s, through-plane, from resampled velocity volumes
    inplane: np.ndarray | None  # m/s, (nt, 2, nz, ny, nx): components along x and y of the image frame
    voxel_size_mm: tuple[float, float]
    origin_mm: tuple[float, float]
    slice_spacing_mm: float | None
    venc_m_s: float | None
    trigger_times_ms: np.ndarray | None
    cardiac_period_ms: float | None
    viscosity_pa_s: float | None
    density_kg_m3: float | None
    record: dict = field(default_factory=dict)
    acquired_voxel_size_mm: tuple[float, float] | None = None

    @property
    def nt(self) -> int:
        return int(self.magnitude.shape[0])

    def frame(self, it: int, source: str) -> Acquisition:
        """Frame ``it`` as an :class:`~wss_nlp.io.files.Acquisition` (what ``reconstruct`` reads)."""
        return Acquisition(
            magnitude=self.magnitude[it],
            phase=None if self.phase is None else self.phase[it],
            velocity=None if self.velocity is None else self.velocity[it],
            velocity_inplane=None if self.inplane is None else self.inplane[it],
            voxel_size_mm=self.voxel_size_mm,
            origin_mm=self.origin_mm,
            slice_spacing_mm=self.slice_spacing_mm,
            venc_m_s=self.venc_m_s,
            viscosity_pa_s=self.viscosity_pa_s,
            density_kg_m3=self.density_kg_m3,
            source=source,
            resampled_from=self.resampled_from,
            noise_venc_m_s=self.record.get("component_venc_m_s"),
            acquired_voxel_size_mm=self.acquired_voxel_size_mm,
        )

    @property
    def resampled_from(self) -> str | None:
        plane = self.record.get("plane")
        if not plane:
            return None
        return (
            f"a 4D-flow volume cut by the plane through {plane['point']} mm with normal {plane['normal']} "
            f"({plane['interpolation']})"
        )

    def summary(self) -> str:
        nt, nz, ny, nx = self.magnitude.shape
        (dy, dx), rec = self.voxel_size_mm, self.record
        text = (
            f"{rec.get('format', '?')} ({rec.get('vendor') or 'vendor not stated'}): {nx} x {ny} voxels of "
            f"{dx:.4g} x {dy:.4g} mm, {nz} slice{'s' if nz > 1 else ''}"
        )
        if self.slice_spacing_mm is not None:
            text += f" {self.slice_spacing_mm:.4g} mm apart"
        if self.trigger_times_ms is not None:
            t = self.trigger_times_ms
            text += f", {nt} frames at {t[0]:.4g}-{t[-1]:.4g} ms"
        if self.venc_m_s is not None:
            text += f"; venc {self.venc_m_s:.4g} m/s ({rec.get('venc_source', '?')})"
        if rec.get("plane"):
            text += f"; resampled on the plane through {rec['plane']['point']} normal {rec['plane']['normal']}"
        if rec.get("flip_through_plane"):
            text += "; through-plane velocity flipped"
        return text


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _check_same(images: list[Image2D], what: str, value, close) -> None:
    first = images[0]
    ref = value(first)
    for im in images[1:]:
        if not close(value(im), ref):
            raise InputError(
                f"{im.where}: its {what} {value(im)} differs from {ref} of {first.where}; all images of one "
                "acquisition share it: pass only the files of one magnitude and one phase series"
            )


def _close(a, b) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=RELATIVE_TOLERANCE, atol=RELATIVE_TOLERANCE))


def _slices(images: list[Image2D], normal: np.ndarray) -> tuple[np.ndarray, float | None]:
    """Sorted distinct positions along the normal and their (equal) spacing."""
    s = np.sort(np.array([float(im.position @ normal) for im in images]))
    distinct = [s[0]]
    for v in s[1:]:
        if v - distinct[-1] > SAME_POSITION_MM:
            distinct.append(v)
    pos = np.array(distinct)
    if pos.size == 1:
        return pos, None
    gaps = np.diff(pos)
    if not np.allclose(gaps, gaps.mean(), rtol=RELATIVE_TOLERANCE, atol=SAME_POSITION_MM):
        raise InputError(
            f"{images[0].where} and others: the slices are not equally spaced (gaps {np.round(gaps, 3).tolist()} mm); "
            "a stack needs one slice spacing: import the slices one by one or leave out the extra ones"
        )
    return pos, float(gaps.mean())


def _frames(images: list[Image2D], role: str, iz: int) -> list[Image2D]:
    if any(im.trigger_ms is None for im in images) and len(images) > 1:
        untimed = next(im for im in images if im.trigger_ms is None)
        other = next((im for im in images if im.series_uid != untimed.series_uid), None)
        if other is not None:
            raise InputError(
                f"{untimed.where} and {other.where}: two {role} images of slice {iz} from two series "
                f"({untimed.series!r}, {other.series!r}); pass the files of only one {role} series"
            )
        raise InputError(
            f"{untimed.where}: {len(images)} {role} images of slice {iz} but no trigger time (DICOM TriggerTime "
            "0018,1060) to order them; a cine series needs one per frame, else pass the files of one frame"
        )
    ordered = sorted(images, key=lambda im: im.trigger_ms or 0.0)
    for a, b in zip(ordered, ordered[1:]):
        if a.trigger_ms == b.trigger_ms:
            raise InputError(
                f"{a.where} and {b.where}: two {role} images of slice {iz} at trigger time {a.trigger_ms} ms "
                f"(series {a.series!r} and {b.series!r}); pass the files of only one {role} series"
            )
    return ordered


def assemble(images: list[Image2D], options: ImportOptions, record: dict) -> Imported:
    """Sort images into ``(nt, nz)`` and check they form one acquisition (see the module notes)."""
    if not images:
        raise InputError(f"{record.get('paths', '?')}: no images found")
    through = "velocity" if any(im.role == "velocity" for im in images) else "phase"
    roles = ["magnitude", through] + [r for r in ("velocity_x", "velocity_y") if any(im.role == r for im in images)]
    by_role = {r: [im for im in images if im.role == r] for r in roles}
    for role in ("magnitude", through):
        if not by_role[role]:
            other = through if role == "magnitude" else "magnitude"
            raise InputError(
                f"{images[0].where}: found {len(by_role[other])} {other} images but no {role} image; "
                f"pass the {role} series too (a folder holding both, or both sets of files)"
            )
    _check_same(images, "image size", lambda im: im.pixels.shape, lambda a, b: a == b)
    _check_same(images, "pixel spacing (mm)", lambda im: im.spacing, _close)
    _check_same(images, "row direction", lambda im: np.round(im.row_dir, 6).tolist(), _close)
    _check_same(images, "column direction", lambda im: np.round(im.col_dir, 6).tolist(), _close)
    first = images[0]
    e_r, e_c = _unit(first.row_dir), _unit(first.col_dir)
    if abs(float(e_r @ e_c)) > RELATIVE_TOLERANCE:
        raise InputError(f"{first.where}: row and column directions are not perpendicular ({e_r}, {e_c})")
    normal = np.cross(e_r, e_c)
    _check_same(
        images,
        "in-plane position (mm)",
        lambda im: [round(float(im.position @ e_r), 4), round(float(im.position @ e_c), 4)],
        lambda a, b: bool(np.allclose(a, b, atol=1e-2 * min(first.spacing))),
    )
    positions, spacing = _slices(images, normal)
    nz = positions.size

    def slice_index(im):
        return int(np.argmin(np.abs(positions - im.position @ normal)))

    grid: dict[str, list[list[Image2D]]] = {}
    for role, found in by_role.items():
        grid[role] = [_frames([im for im in found if slice_index(im) == iz], role, iz) for iz in range(nz)]
    counts = {(role, iz): len(grid[role][iz]) for role in grid for iz in range(nz)}
    nt = max(counts.values())
    short = [(role, iz, n) for (role, iz), n in counts.items() if n != nt]
    if short:
        role, iz, n = short[0]
        where = grid[role][iz][0].where if n else f"slice {iz}"
        raise InputError(
            f"{where}: slice {iz} has {n} {role} frame(s) but other slices/series have {nt}; frames are missing: "
            "pass every frame of both series (or only complete slices)"
        )
    trigger = _trigger_times(grid, nt, nz)

    def stacked(role, convert=lambda im: im.pixels):
        return np.array([[convert(grid[role][iz][it]) for iz in range(nz)] for it in range(nt)], dtype=float)

    magnitude = stacked("magnitude")
    phase = velocity = inplane = None
    venc: float | None
    component_venc = None
    if through == "phase":
        venc, venc_source = _venc(by_role["phase"], options)
        phase = stacked("phase", lambda im: _to_phase(im, venc))
    else:  # u . n of a volume's components may exceed the venc of each: no venc is stored (the record keeps it)
        venc, venc_source = None, "not stored: the through-plane velocity combines three encoded components"
        component_venc = options.venc_m_s
        velocity = stacked("velocity")
    if "velocity_x" in grid:
        inplane = np.stack([stacked("velocity_x"), stacked("velocity_y")], axis=1)
    if options.flip_through_plane:
        phase = None if phase is None else -phase
        velocity = None if velocity is None else -velocity
    period = next((im.period_ms for im in images if im.period_ms), None) if trigger is not None else None
    record = dict(record)
    record.update(
        vendor=first.vendor,
        venc_source=venc_source,
        flip_through_plane=bool(options.flip_through_plane),
        slice_normal=normal.round(8).tolist(),
        row_direction=e_r.round(8).tolist(),
        column_direction=e_c.round(8).tolist(),
        first_slice_position=(first.position + 0.0).round(6).tolist(),
        series={role: sorted({im.series for im in found}) for role, found in by_role.items()},
        images=len(images),
    )
    if component_venc is not None:
        record["component_venc_m_s"] = component_venc
    acquired = _acquired_voxel(images, record)
    return Imported(
        magnitude=magnitude,
        phase=phase,
        velocity=velocity,
        inplane=inplane,
        voxel_size_mm=(float(first.spacing[0]), float(first.spacing[1])),
        origin_mm=(float(first.position @ e_r), float(first.position @ e_c)),
        slice_spacing_mm=spacing,
        venc_m_s=venc,
        trigger_times_ms=trigger,
        cardiac_period_ms=period,
        viscosity_pa_s=options.viscosity_pa_s,
        density_kg_m3=options.density_kg_m3,
        record=record,
        acquired_voxel_size_mm=acquired,
    )


def _acquired_voxel(images: list[Image2D], record: dict) -> tuple[float, float] | None:
    """``(dy, dx)`` of the k-space resolution from the headers' acquisition matrix, if every image states the same.

    ``reconstructed size x spacing / acquired samples`` per axis; recorded in ``record`` either way. A matrix
    larger than the image (the scanner reduced the resolution) is recorded but not used.
    """
    found = {im.acquired_matrix for im in images}
    if found == {None}:
        record["acquired_matrix"] = "not stated in the headers"
        return None
    if len(found) > 1:
        record["acquired_matrix"] = f"differs between images ({sorted(map(str, found))}); not used"
        log.warning("the images state different acquisition matrices (%s); no acquired_voxel_size_mm", found)
        return None
    ny_acq, nx_acq = images[0].acquired_matrix  # type: ignore[misc]
    ny, nx = images[0].pixels.shape
    dy, dx = images[0].spacing
    size = (ny * dy / ny_acq, nx * dx / nx_acq)
    record["acquired_matrix"] = [ny_acq, nx_acq]
    if size[0] < dy * (1 - 1e-6) or size[1] < dx * (1 - 1e-6):
        record["acquired_matrix"] = f"{[ny_acq, nx_acq]} exceeds the image's {[ny, nx]}; not used"
        return None
    return (float(size[0]), float(size[1]))


def _trigger_times(grid: dict, nt: int, nz: int) -> np.ndarray | None:
    """One trigger time per frame: the mean over slices and series, which must agree within a quarter frame."""
    if nt == 1:
        return None
    times = np.array([[[im.trigger_ms for im in grid[r][iz]] for iz in range(nz)] for r in grid], dtype=float)
    mean = times.reshape(-1, nt).mean(axis=0)
    if np.any(np.diff(mean) <= 0):
        raise InputError(f"{grid['phase'][0][0].where}: trigger times {mean.tolist()} ms do not increase")
    step = float(np.min(np.diff(mean)))
    spread = np.abs(times - mean).max(axis=(0, 1))
    worst = int(np.argmax(spread))
    if spread[worst] > 0.25 * step:
        raise InputError(
            f"{grid['phase'][0][worst].where}: frame {worst}'s trigger times differ by {spread[worst]:.3g} ms "
            f"between slices or series (frames are {step:.3g} ms apart); the series do not belong to one cine "
            "acquisition"
        )
    return mean


def _venc(phase_images: list[Image2D], options: ImportOptions) -> tuple[float, str]:
    stated = {(im.venc_m_s, im.venc_source) for im in phase_images if im.venc_m_s is not None}
    values = sorted({v for v, _ in stated})
    if len(values) > 1 and not np.allclose(values, values[0], rtol=RELATIVE_TOLERANCE):
        a = next(im for im in phase_images if im.venc_m_s == values[0])
        b = next(im for im in phase_images if im.venc_m_s == values[-1])
        raise InputError(
            f"{a.where} and {b.where}: venc {values[0]:g} and {values[-1]:g} m/s in one phase series; "
            "import the two encodings separately"
        )
    if options.venc_m_s is not None:
        if not options.venc_m_s > 0:
            raise InputError(f"--venc {options.venc_m_s}: the velocity encoding must be > 0 m/s")
        if values and not np.isclose(values[0], options.venc_m_s, rtol=1e-2):
            # the phase was encoded with the header's venc: another one scales every velocity (and the WSS) by the
            # ratio; only a header known to be wrong justifies it
            if not ranges.allowed("venc", options.allow_unphysical):
                ratio = options.venc_m_s / values[0]
                raise InputError(
                    f"--venc {options.venc_m_s:g} m/s disagrees with the venc {values[0]:g} m/s stated by "
                    f"{sorted(stated)[0][1]} ({ratio:.3g}x): the phase was encoded with the header's, and another "
                    f"venc scales every velocity and the WSS by {ratio:.3g}; drop --venc, or pass "
                    "--allow-unphysical venc if the header is wrong"
                )
            log.warning(
                "--venc %g m/s overrides the venc %g m/s stated by %s (--allow-unphysical): velocities and WSS "
                "scale by %.3g",
                options.venc_m_s,
                values[0],
                sorted(stated)[0][1],
                options.venc_m_s / values[0],
            )
        return float(options.venc_m_s), "given (--venc)"
    if not values:
        raise InputError(
            f"{phase_images[0].where}: the headers state no velocity encoding (venc); pass --venc M_S "
            "(e.g. --venc 1.5 for 150 cm/s)"
        )
    return float(values[0]), sorted(stated)[0][1]


def _to_phase(im: Image2D, venc: float) -> np.ndarray:
    if im.units == "rad":
        phase = im.pixels
        bound, what = np.pi, "phase (rad)"
    elif im.units == "m/s":
        phase = np.pi * im.pixels / venc
        bound, what = venc, "velocity (m/s)"
    else:
        raise InputError(f"{im.where}: a phase image in unknown units {im.units!r}")
    peak = float(np.max(np.abs(phase))) if phase.size else 0.0
    if peak > np.pi * (1 + VENC_SLACK):
        value = peak * bound / np.pi
        raise InputError(
            f"{im.where}: {what} reaches {value:.4g}, beyond the venc ({venc:g} m/s); the venc is wrong (check "
            "--venc, which is in m/s) or the images are not in the units of this vendor's convention "
            "(see --phase-units)"
        )
    return np.clip(phase, -np.pi, np.pi)


def write_import(path: str, imp: Imported, argv=None) -> None:
    """Write ``imp`` as an input file of the contract (atomic); several frames in the time-resolved layout."""
    paths = imp.record.get("paths") or ["the imported files"]
    inputs = paths[0] if len(paths) == 1 else f"{paths[0]} (and {len(paths) - 1} more)"
    frames = [imp.frame(it, f"{inputs}{f' (frame {it})' if imp.nt > 1 else ''}") for it in range(imp.nt)]
    for acq in frames:  # every frame obeys the single-frame rules (shapes, finiteness, phase range, ...)
        acq.validate()  # messages name the files read, never the one about to be written
    frames[0].extra_attrs.update(import_json=json.dumps(imp.record, default=str), import_command=" ".join(argv or []))
    if imp.trigger_times_ms is None:
        write_acquisition(path, frames[0])
    else:
        write_frames(path, frames, imp.trigger_times_ms, imp.cardiac_period_ms)
