"""The reconstruction of one acquisition: geometry -> velocity -> WSS, and its options.

:func:`reconstruct_slice` runs the steps of :mod:`wss_nlp.pipeline.steps` on one slice
alone; :func:`reconstruct` does so for every slice of an
:class:`~wss_nlp.io.files.Acquisition` (or hands a stack to
:func:`wss_nlp.pipeline.steps.reconstruct_stack`), reporting progress, and returns
:class:`SliceResult` objects that carry the numbers, the solver statistics and
what was assumed. :class:`ReconstructionOptions` is the one options schema.
"""

from __future__ import annotations

import contextlib
import functools
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..models import baselines as bl
from ..models import coupled as cpl
from ..models import dephasing as deph
from ..models import geometry as geo
from ..models import kspace
from ..models import near_wall as nw
from . import steps as pipeline
from . import plausibility as plaus
from ..models import preprocess as pp
from ..models import surround
from ..core import radius as rad
from ..uncertainty import sensitivity as sens
from ..models import stack as stk
from ..models import velocity as vel
from ..models import womersley
from ..models import wss as wss_mod
from ..parameters.choice import (  # noqa: F401 (re-exported: the rules' names and grids are part of this module's API)
    ALPHA_RULES,
    ALPHA_STOP,
    AUTO_RULE,
    BETA_RULES,
    BETA_STOP,
    DEPHASING_BETA_RULES,
    balance_alpha,
    choose_alpha,
    kspace_filter,
    choose_beta,
    gcv_beta,
    layer_model,
    parse_rule,
    velocity_beta,
)
from ..errors import InputError, WssNlpError
from ..io.files import DEFAULT_DENSITY, Acquisition, FailedSlice, check_density
from ..models.measurement import VoxelGrid
from .results import SliceResult
from ..core.schema import option


METHODS = ("decoupled", "coupled") + bl.METHODS


_DEFAULT_ALPHA = geo.GeometryOptions().alpha
_DEFAULT_BETA = vel.VelocityOptions().beta
WSS_GROUP = "wall shear stress (Sec. 4)"


def _parameter_word(text, name: str) -> dict:
    """``--alpha`` / ``--beta`` (or a study key): a number is used as given (fixed rule), a word names a rule."""
    rules = ALPHA_RULES if name == "alpha" else BETA_RULES
    part = "geometry" if name == "alpha" else "velocity"
    try:
        return {f"{name}_rule": "fixed", f"{part}.{name}": float(text)}
    except ValueError:
        return {f"{name}_rule": parse_rule(str(text), rules, f"--{name}")}


