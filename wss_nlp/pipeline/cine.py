r"""Time-resolved (cine) reconstruction: every frame of the cycle, then TAWSS and OSI.

Each frame is an acquisition of its own, reconstructed by the driver (:func:`wss_nlp.pipeline.driver.reconstruct`)
with its own parameter choices (the frames of a slice share its lumen box, built solvers and warm starts; their
bands wait until the cycle's model is chosen). Then each slice's velocity over the cycle is chosen by the BIC
(:func:`cycle_models`, :func:`wss_nlp.parameters.cycle.choose`) among the frames' own fits, a periodic temporal
prior (:mod:`wss_nlp.models.temporal`) and the momentum balance of pulsatile flow (:mod:`wss_nlp.models.womersley`),
on the frames' walls regularized in time, with the momentum model's kinematic viscosity fitted to the frames
(:mod:`wss_nlp.parameters.viscosity`); TAWSS and OSI integrate the chosen WSS over the cycle: the momentum model's
on :data:`CYCLE_SAMPLES` instants of the whole cycle (it is a model in continuous time), the frames' own fits by
the frames' trapezoid rule (:mod:`wss_nlp.core.periodic`, which also bridges a failed frame by linear
interpolation in time, and the result says so). Frames that leave part of the cycle without data
(:func:`coverage`) give no TAWSS and OSI, and the result says why.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..models import preprocess as pp
from ..models import surround
from ..core import radius as rad
from ..models import acquisition as acq_model
from ..models import temporal, womersley
from ..parameters import cycle
from ..models import wss as wss_mod
from ..models import velocity as vel
from ..parameters import noise as nl
from .results import SliceResult
from ..core.periodic import bridge, cycle_weights, tawss_osi  # noqa: F401 (part of this module's API)
from ..errors import WssNlpError
from ..io.files import Acquisition, FailedSlice
from .driver import blas_threads, reconstruct
from .options import ReconstructionOptions

log = logging.getLogger(__name__)


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
    tau_std: np.ndarray | None = None  # (nt, nphi), Pa: the band of the chosen model (NaN where unknown)
    mean_std: np.ndarray | None = None  # (nt,), Pa
    model: cycle.CineModelChoice | None = None  # the velocity model over the cycle and why
    incomplete: str | None = None  # why TAWSS and OSI were not computed (frames not covering the cycle)


@dataclass
class CycleModel:
    """The velocity model of one slice over the cycle: the choice, and the momentum model's WSS if chosen."""

    choice: cycle.CineModelChoice
    tau: np.ndarray | None = None  # (nt, nphi), Pa; NaN rows for frames the model gives no value at
    tau_std: np.ndarray | None = None
    mean: np.ndarray | None = None  # (nt,)
    mean_std: np.ndarray | None = None
    walls: np.ndarray | None = None  # (nt, 2N+3): the walls the model used, radius coefficients then centre (mm)
    cycle_tau: np.ndarray | None = None  # (CYCLE_SAMPLES, nphi): a model in continuous time over the whole cycle
    cycle_mean: np.ndarray | None = None  # (CYCLE_SAMPLES,)
    filled: list = field(default_factory=list)  # frames without data of their own whose WSS the model gives


#: Instants over the cycle at which a model in continuous time (the momentum model) is integrated for TAWSS
#: and OSI (trapezoid rule on a periodic function: exact for its trigonometric part; |tau| has kinks where the
#: flow reverses, an error of order (T / CYCLE_SAMPLES)^2 there).
CYCLE_SAMPLES = 256

#: Frames cover the cycle (:func:`coverage`) with at least COVERAGE_FRAMES frames holding data and no gap longer
#: than COVERAGE_GAP mean frame spacings (T / frames of the series) nor COVERAGE_FRACTION of the period; a gap
#: over NOTE_GAP spacings is said (one missing frame leaves two).
COVERAGE_FRAMES, COVERAGE_GAP, COVERAGE_FRACTION, NOTE_GAP = 3, 3.0, 1.0 / 3.0, 1.5


def coverage(times_ms, good, period_ms: float) -> tuple[str | None, str | None]:
    """``(refusal, note)``: why TAWSS and OSI cannot be computed from frames at ``times_ms`` (those with data:
    ``good``) over a cycle of ``period_ms`` (None where they cover it), and a note on a gap that is bridged.

    Frames over part of the cycle, or one or two frames, would give a time average of part of the cycle
    as if it were the whole (issue 42); a longer gap than the limits is refused, not averaged over."""
    times = np.asarray(times_ms, dtype=float)
    t = times[np.asarray(good, dtype=bool)]
    fix = "state cardiac_period_ms if the cycle is shorter, or acquire frames over the whole cycle"
    if t.size < COVERAGE_FRAMES:
        return (
            f"{t.size} frame(s) with data over a {period_ms:g} ms cycle: TAWSS and OSI need frames over the whole "
            f"cycle (at least {COVERAGE_FRAMES}); not computed",
            None,
        )
    gaps = np.diff(np.r_[t, t[0] + period_ms])
    i = int(np.argmax(gaps))
    spacing = period_ms / times.size
    limit = min(COVERAGE_GAP * spacing, COVERAGE_FRACTION * period_ms)
    where = f"between the frames at {t[i]:g} and {t[(i + 1) % t.size]:g} ms"
    if gaps[i] > limit:
        return (
            f"the frames leave {gaps[i]:g} ms of the {period_ms:g} ms cycle without data ({where}; at most "
            f"{limit:.3g} ms is bridged): TAWSS and OSI need frames over the whole cycle; not computed ({fix})",
            None,
        )
    if gaps[i] > NOTE_GAP * spacing:
        return None, f"a gap of {gaps[i]:g} ms {where} ({gaps[i] / spacing:.1f} frame spacings) is bridged"
    return None, None


