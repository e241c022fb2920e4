"""The decoupled reconstruction of one acquisition: geometry -> velocity -> WSS.

:func:`reconstruct_slice` runs the three steps of the paper on one slice;
:func:`reconstruct` does so for every slice of an :class:`~wss_nlp.io.Acquisition`,
reporting progress, and returns :class:`SliceResult` objects that carry the
numbers, the solver statistics and what was assumed.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from . import geometry as geo
from . import measurement as meas
from . import preprocess as pp
from . import velocity as vel
from . import wss as wss_mod
from .errors import InputError, WssNlpError
from .io import Acquisition
from .measurement import VoxelGrid


#: Smallest predicted magnitude loss (1 - D_i) that triggers the dephasing pass.
DEPHASING_THRESHOLD = 0.01


@dataclass(frozen=True)
class ReconstructionOptions:
    """Everything that controls a reconstruction (stored in the result file)."""

    geometry: geo.GeometryOptions = field(default_factory=geo.GeometryOptions)
    velocity: vel.VelocityOptions = field(default_factory=vel.VelocityOptions)
    n_phi: int = 360
    viscosity_pa_s: float | None = None  # overrides the file's value when set
    dephasing_correction: bool = True  # needs venc; see measurement.dephasing_factors

    def __post_init__(self):
        if self.n_phi < 360:
            raise InputError(f"n_phi must be >= 360 (file format), got {self.n_phi}")

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class SliceResult:
    """Result of one slice, with everything needed to write, plot and judge it."""

    index: int
    geometry: geo.GeometryResult
    velocity: vel.VelocityResult
    wss: wss_mod.WssResult
    normalization: pp.Normalization
    lumen: pp.Lumen
    grid: VoxelGrid
    magnitude: np.ndarray  # normalized, (ny, nx)
    velocity_image: np.ndarray  # measured velocity, (ny, nx)
    seconds: dict = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return bool(self.geometry.stats.converged and self.velocity.stats.converged)

    @property
    def warnings(self) -> list[str]:
        out = []
        for name, st in (("geometry", self.geometry.stats), ("velocity", self.velocity.stats)):
            if not st.converged:
                out.append(f"slice {self.index}: {name} solve did not converge ({st.solver}: {st.status})")
        if self.geometry.box_active:
            out.append(f"slice {self.index}: the radius reached the box [{self.geometry.box[0]:.3g}, "
                       f"{self.geometry.box[1]:.3g}] mm; the lumen may not be star-shaped about the centre")
        return out


def resolve_viscosity(acq: Acquisition, options: ReconstructionOptions) -> float:
    mu = options.viscosity_pa_s if options.viscosity_pa_s is not None else acq.viscosity_pa_s
    if mu is None:
        raise InputError(f"{acq.source}: no viscosity: the file has no 'viscosity_pa_s' attribute; "
                         "pass --viscosity (Pa*s, e.g. 3.5e-3 for blood)")
    if not mu > 0:
        raise InputError(f"{acq.source}: viscosity must be > 0 Pa*s, got {mu}")
    return float(mu)


def reconstruct_slice(magnitude: np.ndarray, velocity_image: np.ndarray, grid: VoxelGrid, viscosity_pa_s: float,
                      options: ReconstructionOptions, source: str = "<memory>", index: int = 0,
                      venc: float | None = None) -> SliceResult:
    """Geometry (Sec. 2), velocity (Sec. 3) and WSS (Sec. 4) of one slice.

    With ``options.dephasing_correction`` and a known ``venc``, a second
    geometry and velocity pass uses the magnitude divided by the dephasing
    factors predicted by the first velocity reconstruction
    (:func:`wss_nlp.measurement.dephasing_factors`); an extension of the
    paper's model that removes the radius bias from intra-voxel dephasing.
    """
    where = f"{source} slice {index}"
    t = {}
    t0 = time.perf_counter()
    norm = pp.histogram_peaks(magnitude, where)
    m = pp.normalize_magnitude(magnitude, norm)
    lumen = pp.find_lumen(m, grid, where)
    t["preprocess"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    problem = geo.GeometryProblem(grid, m, lumen.center, lumen.r0, lumen.r1, lumen.r_area)
    g = geo.solve(problem, options.geometry)
    t["geometry"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    vp = vel.assemble(grid, velocity_image, g.coefficients, g.center, options.velocity)
    v = vel.solve(vp, options.velocity)
    t["velocity"] = time.perf_counter() - t0

    factors = None
    if options.dephasing_correction and venc is not None:
        factors = meas.dephasing_factors(vp.voxels, v.evaluate_physical, venc, near_wall=(g.coefficients, grid.h))
    # a second pass only pays where some wall voxel loses more than 1 % of its magnitude
    if factors is not None and np.min(factors) < 1 - DEPHASING_THRESHOLD:
        t0 = time.perf_counter()
        m_corr = m.copy().ravel()
        m_corr[vp.voxels.index] = np.clip(m_corr[vp.voxels.index] / np.maximum(factors, 1e-3), 0.0, 1.0)
        problem = geo.GeometryProblem(grid, m_corr.reshape(m.shape), lumen.center, lumen.r0, lumen.r1, lumen.r_area)
        g = geo.solve(problem, options.geometry, x0=g.coefficients)
        vp = vel.assemble(grid, velocity_image, g.coefficients, g.center, options.velocity, basis=vp.basis)
        v = vel.solve(vp, options.velocity)
        t["dephasing_pass"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    w = wss_mod.from_reconstruction(v, options.n_phi, viscosity_pa_s)
    t["wss"] = time.perf_counter() - t0
    t["min_dephasing_factor"] = float(np.min(factors)) if factors is not None else 1.0
    if not np.all(np.isfinite(w.tau)):
        raise WssNlpError(f"{where}: wall shear stress is not finite; the reconstruction is unusable")
    return SliceResult(index, g, v, w, norm, lumen, grid, m, np.asarray(velocity_image, float), t)


def reconstruct(acq: Acquisition, options: ReconstructionOptions | None = None, progress=None) -> list[SliceResult]:
    """Reconstruct every slice of an acquisition independently.

    Parameters
    ----------
    progress : callable or None
        Called as ``progress(done, total, slice_result)`` after each slice.
    """
    options = options or ReconstructionOptions()
    acq.validate()
    mu = resolve_viscosity(acq, options)
    velocity = acq.velocity_images()
    out = []
    for iz in range(acq.nz):
        res = reconstruct_slice(acq.magnitude[iz], velocity[iz], acq.grid, mu, options, acq.source, iz, acq.venc_m_s)
        out.append(res)
        if progress is not None:
            progress(iz + 1, acq.nz, res)
    return out
