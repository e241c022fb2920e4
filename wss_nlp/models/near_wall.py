r"""Near-wall enrichment of the velocity basis: wall layers thinner than a voxel (issue 13).

The polynomial basis of :mod:`wss_nlp.core.velocity_basis` with the prior
:math:`\beta\|\Delta^t v\|^2` cannot follow a profile whose knee lies inside
the first voxel: every beta small enough to let the polynomials bend that
fast also lets noise through. The enrichment adds a few unpenalized
columns that carry a wall layer of thickness ``l``:

.. math::

    v = \sum_j c_j v_j + \sum_{m=0}^{M} f\!\left(\frac{d}{\ell}\right)\rho^m
        \left(a_m \cos m\theta + b_m \sin m\theta\right),
    \qquad d = S\,(1 - \rho),

on the reference disk (:math:`\rho, \theta` polar coordinates), with
:math:`S = r_{in} + \eta(\bar R - r_{in})` the mean wall-normal stretch of
:math:`\phi_R` at the wall (mm per unit of :math:`\rho`), so ``d`` is the
distance to the wall in mm to first order, and ``l`` (mm) is the layer's
length scale. The profile families, all with :math:`f(0) = 0` (the columns
vanish on the wall, like the basis) and :math:`f'(0) = 1` (so a column's WSS
is :math:`\mu S/\ell` times its angular factor, independent of the family):

* ``wall_law``: Reichardt's law of the wall (Reichardt 1951,
  *Z. angew. Math. Mech.* 31, 208-219),
  :math:`f(y) = \ln(1 + \kappa y)/\kappa + 7.8\,(1 - e^{-y/11} - (y/11)\,e^{-y/3})`,
  :math:`\kappa = 0.41`: turbulent mean flow, ``l`` the viscous length
  :math:`\nu/u_\tau`;
* ``low_re``: Reichardt's form with constants that depend on the friction
  Reynolds number :math:`Re_\tau = R/\ell` (``R`` the lumen's mean radius),
  calibrated on channel DNS (:mod:`wss_nlp.models.families.low_re`): the
  buffer layer of turbulent flow at low :math:`Re_\tau`; the basis of a
  layer of scale ``l`` takes the member at :math:`R/\ell` (:func:`enrich`);
* ``exponential``: :math:`f(y) = 1 - e^{-y}`: laminar layers that saturate
  (developing entrance flow, Stokes layers of pulsatile flow), ``l`` the
  displacement-type thickness.

Which model (plain, or a family and a scale on a grid) is chosen from the
data by :mod:`wss_nlp.parameters.choice` (:func:`wss_nlp.parameters.layer.choose_layer`).

The columns are separable in :math:`(\rho, \theta)`; the fit integrates
them across each quadrature cell (:class:`LayerQuadrature`), and the coupled
method does the same with the cell means written in CasADi
(:func:`cell_mean_function`), so that they move with the wall.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

import casadi as ca

from . import families
from . import measurement as meas
from ..errors import InputError
from .families.wall_law import KAPPA, REICHARDT_C  # noqa: F401 (the law of the wall's constants, kept here)

#: Profile families of the wall layer, one module each (:mod:`wss_nlp.models.families`).
FAMILIES = families.NAMES
#: What ``--near-wall`` accepts: off (the paper's basis alone), auto (chosen from the data), or one family.
MODES = ("off", "auto") + FAMILIES
#: The branches of a cell mean (:func:`cell_mean`): the point value (cells narrow against the profile), the box
#: mean (one projection negligible) and the trapezoid mean.
BRANCHES = ("point", "box", "trapezoid")
#: Below this ratio of the cell's narrower projection to its wider one the box mean replaces the trapezoid.
BOX_RATIO = 1e-3
#: Cells narrower than this (layer units) take the point value of the smoothed inside fraction.
NARROW_INSIDE = 1e-6
#: Cells narrower than this (layer units) take the point value of a profile's cell mean (exact to 1e-4 relative).
NARROW_PROFILE = 0.02


def profile(family: str, y):
    """``f(y)`` of a family (:mod:`wss_nlp.models.families`), for NumPy arrays or CasADi symbols (``y >= 0`` is
    the fluid side).

    Points outside the wall (``y < 0``) only occur within rounding of the
    map's inverse; the formulas are smooth there down to ``y = -1``, where
    they are cut off (``1 + kappa y`` stays positive).
    """
    is_sym = isinstance(y, (ca.SX, ca.MX))
    y = ca.fmax(y, -1.0) if is_sym else np.maximum(y, -1.0)
    return families.get(family).f(y, ca if is_sym else np)


def profile_derivative(family: str, y) -> np.ndarray:
    """``f'(y)`` of a family (NumPy; the same cut-off at ``y = -1`` as :func:`profile`)."""
    return profile_derivatives(family, np.maximum(np.asarray(y, dtype=float), -1.0), 1)


def profile_second_derivative(family: str, y) -> np.ndarray:
    """``f''(y)`` of a family (NumPy; the same cut-off), for the curvature correction of cell means far inside."""
    return profile_derivatives(family, np.maximum(np.asarray(y, dtype=float), -1.0), 2)


def profile_derivatives(family: str, y, order: int) -> np.ndarray:
    r"""``f^(k)(y)`` of a family for any order ``k >= 0`` (NumPy, ``y > -1/kappa``; the cut-off of
    :func:`profile` at order 0 only): the family's closed forms
    (:meth:`wss_nlp.models.families.base.WallFamily.derivative`)."""
    y = np.asarray(y, dtype=float)
    return profile(family, y) if order == 0 else families.get(family).derivative(y, int(order))


#: Relative step in Re_tau of :func:`reynolds_derivative`'s central difference (truncation ~1e-8, rounding ~1e-12).
RE_STEP = 1e-4


def reynolds_derivative(family: str, value):
    r"""``-Re_tau d value(member) / d Re_tau`` at a member ``"<family>@<Re_tau>"`` of a Reynolds-number-dependent
    family, by a central difference of relative step :data:`RE_STEP`; 0 for other families.

    ``value(name)`` evaluates anything built from a family's profile (NumPy). With :math:`Re_\tau = R/\ell` this
    is the shape's part of :math:`d/d\log\ell` at fixed ``R``.
    """
    fam = families.get(family)
    if not fam.reynolds_dependent:
        return 0.0
    base, re_tau = families.base_name(family), float(fam.re_tau)  # type: ignore[attr-defined]
    up, down = (families.at_reynolds(base, re_tau * (1 + s * RE_STEP)) for s in (1, -1))
    return -(np.asarray(value(up)) - np.asarray(value(down))) / (2 * RE_STEP)


