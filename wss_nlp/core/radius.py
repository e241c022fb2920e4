"""Radius functions in the truncated Fourier space V_N (paper Sec. 7.1).

A radius function is stored as the coefficient vector
``c = [b0, b1..bN, a1..aN]`` (the order of the public file format) of

    R(phi) = b0 + sum_k b_k cos(k phi) + a_k sin(k phi),

in millimetres. Everything here is linear in ``c``, so evaluation is a
design matrix that works for NumPy arrays and CasADi symbols alike.
"""

from __future__ import annotations

import numpy as np

import casadi as ca


def n_coefficients(n_fourier: int) -> int:
    """Length ``2N+1`` of the coefficient vector of V_N."""
    return 2 * n_fourier + 1


def n_fourier_from_size(size: int) -> int:
    """Inverse of :func:`n_coefficients`; raises on even sizes."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"a Fourier coefficient vector has odd length 2N+1, got {size}")
    return (size - 1) // 2


def design_matrix(phi, n_fourier: int, derivative: int = 0) -> np.ndarray:
    """Matrix ``B`` with ``B @ c = R^(derivative)(phi)``.

    Parameters
    ----------
    phi : array_like
        Angles in radians, any shape; flattened.
    n_fourier : int
        Highest harmonic N.
    derivative : int
        Order of the derivative with respect to phi.

    Returns
    -------
    ndarray, shape (phi.size, 2N+1)
    """
    phi = np.asarray(phi, dtype=float).ravel()
    # cos(k phi) + i sin(k phi) = z^k with z = exp(i phi): one complex exponential and N - 1 products per angle
    # instead of 2N trigonometric evaluations; d^j/dphi^j z^k = (i k)^j z^k
    powers = np.cumprod(np.broadcast_to(np.exp(1j * phi)[:, None], (phi.size, n_fourier)), axis=1)
    if derivative:
        powers = powers * (1j * np.arange(1, n_fourier + 1)) ** derivative
    const = np.full((phi.size, 1), 1.0 if derivative == 0 else 0.0)
    return np.hstack([const, powers.real, powers.imag])


def weighted_gram_map(n_fourier: int) -> np.ndarray:
    r"""Matrix ``G`` with ``vec(B^T diag(d) B) = G [u; v; w]``, ``u = B^T d``, ``v = B^T (d cos N phi)``,
    ``w = B^T (d sin N phi)``: ``B`` the design matrix of degree ``N``, whatever the angles and weights ``d``.

    Notes
    -----
    The entries of the weighted Gram matrix are Fourier moments of ``d``:
    with :math:`C_m = \sum_j d_j \cos m\phi_j` and
    :math:`S_m = \sum_j d_j \sin m\phi_j`,
    :math:`\sum_j d_j \cos k\phi_j \cos l\phi_j = (C_{|k-l|} + C_{k+l})/2`,
    :math:`\sum_j d_j \sin k\phi_j \sin l\phi_j = (C_{|k-l|} - C_{k+l})/2`,
    :math:`\sum_j d_j \cos k\phi_j \sin l\phi_j = (S_{k+l} + S_{l-k})/2`
    (:math:`S_{-m} = -S_m`, :math:`S_0 = 0`). The moments up to ``N`` are
    ``u``; those above, :math:`C_{N+k} = v_{\cos k} - w_{\sin k}` and
    :math:`S_{N+k} = w_{\cos k} + v_{\sin k}`, follow from
    :math:`\cos(N+k)\phi = \cos N\phi \cos k\phi - \sin N\phi \sin k\phi`
    and the like. So a weighted Gram matrix over many points costs three
    products with :math:`B^\top` instead of :math:`(2N+1)^2` (and no second
    matrix at the points). ``vec`` by columns, as CasADi's (the matrix is
    symmetric, so either order).
    """
    n = n_fourier
    size = 2 * n + 1
    # moments C_0..C_2N at 0..2N and S_1..S_2N at 2N+1..4N, from [u; v; w] (columns of B: cos k at k, sin k at n+k)
    moments = np.zeros((4 * n + 1, 3 * size))
    for m in range(n + 1):
        moments[m, m] = 1.0
        if m:
            moments[2 * n + m, n + m] = 1.0
    for k in range(1, n + 1):
        moments[n + k, size + k] = 1.0  # C_{N+k} = v_cos k - w_sin k
        moments[n + k, 2 * size + n + k] = -1.0
        moments[3 * n + k, 2 * size + k] = 1.0  # S_{N+k} = w_cos k + v_sin k
        moments[3 * n + k, size + n + k] = 1.0
    gram = np.zeros((size, size, 4 * n + 1))

    def add_sin(row, col, m, weight):  # weight * S_m, with S_{-m} = -S_m and S_0 = 0
        if m:
            gram[row, col, 2 * n + abs(m)] += weight * np.sign(m)

    for k in range(n + 1):
        for l in range(n + 1):  # noqa: E741 (the formula's index)
            if k == 0 or l == 0:  # the constant times cos(m phi): the single moment C_{k+l}
                gram[k, l, k + l] += 1.0
            else:
                gram[k, l, abs(k - l)] += 0.5
                gram[k, l, k + l] += 0.5
                gram[n + k, n + l, abs(k - l)] += 0.5
                gram[n + k, n + l, k + l] -= 0.5
        for l in range(1, n + 1):  # noqa: E741 cos(k phi) sin(l phi) and its transpose
            weight = 1.0 if k == 0 else 0.5
            for row, col in ((k, n + l), (n + l, k)):
                add_sin(row, col, k + l, weight)
                if k:
                    add_sin(row, col, l - k, weight)
    return gram.reshape(size * size, 4 * n + 1) @ moments


def weighted_gram(basis: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``B^T diag(d) B`` for the design matrix ``B`` (:func:`design_matrix`) at some angles, from three products
    with ``B^T`` (:func:`weighted_gram_map`) instead of one per pair of columns."""
    n = n_fourier_from_size(basis.shape[1])
    cos_n, sin_n = (basis[:, n], basis[:, 2 * n]) if n else (1.0, 0.0)
    stacked = basis.T @ np.column_stack([d, d * cos_n, d * sin_n])
    return (weighted_gram_map(n) @ stacked.ravel(order="F")).reshape(basis.shape[1], basis.shape[1])


