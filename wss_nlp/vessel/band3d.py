r"""The velocity-noise band of a vessel's wall shear stress, and what moves its mean (issue 38).

Given the wall, the velocity fit of :mod:`wss_nlp.vessel.velocity3d` is linear in the measured voxel velocities:
per world component ``c`` and frame,

.. math:: a_c = H^{-1} T^\top W u_c, \qquad
          H = T^\top W T + \frac{\beta}{\pi L} G_\Delta + \frac{\kappa_v}{\pi L} G_{ss},

(:class:`wss_nlp.vessel.velocity3d.VelocityProblem3D`). With independent voxel noise of standard deviation
``sigma_ic = venc_c z_i`` (:func:`wss_nlp.vessel.velocity3d.velocity_noise`: ``z_i = sigma / (pi S_i)``, the phase
noise of the voxel's summed signal ``S_i``; the components independent), the coefficients' covariance is

.. math:: \operatorname{Cov}(a_c) = \mathrm{venc}_c^2\, C, \qquad C = H^{-1} T^\top W Z^2 W T H^{-1},

the same for every frame (rigid walls, one noise level). A WSS functional at a wall point is linear in the
coefficients of the four velocity B-splines non-zero there (:func:`wss_nlp.vessel.wss3d.wall_wss`): with
``d_u = (w . A_s, w_rho . A, w_theta . A)`` and ``grad u = 1000 d_u M^{-1}`` the traction's part along a unit
tangent ``f`` is

.. math:: f \cdot \tau = -1000 \mu \sum_{c, q} (f_c (M^{-1} n)_q + n_c (M^{-1} f)_q)\, d_{u, cq},

so its gradient ``g_c`` lives on a window of ``4 n_z`` coefficients and ``Var = sum_c venc_c^2 g_c^T C_w g_c``
with ``C_w`` the window's block of ``C``. The band is the exact linear propagation (no sampling):

* ``axial_std_pa`` (per wall point and frame): the standard deviation of the axial WSS ``tau . t``
  (``f = (I - n n^T) t``), the meaning ``tau_std_pa`` has for slices (the signed WSS along the vessel);
* ``plane_mean_std_pa`` (per plane and frame): of the plane table's mean ``|tau|`` over the ring (arc-length
  weights), linearized (``f = tau / |tau|``);
* ``mean_std_pa``: of the mean ``|tau|`` over the covered wall (area weights) and the frames (the frames' noise
  independent).

What moves the mean: ``d a / d beta = -H^{-1} (G_Delta / (pi L)) a`` and ``d a / d kappa_v = -H^{-1} (G_ss / (pi
L)) a`` exactly (a derivative, not a re-solve), so ``d mean / d beta = -sum_c (H^{-1} g_c)^T G_Delta a_c / (pi L)``.

``C``'s window blocks come from one dense inverse of ``H`` (LAPACK ``potrf``/``potri``; ``H`` is stored dense
already) and products that skip ``T^T W Z^2 W T``'s zeros outside its band, only the knot blocks ``C_ij`` with
``|i - j| <= 3``; the whole-wall mean needs one product with ``H^{-1}``. On the aorta-sized phantoms (about 1500
unknowns) this is a few percent of the reconstruction's time (``scripts/results/band_vessel.md``, last column).

**Under the temporal prior** (a cine volume whose frames the prior ties, :mod:`wss_nlp.vessel.cycle3d`) the
coefficients solve ``J a = r`` with ``J = I (x) H + gamma / (pi L) D_2^T D_2 (x) M``; on the temporal DFT's modes
``J`` is ``S_k^{-1} = H + gamma lambda_k M / (pi L)``, and the frames' right-hand sides are independent with the
same covariance ``R = T^T W Z^2 W T``, so every frame's coefficients have

.. math:: C = \frac{1}{n} \sum_{k=0}^{n-1} S_k R S_k = X \big(Q \circ \Omega\big) X^\top, \qquad
          \Omega_{ij} = \frac{1}{n}\sum_k \frac{1}{(\mu_i + c_k)(\mu_j + c_k)},

with ``H X = M X diag(mu)``, ``X^T M X = I``, ``Q = X^T R X``, ``c_k = gamma lambda_k / (pi L)`` (``gamma = 0``:
``C = H^{-1} R H^{-1}``). The frames are no longer independent: the wall mean over the frames, ``sum_t g_t^T a_t``,
has the variance ``(1/n) sum_k ghat_k^H S_k R S_k ghat_k`` (``ghat_k`` the DFT of the ``g_t``), and its
derivative in ``beta`` is ``-(J^{-1} g)^T (I (x) G_Delta / (pi L)) a``.

The band holds the velocity noise only. The magnitude noise moves the wall, and the wall moves the WSS; the slices
carry that part (:mod:`wss_nlp.uncertainty.sensitivity`: the wall fit's implicit-function derivative, then the
velocity's normal equations differentiated along every wall direction with the voxel membership held, then the
WSS's own dependence on the wall). Here none of the three derivatives exists yet: the wall fit's Hessian and active
set (IPOPT's, with the box constraints) are not kept, the velocity operator is assembled in NumPy (the sub-voxel
points' reference coordinates through the wall and ``r_in``, not a CasADi graph), and
:func:`wss_nlp.vessel.wss3d.wall_function` takes the wall as inputs but is not differentiated in them; with
``(2N + 1)`` times the wall's B-splines (several hundred) directions, each an operator derivative over every
sub-voxel point, it is not cheap either. So the band is left without it (the 4D flow guide says what that means
on the phantoms).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from .._lazy import scipy
from . import wss3d

log = logging.getLogger(__name__)

#: What the band holds (the record's ``holds``).
HOLDS = "velocity noise only; the wall's response to the magnitude noise is not included"


@dataclass
class VesselBand:
    """The band of a vessel's WSS and the mean's sensitivities (module notes); stresses in Pa.

    Attributes
    ----------
    axial_std_pa : (nt, ns, np)
        Standard deviation of the axial WSS at every wall point and frame.
    plane_mean_std_pa : (nt, ns)
        Of each plane's mean ``|tau|`` (ring, arc-length weights).
    mean_pa, mean_std_pa : float
        The mean ``|tau|`` over the covered wall (area weights) and the frames, and its standard deviation.
    d_mean_d_beta, d_mean_d_kappa : float
        Exact derivatives of ``mean_pa`` with respect to the velocity prior's ``beta`` and ``kappa_v`` (Pa per unit).
    beta, kappa : float
        The fit's values.
    seconds : float
    """

    axial_std_pa: np.ndarray
    plane_mean_std_pa: np.ndarray
    mean_pa: float
    mean_std_pa: float
    d_mean_d_beta: float
    d_mean_d_kappa: float
    beta: float
    kappa: float
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)

    def record(self) -> dict:
        """The JSON record of the result file (``vessel/`` attribute ``band``)."""
        return {
            "available": True, "holds": HOLDS, "mean_pa": self.mean_pa, "mean_std_pa": self.mean_std_pa,
            "d_mean_d_beta": self.d_mean_d_beta, "d_mean_d_kappa": self.d_mean_d_kappa, "beta": self.beta,
            "kappa_mm4": self.kappa, "seconds": self.seconds, **self.extra,
        }  # fmt: skip


def unavailable(nt: int, ns: int, nph: int, why: str) -> tuple[np.ndarray, np.ndarray, dict]:
    """NaN bands ``(axial (nt, ns, np), planes (nt, ns))`` and the record saying ``why``."""
    return np.full((nt, ns, nph), np.nan), np.full((nt, ns), np.nan), {"available": False, "note": why}


def _factor(sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``sigma (V, 3) = z (V,) scale (3,)``: the common voxel profile and each component's scale."""
    sigma = np.asarray(sigma, float)
    scale = sigma.max(axis=0)
    if not np.all(scale > 0):
        return np.zeros(sigma.shape[0]), np.zeros(3)
    z = sigma[:, 0] / scale[0]
    if not np.allclose(sigma, z[:, None] * scale[None, :], rtol=1e-10, atol=0):
        raise ValueError("the components' voxel noise must be proportional (sigma_ic = venc_c z_i)")
    return z, scale


