r"""Time-resolved (cine) reconstruction: every frame of the cycle, then TAWSS and OSI.

Each frame is reconstructed by the single-frame pipeline (:func:`wss_nlp.reconstruct.reconstruct`), with
its own parameter choices; the frames are not yet coupled in time (issue 15: a temporal prior and the
momentum balance across frames are the next steps). What the cycle adds is computed here.

Notes
-----
With frames at trigger times :math:`t_0 < \dots < t_{n-1}` in a cycle of length :math:`T`, integrals over
the cycle use the periodic trapezoid rule, weights
:math:`w_k = (t_{k+1} - t_{k-1})/2` with :math:`t_{-1} = t_{n-1} - T`, :math:`t_n = t_0 + T`
(exact for trigonometric polynomials of degree below :math:`n/2` at equal spacing). Then, per wall angle,

.. math::

    \mathrm{TAWSS} = \frac{1}{T}\sum_k w_k |\tau_k|, \qquad
    \mathrm{OSI} = \frac12\Big(1 - \frac{|\sum_k w_k \tau_k|}{\sum_k w_k |\tau_k|}\Big),

in Pa and dimensionless (``shared/spec/data-format.md``). A frame that failed is bridged by linear
interpolation in time between its periodic neighbours, and the result says so.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from .errors import InputError, WssNlpError
from .files import Acquisition, FailedSlice
from .reconstruct import ReconstructionOptions, reconstruct

log = logging.getLogger(__name__)


def cycle_weights(times_ms, period_ms: float) -> np.ndarray:
    """Periodic trapezoid weights (ms) of the frames over one cycle (see the module notes)."""
    t = np.asarray(times_ms, dtype=float)
    if t.size == 0 or np.any(np.diff(t) <= 0):
        raise InputError(f"trigger times must increase, got {t.tolist()}")
    if not period_ms > t[-1] - t[0]:
        raise InputError(f"the cardiac period {period_ms:g} ms must exceed the frames' span {t[-1] - t[0]:g} ms")
    if t.size == 1:
        return np.array([float(period_ms)])
    before = np.concatenate([[t[-1] - period_ms], t[:-1]])
    after = np.concatenate([t[1:], [t[0] + period_ms]])
    return (after - before) / 2


def tawss_osi(tau: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(TAWSS in Pa, OSI)`` per column of ``tau (nt, nphi)`` with the cycle weights (module notes)."""
    tau = np.asarray(tau, dtype=float)
    w = np.asarray(weights, dtype=float)[:, None]
    total = float(np.sum(w))
    magnitude = np.sum(w * np.abs(tau), axis=0)
    net = np.abs(np.sum(w * tau, axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        osi = np.where(magnitude > 0, 0.5 * (1 - net / magnitude), 0.0)
    return magnitude / total, osi


def bridge(values: np.ndarray, good: np.ndarray, times_ms, period_ms: float) -> np.ndarray:
    """Rows of ``values (nt, ...)`` where ``good`` is False, linearly interpolated in time (periodically)."""
    values = np.array(values, dtype=float)
    t = np.asarray(times_ms, dtype=float)
    if good.all():
        return values
    if not good.any():
        raise InputError("every frame failed; nothing to interpolate from")
    tg = t[good]
    ext_t = np.concatenate([tg - period_ms, tg, tg + period_ms])
    flat = values.reshape(t.size, -1)
    ext_v = np.concatenate([flat[good]] * 3)
    for k in np.nonzero(~good)[0]:
        flat[k] = [np.interp(t[k], ext_t, ext_v[:, j]) for j in range(flat.shape[1])]
    return flat.reshape(values.shape)


@dataclass
class CineSeries:
    """One slice over the cycle: per-frame WSS and geometry, and the cycle's TAWSS and OSI."""

    index: int
    phi: np.ndarray
    tau: np.ndarray  # (nt, nphi), Pa; failed frames bridged
    mean: np.ndarray  # (nt,), Pa
    center: np.ndarray  # (nt, 2), mm
    coefficients: np.ndarray  # (nt, 2N+1), mm
    radius: np.ndarray  # (nt, nphi), mm
    alpha: np.ndarray
    beta: np.ndarray
    failed: np.ndarray  # (nt,) bool
    tawss: np.ndarray
    osi: np.ndarray
    time_average_mean: float
    notes: list = field(default_factory=list)


@dataclass
class CineResult:
    """Frames of a cine reconstruction: ``frames[k]`` holds the slice results of frame ``k``."""

    frames: list
    times_ms: np.ndarray
    period_ms: float
    weights: np.ndarray
    notes: list = field(default_factory=list)

    @property
    def n_slices(self) -> int:
        return len(self.frames[0])

    def series(self, iz: int) -> CineSeries:
        results = [frame[iz] for frame in self.frames]
        good = np.array([not isinstance(r, FailedSlice) for r in results])
        if not good.any():
            raise WssNlpError(f"slice {iz}: every frame failed ({results[0].reason})")
        ref = next(r for r in results if not isinstance(r, FailedSlice))
        phi = ref.wss.phi
        n_coef = ref.geometry.coefficients.size

        def rows(get, size):
            return np.array([get(r) if ok else np.full(size, np.nan) for r, ok in zip(results, good)], dtype=float)

        tau = rows(lambda r: r.wss.tau, phi.size)
        mean = rows(lambda r: [r.wss.mean], 1)[:, 0]
        center = rows(lambda r: np.asarray(r.geometry.center, dtype=float), 2)
        coefficients = rows(lambda r: r.geometry.coefficients, n_coef)
        radius = rows(lambda r: r.geometry.radius(phi), phi.size)
        alpha = rows(lambda r: [r.geometry.alpha], 1)[:, 0]
        beta = rows(lambda r: [r.velocity.beta], 1)[:, 0]
        notes = list(self.notes)
        if not good.all():
            bad = np.nonzero(~good)[0].tolist()
            notes.append(
                f"frame(s) {bad} failed ({'; '.join(results[k].reason for k in bad[:3])}); TAWSS and OSI bridge "
                "them by linear interpolation in time"
            )
        bridged = bridge(tau, good, self.times_ms, self.period_ms)
        tawss, osi = tawss_osi(bridged, self.weights)
        mean_bridged = bridge(mean[:, None], good, self.times_ms, self.period_ms)[:, 0]
        average = float(np.sum(self.weights * mean_bridged) / np.sum(self.weights))
        return CineSeries(
            iz, phi, tau, mean, center, coefficients, radius, alpha, beta, ~good, tawss, osi, average, notes
        )


#: Why cine frames take the plain basis when the near-wall choice is ``auto``.
PLAIN_FRAMES_NOTE = (
    "near-wall auto chooses layers for steady flows (family by the bulk Reynolds number); on pulsatile frames "
    "it did worse than the plain basis at every h and SNR (scripts/results/cine.md), so cine frames use the "
    "plain basis; --near-wall wall_law or exponential forces a layer"
)


def reconstruct_cine(
    frames: list[Acquisition],
    times_ms,
    period_ms: float,
    options: ReconstructionOptions | None = None,
    progress=None,
    layer_on_frames: bool = False,
) -> CineResult:
    """Reconstruct every frame (``frames[k]`` at ``times_ms[k]``); a frame that fails is recorded, not fatal.

    ``progress(done, total, seconds)`` is called after each frame. With ``near_wall = "auto"`` the frames
    use the plain basis (:data:`PLAIN_FRAMES_NOTE`) unless ``layer_on_frames`` (for studies).
    """
    options = options or ReconstructionOptions()
    notes = []
    if options.velocity.near_wall == "auto" and not layer_on_frames:
        options = replace(options, velocity=replace(options.velocity, near_wall="off"))
        notes.append(PLAIN_FRAMES_NOTE)
    weights = cycle_weights(times_ms, period_ms)
    out: list[list] = []
    t0 = time.perf_counter()
    for k, frame in enumerate(frames):
        results: list
        try:
            results = list(reconstruct(frame, options))
        except WssNlpError as exc:  # this frame only: the others still describe the cycle
            log.warning("frame %d failed: %s", k, exc)
            results = [FailedSlice(iz, f"frame {k}: {exc}") for iz in range(frame.nz)]
        out.append(results)
        if progress is not None:
            progress(k + 1, len(frames), time.perf_counter() - t0)
    if all(isinstance(r, FailedSlice) for frame in out for r in frame):
        raise WssNlpError(f"every frame failed; the first: {out[0][0].reason}")
    return CineResult(out, np.asarray(times_ms, dtype=float), float(period_ms), weights, notes)


def write_result(path: str, cine: CineResult, options: dict, argv=None) -> list[CineSeries]:
    """Write the time-resolved result layout of ``shared/spec/data-format.md`` (atomic); returns the series.

    Each slice group holds the contract's per-frame datasets with a leading time axis, ``wss/time_ms``,
    ``wss/mean_pa_t``, ``wss/tawss_pa``, ``wss/osi`` and ``wss`` attribute ``mean_pa`` (the cycle average of
    the per-frame mean), and every frame's complete single-frame record in ``frames/frame_NNN``.
    """
    from .files import atomic_h5, provenance, write_slice_group

    series = [cine.series(iz) for iz in range(cine.n_slices)]
    with atomic_h5(path) as f:
        for k, v in provenance(options, argv).items():
            f.attrs[k] = v
        f.attrs["n_slices"] = cine.n_slices
        f.attrs["n_frames"] = len(cine.frames)
        f.attrs["trigger_times_ms"] = cine.times_ms
        f.attrs["cardiac_period_ms"] = cine.period_ms
        f.attrs["all_converged"] = bool(all(r.converged for frame in cine.frames for r in frame))
        for s in series:
            g = f.create_group(f"slice_{s.index:03d}")
            g["geometry/center_mm"] = s.center
            g["geometry/coefficients"] = s.coefficients
            g["geometry/phi"] = s.phi
            g["geometry/radius_mm"] = s.radius
            g["wss/phi"] = s.phi
            g["wss/tau_pa"] = s.tau
            g["wss/time_ms"] = cine.times_ms
            g["wss/mean_pa_t"] = s.mean
            g["wss/tawss_pa"] = s.tawss
            g["wss/osi"] = s.osi
            g["wss"].attrs["mean_pa"] = s.time_average_mean
            g.attrs["alpha"] = s.alpha
            g.attrs["beta"] = s.beta
            g.attrs["failed_frames"] = np.nonzero(s.failed)[0].astype(int)
            g.attrs["converged"] = np.array([r[s.index].converged for r in cine.frames], dtype=bool)
            warnings = [
                w for k, frame in enumerate(cine.frames) for w in (f"frame {k}: {x}" for x in frame[s.index].warnings)
            ]
            g.attrs["warnings"] = json.dumps(s.notes + warnings)
            for k, frame in enumerate(cine.frames):
                write_slice_group(g.create_group(f"frames/frame_{k:03d}"), frame[s.index])
    return series