@dataclass
class CineResult:
    """Frames of a cine reconstruction: ``frames[k]`` holds the slice results of frame ``k``.

    ``models[iz]`` is slice ``iz``'s velocity model over the cycle (:class:`CycleModel`); where it is the
    momentum model, the series take their WSS from it, else from the frames' own fits.
    """

    frames: list
    times_ms: np.ndarray
    period_ms: float
    weights: np.ndarray
    notes: list = field(default_factory=list)
    models: dict = field(default_factory=dict)
    slice_spacing_mm: float | None = None
    # slice -> the series' one background offset record (wss_nlp.models.offset.OffsetRecord as a dict; series_offsets)
    offsets: dict = field(default_factory=dict)

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
        tau_std = rows(lambda r: r.wss.tau_std if r.wss.tau_std is not None else np.full(phi.size, np.nan), phi.size)
        mean_std = rows(lambda r: [r.wss.mean_std], 1)[:, 0]
        center = rows(lambda r: np.asarray(r.geometry.center, dtype=float), 2)
        coefficients = rows(lambda r: r.geometry.coefficients, n_coef)
        radius = rows(lambda r: r.geometry.radius(phi), phi.size)
        alpha = rows(lambda r: [r.geometry.alpha], 1)[:, 0]
        beta = rows(lambda r: [r.velocity.beta], 1)[:, 0]
        notes = list(self.notes)
        model = self.models.get(iz)
        valued = good.copy()  # frames with a WSS value (the momentum model's covers the frames without data)
        if model is not None and model.tau is not None:
            valued = np.all(np.isfinite(model.tau), axis=1)
            tau, tau_std, mean, mean_std = model.tau, model.tau_std, model.mean, model.mean_std
            if model.walls is not None:  # the walls its WSS lives on (regularized in time)
                coefficients, center = model.walls[:, :n_coef], model.walls[:, n_coef:]
                radius = np.array([rad.evaluate(c, phi) if np.all(np.isfinite(c)) else np.full(phi.size, np.nan)
                                   for c in coefficients])  # fmt: skip
        if model is not None:
            notes.append(model_note(model.choice))
            if model.choice.model == "momentum" and viscosity_flag(model.choice.viscosity):
                notes.append(str(viscosity_flag(model.choice.viscosity)))
            if model.choice.model == "momentum" and model.choice.sampling.get("flagged"):
                notes.append(sampling_note(model.choice.sampling))

        def reasons(ks):
            return "; ".join(getattr(results[k], "reason", "not in the momentum model's fit") for k in ks[:3])

        filled = np.nonzero(~good & valued)[0].tolist()
        if filled:
            notes.append(f"frame(s) {filled} failed ({reasons(filled)}); their WSS is the momentum model's at their "
                         "times (fitted to the other frames)")  # fmt: skip
        unvalued = np.nonzero(~valued)[0].tolist()
        if unvalued:
            notes.append(f"frame(s) {unvalued} failed ({reasons(unvalued)}); TAWSS and OSI bridge them by linear "
                         "interpolation in time")  # fmt: skip
        refusal, gap_note = coverage(self.times_ms, good, self.period_ms)
        nan = np.full(phi.size, np.nan)
        if refusal is not None:
            notes.append(refusal)
            tawss, osi, average = nan, nan.copy(), float("nan")
        elif model is not None and model.cycle_tau is not None:
            if gap_note:
                notes.append(gap_note + " by the momentum model")
            uniform = np.full(model.cycle_tau.shape[0], self.period_ms / model.cycle_tau.shape[0])
            tawss, osi = tawss_osi(model.cycle_tau, uniform)
            average = float(np.mean(model.cycle_mean))
        else:
            if gap_note:
                notes.append(gap_note + " by the frames' trapezoid rule")
            ok = valued
            bridged = bridge(np.where(ok[:, None], tau, 0.0), ok, self.times_ms, self.period_ms)
            tawss, osi = tawss_osi(bridged, self.weights)
            mean_bridged = bridge(np.where(ok, mean, 0.0)[:, None], ok, self.times_ms, self.period_ms)[:, 0]
            average = float(np.sum(self.weights * mean_bridged) / np.sum(self.weights))
        return CineSeries(
            iz, phi, np.where(valued[:, None], tau, np.nan), np.where(valued, mean, np.nan), center, coefficients,
            radius, alpha, beta, ~good, tawss, osi, average, notes, tau_std, mean_std,
            None if model is None else model.choice, refusal,
        )  # fmt: skip


def model_note(choice: cycle.CineModelChoice) -> str:
    """One line on the cycle's velocity model for the result's warnings."""
    if choice.model == "momentum":
        how = "chosen by the BIC" if np.isfinite(choice.margin) else "forced (--cine-model momentum)"
        walls = choice.walls.get("how", "each frame's own wall")
        return (
            f"velocity over the cycle: the momentum balance of fully developed pulsatile flow (Womersley) with "
            f"{choice.harmonics} harmonic(s), fitted to frames {choice.frames_used}, {how}"
            + (f" (BIC margin {choice.margin:.0f})" if np.isfinite(choice.margin) else "")
            + f"; walls: {walls}; each frame's own fit is in frames/frame_NNN"
            + viscosity_note(choice.viscosity)
        )
    if choice.model == "temporal":
        prior = choice.walls.get("temporal_prior", {})
        how = "chosen by the BIC" if np.isfinite(choice.margin) else "forced (--cine-model temporal)"
        walls = choice.walls.get("how", "each frame's own wall")
        return (
            "velocity over the cycle: the frames' fits tied by a periodic temporal prior (each frame's own beta, "
            f"gamma {prior.get('gamma', float('nan')):.3g}), {how}"
            + (f" (BIC margin {choice.margin:.0f})" if np.isfinite(choice.margin) else "")
            + f"; walls: {walls}; each frame's own fit is in frames/frame_NNN"
        )
    if not choice.bic:
        return f"velocity over the cycle: each frame's own fit ({choice.criterion})"
    return (
        f"velocity over the cycle: each frame's own fit; the momentum model (Womersley) did not fit the data "
        f"{'well enough' if np.isfinite(choice.margin) else '(forced off)'}"
        + (f" (BIC margin {choice.margin:.0f})" if np.isfinite(choice.margin) else "")
    )


