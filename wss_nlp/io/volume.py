"""4D flow volumes: a magnitude and three velocity components on one 3D voxel grid, in and out of HDF5.

The volume layout of the file contract (docs, "File formats"): a file whose root attribute ``layout`` is
``"volume"`` holds

* ``volume/magnitude``: float, ``(nt, ni, nj, nk)``, raw units (``nt = 1`` for one frame);
* ``volume/velocity``: float, ``(nt, 3, ni, nj, nk)``, m/s, the components along the world axes x, y, z
  of ``affine_mm`` (not along the voxel axes);
* root attributes ``affine_mm`` (4 x 4: voxel index ``(i, j, k, 1)`` to world ``(x, y, z, 1)`` in mm, the
  NIfTI convention, voxel centres at integer indices), ``venc_m_s`` (3 floats, per component; optional),
  ``viscosity_pa_s``, ``density_kg_m3`` (optional), ``trigger_times_ms`` (``nt`` floats, increasing;
  required when ``nt > 1``), ``cardiac_period_ms`` (optional), ``source`` (text).

The 2D layouts of ``shared/spec/data-format.md`` have no ``layout`` attribute and a root dataset
``magnitude``; a 2D reader meets no ``magnitude`` at the root of a volume file and refuses it by name.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

#: The value of the root attribute ``layout`` that marks a volume file.
LAYOUT = "volume"


@dataclass
class VolumeAcquisition:
    """A 4D flow acquisition: magnitude ``(nt, ni, nj, nk)`` and velocity ``(nt, 3, ni, nj, nk)`` in m/s.

    The velocity's components are along the world axes of ``affine_mm`` (x, y, z), whatever the voxel axes.
    """

    magnitude: np.ndarray
    velocity: np.ndarray
    affine_mm: np.ndarray
    venc_m_s: tuple[float, float, float] | None = None
    viscosity_pa_s: float | None = None
    density_kg_m3: float | None = None
    trigger_times_ms: np.ndarray | None = None
    cardiac_period_ms: float | None = None
    source: str = "<memory>"
    extra_attrs: dict = field(default_factory=dict)

    @property
    def nt(self) -> int:
        return int(self.magnitude.shape[0])

    @property
    def shape(self) -> tuple[int, int, int]:
        """Voxels along the index axes ``(ni, nj, nk)``."""
        ni, nj, nk = self.magnitude.shape[1:]
        return int(ni), int(nj), int(nk)

    @property
    def voxel_size_mm(self) -> np.ndarray:
        """Edge lengths of a voxel along the index axes i, j, k (mm): the affine's column norms."""
        return np.linalg.norm(np.asarray(self.affine_mm, float)[:3, :3], axis=0)

    def world(self, index: np.ndarray) -> np.ndarray:
        """World coordinates (mm) of voxel indices ``(..., 3)`` (fractional indices allowed)."""
        a = np.asarray(self.affine_mm, float)
        return np.asarray(index, float) @ a[:3, :3].T + a[:3, 3]

    def index(self, world_mm: np.ndarray) -> np.ndarray:
        """Fractional voxel indices of world points ``(..., 3)`` in mm (the inverse of :meth:`world`)."""
        a = np.asarray(self.affine_mm, float)
        return np.linalg.solve(a[:3, :3], (np.asarray(world_mm, float) - a[:3, 3]).reshape(-1, 3).T).T.reshape(
            np.shape(world_mm)
        )

    def frame(self, it: int) -> VolumeAcquisition:
        """Frame ``it`` alone (``nt = 1``, no trigger times)."""
        return VolumeAcquisition(
            self.magnitude[it : it + 1], self.velocity[it : it + 1], self.affine_mm, self.venc_m_s,
            self.viscosity_pa_s, self.density_kg_m3, None, None, f"{self.source} (frame {it})", dict(self.extra_attrs),
        )  # fmt: skip

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

    def validate(self) -> None:
        """Check shapes, finiteness and attributes; raise :class:`wss_nlp.errors.InputError` naming the item."""
        src = self.source
        mag, vel = np.asarray(self.magnitude), np.asarray(self.velocity)
        if mag.ndim != 4:
            raise InputError(f"{src}: 'volume/magnitude' must have shape (nt, ni, nj, nk), got {mag.shape}")
        if vel.shape != (mag.shape[0], 3, *mag.shape[1:]):
            raise InputError(
                f"{src}: 'volume/velocity' must have shape (nt, 3, ni, nj, nk) = {(mag.shape[0], 3, *mag.shape[1:])}, "
                f"got {vel.shape}"
            )
        if min(mag.shape[1:]) < 4:
            raise InputError(f"{src}: a volume of {mag.shape[1:]} voxels is too small to hold a vessel")
        for name, arr in (("volume/magnitude", mag), ("volume/velocity", vel)):
            bad = ~np.isfinite(arr)
            if bad.any():
                raise InputError(f"{src}: '{name}' contains NaN or Inf ({int(bad.sum())} values)")
        if float(mag.min()) < -1e-6 * max(float(np.abs(mag).max()), 1e-300):
            raise InputError(f"{src}: 'volume/magnitude' has negative values; store the modulus of the complex image")
        a = np.asarray(self.affine_mm, float)
        if a.shape != (4, 4) or not np.all(np.isfinite(a)) or abs(np.linalg.det(a[:3, :3])) < 1e-12:
            raise InputError(f"{src}: 'affine_mm' must be a finite, invertible 4 x 4 matrix, got {a.tolist()}")
        if self.venc_m_s is not None:
            v = np.asarray(self.venc_m_s, float)
            if v.shape != (3,) or not np.all(v > 0):
                raise InputError(f"{src}: 'venc_m_s' must be three positive numbers (m/s), got {self.venc_m_s}")
        if self.viscosity_pa_s is not None and not self.viscosity_pa_s > 0:
            raise InputError(f"{src}: 'viscosity_pa_s' must be > 0, got {self.viscosity_pa_s}")
        if self.trigger_times_ms is not None:
            t = np.asarray(self.trigger_times_ms, float).ravel()
            if t.size != mag.shape[0] or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
                raise InputError(
                    f"{src}: 'trigger_times_ms' must be {mag.shape[0]} finite increasing values, got {t.tolist()}"
                )
            if self.cardiac_period_ms is not None and not self.cardiac_period_ms > t[-1] - t[0]:
                raise InputError(f"{src}: 'cardiac_period_ms' {self.cardiac_period_ms:g} must exceed the frames' span")
        elif mag.shape[0] > 1:
            raise InputError(f"{src}: {mag.shape[0]} frames need 'trigger_times_ms'")