def far_cell_mean_derivative(family: str, y, a, b, order: int) -> np.ndarray:
    """The ``order``-th ``y``-derivative of :func:`far_cell_mean_function` (NumPy; cells wholly inside the wall,
    ``a``, ``b`` fixed): ``f^(k)(y) + [max(a, b) > NARROW_PROFILE] (a^2 + b^2)/6 f^(k+2)(y)``."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    curvature = np.where(np.maximum(a, b) > NARROW_PROFILE, (a * a + b * b) / 6, 0.0)
    return profile_derivatives(family, y, order) + curvature * profile_derivatives(family, y, order + 2)


def cell_mean_derivative(family: str, y, a, b, order: int, branch: str) -> np.ndarray:
    r"""The ``order``-th ``y``-derivative of :func:`cell_mean_function` with ``continuous=True`` and ``branch``
    (NumPy; cells ``a``, ``b`` fixed, any ``y``).

    Notes
    -----
    With :math:`F_0 = f\,1(y > 0)` and :math:`F_1, F_2` its antiderivatives from 0
    (:func:`antiderivatives`), :math:`F_k^{(d)} = f^{(d-k)} 1(y > 0)` for ``d >= k``
    (:func:`profile_derivatives`; ``f(0) = 0``, so no jump term), and the
    branches differentiate term by term: ``point`` :math:`F_0^{(d)}(y)`,
    ``box`` :math:`(F_1^{(d)}(y+a) - F_1^{(d)}(y-a))/(2a)`, ``trapezoid`` the
    second differences of :math:`F_2^{(d)}` over ``4ab`` (``a >= b``).
    """

    def term(v, k):  # F_k^(order)(v)
        if order < k:
            return antiderivatives(family, v)[k - order - 1]
        return np.where(v > 0, profile_derivatives(family, np.maximum(v, 0.0), order - k), 0.0)

    return _branch_mean(term, y, a, b, branch)


def _branch_mean(term, y, a, b, branch: str) -> np.ndarray:
    """A cell's mean by the formula ``branch`` from ``term(v, k)``, the function (``k = 0``) or its ``k``-th
    antiderivative (or a derivative of them) at ``v``: the point value, the box mean of ``k = 1``, the
    trapezoid's second differences of ``k = 2`` (half-widths ``a >= b``; NumPy)."""
    y = np.asarray(y, dtype=float)
    a, b = (np.asarray(v, dtype=float) for v in np.broadcast_arrays(a, b))
    a, b = np.maximum(a, b), np.minimum(a, b)
    if branch == "point":
        return term(y, 0)
    if branch == "box":
        return (term(y + a, 1) - term(y - a, 1)) / (2 * np.maximum(a, 1e-300))
    if branch == "trapezoid":
        second = term(y + a + b, 2) - term(y + a - b, 2) - term(y - a + b, 2) + term(y - a - b, 2)
        return second / (4 * np.maximum(a * b, 1e-300))
    raise InputError(f"a cell mean's branch must be one of {BRANCHES}, got {branch!r}")


def cell_half_widths(cell_mm, t) -> tuple[np.ndarray, np.ndarray]:
    """Half-widths (mm) of a quadrature cell's projections on the wall normal at polar angle ``t``.

    The normal is radial to first order, so a ``dx x dy`` cell projects as
    two boxes of half-widths ``dx |cos t| / 2`` and ``dy |sin t| / 2``
    (their convolution is the trapezoid of :func:`cell_mean`).
    """
    return cell_mm[0] / 2 * np.abs(np.cos(t)), cell_mm[1] / 2 * np.abs(np.sin(t))


def stretch(disk_map) -> float:
    r"""``S = r_in + eta (mean R - r_in)``: :math:`\partial_\rho |\phi_R|` at the wall, averaged over the angle (mm)."""
    return float(disk_map.r_in + disk_map.eta * (disk_map.coefficients[0] - disk_map.r_in))


def layer_terms(max_order: int) -> list[tuple[int, str]]:
    """The layer's angular terms ``(m, "cos" | "sin")``, ``m = 0 .. max_order`` (``m = 0``: cosine only)."""
    return [(0, "cos")] + [(m, k) for m in range(1, max_order + 1) for k in ("cos", "sin")]


def layer_columns(family: str, layer_terms, scale, x, y) -> list:
    """Unscaled layer columns ``f((1 - rho)/scale) Re/Im (x + i y)^m`` (NumPy or CasADi; ``scale`` may be a symbol)."""
    is_sym = isinstance(x, (ca.SX, ca.MX))
    rho = ca.sqrt(x * x + y * y) if is_sym else np.hypot(x, y)
    f = profile(family, (1 - rho) / scale)
    re, im = [1.0 + 0 * x], [0 * x]
    for _ in range(max(m for m, _ in layer_terms)):  # (x + i y)^(k+1) = (x + i y) (x + i y)^k
        re_k, im_k = re[-1], im[-1]
        re.append(x * re_k - y * im_k)
        im.append(x * im_k + y * re_k)
    return [f * (re[m] if kind == "cos" else im[m]) for m, kind in layer_terms]


@dataclass(frozen=True)
class LayerTemplate:
    """An enriched basis with its scale left open: the key on which WSS graphs are built once and cached.

    ``symbolic_with(xi, p)`` is the velocity for ``p = [c_base; s c_layer; l/S]``
    (:meth:`EnrichedBasis.wss_parameters`, ``s`` the column scale): linear
    in the first :attr:`size` entries, the scale the last (:attr:`n_shape` = 1).
    """

    base: Any  # a basis of wss_nlp.core.velocity_basis
    family: str
    max_order: int

    @property
    def layer_terms(self) -> list:
        return layer_terms(self.max_order)

    @property
    def size(self) -> int:
        return self.base.size + len(self.layer_terms)

    n_shape = 1

    def symbolic_with(self, xi, p):
        nb = self.base.size
        layer = layer_columns(self.family, self.layer_terms, p[p.numel() - 1], xi[0], xi[1])
        return ca.dot(self.base.symbolic(xi), p[:nb]) + ca.dot(ca.vertcat(*layer), p[nb : self.size])


