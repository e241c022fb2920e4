r"""Linear Tikhonov problems for a whole grid of regularization parameters at once.

The velocity step (paper eq. (tik2), Sec. 7.2) and every rule that chooses
its parameter work on

.. math::

    \min_c \; \|W^{1/2}(T c - u)\|^2 + \frac{\beta}{\pi}\, c^\top G c,
    \qquad W = \operatorname{diag}(w) / \textstyle\sum_i w_i ,

with normal equations :math:`H_\beta c = g`, :math:`H_\beta = K + (\beta/\pi) G`,
:math:`K = T^\top W T`, :math:`g = T^\top W u`. :class:`LinearTikhonov`
forms ``K`` and ``g`` once and answers for one beta by a Cholesky
factorization (:meth:`~LinearTikhonov.solve`) and for a grid of betas from
generalized eigendecompositions of the pencil :math:`(G, B)`,
:math:`B = H_{\beta_r}` for a reference :math:`\beta_r`:

.. math::

    G V = B V \Lambda, \quad V^\top B V = I
    \;\Rightarrow\;
    V^\top H_\beta V = I + \frac{\beta - \beta_r}{\pi}\Lambda =: D_\beta \text{ (diagonal)},

so :math:`c_\beta = V D_\beta^{-1} V^\top g`,
:math:`\operatorname{tr}(H_\beta^{-1} K) = \sum_a (1 - \beta_r\lambda_a/\pi)/d_{\beta,a}`
and the penalty is :math:`\sum_a \lambda_a y_a^2/\pi` with
:math:`y = D_\beta^{-1} V^\top g`. One :math:`O(m^3)` decomposition serves
every beta within :data:`PENCIL_DECADES` decades of its reference (farther
away rounding in :math:`\Lambda` grows like
:math:`\varepsilon\max(\beta/\beta_r, \beta_r/\beta)`), so the grid
``1e-2 .. 1e-14`` of the parameter rules costs 3 decompositions instead of
one factorization and one ``m``-column solve per beta (issue 19).
Units: ``u`` in m/s, ``c`` in m/s, beta dimensionless.
"""

from __future__ import annotations

import functools

import numpy as np

from .._lazy import scipy
from ..errors import NoiseEstimationError, SolverError

#: Smallest beta of the parameter grids (below it the normal matrix loses definiteness in double precision).
BETA_MIN = 1e-14
#: Decades of beta served by one generalized eigendecomposition (accuracy about eps 10^(decades/2) = 2e-13, see
#: _groups): the grids of the parameter rules take 3 decompositions (5 with 3 decades).
PENCIL_DECADES = 6


