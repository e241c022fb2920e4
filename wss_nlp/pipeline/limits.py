"""Every reconstruction option checked before any work: its type and range in the user's words, and what it costs.

Two kinds of checks, both before anything is solved:

* **Values** (:func:`check_values`): each option the user set, from the command line or a study file, against
  :data:`LIMITS` (whole numbers where a count is meant, the range in which the option means something, physical
  quantities against :mod:`wss_nlp.io.ranges`). A refusal names the option as the user wrote it
  (``--quad-order 0: must be a whole number in 1-16 ...``), never the field inside the package.
* **Size** (:func:`check_cost`): the options that scale the problem (``--degree``, ``--angular-order``,
  ``--max-eigenvalue``, ``--n-fourier``, ``--quad-order``, ``--n-phi``; the image's size and the lumen's) give an
  estimate of the memory and the time of one slice (:func:`reconstruction_cost`). What would not fit in the
  memory available is refused; what would take longer than :data:`TIME_LIMIT_S` a slice asks for
  ``--allow-large``.

Notes
-----
The cost model is a sum of the parts that grow (measured on one slice, ``scripts/option_costs.py``, table
``scripts/results/option_costs.md``): the Zernike basis's exact Gram matrices, built term by term
(``~ P D`` for ``P`` functions of degree up to ``D``); the velocity's design matrix
(``~ voxels q^2 P``); the geometry's sub-voxel points (``~ voxels q^2``) and its dense Hessian and box
(``~ N^2``); the WSS and its band at ``n_phi`` angles (``~ n_phi``; the band holds per-angle derivatives). The
constants are those of a 2-core machine shared with other work, so the estimates err on the slow side.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..io import ranges

#: Longest estimated time of one slice (seconds) run without ``--allow-large``.
TIME_LIMIT_S = 900.0
#: Memory assumed available when the system does not say (bytes).
DEFAULT_AVAILABLE = 8 * 2**30


@dataclass(frozen=True)
class Limit:
    """The values an option may take.

    ``integer``: a whole number; ``low``/``high``: the range (inclusive; None: open); ``quantity``: a physical
    quantity of :data:`wss_nlp.io.ranges.QUANTITIES` instead; ``why``: what the range stands for.
    """

    integer: bool = False
    low: float | None = None
    high: float | None = None
    why: str = ""
    quantity: str | None = None
    positive: bool = False  # strictly above ``low``

    def text(self) -> str:
        kind = "a whole number" if self.integer else "a number"
        if self.low is not None and self.high is not None:
            lo = f"above {self.low:g} and up to" if self.positive else f"in {self.low:g}-"
            return f"{kind} {lo}{' ' if self.positive else ''}{self.high:g}"
        if self.low is not None:
            return f"{kind} {'>' if self.positive else '>='} {self.low:g}"
        return kind


#: Smallest Zernike degree accepted from the command line and studies (scripts/option_costs.py measured the WSS
#: error by degree: see the docs page "Input checks").
MIN_DEGREE = 4

#: Each option path's limit (paths of :class:`wss_nlp.pipeline.options.ReconstructionOptions`).
LIMITS: dict[str, Limit] = {
    # the options that scale the problem have no upper limit here: their cost decides (check_cost)
    "geometry.n_fourier": Limit(True, 0, None, "harmonics of R(phi)"),
    "geometry.sobolev_s": Limit(True, 0, 4, "order of the H^s penalty (the paper uses 2)"),
    "geometry.gamma": Limit(False, 0, 5, "width of the smoothed Heaviside in mm, about a voxel's fraction",
                            positive=True),
    "geometry.quad_order": Limit(True, 1, None, "sub-voxel points per axis"),
    "velocity.degree": Limit(True, MIN_DEGREE, None, "Zernike degree; below 4 the basis cannot bend the profile away "
                                                     "from a paraboloid near the wall (--degree 0: +21 % WSS)"),
    "velocity.angular_order": Limit(True, 0, None, "highest angular order of the Zernike functions"),
    "velocity.max_eigenvalue": Limit(False, 5.79, None, "eigenvalue cut-off of the eigenfunction basis "
                                                        "(5.78 keeps none)"),
    "velocity.eta": Limit(False, 2, 16, "exponent of the map phi_R (>= 2, paper eq. (trafo))"),
    "velocity.inner_fraction": Limit(False, 0, 1, "inner radius of phi_R as a fraction of min R", positive=True),
    "velocity.layer_scale_mm": Limit(False, 0, 5, "a wall layer thinner than a voxel, in mm", positive=True),
    "coupled.velocity_weight": Limit(False, 0, 1e12, "weight of the velocity misfit in mm^2/(m/s)^2",
                                     positive=True),
    "coupled.quad_order": Limit(True, 1, None, "sub-voxel points per axis of the coupled velocity misfit"),
    "stack.z_smoothing_mm": Limit(False, 0, 200, "length in mm along the vessel over which slices are pooled"),
    "acquisition.zero_fill": Limit(False, 1, 8, "reported voxels per acquired voxel"),
    "cine.max_harmonics": Limit(True, 0, 64, "temporal harmonics of the momentum model"),
    "n_phi": Limit(True, 360, None, "angles at which the WSS is reported (the file format needs 360)"),
    "viscosity_pa_s": Limit(quantity="viscosity"),
    "density_kg_m3": Limit(quantity="density"),
    "blas_threads": Limit(True, 0, 1024, "BLAS threads (0: as the BLAS is)"),
    "noise_sigma": Limit(False, 0, 1e30, "complex noise per channel in raw magnitude units", positive=True),
    "geometry.alpha": Limit(False, 0, 1e6, "Tikhonov parameter of the radius penalty", positive=True),
    "velocity.beta": Limit(False, 0, 1e6, "Tikhonov parameter of the velocity penalty", positive=True),
    "choice.tau_alpha": Limit(False, 1, 100, "discrepancy factor (> 1: the residual may exceed the noise)"),
    "choice.tau_beta": Limit(False, 1, 100, "discrepancy factor (> 1: the residual may exceed the noise)"),
    "choice.kappa_alpha": Limit(False, 0, 100, "noise deviations the balancing rule allows", positive=True),
    "choice.kappa_beta": Limit(False, 0, 100, "noise deviations the balancing rule allows", positive=True),
    "choice.noise_magnitude": Limit(False, 0, 1e3, "noise level of the normalized magnitude in mm", positive=True),
    "choice.noise_velocity": Limit(False, 0, 10, "noise level of the velocity in m/s", positive=True),
}  # fmt: skip


def check_values(values: dict, spelled: dict) -> None:
    """Refuse a value outside its :data:`LIMITS`, naming the option as the user spelled it.

    ``values``: ``{option path: value}`` of the options the user set; ``spelled``: how each was written
    (``--n-fourier`` or the study key ``N``). Physical quantities (viscosity, density) are checked against
    :mod:`wss_nlp.io.ranges`, with ``--allow-unphysical`` (``screen.allow_unphysical``) honoured.
    """
    allow = values.get("screen.allow_unphysical", ())
    for path, value in values.items():
        limit = LIMITS.get(path)
        if limit is None or value is None:
            continue
        name = spelled.get(path, path)
        if limit.quantity is not None:
            ranges.check(limit.quantity, value, name, allow)
            continue
        _check_number(value, limit, name)


def _check_number(value, limit: Limit, name: str) -> None:
    hint = f" ({limit.why})" if limit.why else ""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{name} {value!r}: must be {limit.text()}{hint}")
    v = float(value)
    bad = not math.isfinite(v)
    bad |= limit.integer and not v.is_integer()
    if limit.low is not None:
        bad |= v <= limit.low if limit.positive else v < limit.low
    if limit.high is not None:
        bad |= v > limit.high
    if bad:
        raise InputError(f"{name} {value:g}: must be {limit.text()}{hint}")


# ------------------------------------------------------------------ cost
#: Measured constants of the cost model (scripts/option_costs.py on 2 shared cores; see the module notes).
SECONDS_BASE = 2.0  # preprocessing, the solves' fixed costs, the dephasing check, at 900 voxels x 36 points
SECONDS_PER_BASIS_TERM = 2.2e-3  # per Zernike function and degree: the exact Gram matrices
SECONDS_PER_POINT_FUNCTION = 1.5e-7  # per sub-voxel point and velocity function: design matrix, fits
SECONDS_PER_HARMONIC2 = 6e-3  # per N^2: geometry Hessian, box, band
SECONDS_PER_ANGLE = 2.1e-3  # per WSS angle with the band (its derivatives); 1e-4 without
BYTES_BASE = 80 * 2**20
BYTES_PER_POINT = 400.0  # per sub-voxel point of the geometry (CasADi graphs)
BYTES_PER_POINT_FUNCTION = 8.0  # per sub-voxel point and velocity function
BYTES_PER_HARMONIC2 = 0.08 * 2**20  # per N^2 with the band
BYTES_PER_ANGLE = 34e3  # per WSS angle with the band; 8 bytes per angle and function without


@dataclass(frozen=True)
class Cost:
    """Estimated peak memory (bytes) and time (seconds) of one slice, and what drives them."""

    memory_bytes: float
    seconds: float
    functions: int
    points: int
    detail: str


def basis_size(options) -> tuple[int, int]:
    """``(P, D)``: the velocity basis's number of functions and its degree (D: the radial order for eigen)."""
    v = options.velocity
    if v.basis == "eigen":
        # Weyl's law for the unit disk: N(lambda) ~ lambda / 4 Dirichlet eigenvalues below lambda
        p = max(1, int(v.max_eigenvalue / 4) + 1)
        return p, int(math.sqrt(v.max_eigenvalue))
    d = int(v.degree)
    mmax = d if v.angular_order is None else min(int(v.angular_order), d)
    # n <= mmax: n + 1 terms; above, mmax + 1 or mmax terms by the parity of n - mmax (closed form: any degree)
    longer = d - mmax
    p = (mmax + 1) * (mmax + 2) // 2 + (longer // 2) * (mmax + 1) + (longer - longer // 2) * mmax
    return p, d