def viscosity_note(record: dict) -> str:
    """What the momentum model's viscosity record says, for its note (empty without a record)."""
    if not record:
        return ""
    stated = f"{1e3 * record['stated_pa_s']:.3g} mPa s"
    if record.get("mode") != "fit":
        return (
            f"; Stokes layer from the stated viscosity {stated} and density {record['density_kg_m3']:g} kg/m^3 "
            f"(Womersley number {record['womersley_number']:.3g}; --cine-viscosity stated)"
        )
    lo, hi = (1e3 * v for v in record["implied_interval_pa_s"])
    implied = (
        f"{1e3 * record['implied_pa_s']:.3g} mPa s ({100 * record['level']:.0f} % interval {lo:.3g}-{hi:.3g} at the "
        f"stated density {record['density_kg_m3']:g} kg/m^3; kinematic {record['nu_m2_s']:.3g} m^2/s, Womersley "
        f"number {record['womersley_number']:.3g})"
    )
    if record["at_bound"]:
        return (
            f"; the frames' Stokes layer points to a viscosity at the bound of the fit ({implied}): the flow may not "
            "be Womersley flow; the stress takes the stated viscosity " + stated
        )
    if not record["determined"]:
        return (
            f"; the frames do not determine the viscosity ({implied}; the profile hardly depends on it at this "
            f"Womersley number); the stress takes the stated viscosity {stated}"
        )
    agree = "inside" if record["agrees"] else "OUTSIDE"
    return (
        f"; Stokes layer fitted: the frames imply a viscosity of {implied}; the stated {stated} lies {agree} the "
        "interval; the stress takes the stated viscosity"
    )


def viscosity_flag(record: dict) -> str | None:
    """A warning where the stated viscosity lies outside the interval the frames imply (None otherwise)."""
    if not record or record.get("mode") != "fit" or record["agrees"] or record["at_bound"]:
        return None
    lo, hi = (1e3 * v for v in record["implied_interval_pa_s"])
    ratio = record["implied_pa_s"] / record["stated_pa_s"]
    return (
        f"viscosity disagreement: the frames' Stokes layer implies {1e3 * record['implied_pa_s']:.3g} mPa s "
        f"({lo:.3g}-{hi:.3g}, {100 * record['level']:.0f} %; {ratio:.2f} x the stated "
        f"{1e3 * record['stated_pa_s']:.3g} mPa s at the stated density {record['density_kg_m3']:g} kg/m^3): the "
        "WSS scales with the stated viscosity; check it (or the density: the data give their ratio)"
    )


#: Aliased harmonics may carry this fraction of the peak |mean WSS| before a momentum model at the frames' highest
#: harmonic is flagged: issue 40's accuracy goal for every frame (2 % of the peak).
SAMPLING_LIMIT = 0.02

#: Largest decay ratio of successive harmonics assumed for the harmonics beyond the frames' highest (a slower
#: decay than this would make their sum unbounded).
SAMPLING_DECAY_CAP = 0.9


def sampling(cycle_mean: np.ndarray, harmonics: int, carried: int, n_frames: int, limit: int | None = None) -> dict:
    r"""Whether the frames resolve the waveform: the momentum model's highest harmonic against what the frames
    can carry.

    ``cycle_mean``: the model's wall-mean WSS at equally spaced instants of the whole cycle (Pa); ``harmonics``: the
    harmonics the BIC chose; ``carried``: the most the frames can carry (the Nyquist harmonic,
    :func:`wss_nlp.models.womersley.max_harmonics`), or the option's ``limit`` (``--max-harmonics``) where that is
    lower (then the harmonics beyond are left out rather than aliased). Below that the BIC stopped adding harmonics
    because the data did not need them: resolved. At it, harmonics beyond may exist and alias onto the fitted ones
    (6 frames of the 4-harmonic phantom: the model chose 3 and missed by 20 % of the peak): with the mean WSS's
    harmonic amplitudes :math:`A_n` (its discrete Fourier transform) decaying like :math:`q = \min(A_K / A_{K-1},
    0.9)`, the harmonics beyond sum to about :math:`A_K q / (1 - q)`; above :data:`SAMPLING_LIMIT` of the peak the
    result is flagged.
    """
    m = cycle_mean.size
    amplitudes = 2.0 * np.abs(np.fft.rfft(np.asarray(cycle_mean, dtype=float)))[: harmonics + 1] / m
    peak = float(np.max(np.abs(cycle_mean)))
    record = {"harmonics": int(harmonics), "carried": int(carried), "frames": int(n_frames),
              "amplitudes_pa": [float(a) for a in amplitudes[1:]], "peak_pa": peak}  # fmt: skip
    at_cap = harmonics >= carried and harmonics >= 1
    beyond = 0.0
    if at_cap:
        top = float(amplitudes[harmonics])
        q = (
            min(top / amplitudes[harmonics - 1], SAMPLING_DECAY_CAP)
            if harmonics >= 2 and amplitudes[harmonics - 1] > 0
            else SAMPLING_DECAY_CAP
        )
        beyond = top * q / (1.0 - q)
    record.update(at_cap=bool(at_cap), beyond_fraction=float(beyond / peak) if peak > 0 else 0.0)
    record["limited_by"] = "max_harmonics" if limit is not None and carried >= limit else "frames"
    record["flagged"] = bool(at_cap and peak > 0 and beyond > SAMPLING_LIMIT * peak)
    return record


def sampling_note(record: dict) -> str:
    """The warning of a series whose frames or harmonic limit may not resolve the waveform (:func:`sampling`)."""
    k = record["harmonics"]
    share = 100 * record["amplitudes_pa"][-1] / record["peak_pa"]
    beyond = f"about {100 * record['beyond_fraction']:.0f} % of the peak, from the decay of the fitted ones"
    if record.get("limited_by") == "max_harmonics":
        return (
            f"waveform cut off? the momentum model needed all {k} harmonic(s) --max-harmonics allows, and its "
            f"highest holds {share:.0f} % of the peak mean WSS: harmonics beyond it ({beyond}) are left out, and the "
            f"WSS can be off by about that much; raise --max-harmonics (the {record['frames']} frames carry up to "
            f"{record['frames'] // 2})"
        )
    return (
        f"undersampled waveform? the momentum model needed the {k} harmonic(s) {record['frames']} frames can carry "
        f"at most, and its highest holds {share:.0f} % of the peak mean WSS: harmonics beyond it ({beyond}) alias "
        "onto the fitted ones, and the WSS at and between the frames can be off by about that much; acquire more "
        f"frames (at least {2 * k + 2}), or read the frames' own fits (frames/frame_NNN)"
    )