class EnrichedBasis:
    """A velocity basis with ``2 M + 1`` wall-layer columns appended (see the module notes).

    Parameters
    ----------
    base : basis of :mod:`wss_nlp.core.velocity_basis`
        The penalized polynomial part.
    family : str
        Profile of the layer: a family of :data:`FAMILIES`, or a member ``"<family>@<Re_tau>"`` of a
        Reynolds-number-dependent one (:func:`wss_nlp.models.families.at_reynolds`).
    scale : float
        ``l / S``: the layer's length scale in units of the reference radius.
    max_order : int
        Highest angular order ``M`` of the layer's amplitude.

    Notes
    -----
    The appended columns are scaled by their value in the core (``1/f(1/scale)``)
    so their coefficients are velocities like the rest; the penalty Gram
    matrix is zero on them (:meth:`laplacian_gram`): the layer's amplitude
    is decided by the data, its shape by ``family`` and ``scale``.
    """

    def __init__(self, base, family: str, scale: float, max_order: int = 2):
        families.get(family)  # an InputError names the known families
        if not 0 < scale < 1:
            raise InputError(f"near-wall scale l/S must lie in (0, 1), got {scale}")
        self.base, self.family, self.scale, self.max_order = base, family, float(scale), int(max_order)
        self.kind = f"{base.kind}+{family}"
        self.layer_terms = layer_terms(self.max_order)
        self.n_layer = len(self.layer_terms)
        self.column_scale = 1.0 / float(profile(family, 1.0 / self.scale))
        core = 1.0 / self.scale
        # d log(column_scale) / d log l: the core value f(S/l) moves with l, and so does the shape of a
        # Reynolds-number-dependent family, whose Re_tau = R/l (-Re_tau d/dRe_tau: reynolds_derivative)
        self.dlog_column_scale = float(
            core * profile_derivative(family, core) * self.column_scale
            - reynolds_derivative(family, lambda fam: profile(fam, core)) * self.column_scale
        )
        nb = base.transform.shape[0]
        self.transform = np.zeros((nb + self.n_layer, base.size + self.n_layer))
        self.transform[:nb, : base.size] = base.transform
        self.transform[nb:, base.size :] = self.column_scale * np.eye(self.n_layer)

    @property
    def size(self) -> int:
        return self.base.size + self.n_layer

    def describe(self) -> dict:
        return {**self.base.describe(), "near_wall": self.family, "layer_scale": self.scale, "size": self.size}

    def _layer_raw(self, x, y):
        return layer_columns(self.family, self.layer_terms, self.scale, x, y)

    def wss_template(self) -> LayerTemplate:
        """What a WSS graph of this basis depends on besides its coefficients (the scale is a parameter)."""
        return LayerTemplate(self.base, self.family, self.max_order)

    def wss_parameters(self, coefficients) -> np.ndarray:
        """The parameters of :meth:`LayerTemplate.symbolic_with` for velocity coefficients ``coefficients``."""
        c = np.asarray(coefficients, dtype=float)
        nb = self.base.size
        return np.concatenate([c[:nb], self.column_scale * c[nb:], [self.scale]])

    def evaluate(self, x, y, average=None) -> np.ndarray:
        """Values at reference points, shape ``(npts, size)`` (or ``average @ values``)."""
        x, y = np.ravel(x), np.ravel(y)
        layer = np.array(self._layer_raw(x, y)).T * self.column_scale
        if average is not None:
            layer = np.asarray(average @ layer)
        return np.hstack([self.base.evaluate(x, y, average=average), layer])

    def evaluate_raw(self, x, y) -> np.ndarray:
        """The base's unnormalized functions and the layer's unscaled columns: ``evaluate = evaluate_raw @
        transform``."""
        x, y = np.ravel(x), np.ravel(y)
        return np.hstack([self.base.evaluate_raw(x, y), np.array(self._layer_raw(x, y)).T])

    def symbolic_raw(self, xi):
        return ca.vertcat(self.base.symbolic_raw(xi), *self._layer_raw(xi[0], xi[1]))

    def symbolic(self, xi):
        return ca.mtimes(ca.DM(self.transform).T, self.symbolic_raw(xi))

    def radial_raw(self, rho) -> np.ndarray:
        return np.vstack([self.base.radial_raw(rho), self.layer_radial(rho)[0]])

    def layer_radial(self, rho, cells=None) -> tuple[np.ndarray, np.ndarray]:
        """Radial factors ``f((1 - rho)/scale) rho^m`` of the layer columns and their rho-derivatives, (n_layer, n).

        ``cells = (a, b)``: half-widths (reference units, per point) of each
        quadrature cell's projection on the wall normal; ``f`` and ``f'`` are
        then the cell means :func:`cell_mean` the fit integrates with.
        """
        rho = np.ravel(rho).astype(float)
        y = (1 - rho) / self.scale
        if cells is None:
            f, df = profile(self.family, y), -profile_derivative(self.family, y) / self.scale
        else:
            a, b = (np.ravel(c) / self.scale for c in cells)
            f = cell_mean(self.family, y, a, b)
            df = -cell_mean(self.family, y, a, b, derivative=True) / self.scale
        values = [f * rho**m for m, _ in self.layer_terms]
        slopes = [df * rho**m + (m * f * rho ** (m - 1) if m else 0.0) for m, _ in self.layer_terms]
        return np.array(values), np.array(slopes)

    def angular_terms(self) -> list[tuple[int, str]]:
        return self.base.angular_terms() + self.layer_terms

    def angular_raw(self, t) -> np.ndarray:
        t = np.ravel(t).astype(float)
        layer = [np.cos(m * t) if kind == "cos" else np.sin(m * t) for m, kind in self.layer_terms]
        return np.vstack([self.base.angular_raw(t)] + layer)

    def laplacian_gram(self, power: int = 1) -> np.ndarray:
        """The base's Gram matrix, padded with zeros: the layer columns are not penalized."""
        out = np.zeros((self.size, self.size))
        out[: self.base.size, : self.base.size] = self.base.laplacian_gram(power)
        return out