class LinearTikhonov:
    """The weighted linear Tikhonov problem above, with its normal equations formed once.

    Parameters
    ----------
    operator : (n, m) array
        ``T``, the forward operator (voxel means of the basis functions).
    weights : (n,) array
        Misfit weights ``w`` (partial volumes, mm^2); normalized internally.
    data : (n,) array
        ``u``, the measured values.
    gram : (m, m) array
        ``G``, the penalty Gram matrix (positive semi-definite).
    normal : (m, m) array, optional
        ``K = T^T W T`` when the caller has it (:meth:`bordered`).
    """

    def __init__(self, operator, weights, data, gram, normal=None):
        self.operator = np.asarray(operator, dtype=float)
        self.w = np.asarray(weights, dtype=float) / np.sum(weights)
        self.data = np.asarray(data, dtype=float)
        self.gram = np.asarray(gram, dtype=float)
        self._pencils: dict = {}
        if normal is None:
            root = self.operator * np.sqrt(self.w)[:, None]
            normal = root.T @ root  # K = T^T W T: NumPy's symmetric rank-k update (syrk), half a product's flops
        self.normal = np.asarray(normal, dtype=float)
        self.rhs = self.operator.T @ (self.w * self.data)  # g = T^T W u

    @functools.cached_property
    def weighted_operator(self) -> np.ndarray:
        """``W T`` (formed when first used)."""
        return self.operator * self.w[:, None]

    def with_data(self, data) -> LinearTikhonov:
        """The same operator, weights and penalty with other data ``u``: the normal matrix and the pencils
        (which do not depend on the data) are shared with this one, only ``g = T^T W u`` is formed (the frames
        of a cine slice on one wall, :func:`wss_nlp.pipeline.cine.plain_problem`)."""
        other = LinearTikhonov.__new__(LinearTikhonov)
        other.operator, other.w, other.gram, other.normal = self.operator, self.w, self.gram, self.normal
        other._pencils = self._pencils  # shared: a pencil computed for one data set serves every other
        other.data = np.asarray(data, dtype=float)
        other.rhs = other.operator.T @ (other.w * other.data)
        if "weighted_operator" in self.__dict__:
            other.__dict__["weighted_operator"] = self.weighted_operator
        return other

    def bordered(self, operator, weights, gram) -> LinearTikhonov:
        """The problem with columns appended (``operator`` = ``[T, E]``, the same weights and data) and the
        penalty ``gram``, its normal matrix by blocks: ``[[K, T^T W E], [E^T W T, E^T W E]]`` from this one's
        ``K``, products with the ``k`` new columns only (``O(n m k)`` instead of ``O(n m^2)``)."""
        operator = np.asarray(operator, dtype=float)
        m = self.normal.shape[0]
        extra = operator[:, m:]
        weighted = extra * self.w[:, None]
        border, corner = self.operator.T @ weighted, extra.T @ weighted
        normal = np.block([[self.normal, border], [border.T, corner]])
        return LinearTikhonov(operator, weights, self.data, gram, normal=normal)

    def hessian(self, beta: float) -> np.ndarray:
        """``H_beta = K + (beta / pi) G``."""
        return self.normal + beta / np.pi * self.gram

    def solve(self, beta: float) -> np.ndarray:
        """``c_beta`` by a Cholesky factorization of ``H_beta`` (one beta, full accuracy)."""
        try:
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(self.hessian(beta)), self.rhs)
        except np.linalg.LinAlgError as exc:
            raise SolverError(f"velocity: normal matrix is not positive definite ({exc}); increase beta") from exc

    def residual_norm(self, coefficients) -> float:
        """``|W^{1/2}(T c - u)|`` for one coefficient vector."""
        return float(np.sqrt(np.sum(self.w * (self.operator @ coefficients - self.data) ** 2)))

    # ------------------------------------------------------------------ many betas
    def pencil(self, beta_ref: float) -> tuple[np.ndarray, np.ndarray]:
        """``(V, lambda)`` with ``G V = B V diag(lambda)``, ``V^T B V = I``, ``B = K + (beta_ref/pi) G`` (cached)."""
        key = float(beta_ref)
        if key not in self._pencils:
            try:
                lam, vec = scipy.linalg.eigh(self.gram, self.hessian(key))
            except np.linalg.LinAlgError as exc:
                raise SolverError(
                    f"velocity: the normal matrix at beta = {key:g} is not positive definite ({exc})"
                ) from exc
            self._pencils[key] = (vec, np.maximum(lam, 0.0))  # G is semi-definite: clip rounding below zero
        return self._pencils[key]

    def _groups(self, betas):
        """``(beta_ref, indices, d)`` per band of :data:`PENCIL_DECADES` decades of beta.

        The eigenvalues carry absolute errors of about ``eps pi / beta_ref``,
        so ``d = 1 + (beta - beta_ref) lambda / pi`` has relative errors of
        about ``eps max(beta / beta_ref, beta_ref / beta)``: a reference at
        the band's centre (in log) keeps them near ``eps 10^(decades/2)``.
        The reference stays at or above ``sqrt(10)`` :data:`BETA_MIN` (the
        pencil needs ``K + beta_ref G / pi`` positive definite): the lowest
        band's betas (``BETA_MIN`` to ``1e-12``) are within 1.5 decades of it.
        """
        betas = np.asarray(betas, dtype=float)
        if np.any(betas <= 0):
            raise ValueError("beta must be > 0")
        band = np.floor(np.log10(betas) / PENCIL_DECADES)
        for b in np.unique(band):
            idx = np.flatnonzero(band == b)
            ref = max(10.0 ** ((b + 0.5) * PENCIL_DECADES), np.sqrt(10.0) * BETA_MIN)
            vec, lam = self.pencil(ref)
            d = 1.0 + ((betas[idx] - ref) / np.pi)[:, None] * lam[None, :]
            yield vec, lam, ref, idx, d

    def coefficients(self, betas) -> np.ndarray:
        """``c_beta`` for every beta, shape ``(n_beta, m)``."""
        out = np.empty((np.size(betas), self.normal.shape[0]))
        for vec, _, _, idx, d in self._groups(betas):
            out[idx] = (vec.T @ self.rhs)[None, :] / d @ vec.T
        return out

    def residual_norms(self, coefficients) -> np.ndarray:
        """``|W^{1/2}(T c - u)|`` for each row of ``coefficients`` (computed directly: no cancellation)."""
        r = np.atleast_2d(coefficients) @ self.operator.T - self.data[None, :]
        return np.sqrt(np.sum(self.w[None, :] * r**2, axis=1))

    def gcv(self, betas) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r"""Generalized cross-validation: ``(gcv, residual_norms, penalties)`` for each beta.

        Notes
        -----
        :math:`\mathrm{GCV}(\beta) = n\,|W^{1/2}(T c_\beta - u)|^2 / (n - \operatorname{tr} A_\beta)^2`
        with the influence matrix trace :math:`\operatorname{tr} A_\beta = \operatorname{tr}(H_\beta^{-1} K)
        = \sum_a (1 - b_0 \lambda_a) / d_{\beta,a}`; penalties :math:`c^\top G c / \pi`.
        """
        n_beta = np.size(betas)
        res, trace, pen = np.empty(n_beta), np.empty(n_beta), np.empty(n_beta)
        for vec, lam, ref, idx, d in self._groups(betas):
            y = (vec.T @ self.rhs)[None, :] / d
            res[idx] = self.residual_norms(y @ vec.T)
            trace[idx] = np.sum((1.0 - ref / np.pi * lam)[None, :] / d, axis=1)  # V^T K V = I - (ref/pi) Lambda
            pen[idx] = np.sum(lam[None, :] * y**2, axis=1) / np.pi
        n = self.data.size
        return n * res**2 / (n - trace) ** 2, res, pen

    def traces(self, betas) -> np.ndarray:
        r"""Effective degrees of freedom :math:`\operatorname{tr}(H_\beta^{-1} K)` for each beta (see :meth:`gcv`)."""
        out = np.empty(np.size(betas))
        for _, lam, ref, idx, d in self._groups(betas):
            out[idx] = np.sum((1.0 - ref / np.pi * lam)[None, :] / d, axis=1)
        return out

    def balance_grams(self, betas, functional, sigma, correlate=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r"""Gram matrices of the estimates ``S c_beta`` and of their noise parts, and the residual norms.

        Notes
        -----
        With independent data noise of standard deviations ``sigma``, the
        noise part of :math:`S c_j` is :math:`M_j n`,
        :math:`M_j = S H_j^{-1} T^\top W \Sigma^{1/2}`, so
        :math:`E\langle e_j, e_k\rangle = \operatorname{tr}(M_j M_k^\top)
        = \sum_{a,b} Q_{ab} R_{ab} / (d_{j,a} d_{k,b})` with
        :math:`Q = (SV)^\top (SV)` and :math:`R = V^\top T^\top W \Sigma W T V`:
        every beta pair costs :math:`O(m^2)` after one :math:`O(m^3)` setup.
        With correlated noise (``correlate(x) = C x``, unit-diagonal ``C``; a
        k-space acquisition) :math:`\Sigma = D C D` in place of :math:`D^2`.
        Returns ``(gram_estimates, gram_noise, residual_norms)``.
        """
        sigma = np.asarray(sigma, dtype=float)
        if not (np.all(np.isfinite(sigma)) and np.any(sigma > 0)):
            raise NoiseEstimationError(
                "the balancing principle needs a positive, finite velocity noise level; got "
                f"{'zero' if np.all(sigma == 0) else 'non-finite values'} "
                "(pass --noise-velocity or a fixed --beta)"
            )
        functional = np.asarray(functional, dtype=float)
        n_beta = np.size(betas)
        est = np.empty((n_beta, functional.shape[0]))
        noise_root = []  # per band: the noise parts' coordinates, so bands can be paired
        res = np.empty(n_beta)
        for vec, _, _, idx, d in self._groups(betas):
            sv = functional @ vec
            y = (vec.T @ self.rhs)[None, :] / d
            est[idx] = y @ sv.T
            res[idx] = self.residual_norms(y @ vec.T)
            noise_root.append((idx, vec, sv, 1.0 / d))
        # E<e_j, e_k> = tr(S H_j^-1 N H_k^-1 S^T), N = T^T W Sigma W T; within a band the pencil diagonalizes both
        # inverses; across bands P = V_a^T N V_b couples them: tr(D_j^-1 P D_k^-1 (S V_b)^T (S V_a))
        twsig = self.weighted_operator * sigma[:, None]
        n_mat = twsig.T @ (twsig if correlate is None else correlate(twsig))
        noise = np.empty((n_beta, n_beta))
        for ia, va, sva, inv_a in noise_root:
            nva = va.T @ n_mat
            for ib, vb, svb, inv_b in noise_root:
                coupling = (nva @ vb) * (sva.T @ svb)
                noise[np.ix_(ia, ib)] = inv_a @ coupling @ inv_b.T
        return est @ est.T, noise, res


class BorderedTikhonov:
    r"""A :class:`LinearTikhonov` problem with ``k`` unpenalized columns appended, solved through its pencils.

    Notes
    -----
    With the extra columns ``E`` the normal matrix is bordered,

    .. math::

        \begin{pmatrix} A_\beta & B \\ B^\top & C \end{pmatrix}
        \begin{pmatrix} c \\ a \end{pmatrix} =
        \begin{pmatrix} g \\ e \end{pmatrix},
        \quad A_\beta = K + \tfrac{\beta}{\pi} G,\; B = T^\top W E,\; C = E^\top W E,\; e = E^\top W u,

    and the Schur complement :math:`S_\beta = C - B^\top A_\beta^{-1} B` (``k x k``)
    gives :math:`a = S^{-1}(e - B^\top A^{-1} g)`, :math:`c = A^{-1}(g - B a)`.
    The original's pencils diagonalize :math:`A_\beta` for every beta, so a
    new set of columns costs ``O(m^2 k)`` once and ``O(m k^2)`` per beta
    instead of new eigendecompositions. The effective number of parameters
    is :math:`m + k - (\beta/\pi) \operatorname{tr}(G [H_\beta^{-1}]_{cc})` with
    :math:`[H^{-1}]_{cc} = A^{-1} + A^{-1} B S^{-1} B^\top A^{-1}`.
    """

    def __init__(self, base: LinearTikhonov, extra, border=None):
        self.base = base
        self.extra = np.asarray(extra, dtype=float)
        te = self.extra * base.w[:, None]
        # ``border``: B = T^T W E computed by the caller (one product with T serving several weightings)
        self.border = base.weighted_operator.T @ self.extra if border is None else np.asarray(border, float)
        self.corner = te.T @ self.extra  # C
        self.extra_rhs = te.T @ base.data  # e

    def coefficients_and_traces(self, betas) -> tuple[np.ndarray, np.ndarray]:
        """``[c_beta, a_beta]`` for every beta, shape ``(n_beta, m + k)``, and the effective parameter counts.

        All betas of a pencil band at once: the ``k x k`` Schur complements
        are formed and solved as one batch.
        """
        betas = np.asarray(betas, dtype=float)
        m, k = self.base.normal.shape[0], self.extra.shape[1]
        coef, traces = np.empty((betas.size, m + k)), np.empty(betas.size)
        for vec, lam, _, idx, d in self.base._groups(betas):
            vb, vg = vec.T @ self.border, vec.T @ self.base.rhs  # V^T B, V^T g
            dinv = 1.0 / d  # (n_beta, m)
            # B^T V diag(x_b) V^T B for every beta b as one batched product: (n_beta, k, m) @ (m, k)
            schur = self.corner[None] - (vb.T[None] * dinv[:, None, :]) @ vb
            try:
                amp = np.linalg.solve(schur, (self.extra_rhs[None] - (dinv * vg) @ vb)[..., None])[..., 0]
                # tr(G [H^-1]_cc) in pencil coordinates: V^T G V = Lambda, V^T A^-1 V = D^-1
                inner = np.linalg.solve(schur, (vb.T[None] * (dinv * lam * dinv)[:, None, :]) @ vb)
            except np.linalg.LinAlgError as exc:
                raise SolverError(f"velocity: the extra columns are linearly dependent ({exc})") from exc
            y = dinv * (vg[None] - amp @ vb.T)  # V^T c
            tr = np.sum(lam * dinv, axis=1) + np.trace(inner, axis1=1, axis2=2)
            coef[idx, :m], coef[idx, m:] = y @ vec.T, amp
            traces[idx] = m + k - betas[idx] / np.pi * tr
        return coef, traces