#: Why cine frames take the plain basis when the near-wall choice is ``auto``.
PLAIN_FRAMES_NOTE = (
    "near-wall auto chooses layers for steady flows (family by the bulk Reynolds number); on pulsatile frames "
    "it did worse than the plain basis at every h and SNR (scripts/results/cine.md), so cine frames use the "
    "plain basis; --near-wall wall_law or exponential forces a layer"
)


def shared_boxes(frames: list[Acquisition], options: ReconstructionOptions) -> dict:
    """Per slice, the :class:`wss_nlp.models.preprocess.LumenBox` covering every frame's own lumen box.

    Frames whose slice cannot be preprocessed (NaN, no vessel) are left out here; they fail on their own in
    the reconstruction. A slice no frame can be preprocessed in gets no shared box.
    """
    ref = frames[0]
    psf = options.acquisition.psf(ref.voxel_size_mm, ref.acquired_voxel_size_mm, f"{ref.source}: ")
    boxes = {}
    for iz in range(ref.nz):
        lumens = []
        # hook (issue 39): a region is a vessel if it flows in some frame (fat never does)
        speed = None if options.tissue.off else np.stack([np.asarray(f.velocity_images()[iz], float) for f in frames])
        clip = acq_model.of(psf).clip_upper
        for frame in frames:
            image = frame.magnitude[iz]
            if not np.all(np.isfinite(image)):
                continue
            try:
                if speed is None:
                    lumens.append(pp.preprocess(image, frame.grid, "", options.screen.vessel, clip)[2])
                else:
                    lumens.append(
                        surround.screen_preprocess(
                            image, speed, frame.grid, "", options.screen.vessel, frame.venc_m_s, clip
                        )[2]
                    )
            except WssNlpError:
                continue
        if lumens:
            boxes[iz] = pp.LumenBox.covering(lumens)
    return boxes


def series_offsets(frames: list[Acquisition], boxes: dict, options: ReconstructionOptions) -> dict:
    """Per slice with a shared box, the series' one background offset (:func:`wss_nlp.models.surround.
    series_offset`), attached to its box: every frame of the slice subtracts the same field.

    The eddy currents repeat with the sequence in every frame; one fit to the frames' mean on the tissue that is
    still in time beats a fit per frame (its noise ``sqrt(T)`` times smaller, and a vessel that pulses is never
    static tissue, however slow its mean). Returns ``{slice: record dict}`` (the cine result's ``offsets``);
    slices whose series cannot be fitted at once (a frame with NaN, no vessel in the mean) keep the frames' own
    fits. Nothing with ``--surround two-level --no-offset-correction`` (Appendix B).
    """
    out: dict = {}
    if options.tissue.off or not boxes:
        return out
    ref = frames[0]
    psf = options.acquisition.psf(ref.voxel_size_mm, ref.acquired_voxel_size_mm, f"{ref.source}: ")
    for iz, box in list(boxes.items()):
        raw = np.stack([np.asarray(f.magnitude[iz], float) for f in frames])
        u = np.stack([np.asarray(f.velocity_images()[iz], float) for f in frames])
        if not (np.all(np.isfinite(raw)) and np.all(np.isfinite(u))):
            continue
        vessel = options.screen.vessel if options.screen.vessel is not None else box.center
        try:
            fit = surround.series_offset(raw, u, ref.grid, f"{ref.source} slice {iz}", vessel, ref.venc_m_s,
                                         acq_model.of(psf))  # fmt: skip
        except WssNlpError as exc:
            log.info(f"{ref.source} slice {iz}: no offset over the series ({exc}); each frame fits its own")
            continue
        boxes[iz] = replace(box, offset=fit)
        out[iz] = fit.record.as_dict()
    return out


def reconstruct_cine(
    frames: list[Acquisition],
    times_ms,
    period_ms: float,
    options: ReconstructionOptions | None = None,
    progress=None,
    layer_on_frames: bool = False,
    share_box: bool = True,
) -> CineResult:
    """Reconstruct every frame (``frames[k]`` at ``times_ms[k]``); a frame that fails is recorded, not fatal.

    ``progress(done, total, seconds)`` is called after each frame. With ``near_wall = "auto"`` the frames
    use the plain basis (:data:`PLAIN_FRAMES_NOTE`) unless ``layer_on_frames`` (for studies). The frames
    of a slice share one polar origin and radius box (:func:`shared_boxes`), so they share the built
    geometry solvers, and each frame's geometry starts from the previous frame's; ``share_box=False``
    gives every frame its own box and a cold start (for studies).
    """
    options = options or ReconstructionOptions()
    with blas_threads(options.blas_threads):  # the model's small factorizations too, not only the frames'
        return _reconstruct_cine(frames, times_ms, period_ms, options, progress, layer_on_frames, share_box)