def is_volume_file(path) -> bool:
    """Whether ``path`` is an HDF5 file of the volume layout (False for anything else, unreadable included)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("layout", None) in (LAYOUT, LAYOUT.encode())
    except OSError:
        return False


def write_volume(path, vol: VolumeAcquisition) -> None:
    """Write a volume file (atomic: nothing at ``path`` until it is complete)."""
    from .files import atomic_h5

    vol.validate()
    with atomic_h5(path) as f:
        f.attrs["layout"] = LAYOUT
        f.create_dataset("volume/magnitude", data=np.asarray(vol.magnitude, float))
        f.create_dataset("volume/velocity", data=np.asarray(vol.velocity, float))
        f.attrs["affine_mm"] = np.asarray(vol.affine_mm, float)
        f.attrs["source"] = vol.source
        if vol.venc_m_s is not None:
            f.attrs["venc_m_s"] = np.asarray(vol.venc_m_s, float)
        for name in ("viscosity_pa_s", "density_kg_m3", "cardiac_period_ms"):
            val = getattr(vol, name)
            if val is not None:
                f.attrs[name] = float(val)
        if vol.trigger_times_ms is not None:
            f.attrs["trigger_times_ms"] = np.asarray(vol.trigger_times_ms, float)
        for k, v in vol.extra_attrs.items():
            f.attrs[k] = v


def read_volume(path) -> VolumeAcquisition:
    """Read and validate a volume file; every problem is an :class:`InputError` naming the file and item."""
    import h5py

    src = str(path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{src}: cannot read as HDF5 ({exc})") from None
    with f:
        if f.attrs.get("layout", None) not in (LAYOUT, LAYOUT.encode()):
            raise InputError(f"{src}: not a volume file (root attribute 'layout' is not '{LAYOUT}')")
        arrays = {}
        for name in ("volume/magnitude", "volume/velocity"):
            if name not in f or not isinstance(f[name], h5py.Dataset):
                raise InputError(f"{src}: missing dataset '{name}'")
            try:
                arrays[name] = np.asarray(f[name][()], dtype=float)
            except (TypeError, ValueError):
                raise InputError(f"{src}: dataset '{name}' is not numeric") from None

        def number(name, size=None):
            if name not in f.attrs:
                return None
            try:
                val = np.asarray(f.attrs[name], dtype=float)
            except (TypeError, ValueError):
                raise InputError(f"{src}: attribute '{name}' must be numeric, got {f.attrs[name]!r}") from None
            if size is not None and val.size != size:
                raise InputError(f"{src}: attribute '{name}' must have {size} values, got {val.size}")
            return val

        affine = number("affine_mm", 16)
        if affine is None:
            raise InputError(f"{src}: missing attribute 'affine_mm' (4 x 4, voxel index to world mm)")
        venc = number("venc_m_s")
        if venc is not None:
            venc = np.full(3, float(venc.ravel()[0])) if venc.size == 1 else venc.ravel()
            if venc.size != 3:
                raise InputError(f"{src}: attribute 'venc_m_s' must have 1 or 3 values, got {venc.size}")
        times = number("trigger_times_ms")
        scalars = {n: number(n, 1) for n in ("viscosity_pa_s", "density_kg_m3", "cardiac_period_ms")}

    def scalar(name: str) -> float | None:
        value = scalars[name]
        return None if value is None else float(value.ravel()[0])

    vol = VolumeAcquisition(
        magnitude=arrays["volume/magnitude"],
        velocity=arrays["volume/velocity"],
        affine_mm=affine.reshape(4, 4),
        venc_m_s=None if venc is None else (float(venc[0]), float(venc[1]), float(venc[2])),
        viscosity_pa_s=scalar("viscosity_pa_s"),
        density_kg_m3=scalar("density_kg_m3"),
        trigger_times_ms=None if times is None else times.ravel(),
        cardiac_period_ms=scalar("cardiac_period_ms"),
        source=src,  # messages name the file the user gave, not where it was first made
    )
    vol.validate()
    return vol