@dataclass(frozen=True)
class ReconstructionOptions:
    """Everything that controls a reconstruction (stored in the result file).

    ``alpha_rule`` / ``beta_rule`` choose the regularization parameters:
    "fixed" uses ``geometry.alpha`` / ``velocity.beta``; "discrepancy"
    searches ``p0 2^-n`` for the largest value whose residual is at most
    ``tau`` times the estimated (or given) noise level, eqs. (disc),
    (disc2); "balance" is Lepskii's balancing principle (on the radius for
    alpha, on the WSS for beta; ``kappa_alpha``, ``kappa_beta``); for beta
    also "gcv" and "lcurve" (see :mod:`wss_nlp.parameters`).
    The defaults, beta by balancing and alpha fixed, and tau = 1.1 come from
    ``scripts/parameter_rules.py`` and ``scripts/accuracy.py --auto`` (docs,
    "Choosing alpha and beta"): the balancing beta's worst case is far
    better than the former fixed beta's (laminar 1.48x against 2.70x the
    oracle, turbulent 5.5-25x against 15-55x); for alpha balancing costs
    about three times a solve and gains nothing measurable over the fixed value.
    """

    schema_group = "method and parameter choice"

    geometry: geo.GeometryOptions = field(default_factory=geo.GeometryOptions)
    velocity: vel.VelocityOptions = field(default_factory=vel.VelocityOptions)
    method: str = option(
        "decoupled",
        "decoupled: geometry, then velocity (the paper's); coupled: both as one NLP "
        "started from the decoupled solution, so the velocity data inform the wall too; oyre / "
        "stalder: the classical baselines (cubic near-wall profile fits / smoothing B-spline on a "
        "50 % magnitude segmentation; docs, 'Classical baselines')",
        cli="--method",
        toml=("method",),
        choices=METHODS,
    )
    coupled: cpl.CoupledOptions = field(default_factory=cpl.CoupledOptions)
    baseline: bl.BaselineOptions = field(default_factory=bl.BaselineOptions)  # method "oyre" / "stalder"
    stack: stk.StackOptions = field(default_factory=stk.StackOptions)  # nz > 1: z-regularization (wss_nlp.models.stack)
    screen: plaus.ScreenOptions = field(default_factory=plaus.ScreenOptions)  # vessel choice, unwrapping
    acquisition: kspace.AcquisitionOptions = field(default_factory=kspace.AcquisitionOptions)  # box or k-space PSF
    cine: womersley.CineModelOptions = field(default_factory=womersley.CineModelOptions)  # frames tied in time
    tissue: surround.TissueOptions = field(default_factory=surround.TissueOptions)  # surround model, offset (#39)
    n_phi: int = option(360, "angles at which tau is reported, >= 360", cli="--n-phi", toml=("n_phi",), group=WSS_GROUP)
    viscosity_pa_s: float | None = option(
        None,
        "dynamic viscosity in Pa*s; overrides the file's 'viscosity_pa_s'",
        cli="--viscosity",
        toml=("viscosity",),
        group=WSS_GROUP,
    )
    density_kg_m3: float | None = option(
        None,
        "fluid density in kg/m^3, used by the law-of-the-wall layer (--near-wall); overrides the file's "
        "'density_kg_m3' (default: blood, 1060)",
        cli="--density",
        toml=("density",),
        group=WSS_GROUP,
    )
    dephasing_correction: bool = option(
        True,
        "skip the second pass that corrects the magnitude for intra-voxel dephasing (needs venc)",
        cli="--no-dephasing-correction",
        toml=("dephasing_correction",),
        flag_off=True,
        group=WSS_GROUP,
    )
    dephasing_beta_rule: str = option(
        "gcv",
        "beta of the velocity fit that predicts dephasing: GCV (keeps steep "
        "boundary layers) or the same beta as the WSS fit",
        cli="--dephasing-beta",
        choices=DEPHASING_BETA_RULES,
        group=WSS_GROUP,
    )
    alpha_rule: str = option(
        "fixed",
        "Tikhonov parameter of the H^s radius penalty (dimensionless), or a rule: "
        "'auto' = 'balance' (Lepskii balancing on the radius), 'discrepancy' (eq. (disc))",
        cli="--alpha",
        toml=("alpha",),
        parse=lambda text: _parameter_word(text, "alpha"),
        default_text=str(_DEFAULT_ALPHA),
        group=geo.GeometryOptions.schema_group,
    )
    beta_rule: str = option(
        "balance",
        "Tikhonov parameter of the ||Delta^t v||^2 penalty (dimensionless, e.g. "
        f"{_DEFAULT_BETA:g}), or a rule: 'auto' = 'balance' (Lepskii balancing on the WSS; see "
        "docs), 'discrepancy' (eq. (disc2)), 'gcv' (generalized cross-validation), 'lcurve'",
        cli="--beta",
        toml=("beta",),
        parse=lambda text: _parameter_word(text, "beta"),
        default_text="auto",
        group=vel.VelocityOptions.schema_group,
    )
    tau_alpha: float = option(
        1.1,
        "discrepancy factor for alpha (the paper's theory uses 4)",
        cli="--tau-alpha",
        toml=("tau_alpha",),
        group=geo.GeometryOptions.schema_group,
    )
    tau_beta: float = option(
        1.1,
        "discrepancy factor for beta (the paper's theory uses 2)",
        cli="--tau-beta",
        toml=("tau_beta",),
        group=vel.VelocityOptions.schema_group,
    )
    kappa_alpha: float = option(
        2.0,
        "balancing rule: radius differences allowed, in noise standard deviations",
        cli="--kappa-alpha",
        toml=("kappa_alpha",),
        group=geo.GeometryOptions.schema_group,
    )
    # beta: noise alone stays below 2, but the least regularized WSS estimates carry a bias of their own (the
    # voxel means do not fix every coefficient), which the rule reads as bias of the more regularized ones; 2.5 is
    # the margin that absorbed it on held-out seeds (scripts/parameter_rules.py --kappa, docs)
    kappa_beta: float = option(
        2.5,
        "balancing rule: WSS differences allowed, in noise standard deviations",
        cli="--kappa-beta",
        toml=("kappa_beta",),
        group=vel.VelocityOptions.schema_group,
    )
    alpha_start: float = 1.0
    beta_start: float = 1e-2
    noise_magnitude: float | None = option(
        None,
        "noise level delta of the normalized magnitude in mm (default: estimated)",
        cli="--noise-magnitude",
        group=geo.GeometryOptions.schema_group,
    )
    noise_velocity: float | None = option(
        None,
        "noise level epsilon of the velocity in m/s (default: estimated)",
        cli="--noise-velocity",
        group=vel.VelocityOptions.schema_group,
    )
    blas_threads: int = option(
        1,
        "BLAS threads for the small dense linear algebra of each slice; 0 leaves the BLAS as it is (more threads "
        "only add overhead at these matrix sizes: scripts/bench_blas.py)",
        cli="--blas-threads",
        group=WSS_GROUP,
    )
    uncertainty: bool = option(
        True,
        "skip the linearized WSS band and the sensitivities (about 1-3x the time of the solve)",
        cli="--no-uncertainty",
        toml=("uncertainty",),
        flag_off=True,
        group=WSS_GROUP,
    )
    noise_sigma: float | None = option(
        None,
        "complex noise per channel in raw magnitude units for the band (default: from the Rayleigh background)",
        cli="--noise-sigma",
        group=WSS_GROUP,
    )

    def __post_init__(self):
        if self.n_phi < 360:
            raise InputError(f"n_phi must be >= 360 (file format), got {self.n_phi}")
        if self.method not in METHODS:
            raise InputError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.alpha_rule not in ALPHA_RULES:
            raise InputError(f"alpha rule must be one of {ALPHA_RULES}, got {self.alpha_rule!r}")
        if self.dephasing_beta_rule not in DEPHASING_BETA_RULES:
            raise InputError(
                f"dephasing beta rule must be one of {DEPHASING_BETA_RULES}, got {self.dephasing_beta_rule!r}"
            )
        if self.beta_rule not in BETA_RULES:
            raise InputError(f"beta rule must be one of {BETA_RULES}, got {self.beta_rule!r}")
        # a value set next to a rule that would ignore it is a mistake to report, not to drop silently
        for name, rule, value, default in (
            ("alpha", self.alpha_rule, self.geometry.alpha, _DEFAULT_ALPHA),
            ("beta", self.beta_rule, self.velocity.beta, _DEFAULT_BETA),
        ):
            if rule != "fixed" and value != default:
                raise InputError(
                    f"{name} = {value:g} is set but the {name} rule is {rule!r}, which chooses {name} "
                    f"from the data; pass {name}_rule='fixed' (CLI: --{name} {value:g}) to use it"
                )
        for name in ("tau_alpha", "tau_beta", "kappa_alpha", "kappa_beta", "alpha_start", "beta_start"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name} must be > 0, got {getattr(self, name)}")
        check_density(self.density_kg_m3, "--density")
        if self.blas_threads < 0:
            raise InputError(f"blas_threads must be >= 0 (0: leave the BLAS as it is), got {self.blas_threads}")
        for name in ("noise_magnitude", "noise_velocity"):
            val = getattr(self, name)
            if val is not None and not val > 0:
                raise InputError(f"{name} must be > 0, got {val}")

    def as_dict(self) -> dict:
        return asdict(self)