def antiderivatives(family: str, y):
    """First and second antiderivatives of ``f(y) 1(y > 0)`` from 0 (zero for ``y <= 0``; NumPy or CasADi).

    ``family`` is a registered family (:meth:`wss_nlp.models.families.base.WallFamily.integrals`) or
    ``"inside"``: ``f = 1``, the cell's area fraction inside the wall.
    """
    is_sym = isinstance(y, (ca.SX, ca.MX))
    y = ca.fmax(y, 0) if is_sym else np.maximum(np.asarray(y, dtype=float), 0.0)
    if family == "inside":
        return y, y * y / 2
    return families.get(family).integrals(y, ca if is_sym else np)


def cell_mean(family: str, y, a, b, derivative: bool = False, moment: bool = False) -> np.ndarray:
    r"""Mean of ``f(y') 1(y' > 0)`` over a square quadrature cell centred at wall distance ``y``.

    Notes
    -----
    A square cell of sides ``2a/|cos|`` and ``2b/|sin|`` (oriented with the
    image axes) projects onto the wall normal as the convolution of two
    boxes of half-widths ``a`` and ``b``: a trapezoid. Its mean of ``f`` is

    .. math::

        \frac{F_2(y+a+b) - F_2(y+a-b) - F_2(y-a+b) + F_2(y-a-b)}{4ab}

    with :math:`F_2'' = f` (:func:`antiderivatives`), the box mean
    :math:`(F_1(y+a) - F_1(y-a))/(2a)` when ``b`` is negligible, and ``f(y)``
    when the cell is small against the layer; cells far inside (``y > 3(a + b)``)
    take :math:`f + (a^2 + b^2) f''/6` (the trapezoid's second moment; next term
    below 1e-4 relative). All lengths in units of ``l``.
    Exact for a straight wall; the part of the cell beyond the wall
    contributes zero velocity (no slip). ``derivative=True`` gives the
    ``y``-derivative of that mean, the cell mean of ``f'`` (antiderivatives
    ``f``, ``F_1``; no jump term since ``f(0) = 0``); ``moment=True`` the
    cell mean of ``y f'(y)`` (antiderivatives ``y f - F_1`` and
    ``y F_1 - 2 F_2``), which is ``-d/d(log l)`` of the cell mean of ``f(y)``.
    """
    y, a, b = (np.asarray(v, dtype=float) for v in np.broadcast_arrays(y, a, b))
    a, b = np.maximum(a, b), np.minimum(a, b)

    def pair(v):
        if moment:
            f1, f2 = antiderivatives(family, v)
            vp = np.maximum(v, 0)
            return vp * profile(family, vp) - f1, vp * f1 - 2 * f2
        if not derivative:
            return antiderivatives(family, v)
        f1 = antiderivatives(family, v)[0]
        return (np.where(v > 0, 1.0, 0.0) * v, f1) if family == "inside" else (profile(family, np.maximum(v, 0)), f1)

    if moment:
        point = y * profile_derivative(family, y)
    elif derivative:
        point = np.zeros_like(y) if family == "inside" else profile_derivative(family, y)
    else:
        point = np.ones_like(y) if family == "inside" else profile(family, y)
    out = np.where(y > 0, point, 0.0)
    wide = a > NARROW_PROFILE  # below, the midpoint value is exact to 1e-4 relative
    if not (derivative or moment or family == "inside"):
        # far inside (y > 3 (a + b)) the trapezoid mean is f + (a^2 + b^2) f''/6 to within 1e-4 relative
        far = wide & (y > 3 * (a + b))
        out[far] += (a[far] ** 2 + b[far] ** 2) / 6 * profile_second_derivative(family, y[far])
        wide &= ~far
    box = wide & (b < BOX_RATIO * a)
    trap = wide & ~box
    if box.any():
        ya, aa = y[box], a[box]
        out[box] = (pair(ya + aa)[0] - pair(ya - aa)[0]) / (2 * aa)
    if trap.any():
        yt, at, bt = y[trap], a[trap], b[trap]

        def f2(v):
            return pair(v)[1]

        out[trap] = (f2(yt + at + bt) - f2(yt + at - bt) - f2(yt - at + bt) + f2(yt - at - bt)) / (4 * at * bt)
    return out