def evaluate(coefficients, phi, derivative: int = 0) -> np.ndarray:
    r"""``R^(derivative)(phi)`` for numeric coefficients (shape of ``phi`` flattened).

    Notes
    -----
    :math:`R = c_0 + \operatorname{Re} \sum_k (a_k - i b_k) z^k` with :math:`z = e^{i\phi}`, by Horner's rule
    in ``z`` (the ``j``-th derivative multiplies the ``k``-th term by :math:`(ik)^j`): N complex products per
    angle, without forming the design matrix (2.5x faster at 24 000 angles).
    """
    c = np.asarray(coefficients, dtype=float).ravel()
    n = n_fourier_from_size(c.size)
    phi = np.asarray(phi, dtype=float).ravel()
    const = c[0] if derivative == 0 else 0.0
    if n == 0:
        return np.full(phi.size, const)
    terms = (c[1 : n + 1] - 1j * c[n + 1 :]) * (1j * np.arange(1, n + 1)) ** derivative
    z = np.exp(1j * phi)
    acc = np.full(phi.size, terms[-1])
    for term in terms[-2::-1]:
        acc = acc * z + term
    return const + (acc * z).real


def symbolic(coefficients, phi, derivative: int = 0):
    """``R^(derivative)(phi)`` for a CasADi coefficient vector and scalar angle."""
    n = n_fourier_from_size(coefficients.numel())
    terms = [1 if derivative == 0 else 0]
    k_list = range(1, n + 1)
    shift = derivative * np.pi / 2
    cos_terms = [k**derivative * ca.cos(k * phi + shift) for k in k_list]
    sin_terms = [k**derivative * ca.sin(k * phi + shift) for k in k_list]
    row = ca.vertcat(*terms, *cos_terms, *sin_terms)
    return ca.dot(row, coefficients)


