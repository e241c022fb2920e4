r"""A periodic temporal prior on the velocity of a cine slice's frames, all on one shared wall.

On one wall every frame has the same voxel operator :math:`T` (the frames differ in their data
:math:`u_k` only), and

.. math::

    \min_{v_0, \dots, v_{n-1}} \sum_k \Big[\|T v_k - u_k\|_W^2 + \frac{\beta}{\pi} v_k^\top G v_k\Big]
    + \frac{\gamma}{\pi}\sum_k \|(D_2 v)_k\|^2_{L^2(B)},
    \qquad (D_2 v)_k = v_{k+1} - 2 v_k + v_{k-1} \text{ (periodic)},

the plain Tikhonov functional of every frame (eq. (tik2), :mod:`wss_nlp.velocity`) tied by the periodic
second difference over equally spaced frames, decouples under the discrete Fourier transform over the
frames: frequency :math:`j` solves

.. math::

    \Big(K + \frac{\beta}{\pi} G + \frac{\gamma}{\pi}\lambda_j G_0\Big)\hat v_j = T^\top W \hat u_j,
    \qquad \lambda_j = (2 - 2\cos(2\pi j/n))^2, \quad K = T^\top W T,

with :math:`G` the penalty's Gram matrix and :math:`G_0` the :math:`L^2(B)` one. One generalized
eigendecomposition per :math:`(\gamma, j)` serves every beta. :math:`\gamma = 0` is independent frames
with a common beta.

Notes
-----
Choice (:func:`fit`): Schwarz's criterion :math:`\nu\chi^2 + \ln(\nu N)\,\mathrm{dof}` over the
:math:`(\beta, \gamma)` grid, :math:`\chi^2 = \sum_k \|T v_k - u_k\|^2_{\Sigma_k^{-1}}` with the per-voxel
noise and :math:`\mathrm{dof} = \sum_j \operatorname{tr}(H_j^{-1} K)` (the smoother's trace), the same
criterion as the frames' own fits and the momentum model (:mod:`wss_nlp.womersley`), which it competes with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from .choice import CRITERION_BETAS
from .velocity import VelocityProblem

#: The temporal weights tried (gamma; 0, independent frames, is the frames' own criterion's business).
GAMMAS = 10.0 ** np.arange(-4.0, 5.0, 1.0)


@dataclass
class PriorFit:
    """The temporal prior's best fit: its parameters, coefficients per frame and criterion."""

    beta: float
    gamma: float
    coefficients: np.ndarray  # (n_frames, n_basis)
    bic: float
    chi2: float
    dof: float


def fit(problem: VelocityProblem, data: np.ndarray, sigma: np.ndarray, nu: float, log_n: float) -> PriorFit:
    """The prior on ``problem``'s wall for the frames' voxel data ``data`` (n_frames, n_vox), BIC-best (notes).

    ``sigma`` (n_frames, n_vox) is the per-voxel noise, ``nu`` the effective fraction of independent voxels,
    ``log_n`` the criterion's ``ln(nu N)`` (shared with the models it competes with).
    """
    t, w = problem.operator, problem.weights / problem.area
    kmat = t.T @ (w[:, None] * t)
    gram, gram0 = problem.gram / np.pi, problem.basis.laplacian_gram(0) / np.pi
    n = data.shape[0]
    rhs_hat = np.fft.fft((w[None, :] * data) @ t, axis=0)  # (n, m)
    lam = (2 - 2 * np.cos(2 * np.pi * np.arange(n) / n)) ** 2
    inv_var = 1.0 / np.asarray(sigma, float) ** 2
    betas = CRITERION_BETAS
    best: PriorFit | None = None
    # the penalty's Gram is singular (functions the penalty does not see): pencils about a reference beta per
    # three decades, H_beta = B + (beta - beta_ref) G with B = H_beta_ref positive definite (as tikhonov.py)
    groups = np.floor(np.log10(betas) / 3.0)
    for gamma in GAMMAS:
        v_hat = np.zeros((betas.size, n, kmat.shape[0]), dtype=complex)
        dof = np.zeros(betas.size)
        for j in range(n // 2 + 1):
            a = kmat + gamma * lam[j] * gram0
            pair = {j, (n - j) % n}
            for g in np.unique(groups):
                idx = np.nonzero(groups == g)[0]
                ref = float(np.sqrt(betas[idx].max() * betas[idx].min()))
                # X^T B X = I, X^T G X = diag(d): H_beta^-1 = X diag(1 / (1 + (beta - ref) d)) X^T
                d, x = scipy.linalg.eigh(gram, a + ref * gram)
                kx = np.einsum("ij,ik,kj->j", x, kmat, x)
                scale = 1.0 / (1.0 + (betas[idx, None] - ref) * d[None, :])
                for jj in pair:
                    v_hat[idx, jj] = (scale * (x.T @ rhs_hat[jj])[None, :]) @ x.T
                dof[idx] += len(pair) * (scale @ kx)
        v = np.fft.ifft(v_hat, axis=1).real  # (n_beta, n, m)
        resid = v @ t.T - data[None]
        chi2 = np.einsum("bkv,kv->b", resid**2, inv_var)
        crit = nu * chi2 + log_n * dof
        i = int(np.argmin(crit))
        if best is None or crit[i] < best.bic:
            best = PriorFit(float(betas[i]), float(gamma), v[i], float(crit[i]), float(chi2[i]), float(dof[i]))
    assert best is not None
    return best


def solve(problem: VelocityProblem, data: np.ndarray, beta: float, gamma: float) -> np.ndarray:
    """The prior's coefficients ``(n_frames, n_basis)`` at one ``(beta, gamma)``: a Cholesky factorization per
    frequency (the reference :func:`fit`'s pencils are checked against)."""
    t, w = problem.operator, problem.weights / problem.area
    kmat = t.T @ (w[:, None] * t)
    gram, gram0 = problem.gram / np.pi, problem.basis.laplacian_gram(0) / np.pi
    n = data.shape[0]
    rhs_hat = np.fft.fft((w[None, :] * data) @ t, axis=0)
    lam = (2 - 2 * np.cos(2 * np.pi * np.arange(n) / n)) ** 2
    v_hat = np.array([scipy.linalg.cho_solve(scipy.linalg.cho_factor(kmat + beta * gram + gamma * lam[j] * gram0),
                                             rhs_hat[j]) for j in range(n)])  # fmt: skip
    return np.fft.ifft(v_hat, axis=0).real