def reconstruction_cost(options, shape, lumen_voxels: int | None = None) -> Cost:
    """Estimate one slice's peak memory and time from the options and the image ``shape`` ``(..., ny, nx)``.

    ``lumen_voxels``: the lumen's size if known (the sub-voxel points cover the lumen and a band around the wall);
    else the whole image is counted.
    """
    ny, nx = int(shape[-2]), int(shape[-1])
    image = ny * nx
    region = image if lumen_voxels is None else min(image, int(2.5 * lumen_voxels) + 100)
    q = options.geometry.quad_order or 6  # auto: at most 6
    points = region * q * q
    p, d = basis_size(options)
    n2 = (2 * options.geometry.n_fourier + 1) ** 2 / 4.0
    band = bool(options.uncertainty)
    n_phi = int(options.n_phi)
    seconds = (
        SECONDS_BASE * points / (900 * 36)
        + SECONDS_PER_BASIS_TERM * p * max(d, 1)
        + SECONDS_PER_POINT_FUNCTION * points * p
        + SECONDS_PER_HARMONIC2 * n2
        + (SECONDS_PER_ANGLE if band else 1e-4) * n_phi * max(p, 119) / 119
    )
    memory = (
        BYTES_BASE
        + BYTES_PER_POINT * points
        + BYTES_PER_POINT_FUNCTION * points * p
        + (BYTES_PER_HARMONIC2 * n2 if band else 0.0)
        + (BYTES_PER_ANGLE * n_phi * max(p, 119) / 119 if band else 8.0 * n_phi * (p + 4 * n2**0.5))
    )
    detail = (
        f"{p} velocity functions of degree {d}, {2 * options.geometry.n_fourier + 1} radius coefficients, "
        f"{points} sub-voxel points ({region} voxels x {q} x {q}), {n_phi} WSS angles"
        + (" with the band" if band else "")
    )
    return Cost(float(memory), float(seconds), p, points, detail)