def _reconstruct_cine(frames, times_ms, period_ms, options, progress, layer_on_frames, share_box) -> CineResult:
    notes = []
    if options.velocity.near_wall == "auto" and not layer_on_frames:
        options = replace(options, velocity=replace(options.velocity, near_wall="off"))
        notes.append(PLAIN_FRAMES_NOTE)
    weights = cycle_weights(times_ms, period_ms)
    boxes = shared_boxes(frames, options) if share_box else {}
    offsets = series_offsets(frames, boxes, options)
    out: list[list] = []
    t0 = time.perf_counter()
    omega = 2 * np.pi / (float(period_ms) / 1000.0)
    # a series of single slices leaves the frames' bands until the model is chosen: where the momentum model
    # wins, its own band replaces them (stacks compute them at once: holding every slice's problem until the
    # end would cost about a megabyte per slice and frame)
    keep = options.cine.model != "independent" and frames[0].nz == 1
    defer = options.uncertainty and keep
    psfs = []  # the acquisition model each frame was reconstructed with (resolved k-space filter)
    failures: list[tuple[int, str]] = []  # said once per kind after the frames, not once per frame
    for k, frame in enumerate(frames):
        results: list
        try:
            done = reconstruct(frame, options, boxes=boxes, defer_band=defer)
            results = list(done)
            psfs.append(done.psf)
        except WssNlpError as exc:  # this frame only: the others still describe the cycle
            failures.append((k, f"failed: {exc}"))
            results = [FailedSlice(iz, f"frame {k}: {exc}") for iz in range(frame.nz)]
        for r in results:
            if not isinstance(r, FailedSlice) and not keep:
                r.problem = None  # rebuilt where needed: a long series of stacks would hold every one otherwise
        out.append(results)
        for r in results:  # the next frame's geometry starts from this one's
            if r.index in boxes and not isinstance(r, FailedSlice):
                boxes[r.index] = replace(boxes[r.index], start=tuple(r.geometry.coefficients))
        if progress is not None:
            progress(k + 1, len(frames), time.perf_counter() - t0)
    for line in group_warnings(failures, len(frames)):
        log.warning(line)
    if all(isinstance(r, FailedSlice) for frame in out for r in frame):
        raise WssNlpError(f"every frame failed; the first: {out[0][0].reason}")
    result = CineResult(out, np.asarray(times_ms, dtype=float), float(period_ms), weights, notes, offsets=offsets)
    spacing = frames[0].slice_spacing_mm
    result.slice_spacing_mm = None if spacing is None else float(spacing)
    psf = next((p for p in psfs if p is not None), None)
    result.models = cycle_models(result, frames, options, omega, psf)
    for iz, model in result.models.items():
        for frame_results in out:
            r = frame_results[iz]
            if isinstance(r, FailedSlice):
                continue
            r.problem = None
            if r.pending_band is None:
                continue
            if model.tau is None:
                r.finish_band()
            else:
                r.pending_band = None
                r.notes.append(MODEL_BAND_NOTE.format(model=MODEL_NAMES[model.choice.model]))
    return result


#: What a frame's own record says when its slice's series comes from a model over the cycle.
MODEL_BAND_NOTE = (
    "no band for this frame's own fit: the slice's WSS over the cycle comes from the {model}, whose band is in "
    "wss/tau_std_pa"
)

#: The models over the cycle by their option names.
MODEL_NAMES = {
    "momentum": "momentum model (wss_nlp.models.womersley)",
    "temporal": "temporal prior (wss_nlp.models.temporal)",
}