def reconstruct_slice(
    magnitude: np.ndarray,
    velocity_image: np.ndarray,
    grid: VoxelGrid,
    viscosity_pa_s: float,
    options: ReconstructionOptions,
    source: str = "<memory>",
    index: int = 0,
    venc: float | None = None,
    density: tuple[float, str] = (DEFAULT_DENSITY, "default (blood)"),
    noise_venc: float | None = None,
    psf: kspace.PSF | None = None,
    box: pp.LumenBox | None = None,
    defer_band: bool = False,
) -> SliceResult:
    """Geometry (Sec. 2), velocity (Sec. 3) and WSS (Sec. 4) of one slice.

    With ``options.dephasing_correction`` and a known ``venc``, a second
    geometry and velocity pass uses the magnitude divided by the dephasing
    factors predicted by the first velocity reconstruction
    (:func:`wss_nlp.models.measurement.dephasing_factors`); an extension of the
    paper's model that removes the radius bias from intra-voxel dephasing.
    ``density`` (kg/m^3 and its source) serves the law-of-the-wall layer.
    ``noise_venc`` sets the velocity noise (``venc sigma / (pi |d_i|)``)
    when there is no ``venc`` (velocity combined from encoded components)
    and the lumen has no plateau to measure it on: the plateau's level is
    preferred, as it also holds what the data's placement adds (resampled
    images; ``scripts/results/plane_extraction.md``). ``psf`` (a k-space
    acquisition, :mod:`wss_nlp.models.kspace`) replaces the voxel means of every
    forward model by the point-spread function. ``box`` replaces the lumen's own
    polar origin, radius box and reference radius (cine frames share one, and
    with it the built geometry solver) and may carry a warm start.
    ``defer_band`` leaves the uncertainty band to :meth:`SliceResult.finish_band`
    (cine frames: only the model the series keeps needs one).
    """
    t = {}
    t0 = time.perf_counter()
    data = pipeline.prepare(
        magnitude, velocity_image, grid, index, source, options.screen.vessel, psf, venc, noise_venc, box,
        options.tissue,
    )  # fmt: skip
    where, norm, m, lumen = data.where, data.norm, data.magnitude, data.lumen
    velocity_image = data.velocity  # hook (issue 39): the offset-corrected velocity of prepare
    t["preprocess"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    problem = data.problem
    start = None if box is None else box.start
    g, alpha_choice = choose_alpha(problem, magnitude, norm, lumen, options, where, start)
    if psf is not None:  # the PSF's tails reach into the background the noise estimates use
        lumen = replace(lumen, signal=norm.m1 * geo.model_image(problem, options.geometry, g))
    t["geometry"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    vp = vel.assemble(grid, velocity_image, g.coefficients, g.center, options.velocity, psf=psf)
    vp, near = pipeline.near_wall_model(data, vp, options, viscosity_pa_s, density, lumen=lumen)
    beta_choice = pipeline.beta_choice(data, vp, near, options, viscosity_pa_s, lumen=lumen)
    v = vel.solve(vp, options.velocity, beta=beta_choice.chosen)
    t["velocity"] = time.perf_counter() - t0

    factors, notes_deph = None, []
    dep: dict = {}  # the dephasing record (SliceResult.dephasing)
    passes = 1 if psf is None else KSPACE_PASSES
    # box: one corrective pass (the factors hardly move after it); k-space: the phase mixing reaches further
    # than a wall voxel, so passes repeat until the wall stops moving, each judged by how well its state
    # explains the measured magnitude (a pass that explains it worse is undone)
    previous, window, explained = None, None, float("inf")
    for k in range(passes + 1):
        if not (options.dephasing_correction and venc is not None):
            break
        t0 = time.perf_counter()
        corr, v_deph = pipeline.predict_dephasing(data, vp, v, g, options, window)
        t["dephasing_check"] = t.get("dephasing_check", 0.0) + time.perf_counter() - t0
        if psf is not None:
            if k == 0:  # the first geometry assumed no phase: its own model is the one a pass must beat
                window, explained = corr.window, corr.misfit_still
            elif corr.misfit_moving >= explained:
                problem, g, vp, v, near, beta_choice, lumen = previous  # type: ignore[misc]
                dep["passes"] = k - 1
                if k == 1:  # later passes that do not help just end the iteration
                    notes_deph.append(deph.UNEXPLAINED_NOTE)
                break
            else:
                explained = corr.misfit_moving
            lumen = replace(lumen, signal=corr.signal)  # the phases' prediction of the background tails
        factors = corr.factors if factors is None else factors
        dep["beta"] = float(v_deph.beta)
        # a further pass only pays where some wall voxel loses more than 1 % of its magnitude
        if k == passes or not corr.worth_a_pass:
            break
        if psf is not None and k > 0 and KSPACE_PASS_PREDICTION:
            # the pass would end the iteration if it moved the wall less than the tolerance: predicted to first
            # order (within 1 % of such small moves on the phantoms), it need not be run
            t0 = time.perf_counter()
            change = geo.predicted_change(problem, options.geometry, g, corr.magnitude)
            t["dephasing_check"] += time.perf_counter() - t0
            if change is not None:
                dep["next_move"] = float(np.max(np.abs(rad.evaluate(change, rad.uniform_angles(72)))) / grid.h)
                if dep["next_move"] < KSPACE_PASS_TOL:
                    break
        t0 = time.perf_counter()
        previous = (problem, g, vp, v, near, beta_choice, lumen)
        problem = replace(problem, magnitude=corr.magnitude)
        g = geo.solve(problem, geo.with_options(options.geometry, alpha=g.alpha), x0=g.coefficients)
        vp = vel.assemble(
            grid,
            corr.velocity,
            g.coefficients,
            g.center,
            options.velocity,
            basis=getattr(vp.basis, "base", vp.basis),
            psf=psf,
        )
        if near is not None and near.model != "plain":
            # the first pass's geometry was biased by the dephasing just corrected, and the layer scale with it
            vp, near = pipeline.near_wall_model(data, vp, options, viscosity_pa_s, density, lumen=lumen, around=near)
            beta_choice = pipeline.beta_choice(data, vp, near, options, viscosity_pa_s, lumen=lumen)
        v = vel.solve(vp, options.velocity, beta=beta_choice.chosen)
        t["dephasing_pass"] = t.get("dephasing_pass", 0.0) + time.perf_counter() - t0
        dep["passes"] = k + 1
        moved = np.max(np.abs(g.radius(rad.uniform_angles(72)) - previous[1].radius(rad.uniform_angles(72))))
        if psf is None or moved < KSPACE_PASS_TOL * grid.h:
            break
    t.setdefault("dephasing_check", 0.0)

    info, cres = {}, None
    if options.method == "coupled":
        t0 = time.perf_counter()
        # vp.data_image: the velocity the last pass corrected (the k-space phase nonlinearity; box: the data)
        cres, info = solve_coupled(data, problem, g, v, lumen, vp.data_image, options)
        g, v = cres.geometry, cres.velocity
        t["coupled"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    w = wss_mod.from_reconstruction(v, options.n_phi, viscosity_pa_s)
    t["wss"] = time.perf_counter() - t0
    dep["min_factor"] = float(np.min(factors, initial=1.0)) if factors is not None else 1.0
    if not np.all(np.isfinite(w.tau)):
        raise WssNlpError(f"{where}: wall shear stress is not finite; the reconstruction is unusable")
    notes, sensitivity, pending = list(notes_deph) + surround.notes(lumen.tissue), None, None  # hook (issue 39)
    band_inputs = (problem, g, vp, v, w, data, lumen, viscosity_pa_s, options, cres, near)
    if options.uncertainty and defer_band:
        pending = functools.partial(uncertainty, *band_inputs)
    elif options.uncertainty:
        t0 = time.perf_counter()
        sensitivity, note = uncertainty(*band_inputs)
        notes += [note] if note else []
        t["uncertainty"] = time.perf_counter() - t0
    return SliceResult(
        index,
        g,
        v,
        w,
        norm,
        lumen,
        grid,
        m,
        np.asarray(velocity_image, float),
        t,
        alpha_choice,
        beta_choice,
        options.method,
        info,
        sensitivity,
        notes,
        near_wall=near,
        problem=vp,
        pending_band=pending,
        dephasing=dep,
    )


#: Largest number of dephasing passes with the k-space model, and the wall movement (in voxels) that ends them.
KSPACE_PASSES, KSPACE_PASS_TOL = 3, 1e-3
#: Skip a pass predicted to move the wall less than KSPACE_PASS_TOL (False: run it; ``scripts/kspace_passes.py``).
KSPACE_PASS_PREDICTION = True


def _add_scale_spread(s, vp, v, w, near, viscosity_pa_s: float, sigma_m: float, sigma_u) -> None:
    """Let the band carry the law-of-the-wall scale's response to the noise (chain rule through l).

    The scale is a function of the data (``u_tau l = nu``), so the WSS moves
    with the data also through it: ``d tau/dp += (d tau/d log l)(d log l/dp)``
    with ``d log l/dp = -(dg/da_0)(da_0/dp)/(dg/d log l)`` for every input
    ``p`` (magnitude and velocity voxels, parameters; ``da_0/dp`` from the
    sensitivities, :func:`wss_nlp.models.near_wall.scale_sensitivity`). Also
    records the scale's own standard deviation (of ``log l``).
    """
    smat, _ = wss_mod.wss_matrix(v.basis, v.disk_map, viscosity_pa_s, w.phi.size)
    nu = viscosity_pa_s / near.density_kg_m3
    dg_da0, dg_dlog, dtau_dlog = nw.scale_sensitivity(vp, v.coefficients, v.beta, smat, nu)
    row = v.basis.base.size  # the layer's first coefficient a_0
    dlog_da0 = -dg_da0 / dg_dlog
    dlog_dp = dlog_da0 * s.d_coef_v[row]
    c = v.disk_map.coefficients
    ds = np.hypot(rad.evaluate(c, w.phi), rad.evaluate(c, w.phi, 1))
    dmean_dlog = float(np.sum(dtau_dlog * ds) / np.sum(ds))
    n_m, n_u = s.m_index.size, s.u_index.size
    # d tau/dp = (d tau/dc) (dc/dp) gains (d tau/d log l) (d log l/d a_0) (d a_0/dp): a term in d tau/d a_0
    s.d_tau_d_coef[:, s.d_coef_r.shape[0] + row] += dlog_da0 * dtau_dlog
    for name, cols in (("m", slice(0, n_m)), ("u", slice(n_m, n_m + n_u))):
        setattr(s, f"d_mean_d_{name}", getattr(s, f"d_mean_d_{name}") + dmean_dlog * dlog_dp[cols])
    s.d_tau = s.d_tau + np.outer(dtau_dlog, dlog_dp[n_m + n_u :])
    s.d_mean = s.d_mean + dmean_dlog * dlog_dp[n_m + n_u :]
    su = np.broadcast_to(np.asarray(sigma_u, float), (n_u,))
    var = sigma_m**2 * np.sum(dlog_dp[:n_m] ** 2) + np.sum((dlog_dp[n_m : n_m + n_u] * su) ** 2)
    near.scale_std_log = float(np.sqrt(var))


def uncertainty(
    problem,
    g,
    vp,
    v,
    w,
    data: pipeline.SliceData,
    lumen,
    viscosity_pa_s,
    options: ReconstructionOptions,
    coupled_result=None,
    near=None,
):
    """Sensitivities and the linearized band (sets ``w.tau_std``, ``w.mean_std``); returns ``(Sensitivity, note)``.

    The noise levels are the slice's (:func:`wss_nlp.pipeline.steps.noise_levels`, with ``lumen`` as the last pass
    left it).

    A band that cannot be computed (no background for the noise level, no
    venc, a failed anchor re-solve) is reported in the note, not raised:
    the reconstruction itself is still valid. With a law-of-the-wall layer
    (``near``) the band includes the scale's response to the noise; with a
    layer whose nearly equally good scales (an exponential layer's interval,
    a wall law's rival roots) give mean WSS further apart than the band, the
    note says so (:func:`wss_nlp.models.near_wall.scale_ambiguity_note`).
    """
    try:
        if coupled_result is not None:
            s = sens.coupled(coupled_result, problem, options.geometry, options.velocity, viscosity_pa_s, w.phi.size)
        else:
            s = sens.decoupled(problem, options.geometry, g, vp, options.velocity, v, viscosity_pa_s, w.phi.size)
        sigma_m, sigma_u, how = pipeline.noise_levels(data, options, s.u_index, lumen)
    except WssNlpError as exc:
        return None, f"no uncertainty band: {exc}"
    if near is not None and near.consistent:
        _add_scale_spread(s, vp, v, w, near, viscosity_pa_s, sigma_m, sigma_u)
    w.tau_std, w.mean_std, s.mean_std_magnitude, s.mean_std_velocity = s.band(sigma_m, sigma_u)
    s.tau_std, s.mean_std = w.tau_std, w.mean_std
    s.noise.update({"sigma_m": sigma_m, "method": how})
    return s, nw.scale_ambiguity_note(near, w.mean, w.mean_std)


def solve_coupled(data: pipeline.SliceData, problem, g, v, lumen, velocity_image, options: ReconstructionOptions):
    """The coupled NLP started from the decoupled ``(g, v)``, with the same alpha and beta.

    Returns the :class:`wss_nlp.models.coupled.CoupledResult` and a dict with the
    weight, how it was chosen (:func:`wss_nlp.pipeline.steps.coupled_weight`) and the decoupled start's mean radius.
    """
    weight, how = pipeline.coupled_weight(data, problem, velocity_image, options, lumen)
    res = cpl.solve(problem, options.geometry, velocity_image, options.velocity, g, v, weight, options.coupled)
    info = {
        "velocity_weight": weight,
        **how,
        "decoupled_mean_radius_mm": float(g.coefficients[0]),
        "decoupled_converged": bool(g.stats.converged and v.stats.converged),
    }
    return res, info


class Results(list):
    """The per-slice results of :func:`reconstruct`, with ``stack`` (a :class:`wss_nlp.models.stack.StackInfo` or None)
    and ``psf`` (the acquisition model used, resolved: a :class:`wss_nlp.models.kspace.PSF`, or None for the box)."""

    stack = None
    psf: kspace.PSF | None = None


def stack_applies(acq: Acquisition, options: ReconstructionOptions) -> bool:
    """Whether a stack is reconstructed with z-regularization (else slice by slice)."""
    ell = options.stack.z_smoothing_mm
    if acq.nz == 1 or ell == 0:
        return False
    supported = stk.supports(options)
    if ell is not None and not supported:
        raise InputError(
            f"{acq.source}: z-regularization (--z-smoothing {ell:g}) supports the decoupled and coupled methods "
            "with a fixed alpha; pass --z-smoothing 0 for independent slices"
        )
    return supported


def reconstruct(
    acq: Acquisition,
    options: ReconstructionOptions | None = None,
    progress=None,
    boxes: dict | None = None,
    defer_band: bool = False,
) -> Results:
    """Reconstruct every slice of an acquisition.

    A stack (``nz > 1``) is reconstructed with z-regularization
    (:func:`wss_nlp.pipeline.steps.reconstruct_stack`) when the options allow it (decoupled or coupled method, fixed
    alpha and beta, ``options.stack.z_smoothing_mm != 0``), else slice by
    slice. In a stack, a slice that cannot be reconstructed (NaN or Inf, no
    vessel, solver failure) becomes a :class:`wss_nlp.io.files.FailedSlice` and
    the others are still solved; a single slice raises instead.

    Returns :class:`SliceResult` objects, or :class:`wss_nlp.models.baselines.BaselineResult`
    for the classical methods (``options.method`` "oyre" or "stalder").

    Parameters
    ----------
    progress : callable or None
        Called as ``progress(done, total, slice_result)`` after each slice.
    boxes : dict or None
        Slice index -> :class:`wss_nlp.models.preprocess.LumenBox` replacing that
        slice's own origin and radius box (cine frames; slice by slice only).
    defer_band : bool
        Leave each slice's uncertainty band to :meth:`SliceResult.finish_band`
        (slice by slice only; a z-regularized stack computes its band with the segment's solve,
        :mod:`wss_nlp.uncertainty.stack_band`).

    Notes
    -----
    Long stack solves report their stages to the ``wss_nlp.models.stack`` logger
    (INFO); the command line shows them on stderr.
    """
    options = options or ReconstructionOptions()
    with blas_threads(options.blas_threads):
        return _reconstruct(acq, options, progress, boxes or {}, defer_band)


def blas_threads(n: int):
    """A context limiting the BLAS to ``n`` threads (threadpoolctl); ``n = 0`` changes nothing."""
    if n == 0:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency; tolerate its absence
        return contextlib.nullcontext()
    return threadpool_limits(limits=n, user_api="blas")


def _reconstruct(acq: Acquisition, options: ReconstructionOptions, progress, boxes: dict, defer_band: bool) -> Results:
    acq.validate()
    mu = acq.viscosity(options.viscosity_pa_s)
    density = acq.density(options.density_kg_m3)
    acq, screens = plaus.screen(acq, options.screen)
    psf = options.acquisition.psf(acq.voxel_size_mm, acq.acquired_voxel_size_mm, f"{acq.source}: ")
    if psf is not None and psf.filter == "auto":
        psf = kspace_filter(acq.magnitude, acq.grid, psf, options, f"{acq.source}: ")
    out = Results()
    out.psf = psf
    if stack_applies(acq, options):
        results, info = pipeline.reconstruct_stack(acq, options, options.stack, progress, psf)
        out.extend(
            r if r is not None else FailedSlice(k, info.failed[k], options.n_phi, options.geometry.n_fourier)
            for k, r in enumerate(results)
        )
        out.stack = info
        return _with_screens(out, screens, acq, psf)
    velocity = acq.velocity_images()
    bad = set(acq.nonfinite_slices())
    for iz in range(acq.nz):
        res: SliceResult | bl.BaselineResult | FailedSlice
        try:
            if iz in bad:
                raise InputError(f"{acq.source} slice {iz}: the images contain NaN or Inf")
            if options.method in bl.METHODS:
                res = bl.reconstruct_slice(
                    acq.magnitude[iz],
                    velocity[iz],
                    acq.grid,
                    mu,
                    options.method,
                    options.baseline,
                    options.n_phi,
                    acq.source,
                    iz,
                    options.screen.vessel,
                )
            else:
                res = reconstruct_slice(
                    acq.magnitude[iz],
                    velocity[iz],
                    acq.grid,
                    mu,
                    options,
                    acq.source,
                    iz,
                    acq.venc_m_s,
                    density,
                    noise_venc=acq.noise_venc_m_s,
                    psf=psf,
                    box=boxes.get(iz),
                    defer_band=defer_band,
                )
        except WssNlpError as exc:
            if acq.nz == 1:
                raise
            res = FailedSlice(iz, str(exc), options.n_phi, options.geometry.n_fourier)
        _with_screens([res], screens, acq, psf)
        if isinstance(res, SliceResult) and not defer_band:
            res.problem = None  # about a megabyte a slice; kept only where a deferred band holds it anyway
        out.append(res)
        if progress is not None:
            progress(iz + 1, acq.nz, res)
    if all(isinstance(r, FailedSlice) for r in out):
        raise WssNlpError(f"{acq.source}: no slice could be reconstructed: " + "; ".join(r.reason for r in out))
    return out


#: Acquired / reported voxel size above which a file counts as zero-filled (the box model then misdescribes it).
ZERO_FILL_TOLERANCE = 1.05
ZERO_FILLED_NOTE = (
    "SUSPECT: the file states an acquired resolution of {acquired} mm for {voxel} mm voxels (zero-filled "
    "k-space), which the box model does not describe; use --acquisition kspace (or auto)"
)

#: What every slice of an input cut from a volume (``resampled_from``) says.
RESAMPLED_NOTE = (
    "the images were cut from a 4D-flow volume (wss-nlp import --plane): each voxel is the nearest volume "
    "voxel's, up to half a voxel from where it was measured; radius errors of several percent and WSS errors "
    "of 3-15 % are typical (docs, 'Your own data': scripts/results/plane_extraction.md)"
)
#: A lumen cut from a volume with a mean radius under this many plane voxels is flagged SUSPECT: with radius
#: 3.6 voxels the WSS missed by up to 1700 %, mostly where no other check fired; with 5.5 voxels by at most
#: 14.5 % on unflagged slices (scripts/results/plane_extraction.md).
RESAMPLED_MIN_RADIUS_VOXELS = 5.0


def _with_screens(results, screens: dict, acq: Acquisition, psf=None):
    """Attach what the plausibility screen found, and the fit's consistency check, to each slice.

    Also what the acquisition model implies: a file that states zero-filling (``acquired_voxel_size_mm``
    above the voxel size) reconstructed with the box model is SUSPECT (the model does not describe such
    images: ``scripts/results/kspace.md``), and an ambiguous k-space filter choice is said.
    """
    acquired = acq.acquired_voxel_size_mm
    zero_filled = acquired is not None and any(a > v * ZERO_FILL_TOLERANCE for a, v in zip(acquired, acq.voxel_size_mm))
    for r in results:
        if isinstance(r, FailedSlice):
            continue
        box_on_kspace = zero_filled and psf is None and isinstance(r, SliceResult)
        note = ZERO_FILLED_NOTE.format(acquired=acquired, voxel=acq.voxel_size_mm)
        if box_on_kspace and note not in r.notes:
            r.notes.append(note)
        choice = None if psf is None else psf.choice
        if choice and choice["ambiguous"] and isinstance(r, SliceResult):
            r.notes.append(
                f"k-space filter chosen from the data: {choice['chosen']}, but {choice['runner_up']} fits the "
                f"magnitude almost as well ({100 * choice['margin']:.1f} % more misfit); pass --kspace-filter if "
                "you know the scanner's"
            )
        found = screens.get(r.index)
        if found is not None:
            r.notes.extend(n for n in found.notes if n not in r.notes)
            r.screen = dict(found.record)
        coarse = False
        if acq.resampled_from and RESAMPLED_NOTE not in r.notes:
            r.notes.append(RESAMPLED_NOTE)
            radius_voxels = float(r.geometry.coefficients[0]) / acq.grid.h
            if radius_voxels < RESAMPLED_MIN_RADIUS_VOXELS:
                coarse = True
                r.notes.append(
                    f"SUSPECT: a lumen of {radius_voxels:.1f} voxels' radius cut from a volume: too coarse for "
                    f"resampled data (under {RESAMPLED_MIN_RADIUS_VOXELS:g}); its WSS is not trustworthy"
                )
        if isinstance(r, SliceResult):
            warning, ratio = plaus.check_fit(r, acq.magnitude[r.index], acq.venc_m_s)
            unresolved = r.near_wall is not None and bool(np.isfinite(r.near_wall.unresolved_mm))
            unbalanced = r.beta_choice is not None and r.beta_choice.rule == "balance" and not r.beta_choice.satisfied
            suspect = bool(warning) or unresolved or unbalanced or coarse or box_on_kspace
            r.screen.update(velocity_residual_to_noise=ratio, suspect=suspect)
            if warning:
                r.notes.append(warning)
    return results