@dataclass
class Covariance:
    """``H^{-1}`` (dense), ``T^T W Z^2 W T`` and the window blocks of ``C = H^{-1} T^T W Z^2 W T H^{-1}``."""

    h_inv: np.ndarray
    noise_normal: np.ndarray  # T^T W Z^2 W T
    blocks: dict  # first knot k -> C on the knots k .. k + 3, (4 n_z, 4 n_z)
    nz: int

    def block(self, knot: int) -> np.ndarray:
        return self.blocks[int(knot)]

    def quadratic(self, g: np.ndarray) -> np.ndarray:
        """``g_c^T C g_c`` per column of global coefficient vectors ``g (n, k)``."""
        x = self.h_inv @ g
        return np.sum(x * (self.noise_normal @ x), axis=0)


def covariance(problem, beta: float, z: np.ndarray, knots) -> Covariance:
    """``H^{-1}`` and ``C``'s blocks on the windows of four knots starting at ``knots`` (module notes): the
    knot blocks ``C_ij`` with ``|i - j| <= 3`` only, from ``Y = (T^T W Z^2 W T) H^{-1}`` computed block row by block
    row within the band."""
    h = problem.hessian(beta)
    c, info = scipy.linalg.lapack.dpotrf(h, lower=0)
    if info != 0:
        raise ValueError(f"the velocity's normal matrix is not positive definite (potrf info {info})")
    h_inv, info = scipy.linalg.lapack.dpotri(c, lower=0)
    h_inv = np.triu(h_inv) + np.triu(h_inv, 1).T
    m = problem.weighted_normal((problem.weights * z) ** 2)
    n, nz, bw = problem.size, problem.basis.disk.size, problem.bandwidth()
    y = np.empty((n, n))
    for r0 in range(0, n, nz):
        r1, c0 = min(n, r0 + nz), max(0, r0 - bw)
        c1 = min(n, r1 + bw)
        y[r0:r1] = m[r0:r1, c0:c1] @ h_inv[c0:c1]
    starts = sorted({int(k) for k in np.ravel(knots)})
    band: dict = {}  # (i, j), i <= j <= i + 3: C_ij = H^-1[:, K_i]^T Y[:, K_j]
    for k in starts:
        for i in range(k, k + 4):
            for j in range(i, k + 4):
                if (i, j) not in band:
                    band[i, j] = h_inv[:, i * nz : (i + 1) * nz].T @ y[:, j * nz : (j + 1) * nz]
    blocks = {}
    for k in starts:
        rows = [[band[i, j] if i <= j else band[j, i].T for j in range(k, k + 4)] for i in range(k, k + 4)]
        blocks[k] = np.block(rows)
    return Covariance(h_inv, m, blocks, nz)


