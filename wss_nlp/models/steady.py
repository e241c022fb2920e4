r"""Whether a slice's velocity data can come from steady flow: what a single frame of pulsatile flow shows.

A slice reconstructed on its own is read as steady flow: its near-wall model is a steady family
(:mod:`wss_nlp.models.near_wall`: the plain basis for fully developed laminar flow, ``exponential`` for
developing laminar layers, ``wall_law`` and ``low_re`` for turbulent mean flow), chosen by the bulk Reynolds
number. A frame of pulsatile flow (Womersley) is none of these: its Stokes layer, thinner than a voxel, leads
the core in phase, so the profile overshoots near the wall, reverses there while the core still flows, or
bends the wrong way (an inflection); and where it looks like a steady profile its layer does not match the
core the way a steady flow's must. The WSS of such a slice misses by far more than its band (issue 40:
18-37 % of the peak at h = 1-1.5 mm). :func:`check` tests the properties every steady family has:

* **no reversal**: steady flow in a straight vessel runs one way across the lumen;
* **monotone**: the velocity does not rise from the axis towards the wall (no near-wall overshoot);
* **concave** away from the wall: every steady profile :math:`u(y)` (wall distance ``y``) is concave, since
  the shear stress :math:`\tau(r) = -(r/2)\,\mathrm{d}p/\mathrm{d}x` (plus, in turbulence, a Reynolds stress
  that only flattens the core) falls linearly to the axis: the laminar parabola, the law of the wall, a
  developing layer :math:`1 - e^{-y/\ell}` and Langhaar's entrance profile :math:`I_0(\epsilon) - I_0(\epsilon
  r/R)` all are; voxel means of a concave function are concave, ring means too. Bins reaching into the
  partial-volume voxels (the velocity drops to zero across the wall there) are left out of this test;
* **turbulent regime** (bulk Reynolds number at least :data:`~wss_nlp.models.near_wall.RE_TURBULENT`): the law
  of the wall's self-consistent layer (``u_tau l = nu``) implies the stated kinematic viscosity within a factor
  :data:`VISCOSITY_FACTOR` (the near-wall choice's ``viscosity_ratio``); where the data chose no turbulent layer
  over the plain basis, the flow may still be laminar (transitional Reynolds numbers), but then fully developed:
  its core falls like the parabola's;
* **peakedness**: no steady flow is more peaked than fully developed laminar flow (the parabola in the
  reference disk): the core's fall from the axis to :data:`CORE_RADIUS` may exceed the parabola's by
  :data:`CORE_MARGIN` and the noise only;
* **laminar regime**: a wall layer of scale ``l`` belongs to a developing flow whose core is flat: Langhaar's
  profile (Langhaar 1942, J. Appl. Mech. 9, A55-A58) with the layer :math:`\ell = R/\epsilon` falls from the
  axis to :math:`0.7R` by :math:`(I_0(0.7\epsilon) - 1)/(I_0(\epsilon) - 1)` (point values; :func:`ring_drop`
  compares ring means with ring means); a core that falls by more than
  that at a layer :data:`LAYER_SLACK` times thicker (plus :data:`CORE_MARGIN` and the noise) is a curved core
  under a thin layer, which no steady laminar flow has.

The first three are tests of shape constraints on ring means of the voxel data (rings of equal width in
:math:`\rho = r/R(\phi)`, from the reconstructed wall), each a chi-square gain of the unconstrained ring means
over the best constrained ones; a gain above :data:`SHAPE_CHI2` (a 5-sigma event for
one constraint) contradicts the property. The thresholds were set on development seeds 0-1 of the Womersley
frames and seeds 0-4 of the steady phantoms; ``scripts/unsteady_frames.py`` reports other seeds.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from .._lazy import scipy
from ..core import radius as rad

#: A chi-square gain of the free ring means over the constrained ones above this contradicts the constraint
#: (5 standard deviations where one constraint is active; noise alone exceeds it with probability 1.4e-4 even
#: with five active, as on a nearly flat core; the steady phantoms reached 14.3, scripts/results/unsteady_frames.md).
SHAPE_CHI2 = 25.0

#: A ring mean this many of its standard deviations against the bulk's direction is a reversal.
REVERSAL_Z = 5.0

#: The law of the wall's data viscosity may differ from the stated one by this factor either way (a stated blood
#: viscosity off by 30 %, and the ratio's scatter on the steady turbulent phantoms, 0.97-1.03 at h = 0.6-1.5 mm).
VISCOSITY_FACTOR = 1.6

#: A laminar layer may be this many times thinner than a developing flow's (Langhaar) with the core as found.
LAYER_SLACK = 3.0

#: Fraction of the axis velocity the core may fall beyond Langhaar's at the slackened layer (model error of the
#: ring means: the parabola's ring means, an exact steady flow, meet Langhaar's curve at small epsilon).
CORE_MARGIN = 0.05

#: Radius of the core test (fraction of the wall radius).
CORE_RADIUS = 0.7


@dataclass
class SteadyCheck:
    """What :func:`check` found: the statistics and the reasons the data contradict steady flow (empty: none)."""

    reasons: list = field(default_factory=list)
    reversal_z: float = float("nan")  # largest ring mean against the bulk's direction, in standard deviations
    overshoot_chi2: float = float("nan")  # chi-square gain over the best non-increasing ring means
    inflection_chi2: float = float("nan")  # over the best concave non-increasing inner ring means
    core_drop: float = float("nan")  # fall of the ring means from the axis to CORE_RADIUS, over the axis value
    core_drop_std: float = float("nan")
    parabola_drop: float = float("nan")  # the parabola's (fully developed laminar flow, the most peaked steady one)
    langhaar_drop: float = float("nan")  # Langhaar's fall at the slackened layer (laminar layer only)
    viscosity_ratio: float = float("nan")  # the law of the wall's data viscosity over the stated (turbulent)
    reynolds: float = float("nan")
    rings: int = 0
    viscosity_reasons: int = 0  # how many of the reasons rest on the stated viscosity (the turbulent regime's)

    @property
    def unsteady(self) -> bool:
        return bool(self.reasons)

    def as_dict(self) -> dict:
        out = asdict(self)
        out["unsteady"] = self.unsteady
        return out

    def note(self) -> str:
        """The slice's warning ("" when the data do not contradict steady flow)."""
        if not self.reasons:
            return ""
        if self.viscosity_reasons == len(self.reasons):
            # every reason is the turbulent regime's, which the stated viscosity sets: steady turbulent flow
            # with its viscosity stated 2x off gives them too (scripts/unsteady_frames.py --viscosity-factors)
            return (
                "SUSPECT: unsteady flow, or the stated viscosity off? at the stated viscosity the near-wall data "
                "contradict every steady family (" + "; ".join(self.reasons) + "): a single frame of pulsatile flow "
                "read as a steady slice, or steady turbulent flow whose viscosity is not the stated one (the bulk "
                "Reynolds number and the law of the wall's layer both take it: check --viscosity); its WSS can "
                "miss by far more than the band, which holds the noise only"
            )
        return (
            "SUSPECT: unsteady flow? the near-wall data contradict every steady family ("
            + "; ".join(self.reasons)
            + "): a single frame of pulsatile flow reconstructed as a steady slice; its WSS can miss by far more "
            "than the band, which holds the noise only (a cine series gives the momentum model: wss-nlp reconstruct "
            "on the frames with their trigger times)"
        )