def spread_branch(a, b, narrow) -> np.ndarray:
    """Which formula of :func:`cell_mean` a cell of projected half-widths ``a``, ``b`` takes (an index into
    :data:`BRANCHES`): the point value when ``max(a, b) <= narrow``, else the box or the trapezoid mean."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    wide, thin = np.maximum(a, b), np.minimum(a, b)
    return np.where(wide <= narrow, 0, np.where(thin < BOX_RATIO * wide, 1, 2))


@functools.lru_cache(maxsize=32)  # a few families and branches; building one costs about 10 ms
def cell_mean_function(family: str, continuous: bool = False, branch: str | None = None) -> ca.Function:
    r""":func:`cell_mean` as a CasADi function ``(y, a, b) -> (mean, d mean / d y)`` of scalars (map it).

    The same branches as the NumPy version (midpoint value for cells small
    against the layer, the curvature-corrected value far inside, the box and
    the trapezoid means of the antiderivatives), so the coupled method's
    layer columns equal the decoupled fit's (``tests/test_coupled.py``);
    the ``y``-derivative is CasADi's exact derivative of that expression.
    ``family`` may also be ``"inside"`` (the cell's area fraction inside
    the wall). ``continuous=True`` drops the branches that switch with ``y``
    (the far-inside value, within a few 1e-4 of the trapezoid, and the inside
    fraction's midpoint step), so the mean is continuously differentiable in
    ``y``, as a wall that moves needs (Newton steps across a switch see a jump).
    ``branch`` (one of :data:`BRANCHES`, with ``continuous=True``) builds that
    formula alone, for cells whose widths select it (:func:`spread_branch`
    with ``narrow =`` :data:`NARROW_PROFILE`): a third to a half of the instructions.
    """
    y, a_in, b_in = ca.SX.sym("y"), ca.SX.sym("a"), ca.SX.sym("b")
    a, b = ca.fmax(a_in, b_in), ca.fmin(a_in, b_in)
    if family == "inside":
        point, curvature = ca.if_else(y > 0, 1.0, 0.0), ca.SX(0)
    else:
        t = ca.SX.sym("t")
        second = ca.Function("f2", [t], [ca.hessian(profile(family, t), t)[0]])
        point = ca.if_else(y > 0, profile(family, ca.fmax(y, 0)), 0.0)
        curvature = ca.if_else(y > 0, second(ca.fmax(y, 0)), 0.0)
    f1 = lambda v: antiderivatives(family, v)[0]  # noqa: E731
    f2 = lambda v: antiderivatives(family, v)[1]  # noqa: E731
    wide = a > NARROW_PROFILE  # below, the midpoint value is exact to 1e-4 relative
    far = wide * (y > 3 * (a + b))  # (the area fraction: exactly 1 there, where the trapezoid only rounds to it)
    if continuous:  # a and b are fixed per cell; only y moves
        far = ca.SX(0)
        wide = ca.SX(1) if family == "inside" else wide
    if branch is not None:
        if not continuous or branch not in BRANCHES:
            raise InputError(f"cell_mean_function: branch must be one of {BRANCHES} with continuous=True")
        value = point if branch == "point" else _spread_mean(f1, f2, y, a, b, branch)
    else:
        value = ca.if_else(
            wide * (1 - far),
            _spread_mean(f1, f2, y, a, b),
            ca.if_else(far, point + (a * a + b * b) / 6 * curvature, point),
        )
    name = f"cell_mean_{_symbol(family)}" + (f"_{branch}" if branch else "")
    return ca.Function(name, [y, a_in, b_in], [value, ca.jacobian(value, y)], {"cse": True})


def _spread_mean(f1, f2, y, a, b, branch: str | None = None):
    """The mean of ``F_1'`` over the trapezoid of half-widths ``a >= b`` centred at ``y`` (CasADi SX): the box
    mean ``(F_1(y+a) - F_1(y-a))/(2a)`` when ``b <`` :data:`BOX_RATIO` ``a``, else the second differences of
    ``F_2`` (``F_2' = F_1``) over ``4ab`` (:func:`cell_mean`); ``branch`` ``"box"`` or ``"trapezoid"``: that
    formula alone."""

    def box():
        return (f1(y + a) - f1(y - a)) / (2 * ca.fmax(a, 1e-300))

    def trapezoid():
        return (f2(y + a + b) - f2(y + a - b) - f2(y - a + b) + f2(y - a - b)) / (4 * ca.fmax(a * b, 1e-300))

    if branch is None:
        return ca.if_else(b < BOX_RATIO * a, box(), trapezoid())
    return box() if branch == "box" else trapezoid()


@functools.lru_cache(maxsize=16)
def smoothed_inside_function(heaviside: str = "erf", branch: str | None = None) -> ca.Function:
    r"""A cell's inside fraction with the geometry's smoothed indicator: ``(y, a, b, g) -> (mean, d mean / d y)``.

    Notes
    -----
    The mean of :math:`H_g(y')` (:func:`wss_nlp.models.measurement.smoothed_heaviside`,
    width ``g``) over the cell's projection on the wall normal, the
    trapezoid of half-widths ``a``, ``b`` centred at depth ``y`` (all in
    layer units), by the box and trapezoid formulas of :func:`cell_mean`
    with the antiderivatives of :math:`H_g`
    (:func:`wss_nlp.models.measurement.heaviside_antiderivatives`); the point value
    :math:`H_g(y)` for cells narrower than :data:`NARROW_INSIDE` (there the box
    formula's differences cancel; the point value is exact to ``a^2 / g^2``).
    Smooth in ``y`` for every cell: the sharp fraction's box mean
    :math:`(y + a)_+ - (y - a)_+` is piecewise linear, and a coupled solve
    whose wall puts a cell's edge there stalls (a turbulent slice, h = 1 mm,
    one cell aligned with the image axes). As ``g -> 0`` it is the sharp
    fraction (``cell_mean("inside", ...)``) of the decoupled fit. ``branch``
    (one of :data:`BRANCHES`): that formula alone, for cells whose widths
    select it (:func:`spread_branch` with ``narrow =`` :data:`NARROW_INSIDE`).
    """
    y, a_in, b_in, g = (ca.SX.sym(name) for name in ("y", "a", "b", "g"))
    a, b = ca.fmax(a_in, b_in), ca.fmin(a_in, b_in)

    def f1(v):
        return meas.heaviside_antiderivatives(v, g, heaviside)[0]

    def f2(v):
        return meas.heaviside_antiderivatives(v, g, heaviside)[1]

    if branch is None:
        value = ca.if_else(a > NARROW_INSIDE, _spread_mean(f1, f2, y, a, b), meas.smoothed_heaviside(y, g, heaviside))
    elif branch in BRANCHES:
        value = meas.smoothed_heaviside(y, g, heaviside) if branch == "point" else _spread_mean(f1, f2, y, a, b, branch)
    else:
        raise InputError(f"smoothed_inside_function: branch must be one of {BRANCHES}, got {branch!r}")
    name = f"inside_{heaviside}" + (f"_{branch}" if branch else "")
    return ca.Function(name, [y, a_in, b_in, g], [value, ca.jacobian(value, y)], {"cse": True})


def smoothed_inside_derivative(y, a, b, g: float, i: int, j: int, branch: str) -> np.ndarray:
    r""":math:`\partial_y^i \partial_g^j` of :func:`smoothed_inside_function` (erf indicator; NumPy; cells ``a``,
    ``b`` fixed, one width ``g``) for the formula ``branch``: the point value, box or trapezoid differences of
    the indicator's and its antiderivatives' derivatives (:func:`wss_nlp.models.measurement.erf_indicator_derivative`).
    """

    def term(x, k):
        return meas.erf_indicator_derivative(x, g, k, i, j)

    return _branch_mean(term, y, a, b, branch)


@functools.lru_cache(maxsize=16)
def far_cell_mean_function(family: str) -> ca.Function:
    """:func:`cell_mean_function` for cells wholly inside the wall, ``y > a + b`` (the branches that apply there)."""
    y, a_in, b_in = ca.SX.sym("y"), ca.SX.sym("a"), ca.SX.sym("b")
    t = ca.SX.sym("t")
    second = ca.Function("f2", [t], [ca.hessian(profile(family, t), t)[0]])
    wide = ca.fmax(a_in, b_in) > NARROW_PROFILE
    value = profile(family, y) + wide * (a_in * a_in + b_in * b_in) / 6 * second(y)
    return ca.Function(
        f"far_cell_mean_{_symbol(family)}", [y, a_in, b_in], [value, ca.jacobian(value, y)], {"cse": True}
    )


def _symbol(family: str) -> str:
    """A family's name as CasADi accepts in a function name (a member ``"low_re@183.2"``: ``low_re_at_183p2``)."""
    return family.replace("@", "_at_").replace(".", "p").replace("-", "m").replace("+", "")


class LayerQuadrature:
    """Voxel means of the layer columns with the layer integrated exactly across each quadrature cell.

    The velocity operator's midpoint rule (``q x q`` cells per voxel,
    :func:`wss_nlp.models.measurement.auto_quad_order`) is spaced about R/60: far
    too coarse for a layer a few micrometres thick (Re_tau 1000 in a 26 mm
    pipe: l = 13 um), and refining it where the layer is would cost
    millions of points. Instead each cell's value of the profile is its
    exact mean across the cell in the wall-normal direction
    (:func:`cell_mean`), while the angular factor, which varies on the
    vessel's scale, keeps the midpoint rule.

    Parameters
    ----------
    problem : wss_nlp.models.velocity.VelocityProblem
        The assembled plain problem (its voxels, map and quadrature cell size).
    """

    def __init__(self, problem):
        vox, dm = problem.voxels, problem.disk_map
        self.rho, self.t = (a.reshape(vox.px.shape) for a in dm.inverse(vox.px.ravel(), vox.py.ravel()))
        self.stretch = stretch(dm)
        self.order = int(round(np.sqrt(vox.px.shape[1])))
        self.half_x, self.half_y = cell_half_widths(problem.cell_mm, self.t)
        self.depth = (1 - self.rho) * self.stretch  # mm from the wall, negative outside
        inside = cell_mean("inside", self.depth, self.half_x, self.half_y)
        self.area = np.sum(inside, axis=1)
        self.averager = problem.averager
        self._angular_cache: dict = {}
        if self.averager is not None:
            self.keep = problem.weights > 0
            self.psf_area = np.where(self.keep, self.averager(inside), 1.0)

    def columns(self, basis: EnrichedBasis) -> np.ndarray:
        """``(n_voxels, n_layer)``: voxel means of the layer columns of ``basis``, scaled as in its ``evaluate``.

        ``sum_cells int_{cell cap Omega} f / sum_cells |cell cap Omega|`` over
        every cell of the voxel (also those whose centre lies outside), so
        the wall voxels' partial volumes are integrated with the layer.
        """
        return self._means(basis, moment=False)

    def columns_dlog_scale(self, basis: EnrichedBasis) -> np.ndarray:
        """``d/d(log l)`` of :meth:`columns` (the scale of the column factor included; a Reynolds-number-dependent
        family's shape moves with ``Re_tau = R/l``, :func:`reynolds_derivative`)."""
        out = basis.dlog_column_scale * self._means(basis, moment=False) - self._means(basis, moment=True)
        if families.get(basis.family).reynolds_dependent:
            out += reynolds_derivative(basis.family, lambda fam: self._means(basis, moment=False, family=fam))
        return out

    def _angular(self, terms: tuple) -> np.ndarray:
        """``rho^m cos(m t)`` / ``rho^m sin(m t)`` at every cell, ``(n_voxels, n_cells, n_terms)`` (kept: no scale)."""
        if terms not in self._angular_cache:
            rho = np.minimum(self.rho, 1.0)
            self._angular_cache[terms] = np.stack(
                [rho**m * (np.cos(m * self.t) if kind == "cos" else np.sin(m * self.t)) for m, kind in terms], axis=-1
            )
        return self._angular_cache[terms]

    def _means(self, basis: EnrichedBasis, moment: bool, family: str | None = None) -> np.ndarray:
        ell = basis.scale * self.stretch  # mm
        family = basis.family if family is None else family
        f = cell_mean(family, self.depth / ell, self.half_x / ell, self.half_y / ell, moment=moment)
        f = f * basis.column_scale
        angular = self._angular(tuple(basis.layer_terms))
        if self.averager is None:
            return np.einsum("vc,vct->vt", f, angular) / self.area[:, None]
        cells = f[..., None] * angular
        # k-space: the PSF image of the cell integrals over the image of the cells' lumen parts (as T_i)
        return np.where(self.keep[:, None], self.averager(cells) / self.psf_area[:, None], 0.0)


@dataclass
class NearWallChoice:
    """Which near-wall model a slice got, and why (recorded in the result file and shown by ``analyze``).

    Attributes
    ----------
    model : str
        ``"plain"`` (the paper's basis alone) or a family of :data:`FAMILIES`.
    scale_mm : float
        The layer scale ``l`` in mm (NaN for the plain model).
    scale_ratio : float
        ``l`` over the mean radius.
    criterion : str
        How the models were compared.
    values : dict
        The criterion of each model at its best scale and beta (smaller is better).
    margin : float
        Criterion of the runner-up model minus the chosen one's.
    tried : list
        ``(model, l/R, criterion)`` of every evaluated candidate.
    ambiguous : bool
        The margin is below :data:`AMBIGUOUS_MARGIN`: the data hardly prefer the choice.
    beta : float
        The beta at which the chosen model's criterion is smallest.
    density_kg_m3, density_source : float, str
        The density behind ``nu`` of the law of the wall, and where it came from.
    reynolds : float
        Bulk Reynolds number from the data (:func:`bulk_reynolds`).
    scale_std_log : float
        Standard deviation of ``log l`` from the velocity noise (law of the wall with the band; else NaN).
    consistent : bool
        The scale is the law of the wall's self-consistent one, ``u_tau l = nu`` (its noise response goes
        into the band); False for every other choice, a wall law without a root included.
    scale_interval : tuple
        A scale chosen by the criterion (``exponential``): the range of ``l/R`` over the evaluated scales
        whose criterion lies within :data:`AMBIGUOUS_MARGIN` of the best; a law-of-the-wall scale with other
        roots of ``u_tau l = nu`` within that margin of its criterion: the range of those roots (the first
        pass's, kept through a dephasing pass, which follows the chosen root only); else NaN.
    scale_wss_spread : float
        The range of the mean WSS over those scales, relative to the chosen scale's (NaN likewise).
        A spread larger than the band flags the slice (:func:`scale_ambiguity_note`).
    quad_order : int
        Quadrature cells per voxel axis of the layer columns (:class:`LayerQuadrature`).
    viscosity_ratio : float
        A self-consistent scale: the kinematic viscosity the data imply (the layer's ``u_tau l`` at the scale of
        smallest criterion within half an octave) over the stated ``nu = mu / rho``
        (:func:`wss_nlp.parameters.layer._data_viscosity`); else NaN.
    voxel_plus : float
        A self-consistent scale: the voxel size over the scale at which the viscosity was read (``h+``; the ratio
        is read only up to :data:`VISCOSITY_RESOLVED`), or over the chosen scale where the voxels are too coarse
        to look for the data's own scale; else NaN.
    warning : str
        A warning about this choice for the slice's notes (:func:`viscosity_note`), or "".
    unresolved_mm : float
        When the best model was an ``exponential`` layer the data cannot resolve (thinner than the voxel
        over :data:`UNRESOLVED_FRACTION`, or with its criterion smallest at the smallest beta tried): its
        scale (the plain model is used and the slice is SUSPECT); else NaN.
    """

    model: str
    scale_mm: float = float("nan")
    scale_ratio: float = float("nan")
    criterion: str = ""
    values: dict = field(default_factory=dict)
    margin: float = float("inf")
    tried: list = field(default_factory=list)
    ambiguous: bool = False
    quad_order: int = 0
    unresolved_mm: float = float("nan")  # scale of a best-fitting layer too thin to resolve (the slice is SUSPECT)
    beta: float = float("nan")
    density_kg_m3: float = float("nan")
    density_source: str = ""
    reynolds: float = float("nan")
    scale_std_log: float = float("nan")
    scale_interval: tuple = (float("nan"), float("nan"))
    scale_wss_spread: float = float("nan")
    consistent: bool = False
    viscosity_ratio: float = float("nan")
    voxel_plus: float = float("nan")
    warning: str = ""

    def as_dict(self) -> dict:
        return asdict(self)


def scale_ambiguity_note(choice: NearWallChoice | None, mean_pa: float, mean_std_pa) -> str:
    """A warning when scales the data hardly tell apart give mean WSS further apart than the band, else "".

    ``mean_std_pa`` is the band's standard deviation of the mean WSS (None or NaN: no band, no judgement).
    """
    if choice is None or not np.isfinite(choice.scale_wss_spread) or mean_std_pa is None:
        return ""
    spread_pa = choice.scale_wss_spread * abs(mean_pa)
    if not np.isfinite(mean_std_pa) or spread_pa <= mean_std_pa:
        return ""
    lo, hi = choice.scale_interval
    return (
        f"near-wall layer scale ambiguous: scales l/R {lo:.3g}-{hi:.3g} fit within {AMBIGUOUS_MARGIN:g} of the "
        f"best criterion and give mean WSS {100 * choice.scale_wss_spread:.2g} % apart ({spread_pa:.2g} Pa), more "
        f"than the band ({mean_std_pa:.2g} Pa), which leaves the scale's spread out: read the spread as the mean "
        "WSS's uncertainty"
    )


#: Largest voxel size in viscous units (h / l, the data's best scale) at which the data's own scale is read as a
#: viscosity (:func:`viscosity_note`): up to it the first voxel holds the buffer layer (y+ < 25-30), beyond it the
#: scale trades against the log law's intercept. On the turbulent phantoms (development seeds 1-2, not kept) the
#: implied nu was 0.86-1.02 x the true one up to h+ = 29 and 0.54-0.94 beyond; report seeds in
#: scripts/results/viscosity_check.md (``python scripts/low_re.py --part viscosity``).
VISCOSITY_RESOLVED = 25.0
#: The data's viscosity and the stated one disagree when their ratio leaves [1/VISCOSITY_TOLERANCE,
#: VISCOSITY_TOLERANCE]; a 30 % error in nu moved the WSS by 3-31 % on the turbulent phantoms.
VISCOSITY_TOLERANCE = 1.2


def viscosity_note(choice: NearWallChoice, viscosity_pa_s: float | None) -> str:
    """A warning about the stated viscosity behind a self-consistent layer scale, else "".

    Where the voxels resolve the buffer layer (``h+ <= VISCOSITY_RESOLVED``): when the data's own scale implies a
    kinematic viscosity that disagrees with the stated one (:attr:`NearWallChoice.viscosity_ratio`). Where they
    do not (the voxels average over the log layer, :math:`U^+ = \\ln(y^+)/\\kappa + B`, where a wrong ``nu`` only
    shifts the intercept by :math:`\\ln(\\nu'/\\nu)/\\kappa`; the data's own scale drifts there,
    :data:`VISCOSITY_RESOLVED`): that the data cannot check it, and what an error in it did to the WSS on the pipe
    phantoms (``python scripts/low_re.py --part viscosity``, ``scripts/results/viscosity_check.md``).
    """
    stated = f"viscosity {viscosity_pa_s:g} Pa s, " if viscosity_pa_s else ""
    source = f"density {choice.density_kg_m3:g} kg/m^3 from {choice.density_source or 'the default'}"
    if choice.consistent and choice.voxel_plus > VISCOSITY_RESOLVED:
        return (
            f"near-wall layer: the voxels span {choice.voxel_plus:.0f} viscous lengths (h+ > {VISCOSITY_RESOLVED:g}) "
            f"and do not resolve the buffer layer, so the data cannot check the stated viscosity ({stated}{source}); "
            "the layer's scale u_tau l = nu, and the WSS with it, rests on it (30 % off moved the WSS by 11-30 % on "
            "the Re_tau 549 pipe phantom at h = 0.6-1.5 mm): check --viscosity and --density"
        )
    ratio = choice.viscosity_ratio
    if not (np.isfinite(ratio) and choice.voxel_plus <= VISCOSITY_RESOLVED):
        return ""
    if 1 / VISCOSITY_TOLERANCE <= ratio <= VISCOSITY_TOLERANCE:
        return ""
    return (
        f"near-wall layer: the data imply a kinematic viscosity {ratio:.2f} x the stated one ({stated}{source}): "
        "the layer's scale u_tau l = nu, and the WSS with it, rests on the stated values (30 % off moved the WSS by "
        "3-31 % on turbulent phantoms); check --viscosity and --density"
    )


#: Bulk Reynolds number above which pipe flow is taken as turbulent (the classical critical value; Reynolds
#: 1883, and e.g. Pope, *Turbulent Flows*, 2000, Sec. 7.3: transition between about 2300 and 4000).
RE_TURBULENT = 2300.0
#: Up to this bulk Reynolds number the regime is reported as transitional.
RE_FULLY_TURBULENT = 4000.0


def bulk_reynolds(problem, nu_m2_s: float) -> float:
    r"""``Re = U D_h / nu`` of the measured flow: bulk velocity and hydraulic diameter of the reconstructed lumen.

    Notes
    -----
    :math:`U = |\sum_i w_i u_i| / \sum_i w_i` (partial-volume weighted mean
    of the measured velocity, m/s), :math:`D_h = 4 A / P` with the lumen
    area :math:`A = \sum_i w_i` and the perimeter ``P`` of :math:`R(\phi)`.
    """
    from ..core import radius as rad

    area = float(np.sum(problem.weights))
    bulk = abs(float(np.sum(problem.weights * problem.data))) / area
    phi = rad.uniform_angles(720)
    c = problem.disk_map.coefficients
    perimeter = float(np.sum(np.hypot(rad.evaluate(c, phi), rad.evaluate(c, phi, 1))) * 2 * np.pi / phi.size)
    return bulk * (4 * area / perimeter) / 1000.0 / nu_m2_s


def regime_families(reynolds: float) -> tuple[str, ...]:
    """The layer families of a flow regime: the turbulent ones above :data:`RE_TURBULENT`, else the others
    (:attr:`wss_nlp.models.families.base.WallFamily.turbulent`)."""
    turbulent = reynolds >= RE_TURBULENT
    return tuple(name for name in FAMILIES if families.get(name).turbulent == turbulent)


#: How the choice record names a law-of-the-wall scale found from u_tau l = nu.
CONSISTENT = "u_tau l = nu"

#: BIC advantage a layer model needs over the plain basis to be chosen (Kass & Raftery 1995, J. Am. Stat. Assoc.
#: 90, 773-795: a difference above 10 is "very strong" evidence): the paper's model stays unless the data insist.
LAYER_EVIDENCE = 10.0

#: A saturating (laminar) layer thinner than the voxel over this is not resolved by voxel means: they see only a
#: velocity jump at the wall, whose WSS ``mu a / l`` the data cannot fix. The developing entrance flow, this
#: family's use, chose l >= h / 5 on every phantom, h and seed (scripts/results/near_wall*.md).
UNRESOLVED_FRACTION = 10.0

#: BIC difference below which a model choice is reported as ambiguous (Kass & Raftery 1995: "not worth more than a
#: bare mention" below 2).
AMBIGUOUS_MARGIN = 2.0


def enrich(problem, family: str, scale_mm: float, laplacian_power: int):
    """``problem`` (plain basis) with the layer columns of ``family`` at scale ``l = scale_mm`` appended (a
    Reynolds-number-dependent family's member at :math:`Re_\\tau = R/\\ell`, ``R`` the mean radius)."""
    family = families.at_reynolds(family, float(problem.disk_map.coefficients[0]) / scale_mm)
    basis = EnrichedBasis(problem.basis, family, scale_mm / stretch(problem.disk_map))
    quadrature = LayerQuadrature(problem)
    return problem.with_layer(basis, quadrature.columns(basis), laplacian_power)


def scale_sensitivity(problem, coefficients, beta: float, wss_matrix, nu_m2_s: float):
    r"""How the law-of-the-wall scale responds to the fit, and the WSS to the scale.

    Returns ``(dg_da0, dg_dlog, dtau_dlog)``: the derivatives of
    :math:`g = a_0\, c_s(\ell)\, \ell / \nu - 1` (whose root is the scale,
    :func:`wss_nlp.parameters.layer._wall_law_scale`) with respect to the m = 0 layer
    coefficient :math:`a_0` and to :math:`\log\ell`, and
    :math:`d\tau/d\log\ell` at fixed data. By the implicit-function
    theorem any data perturbation that moves :math:`a_0` by
    :math:`\delta a_0` at fixed scale moves the scale by
    :math:`\delta\log\ell = -(\partial g/\partial a_0)\,\delta a_0 / (\partial g/\partial\log\ell)`.

    Notes
    -----
    With the fit :math:`H \theta = M^\top W u`, :math:`H = M^\top W M + (\beta/\pi) G`:
    :math:`\partial\theta/\partial\log\ell = H^{-1}(M'^\top W r - M^\top W M'\theta)`,
    :math:`r = u - M\theta`, :math:`M'` the exact ``log l``-derivative of the
    layer's cell-mean columns (:meth:`LayerQuadrature.columns_dlog_scale`).
    The WSS :math:`\tau = S(\ell)\theta` moves by
    :math:`S\,\partial\theta/\partial\log\ell + S'\theta`; the layer
    columns' wall slopes scale as :math:`c_s/\ell`.
    """
    basis = problem.basis
    nb = basis.base.size
    m_op = problem.operator
    w = problem.weights / problem.area
    hmat = m_op.T @ (w[:, None] * m_op) + beta / np.pi * problem.gram
    dm = np.zeros_like(m_op)
    dm[:, nb:] = LayerQuadrature(problem).columns_dlog_scale(basis)
    theta = np.asarray(coefficients, float)
    resid = problem.data - m_op @ theta
    dtheta_dlog = np.linalg.solve(hmat, dm.T @ (w * resid) - m_op.T @ (w * (dm @ theta)))
    ell_m = basis.scale * stretch(problem.disk_map) / 1000.0
    dg_da0 = basis.column_scale * ell_m / nu_m2_s
    dg_dlog = dg_da0 * (theta[nb] * (1 + basis.dlog_column_scale) + dtheta_dlog[nb])
    ds = np.zeros_like(wss_matrix)
    ds[:, nb:] = (basis.dlog_column_scale - 1.0) * wss_matrix[:, nb:]
    return dg_da0, dg_dlog, wss_matrix @ dtheta_dlog + ds @ theta
