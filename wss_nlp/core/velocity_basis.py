"""Velocity bases on the unit disk B that vanish on the wall (Sec. 3, 7.2).

* :class:`ZernikeWallBasis` -- ``(1 - |xi|^2) Z_n^m(xi)`` for ``n <= degree``:
  polynomials, smooth up to the wall, whose Laplacian need *not* vanish on
  the wall. A Poiseuille profile ``1 - |xi|^2`` is the first basis function.
* :class:`DirichletEigenBasis` -- the paper's eigenfunctions
  ``J_m(j_{m,k} rho) {cos, sin}(m t)`` of the Dirichlet Laplacian with
  eigenvalue ``j_{m,k}^2 <= M``. Each has ``Delta v = 0`` on the wall, so a
  profile with nonzero wall Laplacian converges slowly in the wall gradient
  (Lemma 3.3, Remark 3.4).

Both are normalized in L^2(B). Every basis gives values (NumPy), a CasADi
expression in the Cartesian reference point (for exact derivatives) and the
exact Gram matrix ``G_ij = (Delta^t v_i, Delta^t v_j)_{L^2(B)}`` (t = 1 is
eq. (tik2); t = 2 is the stronger penalty of Remark 3.5).
"""

from __future__ import annotations

from functools import lru_cache, cache

import numpy as np

import casadi as ca

from .._lazy import scipy
from ..errors import InputError

BASES = ("zernike", "eigen")


def _zernike_terms(degree: int, max_order: int | None = None):
    """``(n, m)`` pairs with ``m`` signed (negative: sine), ``n <= degree``, ``|m| <= max_order``."""
    mmax = degree if max_order is None else min(max_order, degree)
    return [(n, m) for n in range(degree + 1) for m in range(-n, n + 1, 2) if abs(m) <= mmax]


def _jacobi(k_max: int, a: int, x):
    """Jacobi polynomials ``P_k^{(a,0)}(x)``, ``k = 0..k_max``, by the three-term recurrence.

    Arithmetic only, so it works on NumPy arrays and CasADi symbols, and it
    stays accurate where explicit Zernike sums (factorial coefficients) lose
    all digits beyond degree ~20.
    """
    p = [1.0 + 0 * x]
    if k_max >= 1:
        p.append((a + 1) + (a + 2) * (x - 1) / 2)
    for k in range(1, k_max):
        c = 2 * k + a
        lhs = 2 * (k + 1) * (k + a + 1) * c
        p.append(((c + 1) * ((c + 2) * c * x + a * a) * p[k] - 2 * (k + a) * k * (c + 2) * p[k - 1]) / lhs)
    return p