@dataclass(frozen=True)
class TemporalPrior:
    """The temporal prior a cine volume's velocity was fitted with (:mod:`wss_nlp.vessel.cycle3d`): its ``gamma``,
    the generalized eigenpairs ``H X = M X diag(mu)``, ``X^T M X = I`` of the velocity's normal matrix and the
    penalty's Gram matrix ``M`` that the fit computed, and the temporal modes' eigenvalues ``lam`` and
    multiplicities ``mult`` (``k = 0 .. n // 2``; :func:`wss_nlp.vessel.cycle3d.temporal_eigenvalues`,
    :func:`~wss_nlp.vessel.cycle3d.mode_multiplicity`)."""

    gamma: float
    mu: np.ndarray
    x: np.ndarray
    lam: np.ndarray
    mult: np.ndarray


class _PriorSpectrum:
    """``H X = M X diag(mu)``, ``X^T M X = I`` and the modes' shifts ``c_k`` (module notes, "Under the temporal
    prior"): the per-frame covariance, and the wall mean's variance and ``beta`` derivative over the frames."""

    def __init__(self, problem, prior: TemporalPrior, n: int, m: np.ndarray):
        if prior.lam.size != n // 2 + 1:
            raise ValueError(f"the temporal prior has {prior.lam.size} modes; {n} frames have {n // 2 + 1}")
        self.n = n
        self.mu, self.x = prior.mu, prior.x
        self.shift = self.mu[None, :] + prior.gamma / (np.pi * problem.length_mm) * prior.lam[:, None]
        self.mult = prior.mult  # the real DFT's modes k = 0 .. n // 2 and how many they stand for
        self.q = self.x.T @ m @ self.x

    def covariance(self) -> np.ndarray:
        """``C = (1/n) sum_k S_k R S_k`` (dense)."""
        inv = 1.0 / self.shift  # (modes, size)
        omega = np.einsum("k,ki,kj->ij", self.mult / self.n, inv, inv)
        return self.x @ (self.q * omega) @ self.x.T

    def mean_variance_and_solve(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For the wall mean's gradients ``g (n, size, 3)`` (per frame and component): the variance per component
        ``(3,)`` for unit noise scales (``sum_c s_c^2 var_c`` is the mean's) and ``J^{-1} g`` ``(n, size, 3)``."""
        hat = np.fft.rfft(g, axis=0)  # (modes, size, 3)
        var = np.zeros(g.shape[2])
        solved = np.empty_like(hat)
        for k in range(hat.shape[0]):
            for part in (hat[k].real, hat[k].imag):
                y = (self.x.T @ part) / self.shift[k][:, None]  # (size, 3): D_k X^T ghat_k
                var += self.mult[k] / self.n * np.einsum("ic,ij,jc->c", y, self.q, y)
            solved[k] = self.x @ ((self.x.T @ hat[k]) / self.shift[k][:, None])
        return var, np.fft.irfft(solved, n=self.n, axis=0)


def _prior_covariance(problem, z: np.ndarray, knots, prior: TemporalPrior, n: int):
    """:func:`covariance` under the temporal prior: ``C``'s window blocks from the dense ``C`` and the spectrum
    (``Covariance.h_inv`` is then unused: the wall mean goes through the spectrum)."""
    m = problem.weighted_normal((problem.weights * z) ** 2)
    spectrum = _PriorSpectrum(problem, prior, n, m)
    c = spectrum.covariance()
    nz = problem.basis.disk.size
    blocks = {int(k): c[int(k) * nz : (int(k) + 4) * nz, int(k) * nz : (int(k) + 4) * nz] for k in np.ravel(knots)}
    return Covariance(np.zeros((0, 0)), m, blocks, nz), spectrum


def _directions(pieces: wss3d.WallPieces, f: np.ndarray, mu: float) -> np.ndarray:
    """``K (m, c, q)``: ``d (f . tau) / d d_u[c, q]`` at each point (module notes), ``f (m, 3)`` unit tangents."""
    n, minv = pieces.normal, pieces.minv
    mn = np.einsum("mqb,mb->mq", minv, n)
    mf = np.einsum("mqb,mb->mq", minv, f)
    return -mu * wss3d.PER_MM * (f[:, :, None] * mn[:, None, :] + n[:, :, None] * mf[:, None, :])


def vessel_band(pieces: wss3d.WallPieces, velocity, sigma: np.ndarray, tau: np.ndarray, ring_weights: np.ndarray,
                area_weights: np.ndarray, mu: float, prior: TemporalPrior | None = None) -> VesselBand:  # fmt: skip
    """The band of the WSS at the wall points of ``pieces`` (module notes).

    Parameters
    ----------
    pieces : wss3d.WallPieces
        At the ``ns x np`` wall points (``s`` major: each plane's points share ``s``), for ``velocity``'s basis.
    velocity : wss_nlp.vessel.velocity3d.Velocity3DResult
        The fit (its problem, beta and coefficients ``(nt, n, 3)``).
    sigma : (V, 3)
        Voxel noise std (m/s) per world component (:func:`wss_nlp.vessel.velocity3d.velocity_noise`).
    tau : (nt, ns, np, 3)
        The reconstructed WSS vectors (Pa), where ``|tau|`` is linearized.
    ring_weights : (ns, np)
        Each plane's weights of its mean (rows sum to one).
    area_weights : (ns, np)
        The wall mean's weights (zero off the covered wall; sum one, or all zero: no covered wall).
    mu : float
        Viscosity (Pa s).
    prior : TemporalPrior or None
        The temporal prior the frames were fitted with (None: each frame's own fit).

    Notes
    -----
    ``d_u[c, q] = sum_{a, j} B_q[a] D_q[j] a[k + a, j, c]`` with ``(B_q, D_q) = (B', w), (B, w_rho), (B, w_theta)``,
    ``B`` the four B-splines' values at the plane's ``s``. With ``P_qr = sum_{a, b} B_q[a] B_r[b] C[(k + a), (k +
    b)]`` (``n_z x n_z``, per plane) a functional ``sum_p omega_p f_p . tau_p`` over a plane's points has the variance
    ``sum_c venc_c^2 sum_{q, r} v_cq^T P_qr v_cr`` with ``v_cq = sum_p omega_p K_p[c, q] D_{q, p}`` (a single point:
    ``omega = 1`` there): a few ``n_z``-vectors per point, no ``4 n_z``-vector per point and component.
    """
    t0 = time.perf_counter()
    problem = velocity.problem
    nt, ns, nph, _ = tau.shape
    nz = problem.basis.disk.size
    z, scale = _factor(sigma)
    knots = pieces.knot.reshape(ns, nph)
    if not np.all(knots == knots[:, :1]):
        raise ValueError("the band's wall points must lie on planes of one s each (an ns x np grid, s major)")
    plane_knots = knots[:, 0]
    spectrum = None
    if prior is not None and prior.gamma > 0 and nt > 1:
        cov, spectrum = _prior_covariance(problem, z, plane_knots, prior, nt)
    else:
        cov = covariance(problem, velocity.beta, z, plane_knots)
    b_of = np.stack([pieces.db, pieces.b, pieces.b], axis=1).reshape(ns, nph, 3, 4)[:, 0]  # (ns, q, a)
    d = np.stack([pieces.w, pieces.w_rho, pieces.w_theta], axis=1).reshape(ns, nph, 3, nz)  # (ns, np, q, j)
    p_mat = np.stack([np.einsum("qa,ajbk,rb->qrjk", b_of[i], cov.block(k).reshape(4, nz, 4, nz), b_of[i])
                      for i, k in enumerate(plane_knots)])  # (ns, q, r, nz, nz)  # fmt: skip
    s2 = scale**2
    # per point: E_qr = D_q^T P_qr D_r, then var = sum_c s_c^2 K[c]^T E K[c]
    e_pt = np.empty((ns, nph, 3, 3))
    for q in range(3):
        for r in range(3):
            e_pt[..., q, r] = np.sum(np.matmul(d[:, :, q, :], p_mat[:, q, r]) * d[:, :, r, :], axis=-1)
    e_ax = pieces.t - np.sum(pieces.t * pieces.normal, axis=1, keepdims=True) * pieces.normal  # (I - n n^T) t
    k_ax = _directions(pieces, e_ax, mu).reshape(ns, nph, 3, 3)
    var_axial = np.einsum("ipcq,ipqr,ipcr,c->ip", k_ax, e_pt, k_ax, s2)
    axial_std = np.broadcast_to(np.sqrt(np.maximum(var_axial, 0.0)), (nt, ns, nph)).copy()
    plane_std = np.empty((nt, ns))
    total = float(np.sum(area_weights))
    lap = problem.gram_laplace / (np.pi * problem.length_mm)
    smooth = problem.gram_smooth / (np.pi * problem.length_mm)
    var_mean = d_beta = d_kappa = mean = 0.0
    grads = np.zeros((nt, problem.size, 3))  # the wall mean's gradient in each frame's coefficients
    for t in range(nt):
        vec = tau[t].reshape(-1, 3)
        mag = np.linalg.norm(vec, axis=1)
        f = np.divide(vec, mag[:, None], out=np.zeros_like(vec), where=mag[:, None] > 0)
        k_f = _directions(pieces, f, mu).reshape(ns, nph, 3, 3)
        v = np.einsum("ip,ipcq,ipqj->icqj", ring_weights, k_f, d)
        var_p = np.einsum("icqj,iqrjk,icrk,c->i", v, p_mat, v, s2)
        plane_std[t] = np.sqrt(np.maximum(var_p, 0.0))
        if total > 0:
            mean += float(np.sum(area_weights.ravel() * mag)) / nt
            u = np.einsum("ip,ipcq,ipqj->icqj", area_weights / nt, k_f, d)
            g = np.zeros((problem.size, 3))  # the wall mean's gradient in the coefficients
            for i, k in enumerate(plane_knots):
                g[k * nz : (k + 4) * nz] += np.einsum("qa,cqj->ajc", b_of[i], u[i]).reshape(4 * nz, 3)
            grads[t] = g
            if spectrum is None:  # each frame's own fit: the frames' noise independent
                x = cov.h_inv @ g
                var_mean += float(np.sum(s2 * np.sum(x * (cov.noise_normal @ x), axis=0)))
                a = velocity.coefficients[t]
                d_beta -= float(np.sum(x * (lap @ a)))
                d_kappa -= float(np.sum(x * (smooth @ a)))
    if spectrum is not None and total > 0:  # the prior ties the frames: their noise is correlated
        var_c, x_all = spectrum.mean_variance_and_solve(grads)
        var_mean = float(np.sum(s2 * var_c))
        a_all = np.asarray(velocity.coefficients, float)
        d_beta = -float(np.einsum("tic,ij,tjc->", x_all, lap, a_all))
        d_kappa = -float(np.einsum("tic,ij,tjc->", x_all, smooth, a_all))
    if total <= 0:
        mean = var_mean = d_beta = d_kappa = np.nan
    seconds = time.perf_counter() - t0
    log.info("band: %d wall points x %d frames, %.2f s", ns * nph, nt, seconds)
    frames = (
        "each frame's own fit" if prior is None or spectrum is None else f"the temporal prior (gamma {prior.gamma:.3g})"
    )
    return VesselBand(axial_std, plane_std, float(mean), float(np.sqrt(var_mean)), float(d_beta), float(d_kappa),
                      float(velocity.beta), float(problem.kappa), seconds, {"velocity_model": frames})  # fmt: skip
