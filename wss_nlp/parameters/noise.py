"""Noise levels of the data, each returned with how it was obtained (Theorems 2.1, 3.4 need them).

* :func:`magnitude_noise` (delta, for the normalized magnitude) and
  :func:`velocity_noise` (epsilon, per voxel, for the velocity);
* :func:`complex_noise_sigma` (the complex noise from the Rayleigh
  background) and :func:`phase_noise_std` (the phase noise it implies).

Residuals and noise levels are measured on the voxels where the model
depends on the unknown: the annulus of the geometry model (voxels that no
admissible R can change contribute pure noise, equally for every alpha) and
the voxels that meet the lumen for the velocity. This keeps the discrepancy
independent of the size of the field of view.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._lazy import scipy
from ..errors import NoiseEstimationError
from ..models.preprocess import robust_std, where_prefix

#: Fewest plateau voxels on which a noise level is estimated.
MIN_PLATEAU_VOXELS = 20


@dataclass
class NoiseEstimate:
    value: float
    method: str
    details: dict = field(default_factory=dict)


def _plateaus(mask: np.ndarray, width: int = 2):
    inner = scipy.ndimage.binary_erosion(mask, iterations=width)
    outer = ~scipy.ndimage.binary_dilation(mask, iterations=width)
    return inner, outer


def velocity_plateau(mask: np.ndarray) -> np.ndarray:
    """The lumen plateau on which :func:`velocity_noise` measures the noise without venc (two voxels inside)."""
    inner, _ = _plateaus(mask)
    return inner & scipy.ndimage.binary_erosion(np.ones_like(mask), iterations=1)


def magnitude_noise(
    m: np.ndarray,
    raw: np.ndarray,
    mask: np.ndarray,
    m0: float,
    m1: float,
    voxel_area: float,
    region: np.ndarray,
    source: str = "",
) -> NoiseEstimate:
    """Noise level ``delta`` of the normalized magnitude on the voxels ``region``.

    Notes
    -----
    ``delta^2 = |V| sum_{i in region} E[(m_i - f_i)^2]`` with ``f_i`` the
    noise-free volume fraction. On the lumen plateau (two voxels inside the
    bright region) ``f = 1`` and on the background plateau ``f = 0``, so
    their mean squares are measured there (they include the truncation
    ``T`` and the Rayleigh shape of the background) and applied to every
    voxel more than one voxel inside or outside the bright region. The two
    one-voxel rings at its edge, where the wall crosses, get the mean square
    of truncated Gaussian noise, ``truncated_error_msq(m_i, s)``, with the
    spread of the raw lumen signal
    ``s = 1.4826 MAD(raw on the lumen plateau) / (m1 - m0)`` and their own
    value ``m_i`` in place of the unknown ``f_i``. (Counting the full
    ``s^2`` on a band two voxels wide, as before, over-estimated delta by up
    to 1.47x: most of that band is not crossed by the wall.)
    Units: mm (an L^2(D) norm of a dimensionless image).
    """
    inner, outer = _plateaus(mask)
    where = where_prefix(source)
    if outer.sum() < MIN_PLATEAU_VOXELS:
        raise NoiseEstimationError(
            f"{where}cannot estimate the magnitude noise: no background in the field of view; "
            "pass --noise-magnitude (delta, mm) or a fixed --alpha"
        )
    if inner.sum() < MIN_PLATEAU_VOXELS:
        raise NoiseEstimationError(
            f"{where}cannot estimate the magnitude noise: the lumen is too small for a plateau; "
            "pass --noise-magnitude (delta, mm) or a fixed --alpha"
        )
    msq_in = float(np.mean((1 - m[inner]) ** 2))
    msq_out = float(np.mean(m[outer] ** 2))
    s_wall = robust_std(raw[inner]) / (m1 - m0)
    inside, outside = _plateaus(mask, width=1)
    flat_in, flat_out = inside.ravel()[region], outside.ravel()[region]
    flat_wall = ~(flat_in | flat_out)
    msq_wall = truncated_error_msq(m.ravel()[region][flat_wall], s_wall)
    total = msq_in * flat_in.sum() + msq_out * flat_out.sum() + float(np.sum(msq_wall))
    return NoiseEstimate(
        value=float(np.sqrt(voxel_area * total)),
        method="plateaus: mean squares on lumen and background plateaus; one-voxel rings at the edge: truncated "
        "Gaussian with the raw lumen spread, at their own value",
        details={
            "msq_lumen": msq_in,
            "msq_background": msq_out,
            "var_wall": s_wall**2,
            "msq_wall": float(np.mean(msq_wall)) if msq_wall.size else float("nan"),
            "n_lumen": int(flat_in.sum()),
            "n_background": int(flat_out.sum()),
            "n_wall": int(flat_wall.sum()),
        },
    )


def truncated_error_msq(f: np.ndarray, s: float) -> np.ndarray:
    """``E[(T(f + s Z) - f)^2]`` for ``Z ~ N(0, 1)`` and ``T`` the truncation to [0, 1].

    Notes
    -----
    With ``a = -f/s`` and ``b = (1 - f)/s``,
    ``s^2 (G(b) - G(a)) + f^2 Phi(a) + (1 - f)^2 (1 - Phi(b))``, where
    ``G(c) = Phi(c) - c phi(c)`` is the integral of ``z^2 phi(z)`` up to
    ``c``. It equals ``s^2`` for ``f`` far from 0 and 1 and ``s^2 / 2`` at
    ``f = 0`` or ``f = 1``: a voxel the wall does not cross loses the half
    of its noise that the truncation removes.
    """
    f = np.clip(np.asarray(f, float), 0.0, 1.0)
    if s <= 0:
        return np.zeros_like(f)
    a, b = -f / s, (1 - f) / s
    cdf = scipy.special.ndtr  # the standard normal CDF (what scipy.stats.norm.cdf calls, without its import cost)

    def g(c):
        return cdf(c) - c * np.exp(-0.5 * c**2) / np.sqrt(2 * np.pi)

    return s**2 * (g(b) - g(a)) + f**2 * cdf(a) + (1 - f) ** 2 * cdf(-b)


def complex_noise_sigma(raw: np.ndarray, mask: np.ndarray, signal: np.ndarray | None = None) -> float:
    """Per-channel standard deviation of complex Gaussian noise from the background.

    The background magnitude is Rayleigh distributed, ``E[|d|^2] = 2 sigma^2``.
    ``signal`` (raw units, the image's shape) is the predicted noise-free
    magnitude there, subtracted in power, ``E[|d|^2] = |s|^2 + 2 sigma^2``:
    a k-space acquisition's point-spread function carries the vessel's
    signal past the two voxels of background margin (measured: the plain
    estimate 1.2-1.9 times too high with a Hamming filter and twofold
    zero-filling).
    """
    _, outer = _plateaus(mask)
    if outer.sum() < MIN_PLATEAU_VOXELS:
        return float("nan")
    power = raw[outer] ** 2 - (0.0 if signal is None else np.asarray(signal)[outer] ** 2)
    return float(np.sqrt(max(float(np.mean(power)), 0.0) / 2))


def phase_noise_std(raw_at_voxels: np.ndarray, sigma: float, venc: float) -> np.ndarray:
    """Velocity noise per voxel, ``venc sigma / (pi |d_i|)`` capped at ``venc / sqrt(3)`` (Appendix B).

    ``sigma`` is the complex noise per channel in raw units; the cap is the
    standard deviation of a uniform phase (no signal). Units: those of ``venc``.
    """
    mag = np.maximum(np.asarray(raw_at_voxels, float), 1e-300)
    return np.minimum(venc * sigma / (np.pi * mag), venc / np.sqrt(3))


def velocity_noise(
    velocity: np.ndarray,
    raw: np.ndarray,
    mask: np.ndarray,
    voxel_index: np.ndarray,
    weights: np.ndarray,
    venc: float | None,
    source: str = "",
    signal: np.ndarray | None = None,
) -> NoiseEstimate:
    """Noise level ``epsilon`` of the velocity, in the units of the velocity misfit.

    Notes
    -----
    With ``venc`` (phase data) the phase noise of voxel i is about
    ``sigma / |d_i|`` for complex noise of standard deviation ``sigma`` per
    channel (from the Rayleigh background), so
    ``sigma_u,i = venc sigma / (pi |d_i|)``, capped at the standard deviation
    of a uniform phase, ``venc / sqrt(3)``; it grows as the magnitude falls
    towards the wall (Appendix B). Then
    ``epsilon^2 = sum_i w_i sigma_u,i^2 / sum_i w_i`` with the partial-volume
    weights of the misfit. Without ``venc`` (velocity data only) the level
    ``s`` on the lumen plateau is taken from the high frequencies there
    (``r = u - (mean of the 4 neighbours)`` has variance ``1.25 s^2`` for
    white noise) and, since the velocity still comes from a phase, scaled
    per voxel as the phase noise is: ``sigma_u,i = s m_p / |d_i|`` with
    ``m_p`` the plateau's median magnitude and ``|d_i|`` floored at
    ``sqrt(3) sigma / pi`` (where the cap above sets in).
    """
    where = where_prefix(source)
    sigma = complex_noise_sigma(raw, mask, signal)
    if venc is not None and np.isfinite(sigma):
        su = phase_noise_std(raw.ravel()[voxel_index], sigma, venc)
        eps = float(np.sqrt(np.sum(weights * su**2) / np.sum(weights)))
        return NoiseEstimate(
            eps,
            "phase noise: venc sigma / (pi |d_i|), sigma from the Rayleigh background",
            {"sigma_complex": sigma, "venc_m_s": venc, "per_voxel": su},
        )
    inner = velocity_plateau(mask)
    if inner.sum() < MIN_PLATEAU_VOXELS:
        raise NoiseEstimationError(
            f"{where}cannot estimate the velocity noise: no venc and the lumen is too small "
            "for a plateau; pass --noise-velocity (epsilon, m/s) or a fixed --beta"
        )
    u = velocity
    nb = 0.25 * (np.roll(u, 1, 0) + np.roll(u, -1, 0) + np.roll(u, 1, 1) + np.roll(u, -1, 1))
    r = (u - nb)[inner]
    s = robust_std(r) / np.sqrt(1.25)
    # a velocity from a phase has noise proportional to 1 / |d_i| (as with venc): scale the plateau's level by
    # the plateau magnitude over each voxel's, with |d_i| floored where the phase-noise cap of Appendix B sets in
    m_plateau = float(np.median(raw[inner]))
    floor = np.sqrt(3.0) * sigma / np.pi if np.isfinite(sigma) else 0.05 * m_plateau
    mag = np.maximum(raw.ravel()[voxel_index], max(floor, 1e-300))
    su = s * m_plateau / mag
    eps = float(np.sqrt(np.sum(weights * su**2) / np.sum(weights)))
    return NoiseEstimate(
        eps,
        "high-pass: MAD of u minus its 4-neighbour mean on the lumen plateau, scaled by plateau magnitude / |d_i|",
        {"plateau_m_s": s, "plateau_magnitude": m_plateau, "per_voxel": su},
    )


def given_or_velocity_noise(vp, raw, lumen, venc, given: float | None, where: str) -> NoiseEstimate:
    """Per-voxel velocity noise of a velocity problem ``vp``: ``given`` (``--noise-velocity``, m/s) or estimated
    (:func:`velocity_noise`)."""
    if given is not None:
        return NoiseEstimate(
            given,
            "given (--noise-velocity)",
            {"per_voxel": np.full(vp.data.size, given)},
        )
    return velocity_noise(
        vp.data_image, raw, lumen.noise_mask, vp.voxels.index, vp.weights, venc, where.rstrip(), lumen.signal
    )


def band_noise_levels(
    raw_magnitude: np.ndarray,
    mask: np.ndarray,
    m0: float,
    m1: float,
    u_index: np.ndarray,
    venc: float | None,
    sigma: float | None = None,
    signal: np.ndarray | None = None,
) -> tuple[float, np.ndarray, str]:
    """Per-voxel noise ``(sigma_m, sigma_u[u_index], how)`` from the complex noise level (Appendix B).

    ``sigma`` (per channel, raw units) is estimated from the Rayleigh
    background when not given.
    """
    how = "given"
    if sigma is None:
        sigma = complex_noise_sigma(raw_magnitude, mask, signal)
        how = "Rayleigh background" + (", predicted PSF tails subtracted" if signal is not None else "")
    if not np.isfinite(sigma) or sigma <= 0:
        raise NoiseEstimationError(
            "cannot estimate the complex noise level for the uncertainty band (no background "
            "in the field of view); pass --noise-sigma"
        )
    if venc is None:
        raise NoiseEstimationError("the uncertainty band needs venc (phase data) to convert phase noise to velocity")
    sigma_u = phase_noise_std(np.asarray(raw_magnitude, float).ravel()[u_index], sigma, venc)
    return (
        float(sigma / (m1 - m0)),
        sigma_u,
        f"sigma = {sigma:.4g} ({how}); sigma_m = sigma/(m1-m0), sigma_u,i = venc sigma/(pi |d_i|)",
    )