class ZernikeWallBasis:
    """Span of ``(1 - |xi|^2) Z_n^m(xi)``, ``n <= degree``, ``|m| <= max_order``, orthonormal in L^2(B).

    The functions ``(1 - |xi|^2) Z_n^m`` are far from orthogonal (Gram
    entries up to 0.95), so the basis is ``w = raw @ T`` with ``T = L^{-T}``
    from the Cholesky factor of their Gram matrix; the first function is
    still proportional to the Poiseuille profile ``1 - |xi|^2``.

    Limiting the angular order separately from the degree gives high radial
    resolution (thin boundary layers) without the quadratic growth of the
    full Zernike set.

    The same arithmetic code evaluates NumPy arrays and CasADi symbols:
    ``rho^m cos(m t)`` and ``rho^m sin(m t)`` are the real and imaginary
    parts of ``(x + i y)^m``, built by recurrence, and the radial part is a
    polynomial in ``x^2 + y^2``; nothing is singular at the centre.
    """

    kind = "zernike"

    def __init__(self, degree: int = 10, max_order: int | None = None):
        if degree < 0:
            raise InputError(f"Zernike degree must be >= 0, got {degree}")
        if max_order is not None and max_order < 0:
            raise InputError(f"Zernike angular order must be >= 0, got {max_order}")
        self.degree = int(degree)
        self.max_order = None if max_order is None else int(max_order)
        self.terms = _zernike_terms(self.degree, self.max_order)
        self._grams: dict = {}
        self.transform = np.eye(len(self.terms))
        gram = self._gram(laplacian=0)
        # L^-T by triangular solves: upper triangular exactly (a general inverse leaves rounding below the
        # diagonal), so that products with it can be triangular ones (evaluate); column-major as BLAS takes it
        lower = np.linalg.cholesky(gram)
        self.transform = np.asfortranarray(scipy.linalg.solve_triangular(lower, np.eye(lower.shape[0]), lower=True).T)

    @property
    def size(self) -> int:
        return len(self.terms)

    def describe(self) -> dict:
        return {
            "basis": self.kind,
            "degree": self.degree,
            "max_order": -1 if self.max_order is None else self.max_order,
            "size": self.size,
            "terms_n": [n for n, _ in self.terms],
            "terms_m": [m for _, m in self.terms],
        }

    def _raw(self, x, y):
        """List of unnormalized basis values (arithmetic only).

        ``Z_n^m = rho^|m| P_k^{(|m|,0)}(1 - 2 rho^2) {cos, sin}(|m| t)`` with
        ``k = (n - |m|)/2``, up to sign and scale (absorbed by the orthonormalization).
        """
        s = x * x + y * y
        mmax = max(abs(m) for _, m in self.terms)
        re, im = [1.0 + 0 * x], [0 * x]
        for _ in range(mmax):  # (x + i y)^(k+1) = (x + i y) (x + i y)^k
            re_k, im_k = re[-1], im[-1]
            re.append(x * re_k - y * im_k)
            im.append(x * im_k + y * re_k)
        radial = {a: _jacobi((self.degree - a) // 2, a, 1 - 2 * s) for a in range(mmax + 1)}
        bubble = 1 - s
        out = []
        for n, m in self.terms:
            ang = re[abs(m)] if m >= 0 else im[abs(m)]
            out.append(bubble * radial[abs(m)][(n - abs(m)) // 2] * ang)
        return out

    def evaluate(self, x, y, average=None) -> np.ndarray:
        """Values at reference points, shape ``(npts, size)``.

        With ``average`` (a sparse ``(n_out, npts)`` matrix) returns
        ``average @ values`` without forming ``values``: the linear
        orthonormalizing transform is applied after the averaging, which
        is much cheaper for voxel means.
        """
        x, y = np.ravel(x), np.ravel(y)
        if average is None:
            return self.evaluate_raw(x, y) @ self.transform
        raw = self._raw(x, y)
        # one sparse product per function: the (npts, size) array is never formed (forming it and the product
        # with its transpose took 3x longer; the sums are the same, in the same order), each into a column of a
        # column-major array that BLAS's triangular product (trmm) multiplies by the transform in place: half
        # a general product's work (1.7 against 4.1 ms at 5 900 voxels)
        out = np.empty((average.shape[0], len(raw)), order="F")
        for j, f in enumerate(raw):
            out[:, j] = np.asarray(average @ f).ravel()
        return scipy.linalg.blas.dtrmm(1.0, self.transform, out, side=1, lower=0, overwrite_b=1)

    def evaluate_raw(self, x, y) -> np.ndarray:
        """The unnormalized functions at reference points, ``(npts, size)``: ``evaluate = evaluate_raw @ transform``.

        A linear map of the values (a voxel average, a PSF, a combination with coefficients) is cheaper
        applied to these, with ``transform`` after it on the small result.
        """
        return np.array(self._raw(np.ravel(x), np.ravel(y))).T

    def symbolic(self, xi):
        """CasADi column of the basis functions at the reference point ``xi``."""
        return ca.mtimes(ca.DM(self.transform).T, self.symbolic_raw(xi))

    def symbolic_raw(self, xi):
        """The unnormalized functions, ``symbolic(xi) = transform^T symbolic_raw(xi)``.

        Mapping this over many points and applying ``transform`` as one
        dense product afterwards is far cheaper than mapping :meth:`symbolic`.
        """
        return ca.vertcat(*self._raw(xi[0], xi[1]))

    def radial_raw(self, rho) -> np.ndarray:
        """Radial factors of the raw functions, ``(1 - rho^2) rho^|m| P_k^{(|m|,0)}(1 - 2 rho^2)``, shape (size, n).

        ``raw_j(rho, t) = radial_raw(rho)[j] * angular_raw(t)[j]`` (polar separation, used by the coupled method).
        """
        rho = np.ravel(rho).astype(float)
        s = rho * rho
        out = []
        for n, m in self.terms:
            a = abs(m)
            out.append((1 - s) * rho**a * _jacobi((n - a) // 2, a, 1 - 2 * s)[(n - a) // 2])
        return np.array(out)

    def angular_terms(self) -> list[tuple[int, str]]:
        """``(order, "cos" | "sin")`` of each raw function's angular factor."""
        return [(abs(m), "cos" if m >= 0 else "sin") for _, m in self.terms]

    def angular_raw(self, t) -> np.ndarray:
        """Angular factors ``cos(m t)`` (m >= 0) or ``sin(|m| t)`` (m < 0), shape (size, n)."""
        t = np.ravel(t).astype(float)
        return np.array([np.cos(m * t) if m >= 0 else np.sin(-m * t) for _, m in self.terms])

    def laplacian_gram(self, power: int = 1) -> np.ndarray:
        """Exact ``(Delta^t v_i, Delta^t v_j)_{L^2(B)}``, ``t = power``, by CasADi derivatives and exact quadrature."""
        if power not in self._grams:  # computed once per basis: it takes up to seconds
            self._grams[power] = self._gram(laplacian=power)
        return self._grams[power]

    def _gram(self, laplacian: int) -> np.ndarray:
        """``(Delta^t w_i, Delta^t w_j)_{L^2(B)}`` for ``t = laplacian``, exactly.

        Each raw function is ``g(rho) trig(m t)`` with a polynomial ``g``, and
        ``Delta (g trig) = (g'' + g'/rho - m^2 g/rho^2) trig``; the radial
        derivatives are CasADi's exact ones on 1-D expressions. Angular
        integrals are ``2 pi`` (m = 0), ``pi`` (equal signed m) or 0, and the
        radial integrand is a polynomial of degree <= 2 degree + 5 in rho,
        which Gauss-Legendre with ``degree + 4`` nodes integrates exactly.
        """
        r = ca.SX.sym("r")
        nodes, weights = np.polynomial.legendre.leggauss(self.degree + 4)
        rho, wr = 0.5 * (nodes + 1), 0.5 * weights * 0.5 * (nodes + 1)
        vals = np.empty((self.size, rho.size))
        for i, (n, m) in enumerate(self.terms):
            a = abs(m)
            g = (1 - r**2) * r**a * _jacobi((n - a) // 2, a, 1 - 2 * r**2)[(n - a) // 2]
            for _ in range(int(laplacian)):
                dg = ca.jacobian(g, r)
                g = ca.jacobian(dg, r) + dg / r - a * a * g / r**2
            vals[i] = np.asarray(ca.Function("g", [r], [g]).map(rho.size)(rho)).ravel()
        ms = np.array([m for _, m in self.terms])
        angular = np.where(ms == 0, 2 * np.pi, np.pi)[:, None] * (ms[:, None] == ms[None, :])
        raw = angular * ((vals * wr) @ vals.T)
        return self.transform.T @ raw @ self.transform


# ----------------------------------------------------------------- Bessel basis
class _BesselJ(ca.Callback):
    """``J_m`` of a scalar as a CasADi callback, differentiable to any order.

    CasADi has no Bessel functions; the Jacobian of this callback is
    ``(J_{m-1} - J_{m+1}) / 2`` built from further callbacks, so first and
    higher derivatives are exact (to SciPy's accuracy).
    """

    def __init__(self, order: int):
        ca.Callback.__init__(self)
        self.order = order
        self.construct(f"besselj_{order}".replace("-", "m"), {"enable_fd": False})

    def get_n_in(self):
        return 1

    def get_n_out(self):
        return 1

    def eval(self, arg):
        return [float(scipy.special.jv(self.order, float(arg[0])))]

    def has_jacobian(self):
        return True

    def get_jacobian(self, name, inames, onames, opts):
        x = ca.MX.sym(inames[0])
        out = ca.MX.sym(onames[0])
        d = 0.5 * (bessel_j(self.order - 1)(x) - bessel_j(self.order + 1)(x))
        return ca.Function(name, [x, out], [d], inames, onames, opts)


@cache
def bessel_chebyshev(order: int, scale: float) -> np.ndarray:
    """Chebyshev coefficients of ``x -> J_order(scale x)`` on [-1, 1].

    ``J_m`` is entire, so the coefficients decay faster than geometrically
    once the degree exceeds ``scale``; degree ``scale + 40`` reaches machine
    precision for every cut-off used here (checked in the tests).
    """
    deg = int(np.ceil(scale)) + 40
    return np.polynomial.chebyshev.chebinterpolate(lambda x: scipy.special.jv(order, scale * x), deg)


def clenshaw(coefficients, x):
    """``sum_k c_k T_k(x)`` by Clenshaw's recurrence (arithmetic only: NumPy or CasADi)."""
    b1, b2 = 0 * x, 0 * x
    for c in coefficients[:0:-1]:
        b1, b2 = 2 * x * b1 - b2 + c, b1
    return x * b1 - b2 + coefficients[0]


@cache
def bessel_j(order: int) -> _BesselJ:
    """Cached callback for ``J_order`` (callbacks must outlive their use)."""
    return _BesselJ(order)


class DirichletEigenBasis:
    """Dirichlet-Laplacian eigenfunctions of the unit disk with ``lambda <= M``.

    ``v = J_m(j rho) cos(m t) / c`` or ``J_m(j rho) sin(m t) / c`` with
    ``j = j_{m,k}`` the k-th zero of ``J_m`` and ``c`` the L^2(B) norm
    ``sqrt(pi_m / 2) |J_{m+1}(j)|`` (``pi_0 = 2 pi``, ``pi_m = pi``).
    ``-Delta v = j^2 v``, so the Laplacian Gram matrix is ``diag(j^4)``.
    """

    kind = "eigen"

    def __init__(self, max_eigenvalue: float = 400.0):
        if not max_eigenvalue > scipy.special.jn_zeros(0, 1)[0] ** 2:
            raise InputError(f"eigenvalue cut-off M = {max_eigenvalue} keeps no eigenfunction (need M > 5.78)")
        self.max_eigenvalue = float(max_eigenvalue)
        jmax = np.sqrt(self.max_eigenvalue)
        terms = []
        m = 0
        while True:
            zeros = scipy.special.jn_zeros(m, max(1, int(jmax / np.pi) + 2))
            zeros = zeros[zeros <= jmax]
            if zeros.size == 0:
                break
            for j in zeros:
                terms.append((m, float(j), "cos"))
                if m > 0:
                    terms.append((m, float(j), "sin"))
            m += 1
        terms.sort(key=lambda z: (z[1], z[0], z[2]))
        self.terms = terms
        self.norm = np.array(
            [np.sqrt((2 * np.pi if m == 0 else np.pi) / 2) * abs(scipy.special.jv(m + 1, j)) for m, j, _ in terms]
        )

    @property
    def size(self) -> int:
        return len(self.terms)

    def describe(self) -> dict:
        return {
            "basis": self.kind,
            "max_eigenvalue": self.max_eigenvalue,
            "size": self.size,
            "terms_m": [m for m, _, _ in self.terms],
            "terms_j": [j for _, j, _ in self.terms],
            "terms_sin": [int(k == "sin") for _, _, k in self.terms],
        }

    def evaluate(self, x, y, average=None) -> np.ndarray:
        """Values at reference points, ``(npts, size)``; ``average`` as for :class:`ZernikeWallBasis`."""
        x, y = np.ravel(x), np.ravel(y)
        if average is not None:
            return np.asarray(average @ self.evaluate(x, y))
        rho, t = np.hypot(x, y), np.arctan2(y, x)
        cols = []
        for (m, j, kind), c in zip(self.terms, self.norm):
            ang = np.cos(m * t) if kind == "cos" else np.sin(m * t)
            cols.append(scipy.special.jv(m, j * rho) * ang / c)
        return np.stack(cols, axis=1)

    def symbolic(self, xi, exact_callbacks: bool = False):
        """CasADi column of the basis at ``xi`` (valid away from ``xi = 0``).

        By default ``J_m(j rho)`` is its Chebyshev interpolant on [-1, 1]
        (:func:`bessel_chebyshev`, within 1e-14 of SciPy), evaluated by
        Clenshaw's recurrence: plain arithmetic, so it works in SX graphs and
        maps fast. ``exact_callbacks=True`` uses the SciPy callbacks instead.
        """
        rho = ca.sqrt(ca.dot(xi, xi))
        t = ca.atan2(xi[1], xi[0])
        out = []
        for (m, j, kind), c in zip(self.terms, self.norm):
            ang = ca.cos(m * t) if kind == "cos" else ca.sin(m * t)
            radial = bessel_j(m)(j * rho) if exact_callbacks else clenshaw(bessel_chebyshev(m, j), rho)
            out.append(radial * ang / c)
        return ca.vertcat(*out)

    @property
    def transform(self) -> np.ndarray:
        return np.eye(self.size)

    def evaluate_raw(self, x, y) -> np.ndarray:
        """Same as :meth:`evaluate` (``transform`` is the identity)."""
        return self.evaluate(x, y)

    def symbolic_raw(self, xi):
        """Same as :meth:`symbolic` (the functions are orthonormal already; ``transform`` is the identity)."""
        return self.symbolic(xi)

    def radial_raw(self, rho) -> np.ndarray:
        """``J_m(j rho) / c`` for each function, shape (size, n) (see :meth:`ZernikeWallBasis.radial_raw`)."""
        rho = np.ravel(rho).astype(float)
        return np.array([scipy.special.jv(m, j * rho) / c for (m, j, _), c in zip(self.terms, self.norm)])

    def angular_terms(self) -> list[tuple[int, str]]:
        return [(m, kind) for m, _, kind in self.terms]

    def angular_raw(self, t) -> np.ndarray:
        t = np.ravel(t).astype(float)
        return np.array([np.cos(m * t) if kind == "cos" else np.sin(m * t) for m, _, kind in self.terms])

    def laplacian_gram(self, power: int = 1) -> np.ndarray:
        """``diag(lambda^(2t))``: ``Delta^t v = (-lambda)^t v`` for orthonormal eigenfunctions."""
        return np.diag(np.array([j for _, j, _ in self.terms]) ** (4 * power))


@lru_cache(maxsize=16)
def make_basis(kind: str = "zernike", degree: int = 10, max_eigenvalue: float = 400.0, max_order: int | None = None):
    """Factory used by the options: ``"zernike"`` (degree) or ``"eigen"`` (M).

    Cached: bases are immutable and building the Gram matrices takes a
    noticeable fraction of a second.
    """
    if kind == "zernike":
        return ZernikeWallBasis(degree, max_order)
    if kind == "eigen":
        return DirichletEigenBasis(max_eigenvalue)
    raise InputError(f"unknown velocity basis {kind!r}; choose from {BASES}")