def cycle_models(result: CineResult, frames: list[Acquisition], options, omega: float, psf) -> dict:
    """Each slice's velocity model over the cycle (:func:`wss_nlp.parameters.cycle.choose`) and its WSS per frame.

    The momentum model is fitted on the frames' walls regularized in time
    (:func:`~wss_nlp.parameters.cycle.smooth_walls`), with the Womersley parameters at those walls' mean
    equal-area radius (:func:`equal_area_radius`) and its kinematic viscosity fitted to the frames
    (``options.cine.viscosity``, :mod:`wss_nlp.parameters.viscosity`); its WSS takes the stated viscosity.
    """
    if options.cine.model == "independent":
        choice = cycle.CineModelChoice("independent", criterion="independent frames (--cine-model independent)")
        return {iz: CycleModel(choice) for iz in range(result.n_slices)}
    ref = frames[0]
    mu = ref.viscosity(options.viscosity_pa_s)
    rho = ref.density(options.density_kg_m3)[0]
    nu = mu / rho
    k_max = womersley.max_harmonics(len(frames), options.cine.max_harmonics)
    models = {}
    for iz in range(result.n_slices):
        good = [(k, fr[iz]) for k, fr in enumerate(result.frames) if not isinstance(fr[iz], FailedSlice)]
        times = np.array([result.times_ms[k] / 1000.0 for k, _ in good])
        own = np.array([np.r_[r.geometry.coefficients, r.geometry.center] for _, r in good])
        walls, wall_choice = cycle.smooth_walls(times, omega, own, options.cine.walls, k_max)
        n_r = own.shape[1] - 2
        radius = equal_area_radius(walls[:, :n_r])
        usable, problems, sigmas, betas = [], [], [], []
        previous, shapes = None, None  # frames on one wall (a rigid vessel) share its operator and model shapes
        for (k, r), wall in zip(good, walls):
            problem = plain_problem(r, options, psf, wall[:n_r], wall[n_r:], like=previous)
            if previous is None or problem.operator is not previous.operator:
                shapes = womersley.wall_shapes(problem, k_max, omega, nu, radius)
            previous = problem
            acq = frames[k]
            sigma = velocity_sigma(
                r, problem, acq.magnitude[iz], acq, options.choice.noise_velocity, f"{acq.source} slice {iz}"
            )
            if sigma is not None:  # noise-free data give the models nothing to be weighed by
                time_s = float(result.times_ms[k]) / 1000.0
                usable.append(cycle.frame_terms(problem, sigma, k, time_s, k_max, omega, nu, radius, shapes))
                problems.append(problem)
                sigmas.append(sigma)
                betas.append(r.velocity.beta)
        if len(usable) < 2:
            why = "fewer than two frames with a velocity noise estimate (noise-free data?): independent frames"
            models[iz] = CycleModel(cycle.CineModelChoice("independent", criterion=why))
            continue
        prior = None
        # the prior only competes in the choice: a forced momentum model does not need it (its criterion costs
        # as much as the frames' fits)
        if options.cine.model != "momentum" and len(usable) == len(result.frames) >= 3 and _equally_spaced(result):
            scale, log_n = cycle.criterion_scale(usable)
            prior = temporal.fit(problems, betas, sigmas, scale, log_n)
        data = womersley.CycleData(problems, sigmas, np.array([t.time_s for t in usable]), omega, radius,
                                   voxel_mm=float(ref.grid.h))  # fmt: skip
        choice, fitted = cycle.choose(usable, omega, nu, options.cine, None if prior is None else prior.bic, data)
        choice.walls = wall_choice.as_dict()
        if prior is not None:
            choice.walls["temporal_prior"] = prior.as_dict()
        if choice.fitted_viscosity is not None:
            choice.viscosity = choice.fitted_viscosity.as_dict(mu, rho, radius, omega)
        else:
            choice.viscosity = {
                "mode": "stated", "stated_pa_s": float(mu), "density_kg_m3": float(rho), "nu_m2_s": float(nu),
                "womersley_number": float(radius * 1e-3 * np.sqrt(omega / nu)), "radius_mm": float(radius),
            }  # fmt: skip
        model = CycleModel(choice)
        if choice.model == "temporal" and prior is not None:
            _prior_wall_shear(model, prior, problems, options.n_phi, mu)
        if fitted is not None:
            period_s = result.period_ms / 1000.0
            _momentum_wall_shear(model, fitted, result, usable, wall_choice, omega, period_s, options.n_phi, mu,
                                 fill=fitted.harmonics < k_max)  # fmt: skip
            if model.cycle_mean is not None:
                choice.sampling = sampling(model.cycle_mean, fitted.harmonics, min(k_max, len(usable) // 2),
                                           len(usable), options.cine.max_harmonics)  # fmt: skip
        log.debug("slice %d: %s", iz, model_note(choice))  # the series' note says it (the CLI prints notes once)
        models[iz] = model
    return models


def _momentum_wall_shear(
    model: CycleModel, fitted, result: CineResult, usable: list, wall_choice, omega: float, period_s: float,
    n_phi: int, mu: float, fill: bool = True,
) -> None:  # fmt: skip
    """The momentum model's WSS at every frame (on the walls it was fitted on, moved by its offset; a frame
    without data of its own on the walls' temporal fit at its time) and on :data:`CYCLE_SAMPLES` instants of
    the whole cycle.

    ``fill`` False leaves frames without data of their own NaN (bridged for TAWSS and OSI): the caller's rule
    is to fill only where the BIC chose fewer harmonics than the frames allow, since a model at that cap may
    be truncating the waveform (4 frames of the 4-harmonic phantom, one failed: the fill missed by 36 % of the
    peak), while its value at a frame it was fitted on is still checked by that frame's data."""
    phi = rad.uniform_angles(n_phi)
    used = {t.index: t for t in usable}
    known_t = np.array([t.time_s for t in usable])
    known = np.array([np.r_[t.coefficients, t.center] for t in usable])
    n_r = known.shape[1] - 2
    radius = usable[0].radius_mm

    def walls_at(times_s: np.ndarray) -> np.ndarray:
        at = wall_choice.at(times_s, omega)
        return _periodic_interpolation(known_t, known, times_s, period_s) if at is None else at

    n_t = len(result.frames)
    times_all = result.times_ms / 1000.0
    missing = [k for k in range(n_t) if k not in used] if fill else []
    filled = dict(zip(missing, walls_at(times_all[missing]))) if missing else {}
    model.tau, model.tau_std = np.full((n_t, n_phi), np.nan), np.full((n_t, n_phi), np.nan)
    model.mean, model.mean_std = np.full(n_t, np.nan), np.full(n_t, np.nan)
    model.walls = np.full((n_t, known.shape[1]), np.nan)
    for k in sorted(used) + missing:
        wall = np.r_[used[k].coefficients, used[k].center] if k in used else filled[k]
        model.tau[k], model.tau_std[k], model.mean[k], model.mean_std[k] = womersley.shear_at(
            fitted, wall[:n_r], float(times_all[k]), radius, phi, mu
        )
        model.walls[k] = wall
        model.walls[k, 0] += fitted.offset_mm  # the walls the model's WSS lives on
    model.filled = missing
    grid = np.arange(CYCLE_SAMPLES) * period_s / CYCLE_SAMPLES
    cycle_tau, cycle_mean = np.empty((CYCLE_SAMPLES, n_phi)), np.empty(CYCLE_SAMPLES)
    # derivatives in (a, ln nu, offset) of the cycle-averaged mean WSS and of the wall-mean TAWSS
    d_mean, d_tawss = np.zeros(fitted.coefficients.size + 2), np.zeros(fitted.coefficients.size + 2)
    tawss = 0.0
    for m, (t, wall) in enumerate(zip(grid, walls_at(grid))):
        rows, d_tau = womersley.rows_at(fitted, wall[:n_r], float(t), radius, phi, mu)
        cycle_tau[m] = rows @ fitted.coefficients
        moved = np.array(wall[:n_r])
        moved[0] += fitted.offset_mm
        ds = np.hypot(rad.evaluate(moved, phi), rad.evaluate(moved, phi, 1))
        cycle_mean[m] = float(ds @ cycle_tau[m] / np.sum(ds))
        full = np.hstack([rows, d_tau])
        d_mean += (ds / np.sum(ds)) @ full / CYCLE_SAMPLES
        d_tawss += (ds * np.sign(cycle_tau[m]) / np.sum(ds)) @ full / CYCLE_SAMPLES
        tawss += float(ds @ np.abs(cycle_tau[m]) / np.sum(ds)) / CYCLE_SAMPLES
    model.cycle_tau, model.cycle_mean = cycle_tau, cycle_mean
    joint = fitted.joint_covariance()
    p = fitted.coefficients.size
    model.choice.sensitivity = {
        "std_ln_nu": float(np.sqrt(max(joint[p, p], 0.0))),
        "std_offset_mm": float(np.sqrt(max(joint[p + 1, p + 1], 0.0))),
    }
    for name, value, gradient in (("time_mean", float(np.mean(cycle_mean)), d_mean), ("tawss", tawss, d_tawss)):
        model.choice.sensitivity.update({
            f"{name}_pa": value,
            f"{name}_std_pa": float(np.sqrt(max(gradient @ joint @ gradient, 0.0))),
            f"{name}_d_ln_nu_pa": float(gradient[p]),
            f"{name}_d_offset_pa_per_mm": float(gradient[p + 1]),
        })  # fmt: skip


def _periodic_interpolation(times: np.ndarray, values: np.ndarray, at: np.ndarray, period: float) -> np.ndarray:
    """Rows of ``values`` (one per time of ``times``, increasing) linearly interpolated at ``at``, periodically."""
    ext_t = np.concatenate([times - period, times, times + period])
    ext_v = np.concatenate([values] * 3)
    at = np.mod(np.asarray(at, dtype=float) - times[0], period) + times[0]
    return np.column_stack([np.interp(at, ext_t, ext_v[:, j]) for j in range(values.shape[1])])


def equal_area_radius(coefficients: np.ndarray) -> float:
    """The cycle's radius for the Womersley parameters: the frames' mean equal-area radius (mm),
    ``sqrt(mean_phi R_k(phi)^2)`` of each wall ``k`` (radius coefficients, one row per frame).

    The regularized walls, not the segmentation's reference radius: that one sits about 0.7 % low on the
    phantoms and took the worst frame from 0.2-0.5 % to 0.4-0.7 % of the peak (h = 0.6-1 mm, seeds 0-2)."""
    phi = rad.uniform_angles(256)
    return float(np.mean([np.sqrt(np.mean(rad.evaluate(c, phi) ** 2)) for c in coefficients]))


def _equally_spaced(result: CineResult) -> bool:
    """Frames evenly over the whole cycle (the temporal prior's periodic differences assume it)."""
    t = result.times_ms
    step = result.period_ms / t.size
    return bool(np.allclose(np.diff(np.r_[t, t[0] + result.period_ms]), step, rtol=0.01))


def _prior_wall_shear(model: CycleModel, prior, problems: list, n_phi: int, mu: float) -> None:
    """The temporal prior's WSS per frame on the frames' walls, with its velocity-noise band."""
    phi = rad.uniform_angles(n_phi)
    n_t = len(problems)
    model.tau, model.tau_std = np.empty((n_t, n_phi)), np.empty((n_t, n_phi))
    model.mean, model.mean_std = np.empty(n_t), np.empty(n_t)
    model.walls = np.empty((n_t, problems[0].disk_map.coefficients.size + 2))
    for k, (problem, v, cov) in enumerate(zip(problems, prior.coefficients, prior.covariance)):
        smat, _ = wss_mod.wss_matrix(problem.basis, problem.disk_map, mu, n_phi)
        c = problem.disk_map.coefficients
        model.tau[k], model.tau_std[k], model.mean[k], model.mean_std[k] = womersley.linear_wall_shear(
            smat, v, cov, c, phi
        )
        model.walls[k] = np.r_[c, problem.disk_map.center]


def write_result(
    path: str, cine: CineResult, options: dict, argv=None, notes=(), attrs: dict | None = None
) -> list[CineSeries]:
    """Write the time-resolved result layout of ``shared/spec/data-format.md`` (atomic); returns the series.

    Each slice group holds the contract's per-frame datasets with a leading time axis, ``wss/time_ms``,
    ``wss/mean_pa_t``, ``wss/tawss_pa``, ``wss/osi`` and ``wss`` attribute ``mean_pa`` (the cycle average of
    the per-frame mean), and every frame's complete single-frame record in ``frames/frame_NNN``. Beyond the
    contract: the cycle model's record ``cine_model_json`` (with the viscosity the frames imply), the band,
    ``wss`` attribute ``viscosity_pa_s`` (the stated viscosity the stress takes), and ``tawss_note`` where
    the frames do not cover the cycle (TAWSS and OSI are then NaN); ``notes`` (what the whole series was read
    as, e.g. the timing's range notes) go to the file's ``warnings`` attribute; ``attrs`` are further root
    attributes (the input's import record, for export in world coordinates), written in the same atomic step.
    """
    from ..io.files import atomic_h5, provenance, write_slice_group

    series = [cine.series(iz) for iz in range(cine.n_slices)]
    with atomic_h5(path) as f:
        for k, v in provenance(options, argv).items():
            f.attrs[k] = v
        f.attrs["n_slices"] = cine.n_slices
        f.attrs["n_frames"] = len(cine.frames)
        f.attrs["trigger_times_ms"] = cine.times_ms
        f.attrs["cardiac_period_ms"] = cine.period_ms
        if cine.slice_spacing_mm is not None:
            f.attrs["slice_spacing_mm"] = cine.slice_spacing_mm
        f.attrs["all_converged"] = bool(all(r.converged for frame in cine.frames for r in frame))
        if notes:  # the readings taken and what was allowed are the result's, not only the terminal's
            f.attrs["warnings"] = json.dumps(list(notes))
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
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
            if s.tau_std is not None and np.any(np.isfinite(s.tau_std)):
                g["wss/tau_std_pa"] = s.tau_std  # the band of the model the slice's tau comes from
                g["wss/mean_std_pa_t"] = s.mean_std
            if s.model is not None:
                g.attrs["cine_model_json"] = s.model.as_json()
            if s.index in cine.offsets:  # the series' one background offset (each frame's tissue_json holds it too)
                g.attrs["cine_offset_json"] = json.dumps(cine.offsets[s.index])
            g["wss/tawss_pa"] = s.tawss
            g["wss/osi"] = s.osi
            g["wss"].attrs["mean_pa"] = s.time_average_mean
            viscosity = next((r[s.index].wss.viscosity_pa_s for r in cine.frames
                              if not isinstance(r[s.index], FailedSlice)), None)  # fmt: skip
            if viscosity is not None:
                g["wss"].attrs["viscosity_pa_s"] = float(viscosity)
            if s.incomplete is not None:
                g["wss"].attrs["tawss_note"] = s.incomplete
            g.attrs["alpha"] = s.alpha
            g.attrs["beta"] = s.beta
            g.attrs["failed_frames"] = np.nonzero(s.failed)[0].astype(int)
            g.attrs["converged"] = np.array([r[s.index].converged for r in cine.frames], dtype=bool)
            g.attrs["warnings"] = json.dumps(s.notes + frame_warnings(cine, s.index))
            for k, frame in enumerate(cine.frames):
                write_slice_group(g.create_group(f"frames/frame_{k:03d}"), frame[s.index])
    return series


def frame_warnings(cine: CineResult, iz: int) -> list[str]:
    """The warnings of slice ``iz``'s frames, each said once with the frames it applies to
    (:func:`group_warnings`)."""
    return group_warnings([(k, w) for k, frame in enumerate(cine.frames) for w in frame[iz].warnings], len(cine.frames))


def warning_kind(message: str) -> str:
    """What kind of warning ``message`` is: its text with every number replaced by ``#``.

    Warnings that differ only in their numbers (a slice's or frame's index, a chosen parameter) are one kind,
    said once (:func:`group_warnings`; the command line's log counts the repeats of any warning this way).
    """
    import re

    return re.sub(r"[-+]?\d[\d.eE+-]*", "#", message)


def group_warnings(items: list, total: int, what: str = "frame") -> list[str]:
    """``(index, message)`` pairs as one line per kind of message with the indices it came from.

    Messages that differ only in their numbers (:func:`warning_kind`) are one kind; the line keeps the first
    one's text: ``frames 0-19 (20 of 20): slice 0: no band ...``.
    """
    kinds: dict = {}
    for index, message in items:
        kinds.setdefault(warning_kind(message), (message, []))[1].append(index)
    out = []
    for message, indices in kinds.values():
        indices = sorted(set(indices))
        if len(indices) == 1:
            out.append(f"{what} {indices[0]}: {message}")
        else:
            out.append(f"{what}s {_ranges(indices)} ({len(indices)} of {total}): {message}")
    return out


def cycle_warnings(cine: CineResult, series: list) -> list[str]:
    """Every warning of a cine result for the command line: the slices' notes and their frames' warnings, each
    kind said once with the slices and frames it applies to (:func:`group_warnings`)."""

    items: list[tuple[int, int | None, str]] = [(s.index, None, note) for s in series for note in s.notes]
    for s in series:
        prefix = f"slice {s.index}: "
        for k, frame in enumerate(cine.frames):
            items += [(s.index, k, w[len(prefix) :] if w.startswith(prefix) else w) for w in frame[s.index].warnings]
    kinds: dict = {}
    for iz, frame_index, message in items:
        key = (frame_index is None, warning_kind(message))
        kinds.setdefault(key, (message, []))[1].append((iz, frame_index))
    out = []
    for (per_slice, _), (message, where) in kinds.items():
        slices = sorted({iz for iz, _ in where})
        head = f"slice {slices[0]}" if len(slices) == 1 else f"slices {_ranges(slices)}"
        if not per_slice:
            frames = sorted({k for _, k in where})
            count = f" ({len(frames)} of {len(cine.frames)})"
            head += f", frame {frames[0]}" if len(frames) == 1 else f", frames {_ranges(frames)}{count}"
        out.append(f"{head}: {message}")
    return out


def _ranges(indices: list) -> str:
    """``[0, 1, 2, 5, 7, 8]`` as ``0-2, 5, 7-8``."""
    parts, start = [], indices[0]
    for a, b in zip(indices, indices[1:] + [None]):
        if b is None or b != a + 1:
            parts.append(f"{start}" if a == start else f"{start}-{a}")
            start = b
    return ", ".join(parts)


def velocity_sigma(
    result: SliceResult, problem: vel.VelocityProblem, raw: np.ndarray, acq, noise_velocity: float | None, where: str
):
    """Per-voxel velocity noise of a frame as its own fit estimates it (None for noise-free data)."""
    if noise_velocity is not None:
        return np.full(problem.data.size, float(noise_velocity))
    venc = acq.venc_m_s  # as the slice's own fit chose it (wss_nlp.pipeline.steps.prepare)
    if venc is None and nl.velocity_plateau(result.lumen.noise_mask).sum() < nl.MIN_PLATEAU_VOXELS:
        venc = acq.noise_venc_m_s
    noise = nl.velocity_noise(
        problem.data_image, raw, result.lumen.noise_mask, problem.voxels.index, problem.weights, venc, where,
        result.lumen.signal,
    )  # fmt: skip
    return np.asarray(noise.details["per_voxel"], dtype=float) if noise.value > 0 else None


def plain_problem(
    result: SliceResult, options, psf, coefficients=None, center=None, like: vel.VelocityProblem | None = None
) -> vel.VelocityProblem:
    """The frame's plain velocity problem on a wall (default: its own): the one its fit used, or assembled.

    ``like``: another frame's plain problem; on the same wall and grid its operator serves this frame's data.
    """
    problem, g = result.problem, result.geometry
    coefficients = g.coefficients if coefficients is None else np.asarray(coefficients, dtype=float)
    center = g.center if center is None else (float(center[0]), float(center[1]))
    same = problem is not None and np.array_equal(problem.disk_map.coefficients, coefficients)
    if same and problem is not None and tuple(problem.disk_map.center) == tuple(center):
        if getattr(problem.basis, "base", None) is None:  # not the coupled start, no layer columns
            return problem

    if (
        like is not None
        and np.array_equal(like.disk_map.coefficients, coefficients)
        and tuple(like.disk_map.center) == tuple(center)
        and like.data_image.shape == result.velocity_image.shape
    ):
        image = np.asarray(result.velocity_image, dtype=float)
        same_wall = replace(like, data=image.ravel()[like.voxels.index], data_image=image)
        # the normal matrix and the pencils depend on the wall only: formed once for the frames on it
        same_wall.__dict__["tikhonov"] = like.tikhonov.with_data(same_wall.data)
        return same_wall
    vopt = replace(options.velocity, near_wall="off")
    return vel.assemble(result.grid, result.velocity_image, coefficients, center, vopt, psf=psf)