def available_memory() -> float:
    """Bytes of memory available to a new allocation (``MemAvailable``), or :data:`DEFAULT_AVAILABLE`."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return float(DEFAULT_AVAILABLE)


def _size(b: float) -> str:
    return f"{b / 2**30:.1f} GB" if b >= 2**30 else f"{b / 2**20:.0f} MB"


def _duration(s: float) -> str:
    if s >= 7200:
        return f"{s / 3600:.1f} h"
    return f"{s / 60:.0f} min" if s >= 120 else f"{s:.0f} s"


def check_cost(options, shape, where: str, lumen_voxels: int | None = None, slices: int = 1) -> Cost:
    """Refuse before any work what would not fit in memory, and ask for ``--allow-large`` above the time limit.

    ``slices``: how many slices are held at once (a z-coupled stack's segment).
    """
    cost = reconstruction_cost(options, shape, lumen_voxels)
    memory = cost.memory_bytes * max(slices, 1)
    free = available_memory()
    drivers = "--degree/--angular-order or --max-eigenvalue (velocity functions), --n-fourier, --quad-order, --n-phi"
    if memory > free:
        raise InputError(
            f"{where}: these options need about {_size(memory)} of memory ({cost.detail}), {_size(free)} are "
            f"available; reduce {drivers}"
        )
    if cost.seconds > TIME_LIMIT_S and not options.screen.allow_large:
        raise InputError(
            f"{where}: these options would take about {_duration(cost.seconds)} a slice ({cost.detail}; the limit "
            f"is {_duration(TIME_LIMIT_S)}); reduce {drivers}, or pass --allow-large to run it anyway"
        )
    return cost


def check_memory(nbytes: float, where: str, what: str, reduce: str) -> None:
    """Refuse before any work something that would need more memory than is available."""
    free = available_memory()
    if nbytes > free:
        raise InputError(
            f"{where}: {what} needs about {_size(nbytes)} of memory, {_size(free)} are available; {reduce}"
        )


#: Bytes a phantom's voxel costs while it is built and written (complex signal, magnitude, phase, the voxel-mean
#: velocity, the file's copy), and its sub-voxel points per voxel at most (synthetic.phantoms.acquire).
PHANTOM_BYTES_PER_VOXEL = 120.0


def check_phantom(half_fov_mm: float, h_mm: float, images: int, where: str = "phantom") -> int:
    """Refuse a phantom whose images would not fit in memory; returns the voxels per side."""
    n = int(math.ceil(2 * half_fov_mm / h_mm))
    check_memory(
        PHANTOM_BYTES_PER_VOXEL * n * n * max(images, 1),
        where,
        f"{images} image(s) of {n} x {n} voxels (--h {h_mm:g} mm over {2 * half_fov_mm:g} mm)",
        "use a larger --h (or fewer --nz / --frames)",
    )
    return n
