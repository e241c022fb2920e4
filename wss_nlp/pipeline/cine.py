r"""Time-resolved (cine) reconstruction: every frame of the cycle, then TAWSS and OSI.

Each frame is an acquisition of its own, reconstructed by the driver (:func:`wss_nlp.pipeline.driver.reconstruct`)
with its own parameter choices (the frames of a slice share its lumen box, built solvers and warm starts; their
bands wait until the cycle's model is chosen). Then each slice's velocity over the cycle is chosen by the BIC
(:func:`cycle_models`, :func:`wss_nlp.parameters.cycle.choose`) among the frames' own fits, a periodic temporal
prior (:mod:`wss_nlp.models.temporal`) and the momentum balance of pulsatile flow (:mod:`wss_nlp.models.womersley`),
on the frames' walls regularized in time; TAWSS and OSI integrate the chosen WSS over the cycle
(:mod:`wss_nlp.core.periodic`, which also bridges a failed frame by linear interpolation in time, and the result
says so).
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


@dataclass
class CycleModel:
    """The velocity model of one slice over the cycle: the choice, and the momentum model's WSS if chosen."""

    choice: cycle.CineModelChoice
    tau: np.ndarray | None = None  # (nt, nphi), Pa; NaN rows for frames the model was not fitted on
    tau_std: np.ndarray | None = None
    mean: np.ndarray | None = None  # (nt,)
    mean_std: np.ndarray | None = None
    walls: np.ndarray | None = None  # (nt, 2N+3): the walls the model used, radius coefficients then centre (mm)


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
        if model is not None and model.tau is not None:
            # the momentum model's WSS on the frames it was fitted on; the others count as failed
            good = good & np.all(np.isfinite(model.tau), axis=1)
            tau, tau_std, mean, mean_std = model.tau, model.tau_std, model.mean, model.mean_std
            if model.walls is not None:  # the walls its WSS lives on (regularized in time)
                coefficients, center = model.walls[:, :n_coef], model.walls[:, n_coef:]
                radius = np.array([rad.evaluate(c, phi) if np.all(np.isfinite(c)) else np.full(phi.size, np.nan)
                                   for c in coefficients])  # fmt: skip
        if model is not None:
            notes.append(model_note(model.choice))
        if not good.all():
            bad = np.nonzero(~good)[0].tolist()
            why = "; ".join(getattr(results[k], "reason", "not in the momentum model's fit") for k in bad[:3])
            notes.append(f"frame(s) {bad} failed ({why}); TAWSS and OSI bridge them by linear interpolation in time")
        bridged = bridge(np.where(good[:, None], tau, 0.0), good, self.times_ms, self.period_ms)
        tawss, osi = tawss_osi(bridged, self.weights)
        mean_bridged = bridge(np.where(good, mean, 0.0)[:, None], good, self.times_ms, self.period_ms)[:, 0]
        average = float(np.sum(self.weights * mean_bridged) / np.sum(self.weights))
        return CineSeries(
            iz, phi, np.where(good[:, None], tau, np.nan), np.where(good, mean, np.nan), center, coefficients,
            radius, alpha, beta, ~good, tawss, osi, average, notes, tau_std, mean_std,
            None if model is None else model.choice,
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
    out: list[list] = []
    t0 = time.perf_counter()
    omega = 2 * np.pi / (float(period_ms) / 1000.0)
    # a series of single slices leaves the frames' bands until the model is chosen: where the momentum model
    # wins, its own band replaces them (stacks compute them at once: holding every slice's problem until the
    # end would cost about a megabyte per slice and frame)
    keep = options.cine.model != "independent" and frames[0].nz == 1
    defer = options.uncertainty and keep
    psfs = []  # the acquisition model each frame was reconstructed with (resolved k-space filter)
    for k, frame in enumerate(frames):
        results: list
        try:
            done = reconstruct(frame, options, boxes=boxes, defer_band=defer)
            results = list(done)
            psfs.append(done.psf)
        except WssNlpError as exc:  # this frame only: the others still describe the cycle
            log.warning("frame %d failed: %s", k, exc)
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
    if all(isinstance(r, FailedSlice) for frame in out for r in frame):
        raise WssNlpError(f"every frame failed; the first: {out[0][0].reason}")
    result = CineResult(out, np.asarray(times_ms, dtype=float), float(period_ms), weights, notes)
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
    (:func:`~wss_nlp.parameters.cycle.smooth_walls`),
    with the Womersley parameters at those walls' mean equal-area radius (:func:`equal_area_radius`).
    """
    if options.cine.model == "independent":
        choice = cycle.CineModelChoice("independent", criterion="independent frames (--cine-model independent)")
        return {iz: CycleModel(choice) for iz in range(result.n_slices)}
    ref = frames[0]
    mu = ref.viscosity(options.viscosity_pa_s)
    nu = mu / ref.density(options.density_kg_m3)[0]
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
        if len(usable) == len(result.frames) >= 3 and _equally_spaced(result):
            scale, log_n = cycle.criterion_scale(usable)
            prior = temporal.fit(problems, betas, sigmas, scale, log_n)
        choice, fitted = cycle.choose(usable, omega, nu, options.cine, None if prior is None else prior.bic)
        choice.walls = wall_choice.as_dict()
        if prior is not None:
            choice.walls["temporal_prior"] = prior.as_dict()
        model = CycleModel(choice)
        if choice.model == "temporal" and prior is not None:
            _prior_wall_shear(model, prior, problems, options.n_phi, mu)
        if fitted is not None:
            n_t, n_phi = len(result.frames), options.n_phi
            phi = good[0][1].wss.phi
            model.tau, model.tau_std = np.full((n_t, n_phi), np.nan), np.full((n_t, n_phi), np.nan)
            model.mean, model.mean_std = np.full(n_t, np.nan), np.full(n_t, np.nan)
            model.walls = np.full((n_t, own.shape[1]), np.nan)
            for t in usable:
                k = t.index
                model.tau[k], model.tau_std[k], model.mean[k], model.mean_std[k] = womersley.wall_shear(
                    fitted, t, phi, mu
                )
                model.walls[k] = np.r_[t.coefficients, t.center]
        log.debug("slice %d: %s", iz, model_note(choice))  # the series' note says it (the CLI prints notes once)
        models[iz] = model
    return models


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


def write_result(path: str, cine: CineResult, options: dict, argv=None, notes=()) -> list[CineSeries]:
    """Write the time-resolved result layout of ``shared/spec/data-format.md`` (atomic); returns the series.

    Each slice group holds the contract's per-frame datasets with a leading time axis, ``wss/time_ms``,
    ``wss/mean_pa_t``, ``wss/tawss_pa``, ``wss/osi`` and ``wss`` attribute ``mean_pa`` (the cycle average of
    the per-frame mean), and every frame's complete single-frame record in ``frames/frame_NNN``. ``notes``
    (what the whole series was read as, e.g. the timing's range notes) go to the file's ``warnings`` attribute.
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
        f.attrs["all_converged"] = bool(all(r.converged for frame in cine.frames for r in frame))
        if notes:  # the readings taken and what was allowed are the result's, not only the terminal's
            f.attrs["warnings"] = json.dumps(list(notes))
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
        return replace(like, data=image.ravel()[like.voxels.index], data_image=image)
    vopt = replace(options.velocity, near_wall="off")
    return vel.assemble(result.grid, result.velocity_image, coefficients, center, vopt, psf=psf)