def sobolev_weights(n_fourier: int, s: int = 2) -> np.ndarray:
    """Diagonal weights ``w`` with ``||R||^2_{H^s} = sum w_i c_i^2``.

    Notes
    -----
    The norm is ``||R||^2_{H^s(0,2pi)} = sum_{j=0}^{s} ||R^(j)||^2_{L^2(0,2pi)}``
    (paper eq. (tik1) with s = 2). By Parseval, ``int cos^2(k phi) = pi`` and
    ``int 1 = 2 pi``, so ``w_0 = 2 pi`` and ``w_k = pi sum_j k^(2j)``.
    Units: mm^2 for R in mm.
    """
    if s < 0 or int(s) != s:
        raise ValueError(f"Sobolev index s must be a non-negative integer, got {s}")
    k = np.arange(1, n_fourier + 1, dtype=float)
    wk = np.pi * sum(k ** (2 * j) for j in range(int(s) + 1))
    return np.concatenate([[2 * np.pi], wk, wk])


def sobolev_norm(coefficients, s: int = 2) -> float:
    """``||R||_{H^s(0, 2 pi)}`` of numeric coefficients (see :func:`sobolev_weights`)."""
    c = np.asarray(coefficients, dtype=float).ravel()
    w = sobolev_weights(n_fourier_from_size(c.size), s)
    return float(np.sqrt(np.sum(w * c**2)))


def fit(phi, radius, n_fourier: int) -> np.ndarray:
    """Least-squares projection of sampled radii onto V_N.

    For uniform samples with more than 2N+1 points this is the truncated
    Fourier series (discrete orthogonality).
    """
    b = design_matrix(phi, n_fourier)
    coef, *_ = np.linalg.lstsq(b, np.asarray(radius, dtype=float).ravel(), rcond=None)
    return coef


def uniform_angles(n: int) -> np.ndarray:
    """``n`` uniform angles on [0, 2 pi)."""
    return 2 * np.pi * np.arange(n) / n


def arc_length_mean(values, radius, dradius) -> float:
    """Arc-length weighted mean over a closed curve sampled at uniform angles.

    Notes
    -----
    ``ds = sqrt(R^2 + R'^2) dphi``; the trapezoidal rule on uniform periodic
    samples is spectrally accurate for smooth integrands.
    """
    ds = np.sqrt(np.asarray(radius) ** 2 + np.asarray(dradius) ** 2)
    return float(np.sum(np.asarray(values) * ds) / np.sum(ds))


def polar_about(px, py, center):
    """``(r, cos t, sin t)`` of fixed points (mm) about a CasADi centre, as MX rows."""
    dx = ca.DM(np.ravel(px)).T - center[0]
    dy = ca.DM(np.ravel(py)).T - center[1]
    r = ca.sqrt(dx * dx + dy * dy)
    return r, dx / r, dy / r


def harmonics(c1, s1, n: int):
    """``cos(k t), sin(k t)`` for ``k = 0..n`` from ``cos t, sin t`` (MX rows) by the complex recurrence."""
    cs, sn = [ca.MX.ones(c1.shape), c1], [ca.MX.zeros(c1.shape), s1]
    for _ in range(2, n + 1):
        cs.append(cs[-1] * c1 - sn[-1] * s1)
        sn.append(sn[-1] * c1 + cs[-2] * s1)
    return cs[: n + 1], sn[: n + 1]


def from_harmonics(coefficients, cs, sn):
    """``R(t) = c_0 + sum_k c_k cos(k t) + c_{N+k} sin(k t)`` on rows of harmonics (see :func:`harmonics`)."""
    n = len(cs) - 1
    out = coefficients[0] * cs[0]
    for k in range(1, n + 1):
        out = out + coefficients[k] * cs[k] + coefficients[n + k] * sn[k]
    return out
