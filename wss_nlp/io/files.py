"""Reading and writing the HDF5 formats of ``shared/spec/data-format.md``.

Input: one acquisition (``magnitude`` and ``velocity`` or ``phase``, with
attributes). Output: one group ``slice_NNN`` per slice with ``geometry/``,
``wss/`` and extras. Writes are atomic: a temporary file in the target
folder is renamed into place only after it is complete.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import re
import sys
from ..models.baselines import BaselineResult
from dataclasses import dataclass, field

import numpy as np

from ..core import radius as rad

from ..errors import InputError
from ..models.measurement import VoxelGrid


@dataclass
class Acquisition:
    """Images of one acquisition, arrays of shape ``(nz, ny, nx)``."""

    magnitude: np.ndarray
    velocity: np.ndarray | None = None
    phase: np.ndarray | None = None
    voxel_size_mm: tuple[float, float] = (1.0, 1.0)
    origin_mm: tuple[float, float] = (0.0, 0.0)
    slice_spacing_mm: float | None = None
    venc_m_s: float | None = None
    viscosity_pa_s: float | None = None
    density_kg_m3: float | None = None
    source: str = "<memory>"
    extra_attrs: dict = field(default_factory=dict)
    velocity_inplane: np.ndarray | None = None  # (2, nz, ny, nx): in-plane components x, y in m/s (4D flow)
    resampled_from: str | None = None  # how the images were cut from a volume (wss-nlp import --plane), else None
    noise_venc_m_s: float | None = None  # the components' venc when the velocity combines several (noise model only)
    acquired_voxel_size_mm: tuple[float, float] | None = None  # (dy, dx) of the k-space resolution; None: the voxels

    @property
    def nz(self) -> int:
        return int(self.magnitude.shape[0])

    @property
    def grid(self) -> VoxelGrid:
        (dy, dx), (x0, y0) = self.voxel_size_mm, self.origin_mm
        ny, nx = self.magnitude.shape[1:]
        return VoxelGrid((int(ny), int(nx)), (float(dy), float(dx)), (float(x0), float(y0)))

    def velocity_images(self) -> np.ndarray:
        """Through-plane velocity in m/s, from ``velocity`` or ``venc * phase / pi``."""
        if self.velocity is not None:
            return self.velocity
        if self.phase is None or self.venc_m_s is None:
            raise InputError(f"{self.source}: no velocity: give 'velocity', or 'phase' with 'venc_m_s'")
        return self.venc_m_s * self.phase / np.pi

    def viscosity(self, override: float | None = None) -> float:
        """Dynamic viscosity in Pa*s: ``override`` (the command line's) or the file's ``viscosity_pa_s``."""
        mu = override if override is not None else self.viscosity_pa_s
        if mu is None:
            raise InputError(
                f"{self.source}: no viscosity: the file has no 'viscosity_pa_s' attribute; "
                "pass --viscosity (Pa*s, e.g. 3.5e-3 for blood)"
            )
        if not mu > 0:
            raise InputError(f"{self.source}: viscosity must be > 0 Pa*s, got {mu}")
        return float(mu)

    def density(self, override: float | None = None) -> tuple[float, str]:
        """Fluid density in kg/m^3 and where it came from: ``override``, the file's ``density_kg_m3``, or blood's.

        Only the law-of-the-wall layer (``--near-wall``) uses it, through the
        kinematic viscosity ``nu = mu / rho``.
        """
        if override is not None:
            return float(override), "given (--density)"
        if self.density_kg_m3 is not None:
            return float(self.density_kg_m3), "file attribute 'density_kg_m3'"
        return DEFAULT_DENSITY, f"default (blood, {DEFAULT_DENSITY:g} kg/m^3; pass --density for other fluids)"

    def nonfinite_slices(self) -> list[int]:
        """Indices of slices with NaN or Inf in any image."""
        arrays = [a for a in (self.magnitude, self.velocity, self.phase) if a is not None]
        if self.velocity_inplane is not None:
            arrays += list(self.velocity_inplane)
        bad = np.zeros(self.magnitude.shape[0], dtype=bool)
        for a in arrays:
            if a.shape[:1] == bad.shape:
                bad |= ~np.all(np.isfinite(a.reshape(a.shape[0], -1)), axis=1)
        return np.nonzero(bad)[0].tolist()

    def validate(self) -> None:
        """Check shapes, finiteness and attributes; raise :class:`InputError`."""
        src = self.source
        mag = self.magnitude
        if mag.ndim != 3:
            raise InputError(f"{src}: 'magnitude' must have shape (nz, ny, nx), got {mag.shape}")
        if mag.shape[0] == 0:
            raise InputError(f"{src}: 'magnitude' has no slices (shape {mag.shape}); nz must be >= 1")
        if (self.velocity is None) == (self.phase is None):
            raise InputError(f"{src}: exactly one of 'velocity' and 'phase' must be present")
        name = "velocity" if self.velocity is not None else "phase"
        other = self.velocity if self.velocity is not None else self.phase
        assert other is not None  # exactly one of velocity and phase, checked above
        if other.shape != mag.shape:
            raise InputError(f"{src}: shape mismatch: 'magnitude' {mag.shape} but '{name}' {other.shape}")
        if min(mag.shape[1:]) < 4:
            raise InputError(f"{src}: images of {mag.shape[1:]} voxels are too small to hold a vessel")
        if self.velocity_inplane is not None and self.velocity_inplane.shape != (2, *mag.shape):
            raise InputError(
                f"{src}: in-plane velocity must have shape (2, nz, ny, nx) = (2, *{mag.shape}), got "
                f"{self.velocity_inplane.shape}"
            )
        bad_slices = self.nonfinite_slices()
        # in a stack, a corrupt slice is reported and skipped by the reconstruction; only all-bad data is an error
        if bad_slices and (self.nz == 1 or len(bad_slices) == self.nz):
            for nm, arr in (("magnitude", mag), (name, other)):
                bad = ~np.isfinite(arr)
                if bad.any():
                    iz = sorted(set(np.nonzero(bad)[0].tolist()))
                    raise InputError(f"{src}: '{nm}' contains NaN or Inf ({int(bad.sum())} voxels, slices {iz[:10]})")
        finite_mag = mag[np.isfinite(mag)]
        if finite_mag.size and float(finite_mag.min()) < -1e-6 * max(float(np.abs(finite_mag).max()), 1e-300):
            raise InputError(
                f"{src}: 'magnitude' has negative values (min {float(finite_mag.min()):.4g}); a "
                "magnitude image is >= 0: store the modulus of the complex image, not its real part"
            )
        vs = np.asarray(self.voxel_size_mm, dtype=float)
        if vs.shape != (2,) or not np.all(np.isfinite(vs)) or np.any(vs <= 0):
            raise InputError(f"{src}: 'voxel_size_mm' must be two positive numbers [dy, dx], got {self.voxel_size_mm}")
        org = np.asarray(self.origin_mm, dtype=float)
        if org.shape != (2,) or not np.all(np.isfinite(org)):
            raise InputError(f"{src}: 'origin_mm' must be two finite numbers [x0, y0], got {self.origin_mm}")
        if self.nz > 1 and not (self.slice_spacing_mm is not None and self.slice_spacing_mm > 0):
            raise InputError(f"{src}: 'slice_spacing_mm' (> 0) is required when nz = {self.nz} > 1")
        if self.phase is not None:
            if self.venc_m_s is None or not self.venc_m_s > 0:
                raise InputError(f"{src}: attribute 'venc_m_s' (> 0) is required with 'phase'")
            finite_phase = np.abs(self.phase[np.isfinite(self.phase)])
            if finite_phase.size and float(finite_phase.max()) > np.pi + 1e-6:
                big = float(finite_phase.max())
                low = float(np.min(self.phase[np.isfinite(self.phase)]))
                hint = (
                    "; the values lie in [0, 2 pi) radians: wrap them to (-pi, pi] (subtract 2 pi where phase > pi)"
                    if big <= 2 * np.pi + 1e-6 and low >= -1e-6
                    else "; the values look like degrees (multiply by pi/180)"
                    if big <= 180 + 1e-6
                    else "; the values look like raw scanner integers (apply the rescale slope and intercept "
                    "to radians, or use 'wss-nlp import')"
                )
                raise InputError(f"{src}: 'phase' must lie in (-pi, pi] radians, found |phase| up to {big:.4g}{hint}")
        if self.noise_venc_m_s is not None and not self.noise_venc_m_s > 0:
            raise InputError(f"{src}: 'noise_venc_m_s' must be > 0 m/s, got {self.noise_venc_m_s}")
        if self.acquired_voxel_size_mm is not None and not all(
            a >= v * (1 - 1e-6) for a, v in zip(self.acquired_voxel_size_mm, self.voxel_size_mm)
        ):
            raise InputError(
                f"{src}: 'acquired_voxel_size_mm' {tuple(self.acquired_voxel_size_mm)} must be >= 'voxel_size_mm' "
                f"{tuple(self.voxel_size_mm)} per axis (the k-space resolution before zero-filling)"
            )
        if self.viscosity_pa_s is not None and not self.viscosity_pa_s > 0:
            raise InputError(f"{src}: 'viscosity_pa_s' must be > 0, got {self.viscosity_pa_s}")
        check_density(self.density_kg_m3, f"{src}: 'density_kg_m3'")


#: Density of blood (kg/m^3), used when neither the file nor the command line gives one.
DEFAULT_DENSITY = 1060.0


def check_density(rho: float | None, what: str) -> None:
    """InputError unless ``rho`` is None or a plausible liquid density in kg/m^3 (:mod:`wss_nlp.io.ranges`:
    500-3000; g/cm^3 named as the likely slip)."""
    from . import ranges

    if rho is not None:
        ranges.check("density", rho, what, fix="store" if "'" in what else "pass")


def _attr(f, name, src, required=False, size=None):
    if name not in f.attrs:
        if required:
            raise InputError(f"{src}: missing attribute '{name}'")
        return None
    try:
        val = np.asarray(f.attrs[name], dtype=float).ravel()
    except (TypeError, ValueError):
        raise InputError(f"{src}: attribute '{name}' must be numeric, got {f.attrs[name]!r}") from None
    if val.size != (size or 1):
        n = size or 1
        raise InputError(f"{src}: attribute '{name}' must have {n} value{'s' if n > 1 else ''}, got {val.size}")
    if not np.all(np.isfinite(val)):
        raise InputError(f"{src}: attribute '{name}' is not finite: {val}")
    return tuple(val.tolist()) if size and size > 1 else float(val[0])


def _velocity_components(f, dataset, src, shape):
    """``(through-plane velocity or None, in-plane (2, ...) or None)`` from the velocity layouts.

    Layouts: ``velocity`` (nz, ny, nx), the through-plane component; ``velocity``
    (3, nz, ny, nx), components x, y, z of the image frame (z through-plane);
    ``velocity_x`` and ``velocity_y`` (nz, ny, nx) next to ``velocity`` or
    ``phase`` (through-plane), or with ``velocity_z`` in place of ``velocity``.
    """
    vel = dataset("velocity")
    if vel is not None and np.ndim(vel) == 4:
        if vel.shape[0] != 3:
            raise InputError(f"{src}: a 4D 'velocity' must have shape (3, nz, ny, nx), got {vel.shape}")
        if any(k in f for k in ("velocity_x", "velocity_y", "velocity_z")):
            raise InputError(f"{src}: give the components either as a 4D 'velocity' or as 'velocity_x/_y/_z', not both")
        return vel[2], vel[:2]
    through = vel
    vz = dataset("velocity_z")
    if vz is not None:
        if through is not None:
            raise InputError(f"{src}: both 'velocity' and 'velocity_z' given; 'velocity_z' replaces 'velocity'")
        through = vz
    vx, vy = dataset("velocity_x"), dataset("velocity_y")
    if (vx is None) != (vy is None):
        raise InputError(f"{src}: 'velocity_x' and 'velocity_y' come together; one of them is missing")
    if vx is None:
        if vz is not None:
            raise InputError(f"{src}: 'velocity_z' needs 'velocity_x' and 'velocity_y' (else name it 'velocity')")
        return through, None
    for name, arr in (("velocity_x", vx), ("velocity_y", vy)):
        if arr.shape != tuple(shape):
            raise InputError(f"{src}: shape mismatch: 'magnitude' {tuple(shape)} but '{name}' {arr.shape}")
    return through, np.stack([vx, vy])


def _open_input(path):
    """``(name, open h5py.File)`` of an input file; a missing or non-HDF5 file is an :class:`InputError`."""
    import h5py

    src = str(path)
    if not os.path.exists(src):
        raise InputError(f"{src}: no such file")
    try:
        return src, h5py.File(src, "r")
    except OSError as exc:
        raise InputError(_open_error(src, exc)) from None


def _open_error(src: str, exc: OSError) -> str:
    """Why an existing file would not open for reading, in one line."""
    text = " ".join(str(exc).split())
    if "truncated file" in text.lower():  # HDF5's own words; its message also holds "sblock", not a lock
        return f"{src}: not an HDF5 file: truncated, an interrupted copy or write ({text})"
    if re.search(r"\b(file locking|unable to lock)\b", text.lower()):
        return (
            f"{src}: is open for writing by another program (HDF5 file locking: {text}); wait until it is closed "
            "(or, if it is not being written, set HDF5_USE_FILE_LOCKING=FALSE)"
        )
    if os.path.isdir(src):
        return f"{src}: is a folder; name an HDF5 file"
    if not os.access(src, os.R_OK) or "permission" in text.lower():
        return f"{src}: cannot be read (permission denied); check its permissions"
    return f"{src}: not an HDF5 file ({text})"


def read_acquisition(path) -> Acquisition:
    """Read and validate an input file (see the format document)."""

    src, f = _open_input(path)
    with f:
        if "trigger_times_ms" in f.attrs:
            raise InputError(
                f"{src}: a time-resolved (cine) file ('trigger_times_ms'): read it with read_frames "
                "(wss-nlp reconstruct reads both layouts)"
            )

        def dataset(name):
            arr = _numeric_dataset(f, name, src)
            if arr is not None and arr.ndim == 2:  # a single slice stored without the nz axis
                arr = arr[None]
            return arr

        mag = dataset("magnitude")
        if mag is None:
            raise InputError(f"{src}: missing dataset 'magnitude'")
        velocity, inplane = _velocity_components(f, dataset, src, mag.shape)
        acq = Acquisition(
            magnitude=mag,
            velocity=velocity,
            velocity_inplane=inplane,
            phase=dataset("phase"),
            source=src,
            **_input_attrs(f, src),
        )
    if acq.velocity is None and acq.phase is None:
        raise InputError(f"{src}: missing dataset 'velocity' (or 'phase' with 'venc_m_s')")
    acq.validate()
    return acq


def _numeric_dataset(f, name: str, src: str) -> np.ndarray | None:
    """Dataset ``name`` as floats, or None if absent; groups, complex and text data are errors."""
    import h5py

    link = f.get(name, getlink=True)
    if link is None:
        return None
    try:
        obj = f[name]
    except (KeyError, OSError) as exc:  # a soft or external link whose target is missing or unreadable
        kind = "an external link" if isinstance(link, h5py.ExternalLink) else "a link"
        target = f" to {link.filename}:{link.path}" if isinstance(link, h5py.ExternalLink) else (
            f" to {link.path}" if isinstance(link, h5py.SoftLink) else "")  # fmt: skip
        raise InputError(
            f"{src}: '{name}' is {kind}{target} that cannot be followed ({' '.join(str(exc).split())}); store the "
            "data in the file itself"
        ) from None
    if not isinstance(obj, h5py.Dataset):
        raise InputError(f"{src}: '{name}' must be a dataset")
    kind = obj.dtype.kind
    if kind == "b":
        raise InputError(
            f"{src}: '{name}' is boolean (a mask?); store the {'magnitude image' if name == 'magnitude' else 'values'}"
            " as numbers"
        )
    if kind == "c":
        fix = "its modulus (np.abs)" if name == "magnitude" else "real values (np.angle of the complex image)"
        raise InputError(f"{src}: '{name}' is complex ({obj.dtype}); store {fix}")
    if kind not in "fiu":
        raise InputError(f"{src}: '{name}' must hold numbers, got dtype {obj.dtype}")
    return np.asarray(obj[()], dtype=float)


def _input_attrs(f, src: str) -> dict:
    """The attributes an input file shares between its frames, as :class:`Acquisition` fields."""
    return {
        "voxel_size_mm": _attr(f, "voxel_size_mm", src, required=True, size=2),
        "origin_mm": _attr(f, "origin_mm", src, required=True, size=2),
        "slice_spacing_mm": _attr(f, "slice_spacing_mm", src),
        "venc_m_s": _attr(f, "venc_m_s", src),
        "viscosity_pa_s": _attr(f, "viscosity_pa_s", src),
        "density_kg_m3": _attr(f, "density_kg_m3", src),
        "resampled_from": _text_attr(f, "resampled_from"),
        "noise_venc_m_s": _attr(f, "noise_venc_m_s", src),
        "acquired_voxel_size_mm": _attr(f, "acquired_voxel_size_mm", src, size=2),
    }


def _text_attr(f, name: str) -> str | None:
    value = f.attrs.get(name)
    if value is None:
        return None
    return value.decode() if isinstance(value, bytes) else str(value)


def read_frames(path) -> tuple[list[Acquisition], np.ndarray, float]:
    """Read a time-resolved (cine) input file: ``(frames, trigger_times_ms, cardiac_period_ms)``.

    Every image dataset has the leading time axis ``(nt, nz, ny, nx)``; each
    frame is validated like a single-frame file, except that a frame holding
    NaN or Inf is returned as it is (the cine reconstruction reports it by
    index and bridges it) unless every frame does. The period defaults to the
    last trigger time plus the mean frame spacing (the format document).
    """
    src, f = _open_input(path)
    with f:
        if "trigger_times_ms" not in f.attrs:
            raise InputError(f"{src}: not time-resolved (no attribute 'trigger_times_ms'); use read_acquisition")
        try:
            times = np.asarray(f.attrs["trigger_times_ms"], dtype=float).ravel()
        except (TypeError, ValueError):
            raise InputError(
                f"{src}: attribute 'trigger_times_ms' must be numbers (ms, one per frame), got "
                f"{f.attrs['trigger_times_ms']!r}"
            ) from None
        if times.size == 0 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
            raise InputError(f"{src}: 'trigger_times_ms' must be finite and increasing, got {times.tolist()}")
        nt = times.size
        arrays = {}
        for name in ("magnitude", "velocity", "phase", "velocity_x", "velocity_y"):
            arr = _numeric_dataset(f, name, src)
            if arr is not None:
                if arr.ndim != 4 or arr.shape[0] != nt:
                    raise InputError(
                        f"{src}: '{name}' of a time-resolved file must have shape (nt = {nt}, nz, ny, nx), "
                        f"got {arr.shape}"
                    )
                arrays[name] = arr
        if "magnitude" not in arrays:
            raise InputError(f"{src}: missing dataset 'magnitude'")
        if ("velocity_x" in arrays) != ("velocity_y" in arrays):
            raise InputError(f"{src}: 'velocity_x' and 'velocity_y' come together; one of them is missing")
        common = _input_attrs(f, src)
        period = _attr(f, "cardiac_period_ms", src)
    frames = []
    for it in range(nt):
        acq = Acquisition(
            magnitude=arrays["magnitude"][it],
            velocity=arrays["velocity"][it] if "velocity" in arrays else None,
            phase=arrays["phase"][it] if "phase" in arrays else None,
            velocity_inplane=(
                np.stack([arrays["velocity_x"][it], arrays["velocity_y"][it]]) if "velocity_x" in arrays else None
            ),
            source=f"{src} (frame {it})",
            **common,
        )
        if not acq.nonfinite_slices():
            acq.validate()
        frames.append(acq)  # a frame with NaN/Inf is kept: the cine reconstruction fails it by index, not the file
    if all(a.nonfinite_slices() for a in frames):
        frames[0].validate()  # every frame is bad: the single-frame message names the problem
    if period is None and nt == 1:
        raise InputError(f"{src}: one frame and no 'cardiac_period_ms': the cycle's length is not defined; add it")
    if period is None:
        period = float(times[-1] + np.mean(np.diff(times)))
    elif not period > times[-1]:
        raise InputError(f"{src}: 'cardiac_period_ms' {period:g} must exceed the last trigger time {times[-1]:g}")
    return frames, times, float(period)


@contextlib.contextmanager
def atomic_h5(path):
    """An HDF5 file built in memory and written to ``path`` only when complete (:func:`wss_nlp.io.outputs.write_bytes`).

    The HDF5 library never touches the disk: a full disk or any other OS error surfaces once, from the final
    write, as one :class:`InputError` line naming ``path``, and leaves nothing behind (neither a partial file nor
    a temporary one); an existing ``path`` that is not a regular file (a device, a FIFO) is refused, never
    replaced.
    """
    import io

    import h5py

    from .outputs import check_replaceable, write_bytes

    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"{path}: output folder {folder} does not exist")
    check_replaceable(path)
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as f:
        yield f
    write_bytes(path, buffer.getvalue())


def atomic_write(path, data) -> None:
    """Write text or bytes to ``path`` through a temporary file, renamed only when complete
    (:func:`wss_nlp.io.outputs.write_bytes`)."""
    from .outputs import write_bytes

    write_bytes(path, data.encode() if isinstance(data, str) else data)


def write_acquisition(path, acq: Acquisition) -> None:
    """Write an input file in the public format (atomic)."""
    with atomic_h5(path) as f:
        _write_input(f, [acq])


def write_frames(path, frames: list[Acquisition], trigger_times_ms, cardiac_period_ms: float | None = None) -> None:
    """Write a time-resolved (cine) input file: the frames' images with a leading time axis (atomic).

    The frames share everything but their images; the inverse of :func:`read_frames`.
    """
    times = np.asarray(trigger_times_ms, dtype=float).ravel()
    if times.size != len(frames) or np.any(np.diff(times) <= 0):
        raise InputError(f"{path}: {len(frames)} frames need as many increasing trigger times, got {times.tolist()}")
    with atomic_h5(path) as f:
        _write_input(f, frames, time_axis=True)
        f.attrs["trigger_times_ms"] = times
        if cardiac_period_ms is not None:
            f.attrs["cardiac_period_ms"] = float(cardiac_period_ms)


def _write_input(f, frames: list[Acquisition], time_axis: bool = False) -> None:
    """Datasets and attributes of one frame, or of frames with a leading time axis, into an open file."""
    acq = frames[0]

    def images(get):
        return np.stack([get(a) for a in frames]) if time_axis else get(acq)

    f.create_dataset("magnitude", data=images(lambda a: a.magnitude))
    if acq.velocity is not None:
        f.create_dataset("velocity", data=images(lambda a: a.velocity))
    if acq.phase is not None:
        f.create_dataset("phase", data=images(lambda a: a.phase))
    if acq.velocity_inplane is not None:  # extra datasets: readers of the single-component layout ignore them
        f.create_dataset("velocity_x", data=images(lambda a: a.velocity_inplane[0]))
        f.create_dataset("velocity_y", data=images(lambda a: a.velocity_inplane[1]))
    f.attrs["voxel_size_mm"] = np.asarray(acq.voxel_size_mm, dtype=float)
    f.attrs["origin_mm"] = np.asarray(acq.origin_mm, dtype=float)
    for name in ("slice_spacing_mm", "venc_m_s", "viscosity_pa_s", "density_kg_m3"):
        val = getattr(acq, name)
        if val is not None:
            f.attrs[name] = float(val)
    if acq.resampled_from is not None:
        f.attrs["resampled_from"] = acq.resampled_from
    if acq.noise_venc_m_s is not None:
        f.attrs["noise_venc_m_s"] = float(acq.noise_venc_m_s)
    if acq.acquired_voxel_size_mm is not None:
        f.attrs["acquired_voxel_size_mm"] = np.asarray(acq.acquired_voxel_size_mm, dtype=float)
    for k, v in acq.extra_attrs.items():
        f.attrs[k] = v


def provenance(options: dict | None = None, argv=None) -> dict:
    """File-level provenance attributes: versions, options, command line, time."""
    import casadi

    from .. import __version__

    out = {
        "wss_nlp_version": __version__,
        "casadi_version": getattr(casadi, "__version__", "unknown"),  # not in CasADi's type stubs
        "ipopt_version": _ipopt_version(),
        "numpy_version": np.__version__,
        "python_version": sys.version.split()[0],
        "command_line": " ".join(argv if argv is not None else sys.argv),
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    if options:
        out["options_json"] = json.dumps(options, sort_keys=True, default=str)
    return out


def _ipopt_version() -> str:
    """IPOPT version as reported by the library CasADi loads."""
    import ctypes
    import glob

    import casadi

    libs = glob.glob(os.path.join(os.path.dirname(casadi.__file__), "libipopt*"))
    for lib in libs:
        try:
            handle = ctypes.CDLL(lib)
            fn = handle.GetIpoptVersion
        except (OSError, AttributeError):
            continue
        major, minor, release = ctypes.c_int(), ctypes.c_int(), ctypes.c_int()
        fn(ctypes.byref(major), ctypes.byref(minor), ctypes.byref(release))
        return f"{major.value}.{minor.value}.{release.value}"
    return "unknown"


def _stats_attrs(group, stats, prefix):
    for k, v in stats.as_attrs(prefix).items():
        group.attrs[k] = v if not isinstance(v, (dict, list)) else str(v)


def write_result(path, results, options: dict, argv=None, extra_attrs: dict | None = None) -> None:
    """Write reconstructions in the output format (one group per slice, atomic).

    Parameters
    ----------
    results : list of :class:`~wss_nlp.pipeline.results.SliceResult` or
        :class:`~wss_nlp.models.baselines.BaselineResult`
    options : dict
        The options used, stored as JSON in the provenance.
    """

    with atomic_h5(path) as f:
        for k, v in provenance(options, argv).items():
            f.attrs[k] = v
        for k, v in (extra_attrs or {}).items():
            f.attrs[k] = v
        f.attrs["n_slices"] = len(results)
        f.attrs["all_converged"] = bool(all(r.converged for r in results))
        failed = [r.index for r in results if isinstance(r, FailedSlice)]
        f.attrs["failed_slices"] = np.asarray(failed, dtype=int)
        if getattr(results, "stack", None) is not None:
            f.attrs["stack_json"] = json.dumps(results.stack.as_dict(), default=float)
        for r in results:
            write_slice_group(f.create_group(f"slice_{r.index:03d}"), r)


def write_slice_group(s, r) -> None:
    """One slice's result into the group ``s``: the contract's datasets and everything else the result holds."""
    if isinstance(r, FailedSlice):
        _write_failed(s, r)
        return
    _write_core(s, r)
    if getattr(r, "screen", None):
        s.attrs["screen_json"] = json.dumps(r.screen, default=float)
    if getattr(getattr(r, "lumen", None), "tissue", None):  # hook (issue 39): surround model, offset correction
        s.attrs["tissue_json"] = json.dumps(r.lumen.tissue, default=float)
    if getattr(r, "near_wall", None) is not None:
        s.attrs["near_wall_json"] = json.dumps(r.near_wall.as_dict(), default=float)
    if isinstance(r, BaselineResult):  # a classical method: no velocity model to store
        s.attrs["baseline_json"] = json.dumps(r.info)
        s["geometry"].attrs["segmentation_threshold"] = r.geometry.threshold
        return
    g, v, w = r.geometry, r.velocity, r.wss
    if getattr(r, "coupled_info", None):
        s.attrs["coupled_json"] = json.dumps(r.coupled_info)
    gg = s["geometry"]
    gg.attrs.update(
        {
            "gamma_mm": g.gamma,
            "box_r0_mm": g.box[0],
            "box_r1_mm": g.box[1],
            "box_active": g.box_active,
            "residual_norm_mm": g.residual_norm,
            "penalty_mm2": g.penalty,
            "options_json": json.dumps(g.options, default=str),
        }
    )
    _stats_attrs(gg, g.stats, "solver_")
    wg = s["wss"]
    vec = getattr(w, "vector", None)
    if vec is not None:  # stacks with three velocity components (wss_nlp.models.wss.wss_vector)
        for name, arr in (
            ("vector_pa", vec.vector),
            ("normal_3d", vec.normal),
            ("axial_pa", vec.axial),
            ("circumferential_pa", vec.circumferential),
            ("normal_part_pa", vec.normal_part),
            ("magnitude_pa", vec.magnitude),
        ):
            wg[name] = arr
        wg.attrs["mean_axial_pa"] = rad.arc_length_mean(vec.axial, g.radius(w.phi), g.radius(w.phi, 1))
        wg.attrs["mean_magnitude_pa"] = rad.arc_length_mean(vec.magnitude, g.radius(w.phi), g.radius(w.phi, 1))
    if getattr(w, "tau_std", None) is not None:
        wg["tau_std_pa"] = w.tau_std
        wg.attrs["mean_std_pa"] = float(w.mean_std)
    sen = getattr(r, "sensitivity", None)
    if sen is not None:
        _write_sensitivity(s.create_group("sensitivity"), sen, r.grid.shape, r.grid.h)
    vg = s.create_group("velocity")
    vg["coefficients"] = v.coefficients
    vg["voxel_index"] = v.voxel_index
    vg["voxel_fraction"] = v.voxel_fraction
    vg["fitted_m_s"] = v.fitted
    vg.attrs.update(
        {
            "basis_json": json.dumps(v.basis.describe()),
            "r_in_mm": v.disk_map.r_in,
            "eta": v.disk_map.eta,
            "residual_norm_m_s": v.residual_norm,
            "penalty": v.penalty,
            "options_json": json.dumps(v.options, default=str),
        }
    )
    _stats_attrs(vg, v.stats, "solver_")
    for ch in (r.alpha_choice, r.beta_choice):
        if ch is None:
            return
        ag = s.create_group(f"analysis/{ch.name}")
        ag["parameters"] = np.asarray(ch.parameters, dtype=float)
        ag["residuals"] = np.asarray(ch.residuals, dtype=float)
        ag["criterion"] = np.asarray(ch.criterion, dtype=float)
        ag.attrs.update(
            {
                "rule": ch.rule,
                "chosen": float(ch.chosen),
                "noise": float(ch.noise),
                "noise_method": ch.noise_method,
                "tau": float(ch.tau),
                "satisfied": bool(ch.satisfied),
            }
        )


@dataclass
class FailedSlice:
    """A slice of a stack that could not be reconstructed; its group holds NaN and says why."""

    index: int
    reason: str
    n_phi: int = 360
    n_fourier: int = 8

    converged = False

    @property
    def warnings(self) -> list[str]:
        return [f"slice {self.index}: FAILED, not reconstructed: {self.reason}"]


def _write_failed(s, r: FailedSlice) -> None:
    """The required datasets filled with NaN, and ``failed = True`` with the reason."""
    phi = 2 * np.pi * np.arange(r.n_phi) / r.n_phi
    nan = np.full(r.n_phi, np.nan)
    s.attrs.update(
        {
            "failed": True,
            "error": r.reason,
            "converged": False,
            "alpha": np.nan,
            "beta": np.nan,
            "warnings": json.dumps(r.warnings),
            "method": "none",
        }
    )
    s["geometry/center_mm"] = np.full(2, np.nan)
    s["geometry/coefficients"] = np.full(2 * r.n_fourier + 1, np.nan)
    s["geometry/phi"] = phi
    s["geometry/radius_mm"] = nan
    s["wss/phi"] = phi
    s["wss/tau_pa"] = nan
    s["wss"].attrs["mean_pa"] = np.nan


def _write_core(s, r) -> None:
    """The datasets and attributes every result has (the format's required part, plus wall points)."""
    g, w = r.geometry, r.wss
    s.attrs["alpha"] = float(g.alpha)
    s.attrs["beta"] = float("nan") if isinstance(r, BaselineResult) else float(r.velocity.beta)
    s.attrs["converged"] = bool(r.converged)
    s.attrs["warnings"] = json.dumps(r.warnings)
    s.attrs["seconds_json"] = json.dumps(r.seconds)
    if getattr(r, "dephasing", None):
        s.attrs["dephasing_json"] = json.dumps(r.dephasing.as_dict())
    s.attrs["method"] = getattr(r, "method", "decoupled")
    gg = s.create_group("geometry")
    gg["center_mm"] = np.asarray(g.center, dtype=float)
    gg["coefficients"] = g.coefficients
    gg["phi"] = w.phi
    gg["radius_mm"] = g.radius(w.phi)
    gg.attrs.update(
        {"magnitude_m0": r.normalization.m0, "magnitude_m1": r.normalization.m1, "equal_area_radius_mm": r.lumen.r_area}
    )
    wg = s.create_group("wss")
    wg["phi"] = w.phi
    wg["tau_pa"] = w.tau
    wg["wall_x_mm"] = w.wall_x
    wg["wall_y_mm"] = w.wall_y
    wg.attrs["mean_pa"] = float(w.mean)
    wg.attrs["viscosity_pa_s"] = float(w.viscosity_pa_s)


def _open_result(src: str):
    """Open an HDF5 file for reading, with an InputError naming the file if it is missing or not HDF5."""
    import h5py

    if not os.path.exists(src):
        raise InputError(f"{src}: no such file")
    try:
        return h5py.File(src, "r")
    except OSError as exc:
        raise InputError(_open_error(src, exc)) from None


def _write_sensitivity(group, sen, shape, h_mm: float) -> None:
    """Derivatives of tau and mean tau (see wss_nlp.uncertainty.sensitivity) and the band's two parts."""
    group["names"] = np.array(sen.names, dtype="S")
    group["d_tau"] = sen.d_tau  # (n_phi, n_names), Pa per unit
    group["d_mean"] = sen.d_mean
    for name, index, values in (
        ("d_mean_d_magnitude", sen.m_index, sen.d_mean_d_m),
        ("d_mean_d_velocity", sen.u_index, sen.d_mean_d_u),
    ):
        image = np.zeros(int(np.prod(shape)))
        image[index] = values
        group[name] = image.reshape(shape)  # per voxel of the normalized magnitude / velocity (m/s) image
    group.attrs.update(
        {
            "mean_std_pa": float(sen.mean_std),
            "mean_std_magnitude_pa": float(sen.mean_std_magnitude),
            "mean_std_velocity_pa": float(sen.mean_std_velocity),
            "seconds": float(sen.seconds),
            "h_mm": float(h_mm),
            "noise_json": json.dumps(
                {k: v for k, v in sen.noise.items() if not isinstance(v, np.ndarray)}, default=float
            ),
        }
    )


def read_sensitivity(path) -> dict:
    """``{slice name: {"names", "d_mean", "d_tau", "mean_std_*", "h_mm", "alpha", "beta", "gamma", "mean_pa"}}``.

    A time-resolved result's frames that kept their own fit (and band) appear as ``slice_NNN/frame_KKK``."""
    out = {}
    with _open_result(str(path)) as f:
        for name, s in _record_groups(f):
            if "sensitivity" not in s:
                continue
            g = s["sensitivity"]
            out[name] = {
                "names": [n.decode() for n in g["names"][()]],
                "d_mean": np.asarray(g["d_mean"]),
                "d_tau": np.asarray(g["d_tau"]),
                "mean_std_pa": float(g.attrs["mean_std_pa"]),
                "mean_std_magnitude_pa": float(g.attrs["mean_std_magnitude_pa"]),
                "mean_std_velocity_pa": float(g.attrs["mean_std_velocity_pa"]),
                "alpha": float(s.attrs["alpha"]),
                "beta": float(s.attrs["beta"]),
                "gamma": float(s["geometry"].attrs["gamma_mm"]),
                "mean_pa": float(s["wss"].attrs["mean_pa"]),
                "h_mm": float(g.attrs["h_mm"]),
            }
    return out


def _record_groups(f):
    """``(name, group)`` of every single-slice record of a result: each slice group, or in a time-resolved
    result each frame's record ``slice_NNN/frame_KKK`` (the slice groups hold the series)."""
    for name in sorted(k for k in f if k.startswith("slice_")):
        s = f[name]
        if "frames" in s:
            for frame in sorted(s["frames"]):
                yield f"{name}/{frame}", s["frames"][frame]
        else:
            yield name, s


def _per_frame(value):
    """A slice attribute that is a scalar, or one value per frame in a time-resolved result."""
    array = np.asarray(value, dtype=float)
    return float(array) if array.ndim == 0 else array


def result_layout(path) -> str:
    """What a result (or truth) file holds: ``"slice"``, ``"stack"``, ``"cine"`` or ``"stack of cines"``."""
    with _open_result(str(path)) as f:
        names = [k for k in f if k.startswith("slice_")]
        if not names:
            raise InputError(f"{path}: no 'slice_NNN' groups; not a wss-nlp result file")
        cine = "trigger_times_ms" in f.attrs
    if cine:
        return "stack of cines" if len(names) > 1 else "cine"
    return "stack" if len(names) > 1 else "slice"


def read_cine_models(path) -> dict:
    """``{slice name: record}``: each slice's velocity model over the cycle (``cine_model_json``: the model chosen
    and why, the candidates' criteria, the walls, the viscosity the frames imply), with ``failed_frames``,
    ``time_ms``, the per-frame ``alpha`` and ``beta``, ``warnings`` and ``tawss_note`` where the frames do not
    cover the cycle."""
    out = {}
    with _open_result(str(path)) as f:
        for name in sorted(k for k in f if k.startswith("slice_")):
            s = f[name]
            rec = json.loads(s.attrs["cine_model_json"]) if "cine_model_json" in s.attrs else {}
            rec["failed_frames"] = [int(k) for k in np.atleast_1d(s.attrs.get("failed_frames", []))]
            rec["time_ms"] = s["wss/time_ms"][()] if "wss/time_ms" in s else np.array([])
            rec["alpha"] = np.atleast_1d(np.asarray(s.attrs.get("alpha", np.nan), dtype=float))
            rec["beta"] = np.atleast_1d(np.asarray(s.attrs.get("beta", np.nan), dtype=float))
            rec["warnings"] = json.loads(s.attrs.get("warnings", "[]"))
            if "wss" in s and "tawss_note" in s["wss"].attrs:
                rec["tawss_note"] = str(s["wss"].attrs["tawss_note"])
            out[name] = rec
    return out


def read_result(path) -> list[dict]:
    """Read a result (or truth) file into one dictionary per slice.

    Keys: ``center``, ``coefficients``, ``phi``, ``radius``, ``tau``,
    ``mean_tau``, ``alpha``, ``beta``, ``converged`` and, where present,
    ``wall_x``, ``wall_y``, ``tau_std``, ``mean_std``. A time-resolved result (or truth) gives the slice's
    series: ``tau (nt, nphi)``, ``radius (nt, nphi)``, ``alpha`` and ``beta`` per frame, and ``time_ms``,
    ``mean_tau_t``, ``tawss``, ``osi``, ``viscosity_pa_s`` where present.
    """
    src = str(path)
    out = []
    with _open_result(src) as f:
        names = sorted(k for k in f if k.startswith("slice_"))
        if not names:
            raise InputError(f"{src}: no 'slice_NNN' groups; not a wss-nlp result file")
        for name in names:
            s = f[name]
            try:
                d = {
                    "name": name,
                    "center": s["geometry/center_mm"][()],
                    "coefficients": s["geometry/coefficients"][()],
                    "phi": s["geometry/phi"][()],
                    "radius": s["geometry/radius_mm"][()],
                    "tau": s["wss/tau_pa"][()],
                    "mean_tau": float(s["wss"].attrs["mean_pa"]),
                    "alpha": _per_frame(s.attrs.get("alpha", np.nan)),
                    "beta": _per_frame(s.attrs.get("beta", np.nan)),
                    "converged": bool(np.all(s.attrs.get("converged", True))),
                    "failed": bool(s.attrs.get("failed", False)),
                }
            except KeyError as exc:
                raise InputError(f"{src}: group {name} lacks {exc}") from exc
            for key, ds in (("time_ms", "wss/time_ms"), ("mean_tau_t", "wss/mean_pa_t"), ("tawss", "wss/tawss_pa"),
                            ("osi", "wss/osi"), ("mean_std_t", "wss/mean_std_pa_t")):  # fmt: skip
                if ds in s:
                    d[key] = s[ds][()]
            if "viscosity_pa_s" in s["wss"].attrs:
                d["viscosity_pa_s"] = float(s["wss"].attrs["viscosity_pa_s"])
            for key, ds in (
                ("wall_x", "wss/wall_x_mm"),
                ("wall_y", "wss/wall_y_mm"),
                ("tau_std", "wss/tau_std_pa"),
                ("tau_vector", "wss/vector_pa"),
                ("tau_axial", "wss/axial_pa"),
                ("tau_circumferential", "wss/circumferential_pa"),
            ):
                if ds in s:
                    d[key] = s[ds][()]
            if "mean_std_pa" in s["wss"].attrs:
                d["mean_std"] = float(s["wss"].attrs["mean_std_pa"])
            if "velocity_true_m_s" in s:
                d["velocity_true"] = s["velocity_true_m_s"][()]
            out.append(d)
    return out


def read_choices(path) -> dict:
    """``{slice name: {"alpha": ParameterChoice, "beta": ParameterChoice}}`` from a result file."""
    import h5py

    from ..parameters.rules import ParameterChoice

    read_result(path)  # validates the file and its slices
    out: dict = {}
    with h5py.File(path, "r") as f:
        for name, s in _record_groups(f):
            out[name] = {}
            for which in ("alpha", "beta"):
                key = f"analysis/{which}"
                if key not in s:
                    continue
                g = s[key]
                a = g.attrs
                out[name][which] = ParameterChoice(
                    which,
                    str(a["rule"]),
                    float(a["chosen"]),
                    g["parameters"][()],
                    g["residuals"][()],
                    float(a["noise"]),
                    str(a["noise_method"]),
                    float(a["tau"]),
                    bool(a["satisfied"]),
                    g["criterion"][()],
                )
    return out


def read_dephasing(path) -> dict:
    """``{slice name: {"passes", "min_factor", "next_move"}}``: each slice's dephasing passes (``dephasing_json``).

    ``min_factor`` is the smallest predicted magnitude factor of the first check (a pass runs below
    ``1 - DEPHASING_THRESHOLD``); ``next_move`` the last predicted wall move of a further k-space pass in
    voxels (None when none was predicted). Files written before ``dephasing_json`` existed kept these
    numbers in ``seconds_json`` (``dephasing_passes``, ``min_dephasing_factor``, ``dephasing_next_move``).
    """
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        for name, s in _record_groups(f):
            attrs = s.attrs
            if "dephasing_json" in attrs:
                rec = json.loads(attrs["dephasing_json"])
            else:
                old = json.loads(attrs.get("seconds_json", "{}"))
                rec = {new: old[key] for new, key in _OLD_DEPHASING_KEYS.items() if key in old}
            if "min_factor" in rec:
                out[name] = {
                    "passes": int(rec.get("passes", 0)),
                    "min_factor": float(rec["min_factor"]),
                    "next_move": rec.get("next_move"),
                }
    return out


#: Where files written before ``dephasing_json`` kept the dephasing record (inside ``seconds_json``).
_OLD_DEPHASING_KEYS = {"passes": "dephasing_passes", "min_factor": "min_dephasing_factor",
                       "next_move": "dephasing_next_move", "beta": "dephasing_beta"}  # fmt: skip


def read_near_wall(path) -> dict:
    """``{slice name: dict}``: the near-wall model record of each slice that has one (``near_wall_json``).

    In a time-resolved result the names are the frames' records, ``slice_NNN/frame_MMM`` (also for
    :func:`read_choices` and :func:`read_dephasing`).
    """
    import h5py

    with h5py.File(path, "r") as f:
        return {
            name: json.loads(s.attrs["near_wall_json"]) for name, s in _record_groups(f) if "near_wall_json" in s.attrs
        }
