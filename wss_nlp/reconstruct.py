"""The decoupled reconstruction of one acquisition: geometry -> velocity -> WSS.

:func:`reconstruct_slice` runs the three steps of the paper on one slice;
:func:`reconstruct` does so for every slice of an :class:`~wss_nlp.io.Acquisition`,
reporting progress, and returns :class:`SliceResult` objects that carry the
numbers, the solver statistics and what was assumed.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from . import analysis as an
from . import baselines as bl
from . import coupled as cpl
from . import geometry as geo
from . import measurement as meas
from . import plausibility as plaus
from . import preprocess as pp
from . import radius as rad
from . import sensitivity as sens
from . import stack as stk
from . import velocity as vel
from . import wss as wss_mod
from .errors import InputError, WssNlpError
from .io import Acquisition, FailedSlice
from .measurement import VoxelGrid


#: Smallest beta of the GCV and L-curve grids (below it the normal matrix loses definiteness in double precision).
BETA_STOP = 1e-14

#: Smallest predicted magnitude loss (1 - D_i) that triggers the dephasing pass.
DEPHASING_THRESHOLD = 0.01


ALPHA_RULES = ("fixed", "discrepancy", "balance")
ALPHA_STOP = 1e-6  # smallest alpha a balancing search tries (V_N with N = 8 hardly amplifies noise below it)
BETA_RULES = ("fixed", "discrepancy", "gcv", "lcurve", "balance")
DEPHASING_BETA_RULES = ("gcv", "same")
#: What ``auto`` means for alpha and beta: the rule closest to the oracle in scripts/accuracy.py --auto (README).
AUTO_RULE = "balance"


def parse_rule(word: str, rules: tuple, name: str) -> str:
    """The rule a user's word names (``auto`` -> :data:`AUTO_RULE`); InputError lists the accepted words."""
    word = word.strip().lower()
    if word == "auto":
        return AUTO_RULE
    if word in rules and word != "fixed":
        return word
    words = ["auto"] + [r for r in rules if r != "fixed"]
    raise InputError(f"{name} must be a number or one of {', '.join(words)}; got {word!r}")
METHODS = ("decoupled", "coupled") + bl.METHODS


_DEFAULT_ALPHA = geo.GeometryOptions().alpha
_DEFAULT_BETA = vel.VelocityOptions().beta