def ring_means(u, sigma, rho, rings: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(centres, means, stds, outer edges)`` of rings of equal width in ``rho`` (in [0, 1)).

    Inverse-variance weighted means of the voxel values ``u`` (noise ``sigma``) and of their ``rho`` (the
    centres: a linear profile's ring mean is its value there, and equal widths give every ring the same
    second-order error, so concave profiles give concave ring means); empty rings are dropped."""
    edges = np.linspace(0.0, 1.0, rings + 1)
    which = np.clip(np.digitize(rho, edges) - 1, 0, rings - 1)
    w = 1.0 / np.asarray(sigma, float) ** 2
    wsum = np.bincount(which, weights=w, minlength=rings)
    keep = wsum > 0
    means = np.bincount(which, weights=w * u, minlength=rings)[keep] / wsum[keep]
    centres = np.bincount(which, weights=w * rho, minlength=rings)[keep] / wsum[keep]
    return centres, means, 1.0 / np.sqrt(wsum[keep]), edges[1:][keep]


def antitonic(y, w) -> np.ndarray:
    """The weighted least-squares non-increasing fit to ``y`` (pool-adjacent-violators)."""
    sums, weights, counts = [], [], []
    for yi, wi in zip(y, w):
        sums.append(yi * wi)
        weights.append(wi)
        counts.append(1)
        while len(sums) > 1 and sums[-2] / weights[-2] < sums[-1] / weights[-1]:
            s, ww, c = sums.pop(), weights.pop(), counts.pop()
            sums[-1] += s
            weights[-1] += ww
            counts[-1] += c
    return np.repeat(np.array(sums) / np.array(weights), counts)


def concave_decreasing(x, y, w) -> np.ndarray:
    """The weighted least-squares concave non-increasing fit to ``y`` at increasing ``x``.

    Written ``f(x) = a - sum_j s_j (x - x_j)_+`` with ``s_j >= 0`` at the knots ``x_0 .. x_{n-2}``: piecewise
    linear, its slope ``-sum_{j: x_j < x} s_j`` non-positive and falling."""
    x, y, sw = np.asarray(x, float), np.asarray(y, float), np.sqrt(np.asarray(w, float))
    knots = x[:-1]
    design = np.column_stack([np.ones_like(x)] + [-np.maximum(x - k, 0.0) for k in knots])
    lower = np.r_[-np.inf, np.zeros(knots.size)]
    solution = scipy.optimize.lsq_linear(design * sw[:, None], y * sw, bounds=(lower, np.inf)).x
    return design @ solution


def langhaar(epsilon: float):
    r"""Langhaar's entrance profile over its axis value, :math:`(I_0(\epsilon) - I_0(\epsilon\rho)) /
    (I_0(\epsilon) - 1)` as a function of :math:`\rho = r/R` (the parabola :math:`1 - \rho^2` as
    :math:`\epsilon \to 0`; exponentially scaled Bessel functions keep large :math:`\epsilon` finite)."""
    if epsilon < 1e-3:
        return lambda rho: 1.0 - np.asarray(rho) ** 2
    ive = scipy.special.ive

    def profile(rho):
        rho = np.asarray(rho, dtype=float)
        return (ive(0, epsilon) - ive(0, epsilon * rho) * np.exp(epsilon * (rho - 1))) / (
            ive(0, epsilon) - np.exp(-epsilon)
        )

    return profile


def ring_drop(profile, rings: int, at: float = CORE_RADIUS) -> float:
    """The core drop (:attr:`SteadyCheck.core_drop`) a radial ``profile(rho)`` gives with :func:`ring_means`'
    rings of a uniform lumen: its area-weighted ring means (midpoint rule, 64 points a ring) at their mean
    ``rho``, from the first ring to ``r = at R``, over the first ring's."""
    edges = np.linspace(0.0, 1.0, rings + 1)
    r = edges[:-1, None] + (np.arange(64) + 0.5)[None, :] / 64 * np.diff(edges)[:, None]
    means = np.sum(r * profile(r), axis=1) / np.sum(r, axis=1)
    centres = np.sum(r * r, axis=1) / np.sum(r, axis=1)
    return float(1.0 - np.interp(at, centres, means) / means[0])


def check(u, sigma, x_mm, y_mm, coefficients, center, voxel_mm: float, reynolds: float, near=None) -> SteadyCheck:
    """Test a slice's voxel velocities against the properties of every steady family (module notes).

    Parameters
    ----------
    u, sigma : arrays
        Measured velocity of the lumen voxels and its noise (m/s).
    x_mm, y_mm : arrays
        The voxels' centres (mm).
    coefficients, center
        The reconstructed wall: radius coefficients (mm) and centre (mm).
    voxel_mm : float
        In-plane voxel size (the partial-volume rings are left out of the concavity test).
    reynolds : float
        Bulk Reynolds number of the slice (:func:`wss_nlp.models.near_wall.bulk_reynolds`).
    near : NearWallChoice or None
        The slice's near-wall choice (its law-of-the-wall viscosity ratio, its laminar layer's scale).
    """
    from . import near_wall as nw

    u, sigma = np.asarray(u, float), np.asarray(sigma, float)
    dx, dy = np.asarray(x_mm, float) - center[0], np.asarray(y_mm, float) - center[1]
    rho = np.hypot(dx, dy) / rad.evaluate(np.asarray(coefficients, float), np.arctan2(dy, dx))
    inside = (rho < 1.0) & np.isfinite(u) & (sigma > 0)
    u, sigma, rho = u[inside], sigma[inside], rho[inside]
    out = SteadyCheck(reynolds=float(reynolds))
    radius = float(coefficients[0])
    rings = int(max(4, np.floor(radius / voxel_mm)))
    if u.size < 3 * rings:
        return out
    direction = 1.0 if np.sum(u / sigma**2) >= 0 else -1.0
    centres, means, stds, outer = ring_means(direction * u, sigma, rho, rings)
    out.rings = int(centres.size)
    w = 1.0 / stds**2
    out.reversal_z = float(np.max(-means / stds))
    if out.reversal_z > REVERSAL_Z:
        i = int(np.argmax(-means / stds))
        out.reasons.append(
            f"flow reversal: the ring at r/R {centres[i]:.2f} flows against the bulk ({out.reversal_z:.0f} standard "
            "deviations)"
        )
    out.overshoot_chi2 = float(np.sum(w * (means - antitonic(means, w)) ** 2))
    if out.overshoot_chi2 > SHAPE_CHI2:
        out.reasons.append(
            f"near-wall overshoot: the velocity rises towards the wall (chi-square {out.overshoot_chi2:.0f} over the "
            f"best non-increasing profile, > {SHAPE_CHI2:g})"
        )
    inner = outer <= 1.0 - voxel_mm / radius
    if np.count_nonzero(inner) >= 4:
        fit = concave_decreasing(centres[inner], means[inner], w[inner])
        out.inflection_chi2 = float(np.sum(w[inner] * (means[inner] - fit) ** 2))
        if out.inflection_chi2 > SHAPE_CHI2:
            out.reasons.append(
                f"inflection: the profile is convex away from the wall (chi-square {out.inflection_chi2:.0f} over "
                f"the best concave profile, > {SHAPE_CHI2:g})"
            )
        axis = means[0]
        at = float(np.interp(CORE_RADIUS, centres, means))
        if axis > 0:
            out.core_drop = float(1.0 - at / axis)
            out.core_drop_std = float(np.hypot(stds[0], stds[np.argmin(np.abs(centres - CORE_RADIUS))]) / axis)
            out.parabola_drop = ring_drop(langhaar(0.0), rings)
            if out.core_drop - out.parabola_drop - CORE_MARGIN > 3.0 * out.core_drop_std:
                out.reasons.append(
                    f"a core more peaked than the parabola: the velocity falls by {100 * out.core_drop:.0f} % from the "
                    f"axis to r = {CORE_RADIUS:g} R (fully developed laminar flow, the most peaked steady flow: "
                    f"{100 * out.parabola_drop:.0f} %)"
                )
    if near is None:
        return out
    if reynolds >= nw.RE_TURBULENT:
        ratio = float(getattr(near, "viscosity_ratio", float("nan")))
        out.viscosity_ratio = ratio
        if np.isfinite(ratio) and not 1.0 / VISCOSITY_FACTOR <= ratio <= VISCOSITY_FACTOR:
            out.reasons.append(
                f"turbulent regime (Re {reynolds:.0f}), but the law of the wall's layer implies {ratio:.2f} x the "
                f"stated kinematic viscosity (steady turbulent flow: within a factor {VISCOSITY_FACTOR:g}; or the "
                f"true viscosity is {ratio:.2g} x the stated one)"
            )
            out.viscosity_reasons += 1
        flat = out.parabola_drop - out.core_drop - CORE_MARGIN
        if near.model == "plain" and np.isfinite(flat) and flat > 3.0 * out.core_drop_std:
            out.reasons.append(
                f"turbulent regime (Re {reynolds:.0f}), but the data chose no turbulent wall layer over the plain "
                f"basis, and the core is not the laminar parabola either (falls by {100 * out.core_drop:.0f} % to "
                f"r = {CORE_RADIUS:g} R, the parabola by {100 * out.parabola_drop:.0f} %; or the stated viscosity "
                "is too high: it lowers the Reynolds number and thickens the law of the wall's layer)"
            )
            out.viscosity_reasons += 1
    else:
        scale = laminar_layer(near, radius)
        if np.isfinite(scale) and np.isfinite(out.core_drop):
            out.langhaar_drop = ring_drop(langhaar(1.0 / (LAYER_SLACK * scale)), rings)
            excess = out.core_drop - out.langhaar_drop - CORE_MARGIN
            if excess > 3.0 * out.core_drop_std:
                out.reasons.append(
                    f"laminar regime (Re {reynolds:.0f}): a wall layer of {scale:.3g} R under a core that falls by "
                    f"{100 * out.core_drop:.0f} % to r = {CORE_RADIUS:g} R; a developing flow with that layer "
                    f"(Langhaar) has a flat core (falls by {100 * out.langhaar_drop:.0f} % at a {LAYER_SLACK:g}x "
                    "thicker layer)"
                )
    return out


def laminar_layer(near, radius_mm: float) -> float:
    """``l / R`` of the laminar layer the near-wall choice found (the ``exponential`` family), NaN without one:
    the chosen layer, or the one it set aside as too thin for the voxels (``unresolved_mm``: the best model, but
    the slice is SUSPECT and takes the plain basis)."""
    if near is None:
        return float("nan")
    if near.model == "exponential":
        return float(near.scale_ratio)
    if np.isfinite(near.unresolved_mm):
        return float(near.unresolved_mm / radius_mm)
    return float("nan")
