"""The near-wall model of a slice from the data: the plain basis, or a layer family and scale, by BIC.

:func:`layer_model` applies ``--near-wall`` to a velocity problem: a given scale, or :func:`choose_layer`, which
scores the plain basis and every candidate family (:mod:`wss_nlp.models.families`) with :class:`PlainCriterion`
at each one's best beta; a family's scale is where its fitted layer obeys the law of the wall
(:func:`_wall_law_scale`, families with ``scale_rule = "consistent"``) or the scale that minimizes the criterion
(:func:`_bic_scale`).
"""

from __future__ import annotations

import functools

import numpy as np

from ..core import radius as rad
from ..core.tikhonov import BorderedTikhonov
from ..models import near_wall as nw
from ..models import velocity as vel
from ..models import wss as wss_mod
from . import noise as nl

#: Layer scales l / R of the coarse search (octaves); the best is refined by golden-section search.
LAYER_RATIOS = 2.0 ** -np.arange(4.0, 13.0)
#: betas over which each candidate's criterion is minimized (half decades).
CRITERION_BETAS = 10.0 ** -np.arange(3.0, 13.5, 0.5)
GOLDEN_STEPS = 8


class PlainCriterion:
    r"""``min_beta chi^2 + ln(n) dof`` of the plain problem with optional extra (layer) columns.

    Notes
    -----
    :math:`\chi^2(\beta) = \sum_i (M_i \theta_\beta - u_i)^2/\sigma_i^2` with the
    per-voxel noise :math:`\sigma_i`, and
    :math:`\mathrm{dof} = \operatorname{tr}(H_\beta^{-1} K)` the effective
    number of parameters: Schwarz's criterion with the smoother's trace in
    place of the parameter count (Hastie & Tibshirani 1990, Sec. 3.5).
    :math:`\chi^2` is evaluated as the quadratic form
    :math:`\theta^\top M^\top \Sigma^{-1} M \theta - 2 \theta^\top M^\top \Sigma^{-1} u + u^\top \Sigma^{-1} u`
    with the plain block formed once (relative rounding about 1e-13 of
    :math:`u^\top\Sigma^{-1}u`, far below the BIC differences that decide); extra
    columns go through the plain problem's pencils
    (:class:`wss_nlp.core.tikhonov.BorderedTikhonov`).
    """

    def __init__(self, plain: vel.VelocityProblem, sigma: np.ndarray):
        self.plain, self.inv_var = plain, 1.0 / np.asarray(sigma, float) ** 2
        t = plain.operator
        root = t * np.sqrt(self.inv_var)[:, None]
        self.tst = root.T @ root  # T^T Sigma^-1 T by a symmetric rank-k update (syrk)
        self.tsu = t.T @ (self.inv_var * plain.data)
        self.usu = float(plain.data @ (self.inv_var * plain.data))
        # correlated (k-space) noise: chi^2 and the sample count of nu n effectively independent voxels
        self.nu = 1.0 if plain.noise_correlation is None else plain.noise_correlation.effective_fraction
        self.log_n = float(np.log(self.nu * plain.data.size))

    def __call__(self, extra: np.ndarray | None = None) -> tuple[float, float, np.ndarray]:
        """The criterion, the minimizing beta and its coefficients (plain ones first, then the extra columns')."""
        return self._minimum(*self.curve(extra))

    def many(self, extras: list) -> list:
        """``[self(extra) for extra in extras]``, with one pass over ``T`` for all of them (:meth:`curves`)."""
        return [self._minimum(*curve) for curve in self.curves(extras)]

    def _minimum(self, chi2, dof, coef) -> tuple[float, float, np.ndarray]:
        crit = self.nu * chi2 + self.log_n * dof
        i = int(np.argmin(crit))
        return float(crit[i]), float(CRITERION_BETAS[i]), coef[i]

    def curve(self, extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``chi^2``, dof and coefficients on :data:`CRITERION_BETAS` (a criterion over several problems, the
        frames of a cine slice in :mod:`wss_nlp.models.womersley`, weighs each with the joint ``ln n``)."""
        if extra is None:
            tk = self.plain.tikhonov
            coef, dof = tk.coefficients(CRITERION_BETAS), tk.traces(CRITERION_BETAS)
            return np.sum((coef @ self.tst) * coef, axis=1) - 2 * coef @ self.tsu + self.usu, dof, coef
        return self.curves([extra])[0]

    def curves(self, extras: list) -> list:
        r""":meth:`curve` for each of several sets of extra columns.

        The products with ``T`` (``n x m``, the largest array) of every set and of both weightings of its
        columns, the misfit's ``W`` and the criterion's :math:`\Sigma^{-1}`, are one matrix product: a
        product with a few columns streams ``T`` from memory for little arithmetic.
        """
        tk = self.plain.tikhonov
        weighted = [(tk.w[:, None] * extra, self.inv_var[:, None] * extra) for extra in extras]
        both = self.plain.operator.T @ np.hstack([block for pair in weighted for block in pair])
        out, start = [], 0
        for extra, (_, se) in zip(extras, weighted):
            k = extra.shape[1]
            border, cross = both[:, start : start + k], both[:, start + k : start + 2 * k]
            start += 2 * k
            coef, dof = BorderedTikhonov(tk, extra, border=border).coefficients_and_traces(CRITERION_BETAS)
            c, a = coef[:, :-k], coef[:, -k:]
            chi2 = (
                np.sum((c @ self.tst + 2 * a @ cross.T) * c, axis=1)
                + np.sum((a @ (extra.T @ se)) * a, axis=1)
                - 2 * (c @ self.tsu + a @ (se.T @ self.plain.data))
                + self.usu
            )
            out.append((chi2, dof, coef))
        return out


def _golden(score, lo: float, hi: float, steps: int = GOLDEN_STEPS) -> float:
    """Minimizer of ``score`` on ``[lo, hi]`` by golden-section search (``steps`` shrinkings, 0.618 each)."""
    g = (np.sqrt(5) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = score(a), score(b)
    for _ in range(steps):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = score(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = score(b)
    return a if fa <= fb else b


def choose_layer(
    vp: vel.VelocityProblem,
    sigma: np.ndarray,
    mode: str,
    vopt: vel.VelocityOptions,
    nu_m2_s: float | None = None,
    around: nw.NearWallChoice | None = None,
    reynolds: float | None = None,
) -> tuple[vel.VelocityProblem, nw.NearWallChoice]:
    r"""The near-wall model of one slice: the plain basis, or a layer family and scale, by BIC.

    With the bulk Reynolds number ``reynolds`` the families are the flow
    regime's (:func:`wss_nlp.models.near_wall.regime_families`: the laws of the wall
    for turbulent flow, the exponential layer for laminar flow) and only
    plain-or-layer is left to the BIC, which cannot tell the laminar and turbulent families apart
    (both fit thin layers about equally well; measured in
    scripts/results/near_wall.md). Without it all families compete. In
    ``"auto"`` a family that another candidate supersedes
    (:attr:`wss_nlp.models.families.base.WallFamily.supersedes`: ``wall_law``
    by ``low_re``) is not tried: at h = 1.5 mm on the Re_tau 180 pipe the two
    differ in BIC by 0.5-2, within the ambiguity margin, and by 3 % in WSS.

    Candidates: the plain basis; ``exponential`` at the scale minimizing
    :class:`PlainCriterion` (octaves :data:`LAYER_RATIOS` x mean R, refined by
    golden-section search in log l); ``wall_law`` and ``low_re`` at the scale where the
    fitted layer obeys the law of the wall, :math:`u_\tau \ell = \nu`
    (:func:`_wall_law_scale`; by BIC like the exponential when ``nu_m2_s``
    is None), ``low_re`` with the profile of :math:`Re_\tau = R/\ell` at each
    scale ``l`` (its member, :func:`wss_nlp.models.families.at_reynolds`). Each is scored by
    :class:`PlainCriterion` at its best beta; the smallest
    score wins. ``mode`` restricts the candidates (``"auto"``: all; a family
    name: that family, plain excluded). ``around`` (an earlier choice on a
    nearby geometry, e.g. before the dephasing pass) keeps its family and
    searches half an octave either side of its scale (the law of the wall:
    from its root outwards). A self-consistent scale comes with the viscosity
    the data's own best scale implies (:func:`_data_viscosity`, in the record).
    Returns the chosen problem (the plain one or its enrichment) and the record
    of the choice.
    """
    big_r = float(vp.disk_map.coefficients[0])
    quad = nw.LayerQuadrature(vp)
    criterion = PlainCriterion(vp, sigma)
    tried, best, notes = [], {}, {}
    plain, plain_beta, _ = criterion()
    if mode == "auto":
        best["plain"] = (plain, float("nan"), vp, plain_beta)
        tried.append(("plain", float("nan"), plain))
    stretch = nw.stretch(vp.disk_map)

    scored: dict = {}  # the searches revisit their final scale; the cell means are the expensive part

    def prefetch(family, log_ratios):
        """Score the scales not scored yet together (one pass over the operator for all their columns)."""
        todo = list(dict.fromkeys(float(x) for x in log_ratios if (family, float(x)) not in scored))
        # a Reynolds-number-dependent family's shape at each scale is its member at Re_tau = R/l = 2^-x
        bases = [nw.EnrichedBasis(vp.basis, nw.families.at_reynolds(family, 2.0**-x), 2.0**x * big_r / stretch)
                 for x in todo]  # fmt: skip
        columns = [quad.columns(basis) for basis in bases]
        for x, basis, cols, (crit, beta, coef) in zip(todo, bases, columns, criterion.many(columns)):
            tried.append((family, 2.0**x, crit))
            scored[family, x] = (crit, basis, beta, coef, cols)

    def score(family, log_ratio):
        key = (family, float(log_ratio))
        if key not in scored:
            prefetch(family, [log_ratio])
        return scored[key][:4]

    previous, chosen_log = None, {}
    voxel_mm = max(vp.cell_mm or (np.nan,)) * quad.order
    fitted: dict = {}  # family -> its scale minimizes the criterion (rather than solving u_tau l = nu)
    implied: dict = {}  # family -> (nu the data imply / the stated nu, log2 l/R of the data's best scale)
    rivals: dict = {}  # family -> other roots of u_tau l = nu whose criterion is within the ambiguity margin
    if around is not None and around.model in nw.FAMILIES:
        families: tuple = (around.model,)
        previous = float(np.log2(around.scale_mm / big_r))
        brackets = {around.model: (previous - 0.5, previous + 0.5)}
    else:
        families = (mode,) if mode != "auto" else nw.FAMILIES if reynolds is None else nw.regime_families(reynolds)
        if mode == "auto":  # a family calibrated to replace another is tried in its place
            families = tuple(f for f in families if not any(f in nw.families.get(g).supersedes for g in families))
        logs = np.log2(LAYER_RATIOS)
        brackets = {f: (logs[-1], logs[0]) for f in families}
    for family in families:
        lo, hi = brackets[family]
        family_score = functools.partial(score, family)
        if nw.families.get(family).scale_rule == "consistent" and nu_m2_s is not None:
            predicted = None if reynolds is None or reynolds <= 0 else blasius_scale(reynolds)
            x, how, rival_roots = _wall_law_scale(
                family_score, lo, hi, big_r, nu_m2_s, vp.basis.size, predicted, previous,
                prefetch=functools.partial(prefetch, family),
            )  # fmt: skip
            fitted[family] = how == NO_ROOT  # no root: the BIC's scale
        else:
            x, how, fitted[family], rival_roots = _bic_scale(family_score, lo, hi), "the BIC's", True, []
        notes[family] = how + (", + ln(n) for the fitted scale" if fitted[family] else "")
        if nw.families.get(family).reynolds_dependent:
            notes[family] += f"; profile of Re_tau = R/l = {2.0**-x:.0f}"
        crit, basis, beta, _ = score(family, x)
        rivals[family] = [r for c, r in rival_roots if c <= crit + nw.AMBIGUOUS_MARGIN]
        # the data's own scale, where the voxels may resolve the buffer layer (the root's h+ is within 1.5x of it
        # for nu off by up to 30 %)
        if not fitted[family] and nu_m2_s is not None and voxel_mm <= 1.5 * nw.VISCOSITY_RESOLVED * 2.0**x * big_r:
            implied[family] = _data_viscosity(
                family_score, functools.partial(prefetch, family), float(x), big_r, nu_m2_s, vp.basis.size
            )
        if fitted[family]:
            # a scale fitted to the data is one more parameter, which tr(H^-1 K) does not count
            crit += criterion.log_n
        problem = vp.with_layer(basis, scored[family, float(x)][4], vopt.laplacian_power)
        best[family] = (crit, 2.0**x * big_r, problem, beta)
        chosen_log[family] = float(x)
    # the paper's model is the null hypothesis: a layer must be preferred by "very strong" evidence
    penalty = {m: (nw.LAYER_EVIDENCE if m != "plain" else 0.0) for m in best}
    order = sorted(best, key=lambda m: best[m][0] + penalty[m])
    chosen = order[0]
    margin = best[order[1]][0] + penalty[order[1]] - best[chosen][0] - penalty[chosen] if len(order) > 1 else np.inf
    unresolved = float("nan")
    # a saturating layer that is thinner than the voxels resolve, or that needs no regularization at all, is a
    # velocity jump at the wall; the wall law is exempt: its scale is fixed by u_tau l = nu, not by the data's
    # shape, and on turbulent data its best beta may well be the smallest (the soak's aliased Re_tau 998 runs)
    saturating = chosen != "plain" and nw.families.get(chosen).saturating
    at_floor = saturating and best[chosen][3] <= CRITERION_BETAS[-1] * (1 + 1e-9)
    thin = saturating and best[chosen][1] < voxel_mm / nw.UNRESOLVED_FRACTION
    if mode == "auto" and (thin or at_floor):
        # a jump at the wall, not a layer: no WSS follows from it; keep the paper's model and flag the slice
        unresolved, chosen = best[chosen][1], "plain"
        margin = float("nan")
    interval, spread = (float("nan"), float("nan")), float("nan")
    if fitted.get(chosen, False):
        interval, spread = _scale_spread(
            functools.partial(score, chosen), chosen_log[chosen], brackets[chosen], vp.disk_map
        )
    elif rivals.get(chosen):  # several self-consistent scales the data hardly tell apart
        interval, spread = _scales_spread(functools.partial(score, chosen), [chosen_log[chosen], *rivals[chosen]],
                                          vp.disk_map)  # fmt: skip
    elif around is not None and around.consistent and chosen == around.model and np.isfinite(around.scale_wss_spread):
        # a dephasing pass follows the chosen root only (a few hundredths of an octave away): keep the first
        # pass's range and spread of the rival roots
        interval, spread = around.scale_interval, around.scale_wss_spread
    how = "BIC = chi^2 + ln(n) tr(H^-1 K), each model at its best beta; "
    how += f"a layer needs a BIC {nw.LAYER_EVIDENCE:g} below plain"
    if reynolds is not None and mode == "auto" and around is None:
        how += f"; family by the flow regime (bulk Re {reynolds:.0f})"
    choice = nw.NearWallChoice(
        model=chosen,
        scale_mm=best[chosen][1],
        scale_ratio=best[chosen][1] / big_r,
        criterion=how + (f"; scale: {notes[chosen]}" if chosen in notes else ""),
        values={m: v[0] for m, v in best.items()},
        margin=float(margin),
        tried=tried,
        ambiguous=bool(margin < nw.AMBIGUOUS_MARGIN),
        quad_order=quad.order,
        unresolved_mm=unresolved,
        beta=best[chosen][3],
        scale_interval=interval,
        scale_wss_spread=spread,
        consistent=chosen != "plain"
        and nw.families.get(chosen).scale_rule == "consistent"
        and not fitted.get(chosen, True),
    )
    if chosen in implied:
        choice.viscosity_ratio = implied[chosen][0]
        choice.voxel_plus = voxel_mm / (2.0 ** implied[chosen][1] * big_r)
    elif choice.consistent:  # too coarse to look for the data's own scale: the voxel over the chosen one
        choice.voxel_plus = voxel_mm / best[chosen][1]
    return best[chosen][2], choice


#: Offsets (octaves) of the probes about a self-consistent scale that locate the data's own best scale
#: (:func:`_data_viscosity`; a 30 % error in nu moves the root by about a quarter octave), and of the second
#: probes about the best of them.
VISCOSITY_PROBES = (-0.5, -0.25, -0.125, 0.0, 0.125, 0.25, 0.5)
VISCOSITY_REFINE = 1.0 / 32


def _data_viscosity(score, prefetch, x_root: float, big_r: float, nu_m2_s: float, n_base: int) -> tuple[float, float]:
    r"""The kinematic viscosity the data imply, over the stated one, and the scale at which they imply it.

    Notes
    -----
    The criterion is scored at the self-consistent scale and at :data:`VISCOSITY_PROBES` octaves about it,
    then at :data:`VISCOSITY_REFINE` either side of the best of those (two passes over the operator); a
    parabola in :math:`\log_2\ell` through the best point and its nearest neighbours gives the data's best
    scale :math:`\ell^*` (at most half an octave away). There the layer's amplitude :math:`u_\tau(\ell^*)` and
    the scale imply :math:`\nu^* = u_\tau(\ell^*)\,\ell^*`: with the consistency
    :math:`g(\ell) = u_\tau(\ell)\ell/\nu - 1` (a parabola through the same points) the ratio is
    :math:`\nu^*/\nu = 1 + g(\ell^*)`. Only where the voxels resolve the buffer layer does the criterion fix
    :math:`\ell^*` (:data:`wss_nlp.models.near_wall.VISCOSITY_RESOLVED`); elsewhere it trades against the
    log-law intercept. Returns ``(nu*/nu, log2 l*/R)``.
    """
    values: dict = {}

    def at(xs):
        prefetch(xs)
        for x in xs:
            if float(x) not in values:
                c, basis, _, coef = score(float(x))
                u_tau = coef[n_base] * basis.column_scale
                values[float(x)] = (c, u_tau * 2.0**x * big_r / 1000.0 / nu_m2_s - 1.0)

    at(x_root + np.array(VISCOSITY_PROBES))
    best = min(values, key=lambda x: values[x][0])
    lo, hi = x_root + VISCOSITY_PROBES[0], x_root + VISCOSITY_PROBES[-1]
    at(np.clip(best + np.array([-VISCOSITY_REFINE, VISCOSITY_REFINE]), lo, hi))
    xs = np.array(sorted(values))
    k = int(np.clip(np.searchsorted(xs, min(values, key=lambda x: values[x][0])), 1, xs.size - 2))
    near = xs[k - 1 : k + 2]
    crit, g = (np.array([values[float(x)][i] for x in near]) for i in (0, 1))
    a, b, _ = np.polyfit(near - near[1], crit, 2)
    dx = -b / (2 * a) if a > 0 else 0.0
    x_star = float(np.clip(near[1] + dx, lo, hi))
    return float(1.0 + np.polyval(np.polyfit(near - near[1], g, 2), x_star - near[1])), x_star


def _scale_spread(score, x_best: float, bracket: tuple, disk_map) -> tuple[tuple[float, float], float]:
    """The scales the data hardly tell from the chosen one, and how far apart their mean WSS lie.

    Returns ``((l_lo/R, l_hi/R), spread)``: the interval of ``log2(l/R)`` about ``x_best`` on which the
    criterion ``score(x)[0]`` stays within :data:`wss_nlp.models.near_wall.AMBIGUOUS_MARGIN` of its value at
    ``x_best`` (each end widened from :data:`SPREAD_RESOLUTION` octaves in doubling steps, then bisected to a
    quarter of its distance from ``x_best``, inside ``bracket``), and
    the range of the mean wall shear stress of the fits at the two ends and at ``x_best`` (each at its own
    best beta) over the chosen fit's. For a correctly specified Gaussian likelihood in ``log l`` the interval
    would span about +-1.4 standard deviations (a criterion rise of 2); on the entrance flow the spread came
    out near one Monte-Carlo standard deviation of the mean WSS instead (``scripts/results/scale_spread.md``).
    """
    limit = score(x_best)[0] + nw.AMBIGUOUS_MARGIN
    ends = []
    for side, stop in ((-1.0, bracket[0]), (1.0, bracket[1])):
        inner, step = x_best, SPREAD_RESOLUTION
        outer = inner
        while side * (stop - outer) > 0:  # widen until the criterion leaves the margin or the bracket ends
            outer = float(np.clip(inner + side * step, min(bracket), max(bracket)))
            if score(outer)[0] > limit:
                break
            inner, step = outer, 2 * step
        else:
            ends.append(inner)
            continue
        # to a quarter of the half-width found (a sharp minimum gets a fine end, a flat one a coarse one)
        while abs(outer - inner) > max(SPREAD_RESOLUTION, abs(outer - x_best) / 4):
            mid = (inner + outer) / 2
            inner, outer = (mid, outer) if score(mid)[0] <= limit else (inner, mid)
        ends.append(inner)
    return _scales_spread(score, [x_best, ends[0], ends[1]], disk_map)


def _scales_spread(score, xs: list, disk_map) -> tuple[tuple[float, float], float]:
    """``((min l/R, max l/R), spread)`` over the scales ``log2(l/R) = xs`` (the chosen one first): the range of
    their fits' mean WSS (each at its own best beta) over the chosen fit's."""
    fits = [score(x) for x in xs]  # (criterion, basis, beta, coefficients)
    means = [_mean_wall_slope(basis, coef, disk_map) for _, basis, _, coef in fits]
    return (float(2.0 ** min(xs)), float(2.0 ** max(xs))), float((max(means) - min(means)) / abs(means[0]))


#: First step and finest resolution (octaves, 0.14 % of l) of the ends of the scale interval of :func:`_scale_spread`.
SPREAD_RESOLUTION = 1.0 / 512


def _mean_wall_slope(basis, coefficients, disk_map, n_phi: int = 180) -> float:
    """Arc-length mean of ``-dU/dn`` on the wall (the mean WSS over the viscosity) of a fit."""
    slope, _ = wss_mod.wss_matrix(basis, disk_map, 1.0, n_phi)
    phi, c = rad.uniform_angles(n_phi), disk_map.coefficients
    return rad.arc_length_mean(slope @ np.asarray(coefficients, float), rad.evaluate(c, phi), rad.evaluate(c, phi, 1))


def _bic_scale(score, lo: float, hi: float) -> float:
    """log2(l/R) minimizing the BIC on ``[lo, hi]``: octave scan, then golden-section search around the best."""
    grid = np.arange(hi, lo - 1e-9, -1.0) if hi - lo > 1.5 else np.array([(lo + hi) / 2])
    crit = [score(float(x))[0] for x in grid]
    k = int(np.argmin(crit))
    half = 1.0 if grid.size > 1 else (hi - lo) / 2
    x = _golden(lambda v: score(v)[0], grid[k] - half, grid[k] + half)
    return x if score(x)[0] <= crit[k] else float(grid[k])


def blasius_scale(reynolds: float) -> float:
    r"""log2 of the viscous length over the radius that Blasius's friction law predicts for a smooth pipe.

    Notes
    -----
    :math:`f = 0.316\,Re^{-1/4}` (Darcy; Blasius 1913, smooth pipes up to
    about Re = 1e5) and :math:`u_\tau = U\sqrt{f/8}` give
    :math:`Re_\tau = u_\tau R/\nu = 0.0994\,Re^{7/8}` and
    :math:`\ell/R = 1/Re_\tau`. Only a starting window for the scan of
    :func:`_wall_law_scale`, never the answer.
    """
    return float(-np.log2(0.0994 * reynolds**0.875))


#: What the record says when no scale satisfies the law of the wall's consistency (the BIC's scale is taken).
NO_ROOT = "no scale satisfies the wall law's consistency; the BIC's scale"
#: Resolution (octaves of l) to which a root of the wall-law consistency is located.
ROOT_RESOLUTION = 1.0 / 128
#: Half-widths (octaves) of the widening probes around a previous root (a dephasing pass moves it by ~1e-3).
LOCAL_STEPS = (ROOT_RESOLUTION / 2, 1.0 / 32, 1.0 / 4)


def _wall_law_scale(
    score,
    lo: float,
    hi: float,
    big_r: float,
    nu_m2_s: float,
    n_base: int,
    predicted: float | None = None,
    previous: float | None = None,
    prefetch=None,
) -> tuple[float, str, list]:
    r"""log2(l/R) at which the fitted wall-law layer is self-consistent, and how it was found.

    Notes
    -----
    Near the wall :math:`u = u_\tau U^+(y u_\tau/\nu)`, so the layer's
    amplitude and its scale are one parameter: with the m = 0 column
    :math:`a f(d/\ell)` fitted at scale :math:`\ell`, the law holds where
    :math:`g(\ell) = a \ell / \nu - 1 = 0` (``nu`` from the viscosity and
    the density). ``g`` is scanned on quarter octaves, each sign change is
    refined to :data:`ROOT_RESOLUTION` octaves by regula falsi
    (:func:`_refine_root`); of several roots the one with the smallest BIC
    is taken (spurious roots sit where the layer's amplitude changes sign,
    far from the data's optimum: 243-493 above the chosen one on the
    Re_tau 180 phantoms, none at Re_tau 549 and 998;
    ``scripts/results/wall_law_roots.md``); :func:`choose_layer` records
    the WSS spread of rivals within the ambiguity margin. With a
    ``predicted`` log2(l/R) (:func:`blasius_scale`) the scan starts two
    octaves either side of it and widens to the whole range only if that
    window holds no root. A ``previous`` root (the same slice before a
    dephasing pass moved its wall a little) is followed locally: probes
    either side of it at widening distances (:data:`LOCAL_STEPS`), and the
    scan only if none brackets a root. Without a root the BIC's scale is
    used and the record says so. ``prefetch`` (optional) is given the
    scales of each scan and of each pair of probes before they are
    scored one by one (:func:`choose_layer` scores them together). Returns
    ``(log2 l/R, how, rivals)`` with ``rivals`` the other roots found,
    ``(criterion, log2 l/R)``, best first.
    """
    memo: dict = {}

    def consistency(x):
        x = float(x)
        if x not in memo:
            crit, basis, _, c = score(x)
            u_tau = c[n_base] * basis.column_scale  # m/s: the m = 0 layer column is u_tau f(d/l)
            memo[x] = (u_tau * 2.0**x * big_r / 1000.0 / nu_m2_s - 1.0, crit)
        return memo[x]

    def roots_on(xs):
        if prefetch is not None:  # the scan's scales at once
            prefetch(xs)
        vals = [consistency(x) for x in xs]
        found = []
        for i in range(xs.size - 1):
            if np.sign(vals[i][0]) != np.sign(vals[i + 1][0]):
                x = _refine_root(lambda v: consistency(v)[0], float(xs[i]), float(xs[i + 1]))
                found.append((consistency(x)[1], x))
        return found

    roots: list = []
    for step in () if previous is None else LOCAL_STEPS:
        roots = roots_on(previous + np.array([-step, step]))
        if roots:
            break
    xs = np.arange(hi, lo - 1e-9, -0.25)
    window = xs if predicted is None else xs[np.abs(xs - predicted) <= 2.0]
    if not roots:
        roots = roots_on(window) if window.size > 1 else []
    if not roots and window.size < xs.size:
        roots = roots_on(xs)
    if not roots:
        return _bic_scale(score, lo, hi), NO_ROOT, []
    crit, x = min(roots)
    rivals = sorted(r for r in roots if r[1] != x)
    how = f"law of the wall {nw.CONSISTENT} ({len(roots)} root(s), the one with the smallest BIC"
    how += f"; the next {rivals[0][0] - crit:.3g} above)" if rivals else ")"
    return x, how, rivals


def _refine_root(g, a: float, b: float, resolution: float = ROOT_RESOLUTION) -> float:
    """A root of ``g`` in ``[a, b]`` (``g(a)``, ``g(b)`` of opposite signs) to about ``resolution``.

    The Anderson-Bjoerck variant of regula falsi (a retained end's value is
    scaled down, so both ends move; Galdino 2011 compares the variants),
    stopped when two successive iterates agree to half the resolution or
    the bracket is within it: two or three evaluations where bisection to
    1/128 octave from a quarter-octave bracket takes five and one more at
    the midpoint. Returns the last point evaluated (its criterion is
    known), a root of ``g`` to within the resolution.
    """
    a, b = min(a, b), max(a, b)
    ga, gb = g(a), g(b)
    side, last = 0, None
    for _ in range(32):
        if ga == gb:
            break
        x = float(np.clip(a - ga * (b - a) / (gb - ga), a + resolution / 8, b - resolution / 8))
        gx = g(x)
        if np.sign(gx) == np.sign(ga):
            scale = 1 - gx / ga
            gb = gb * (scale if scale > 0 else 0.5) if side == -1 else gb
            a, ga, side = x, gx, -1
        else:
            scale = 1 - gx / gb
            ga = ga * (scale if scale > 0 else 0.5) if side == 1 else ga
            b, gb, side = x, gx, 1
        if (last is not None and abs(x - last) <= resolution / 2) or b - a <= resolution:
            return x
        last = x
    return (a + b) / 2 if last is None else last


def layer_model(
    vp: vel.VelocityProblem,
    raw,
    lumen,
    venc,
    vopt: vel.VelocityOptions,
    noise_velocity: float | None,
    where: str,
    viscosity_pa_s: float | None = None,
    density: tuple[float, str] | None = None,
    around: nw.NearWallChoice | None = None,
) -> tuple[vel.VelocityProblem, nw.NearWallChoice]:
    """The velocity problem with the near-wall model ``vopt.near_wall`` asks for, and the record.

    A given ``layer_scale_mm`` fixes the layer (no choice); otherwise the
    model and scale come from :func:`choose_layer` (``around``: refine an
    earlier choice on a corrected geometry; ``nu = viscosity / density``
    for the law of the wall), which needs the velocity noise (``noise_velocity`` when given): without it
    (noise-free data) the plain basis is kept and the record says why.
    """
    if vopt.layer_scale_mm is not None:
        problem = nw.enrich(vp, vopt.near_wall, vopt.layer_scale_mm, vopt.laplacian_power)
        big_r = float(vp.disk_map.coefficients[0])
        return problem, nw.NearWallChoice(
            vopt.near_wall, vopt.layer_scale_mm, vopt.layer_scale_mm / big_r, "given (--layer-scale)"
        )
    noise = nl.given_or_velocity_noise(vp, raw, lumen, venc, noise_velocity, where)
    if not noise.value > 0:
        return vp, nw.NearWallChoice("plain", criterion=f"no velocity noise estimate ({noise.method}): plain basis")
    nu = None if viscosity_pa_s is None or density is None else viscosity_pa_s / density[0]
    reynolds = None if nu is None else nw.bulk_reynolds(vp, nu)
    problem, choice = choose_layer(vp, noise.details["per_voxel"], vopt.near_wall, vopt, nu, around, reynolds)
    if density is not None:
        choice.density_kg_m3, choice.density_source = density
    choice.reynolds = float("nan") if reynolds is None else reynolds
    choice.warning = nw.viscosity_note(choice, viscosity_pa_s)
    return problem, choice