@dataclass(frozen=True)
class ReconstructionOptions:
    """Everything that controls a reconstruction (stored in the result file).

    ``alpha_rule`` / ``beta_rule`` choose the regularization parameters:
    "fixed" uses ``geometry.alpha`` / ``velocity.beta``; "discrepancy"
    searches ``p0 2^-n`` for the largest value whose residual is at most
    ``tau`` times the estimated (or given) noise level, eqs. (disc),
    (disc2); "balance" is Lepskii's balancing principle (on the radius for
    alpha, on the WSS for beta; ``kappa_alpha``, ``kappa_beta``); for beta
    also "gcv" and "lcurve" (see :mod:`wss_nlp.analysis`).
    The defaults, beta by balancing and alpha fixed, and tau = 1.1 come from
    ``scripts/parameter_rules.py`` and ``scripts/accuracy.py --auto`` (README,
    "Choosing alpha and beta"): the balancing beta's worst case is far
    better than the former fixed beta's (laminar 1.48x against 2.70x the
    oracle, turbulent 5.5-25x against 15-55x); for alpha balancing costs
    about three times a solve and gains nothing measurable over the fixed value.
    """

    geometry: geo.GeometryOptions = field(default_factory=geo.GeometryOptions)
    velocity: vel.VelocityOptions = field(default_factory=vel.VelocityOptions)
    method: str = "decoupled"  # "coupled": one NLP for geometry and velocity, started from the decoupled solution
    coupled: cpl.CoupledOptions = field(default_factory=cpl.CoupledOptions)
    baseline: bl.BaselineOptions = field(default_factory=bl.BaselineOptions)  # method "oyre" / "stalder"
    stack: stk.StackOptions = field(default_factory=stk.StackOptions)  # nz > 1: z-regularization (wss_nlp.stack)
    screen: plaus.ScreenOptions = field(default_factory=plaus.ScreenOptions)  # vessel choice, unwrapping
    n_phi: int = 360
    viscosity_pa_s: float | None = None  # overrides the file's value when set
    dephasing_correction: bool = True  # needs venc; see measurement.dephasing_factors
    dephasing_beta_rule: str = "gcv"  # beta of the velocity that predicts dephasing: "gcv" or "same"
    alpha_rule: str = "fixed"
    beta_rule: str = "balance"
    tau_alpha: float = 1.1
    tau_beta: float = 1.1
    kappa_alpha: float = 2.0  # balancing principle: differences up to two noise standard deviations
    # beta: noise alone stays below 2, but the least regularized WSS estimates carry a bias of their own (the
    # voxel means do not fix every coefficient), which the rule reads as bias of the more regularized ones; 2.5 is
    # the margin that absorbed it on held-out seeds (scripts/parameter_rules.py --kappa, README)
    kappa_beta: float = 2.5
    alpha_start: float = 1.0
    beta_start: float = 1e-2
    noise_magnitude: float | None = None  # delta in mm; estimated when None
    noise_velocity: float | None = None  # epsilon in m/s; estimated when None
    uncertainty: bool = True  # linearized WSS band and sensitivities (wss_nlp.sensitivity)
    noise_sigma: float | None = None  # complex noise per channel (raw units) for the band; estimated when None

    def __post_init__(self):
        if self.n_phi < 360:
            raise InputError(f"n_phi must be >= 360 (file format), got {self.n_phi}")
        if self.method not in METHODS:
            raise InputError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.alpha_rule not in ALPHA_RULES:
            raise InputError(f"alpha rule must be one of {ALPHA_RULES}, got {self.alpha_rule!r}")
        if self.dephasing_beta_rule not in DEPHASING_BETA_RULES:
            raise InputError(f"dephasing beta rule must be one of {DEPHASING_BETA_RULES}, "
                             f"got {self.dephasing_beta_rule!r}")
        if self.beta_rule not in BETA_RULES:
            raise InputError(f"beta rule must be one of {BETA_RULES}, got {self.beta_rule!r}")
        # a value set next to a rule that would ignore it is a mistake to report, not to drop silently
        for name, rule, value, default in (("alpha", self.alpha_rule, self.geometry.alpha, _DEFAULT_ALPHA),
                                           ("beta", self.beta_rule, self.velocity.beta, _DEFAULT_BETA)):
            if rule != "fixed" and value != default:
                raise InputError(f"{name} = {value:g} is set but the {name} rule is {rule!r}, which chooses {name} "
                                 f"from the data; pass {name}_rule='fixed' (CLI: --{name} {value:g}) to use it")
        for name in ("tau_alpha", "tau_beta", "kappa_alpha", "kappa_beta", "alpha_start", "beta_start"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("noise_magnitude", "noise_velocity"):
            val = getattr(self, name)
            if val is not None and not val > 0:
                raise InputError(f"{name} must be > 0, got {val}")

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
    alpha_choice: an.ParameterChoice | None = None
    beta_choice: an.ParameterChoice | None = None
    method: str = "decoupled"
    coupled_info: dict = field(default_factory=dict)  # weight, how it was chosen, the decoupled start's numbers
    sensitivity: sens.Sensitivity | None = None
    notes: list = field(default_factory=list)  # things the user should know that are not failures
    screen: dict = field(default_factory=dict)  # what wss_nlp.plausibility found (vessels, aliasing)

    @property
    def converged(self) -> bool:
        return bool(self.geometry.stats.converged and self.velocity.stats.converged)

    @property
    def warnings(self) -> list[str]:
        out = []
        for name, st in (("geometry", self.geometry.stats), ("velocity", self.velocity.stats)):
            if not st.converged:
                out.append(f"slice {self.index}: {name} solve did not converge ({st.solver}: {st.status})")
        for ch in (self.alpha_choice, self.beta_choice):
            if ch is not None and ch.noise == 0:
                out.append(f"slice {self.index}: {ch.name}: {ch.noise_method}: {ch.name} = {ch.chosen:g}")
            if ch is not None and ch.rule == "discrepancy" and not ch.satisfied:
                out.append(f"slice {self.index}: no {ch.name} reached residual <= {ch.tau:g} x noise "
                           f"({ch.noise:.3g}); model error dominates, took {ch.name} = {ch.chosen:.3g} where the "
                           "residual stopped falling")
        out.extend(f"slice {self.index}: {n}" for n in self.notes)
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
    norm, m, lumen = pp.preprocess(magnitude, grid, where, options.screen.vessel)
    t["preprocess"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    problem = geo.GeometryProblem(grid, m, lumen.center, lumen.r0, lumen.r1, lumen.r_area)
    g, alpha_choice = choose_alpha(problem, magnitude, norm, lumen, options, where)
    t["geometry"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    vp = vel.assemble(grid, velocity_image, g.coefficients, g.center, options.velocity)
    beta_choice = choose_beta(vp, magnitude, lumen, venc, options, where, viscosity_pa_s)
    v = vel.solve(vp, options.velocity, beta=beta_choice.chosen)
    t["velocity"] = time.perf_counter() - t0

    factors = None
    t0 = time.perf_counter()
    if options.dephasing_correction and venc is not None:
        # Dephasing is set by the velocity variation inside wall voxels, which a beta tuned for WSS may smooth
        # away (turbulent boundary layers); GCV targets the voxel-level prediction that matters here.
        v_deph = v
        if options.dephasing_beta_rule == "gcv":
            v_deph = vel.solve(vp, replace(options.velocity, solver="cholesky"), beta=gcv_beta(vp, options).chosen)
        factors = meas.dephasing_factors(vp.voxels, v_deph.evaluate_physical, venc,
                                         near_wall=(g.coefficients, grid.h))
        t["dephasing_beta"] = float(v_deph.beta)
    t["dephasing_check"] = time.perf_counter() - t0
    # a second pass only pays where some wall voxel loses more than 1 % of its magnitude
    if factors is not None and np.min(factors) < 1 - DEPHASING_THRESHOLD:
        t0 = time.perf_counter()
        m_corr = m.copy().ravel()
        m_corr[vp.voxels.index] = np.clip(m_corr[vp.voxels.index] / np.maximum(factors, 1e-3), 0.0, 1.0)
        problem = geo.GeometryProblem(grid, m_corr.reshape(m.shape), lumen.center, lumen.r0, lumen.r1, lumen.r_area)
        g = geo.solve(problem, geo.with_options(options.geometry, alpha=g.alpha), x0=g.coefficients)
        vp = vel.assemble(grid, velocity_image, g.coefficients, g.center, options.velocity, basis=vp.basis)
        v = vel.solve(vp, options.velocity, beta=beta_choice.chosen)
        t["dephasing_pass"] = time.perf_counter() - t0

    info, cres = {}, None
    if options.method == "coupled":
        t0 = time.perf_counter()
        cres, info = solve_coupled(problem, g, v, magnitude, norm, lumen, velocity_image, venc, options, where)
        g, v = cres.geometry, cres.velocity
        t["coupled"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    w = wss_mod.from_reconstruction(v, options.n_phi, viscosity_pa_s)
    t["wss"] = time.perf_counter() - t0
    t["min_dephasing_factor"] = float(np.min(factors)) if factors is not None else 1.0
    if not np.all(np.isfinite(w.tau)):
        raise WssNlpError(f"{where}: wall shear stress is not finite; the reconstruction is unusable")
    notes, sensitivity = [], None
    if options.uncertainty:
        t0 = time.perf_counter()
        sensitivity, note = uncertainty(problem, g, vp, v, w, magnitude, norm, lumen, venc, viscosity_pa_s, options,
                                        cres)
        notes += [note] if note else []
        t["uncertainty"] = time.perf_counter() - t0
    return SliceResult(index, g, v, w, norm, lumen, grid, m, np.asarray(velocity_image, float), t,
                       alpha_choice, beta_choice, options.method, info, sensitivity, notes)


def uncertainty(problem, g, vp, v, w, raw, norm, lumen, venc, viscosity_pa_s, options: ReconstructionOptions,
                coupled_result=None):
    """Sensitivities and the linearized band (sets ``w.tau_std``, ``w.mean_std``); returns ``(Sensitivity, note)``.

    A band that cannot be computed (no background for the noise level, no
    venc, a failed anchor re-solve) is reported in the note, not raised:
    the reconstruction itself is still valid.
    """
    try:
        if coupled_result is not None:
            s = sens.coupled(coupled_result, problem, options.geometry, options.velocity, viscosity_pa_s, w.phi.size)
        else:
            s = sens.decoupled(problem, options.geometry, g, vp, options.velocity, v, viscosity_pa_s, w.phi.size)
        sigma_m, sigma_u, how = sens.noise_levels(raw, lumen.noise_mask, norm.m0, norm.m1, s.u_index, venc,
                                                  options.noise_sigma)
    except WssNlpError as exc:
        return None, f"no uncertainty band: {exc}"
    w.tau_std, w.mean_std, s.mean_std_magnitude, s.mean_std_velocity = s.band(sigma_m, sigma_u)
    s.tau_std, s.mean_std = w.tau_std, w.mean_std
    s.noise.update({"sigma_m": sigma_m, "method": how})
    return s, ""


def solve_coupled(problem, g, v, raw, norm, lumen, velocity_image, venc, options: ReconstructionOptions, where: str):
    """The coupled NLP started from the decoupled ``(g, v)``, with the same alpha and beta.

    Returns the :class:`wss_nlp.coupled.CoupledResult` and a dict with the
    weight, how it was chosen and the decoupled start's mean radius.
    """
    copt = options.coupled
    if copt.velocity_weight is not None:
        weight, how = copt.velocity_weight, {"weight_method": "given (--velocity-weight)"}
    else:
        weight, how = cpl.weight_from_data(problem, options.geometry, raw, norm, lumen.noise_mask, velocity_image, venc,
                                           where.rstrip())
        how["weight_method"] = "likelihood: W sigma_m^2 / sigma_u^2 from the estimated noise levels"
    res = cpl.solve(problem, options.geometry, velocity_image, options.velocity, g, v, weight, copt)
    info = {"velocity_weight": weight, **how, "decoupled_mean_radius_mm": float(g.coefficients[0]),
            "decoupled_converged": bool(g.stats.converged and v.stats.converged)}
    return res, info


def _noise_free_choice(name: str, rule: str, fixed: float, noise: an.NoiseEstimate) -> an.ParameterChoice:
    """The fixed value, recorded as such, when the estimated noise is zero (noise-free synthetic data).

    There is no noise to balance against or to match a residual to; the
    choice says so (``SliceResult.warnings`` reports it) instead of guessing.
    """
    return an.ParameterChoice(name, "fixed", fixed, noise=0.0,
                              noise_method=f"{rule} needs noise, the estimate is zero ({noise.method}); "
                                           "the fixed value is used")


def choose_alpha(problem: geo.GeometryProblem, raw, norm, lumen, options: ReconstructionOptions, where: str):
    """Geometry solve with alpha fixed, from the discrepancy principle (eq. (disc)) or from balancing.

    The residual and the noise level are both taken on the annulus voxels
    (see :mod:`wss_nlp.analysis`); each solve starts from the previous one.
    """
    gopt = options.geometry
    if options.alpha_rule == "fixed":
        g = geo.solve(problem, gopt)
        return g, an.ParameterChoice("alpha", "fixed", g.alpha)
    if gopt.solver == "ipopt":
        solver = geo.IpoptGeometrySolver(problem, gopt)
        annulus = solver.nlp.model.annulus

        def run(alpha, prev):
            return solver.solve(alpha, None if prev is None else prev.coefficients)
    else:
        annulus = meas.annulus_model(problem.grid, problem.center, problem.r0, problem.r1,
                                     geo.quad_order(problem, gopt)).annulus

        def run(alpha, prev):
            return geo.solve_projected_gauss_newton(problem, gopt, None if prev is None else prev.coefficients, alpha)
    if options.noise_magnitude is not None:
        noise = an.NoiseEstimate(options.noise_magnitude, "given (--noise-magnitude)")
    else:
        noise = an.magnitude_noise(problem.magnitude, raw, lumen.noise_mask, norm.m0, norm.m1, problem.grid.voxel_area,
                                   annulus, where.rstrip())
    if not noise.value > 0:
        g = geo.solve(problem, gopt)
        return g, _noise_free_choice("alpha", options.alpha_rule, g.alpha, noise)
    if options.alpha_rule == "balance":
        return balance_alpha(problem, gopt, run, noise, annulus.size, options)

    def solve(alpha, prev):
        r = run(alpha, prev)
        return r, r.annulus_residual_norm

    g, choice = an.discrepancy_search(solve, options.alpha_start, noise.value, options.tau_alpha)
    choice.name, choice.noise_method = "alpha", noise.method
    return g, choice


def balance_alpha(problem: geo.GeometryProblem, gopt: geo.GeometryOptions, run, noise: an.NoiseEstimate,
                  n_annulus: int, options: ReconstructionOptions):
    """alpha by the balancing principle on the radius ``R(phi_j)`` (:func:`wss_nlp.analysis.balancing_principle`).

    Notes
    -----
    On the grid ``alpha_start 2^-n`` down to :data:`ALPHA_STOP`, each solve
    warm-started from the previous one. The noise part of ``R_alpha`` is
    linearized, ``e_alpha = D (dc/dm) n_m`` with ``dc/dm`` from the implicit
    function theorem on the KKT system (:func:`wss_nlp.sensitivity.geometry_kkt`,
    CasADi derivatives, active box rows included) and independent voxel noise
    of standard deviation ``sigma_m = delta / sqrt(|V| n_annulus)`` (the
    per-voxel level behind ``delta``, eq. (disc)). Units: R in mm.
    """
    alphas = an.geometric_grid(options.alpha_start, ALPHA_STOP)
    sigma_m = noise.value / np.sqrt(problem.grid.voxel_area * n_annulus)
    design = rad.design_matrix(gopt.box_angles(), gopt.n_fourier)
    n_box = design.shape[0]
    results, radii, maps, res = [], [], [], []
    prev = None
    for alpha in alphas:
        prev = run(alpha, prev)
        lam = prev.box_multipliers if prev.box_multipliers.size == n_box else np.zeros(n_box)
        dc, annulus = sens.geometry_kkt(problem, gopt, prev.coefficients, alpha, prev.gamma, lam)
        results.append(prev)
        radii.append(design @ prev.coefficients)
        maps.append((design @ dc[:, :annulus.size] * sigma_m).ravel())
        res.append(prev.annulus_residual_norm)
    radii, maps = np.array(radii), np.array(maps)
    j, ratio = an.balancing_principle(radii @ radii.T, maps @ maps.T, options.kappa_alpha)
    return results[j], an.ParameterChoice("alpha", "balance", float(alphas[j]), alphas, np.array(res), noise.value,
                                          noise.method, options.kappa_alpha, criterion=ratio)


def choose_beta(vp: vel.VelocityProblem, raw, lumen, venc, options: ReconstructionOptions, where: str,
                viscosity_pa_s: float):
    """beta fixed, from the discrepancy principle (eq. (disc2), with the residual), GCV, the L-curve or balancing.

    The searches use direct Cholesky solves of the (linear) velocity problem;
    the chosen beta is then solved with the configured solver.
    """
    rule = options.beta_rule
    if rule == "fixed":
        return an.ParameterChoice("beta", "fixed", options.velocity.beta)
    if rule == "gcv":
        return gcv_beta(vp, options)
    betas = an.geometric_grid(options.beta_start, BETA_STOP)
    if rule == "lcurve":
        _, res, pen = an.gcv_curve(vp.operator, vp.weights, vp.data, vp.gram, betas)
        i, k = an.lcurve_corner(res, pen)
        return an.ParameterChoice("beta", "lcurve", float(betas[i]), betas, res, criterion=k)
    if options.noise_velocity is not None:
        noise = an.NoiseEstimate(options.noise_velocity, "given (--noise-velocity)",
                                 {"per_voxel": np.full(vp.data.size, options.noise_velocity)})
    else:
        noise = an.velocity_noise(vp.data_image, raw, lumen.noise_mask, vp.voxels.index, vp.weights, venc,
                                  where.rstrip())
    if not noise.value > 0:
        return _noise_free_choice("beta", rule, options.velocity.beta, noise)
    if rule == "balance":
        smat, _ = wss_mod.wss_matrix(vp.basis, vp.disk_map, viscosity_pa_s, options.n_phi)
        i, ratio, res = an.wss_balance(vp.operator, vp.weights, vp.data, vp.gram, betas, smat,
                                       noise.details["per_voxel"], options.kappa_beta)
        return an.ParameterChoice("beta", "balance", float(betas[i]), betas, res, noise.value, noise.method,
                                  options.kappa_beta, criterion=ratio)

    def solve(beta, prev):
        c = vel.solve_cholesky(vp, beta)
        return c, vp.residual_norm(c)

    _, choice = an.discrepancy_search(solve, options.beta_start, noise.value, options.tau_beta, smallest=BETA_STOP)
    choice.name, choice.noise_method = "beta", noise.method
    return choice


def gcv_beta(vp: vel.VelocityProblem, options: ReconstructionOptions) -> an.ParameterChoice:
    """beta minimizing GCV on the grid ``beta_start 2^-n`` down to ``BETA_STOP``."""
    betas = an.geometric_grid(options.beta_start, BETA_STOP)
    gcv, res, _ = an.gcv_curve(vp.operator, vp.weights, vp.data, vp.gram, betas)
    i = int(np.argmin(gcv))
    return an.ParameterChoice("beta", "gcv", float(betas[i]), betas, res, criterion=gcv)


class Results(list):
    """The per-slice results of :func:`reconstruct`, with ``stack`` (a :class:`wss_nlp.stack.StackInfo` or None)."""

    stack = None


def stack_applies(acq: Acquisition, options: ReconstructionOptions) -> bool:
    """Whether a stack is reconstructed with z-regularization (else slice by slice)."""
    ell = options.stack.z_smoothing_mm
    if acq.nz == 1 or ell == 0:
        return False
    supported = stk.supports(options)
    if ell is not None and not supported:
        raise InputError(f"{acq.source}: z-regularization (--z-smoothing {ell:g}) supports the decoupled method "
                         "with fixed alpha and beta; pass --z-smoothing 0 for independent slices")
    return supported


def reconstruct(acq: Acquisition, options: ReconstructionOptions | None = None, progress=None, log=None) -> Results:
    """Reconstruct every slice of an acquisition.

    A stack (``nz > 1``) is reconstructed with z-regularization
    (:mod:`wss_nlp.stack`) when the options allow it (decoupled method, fixed
    alpha and beta, ``options.stack.z_smoothing_mm != 0``), else slice by
    slice. In a stack, a slice that cannot be reconstructed (NaN or Inf, no
    vessel, solver failure) becomes a :class:`wss_nlp.io.FailedSlice` and
    the others are still solved; a single slice raises instead.

    Returns :class:`SliceResult` objects, or :class:`wss_nlp.baselines.BaselineResult`
    for the classical methods (``options.method`` "oyre" or "stalder").

    Parameters
    ----------
    progress : callable or None
        Called as ``progress(done, total, slice_result)`` after each slice.
    log : callable or None
        Called with a message as a z-regularized stack solve proceeds.
    """
    options = options or ReconstructionOptions()
    acq.validate()
    mu = resolve_viscosity(acq, options)
    acq, screens = plaus.screen(acq, options.screen)
    out = Results()
    if stack_applies(acq, options):
        results, info = stk.reconstruct_stack(acq, options, options.stack, progress, log)
        out.extend(r if r is not None else FailedSlice(k, info.failed[k], options.n_phi, options.geometry.n_fourier)
                   for k, r in enumerate(results))
        out.stack = info
        return _with_screens(out, screens)
    velocity = acq.velocity_images()
    bad = set(acq.nonfinite_slices())
    for iz in range(acq.nz):
        try:
            if iz in bad:
                raise InputError(f"{acq.source} slice {iz}: the images contain NaN or Inf")
            if options.method in bl.METHODS:
                res = bl.reconstruct_slice(acq.magnitude[iz], velocity[iz], acq.grid, mu, options.method,
                                           options.baseline, options.n_phi, acq.source, iz, options.screen.vessel)
            else:
                res = reconstruct_slice(acq.magnitude[iz], velocity[iz], acq.grid, mu, options, acq.source, iz,
                                        acq.venc_m_s)
        except WssNlpError as exc:
            if acq.nz == 1:
                raise
            res = FailedSlice(iz, str(exc), options.n_phi, options.geometry.n_fourier)
        _with_screens([res], screens)
        out.append(res)
        if progress is not None:
            progress(iz + 1, acq.nz, res)
    if all(isinstance(r, FailedSlice) for r in out):
        raise WssNlpError(f"{acq.source}: no slice could be reconstructed: " + "; ".join(r.reason for r in out))
    return out


def _with_screens(results, screens: dict):
    """Attach what the plausibility screen found to each slice's notes and record."""
    for r in results:
        found = screens.get(r.index)
        if found is not None and not isinstance(r, FailedSlice):
            r.notes.extend(n for n in found.notes if n not in r.notes)
            r.screen = found.record
    return results
