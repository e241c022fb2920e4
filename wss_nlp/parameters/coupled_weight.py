"""The coupled method's velocity weight from the data: the likelihood weight of the estimated noise levels.

:func:`wss_nlp.models.coupled.likelihood_weight` is the formula; here both noise levels are estimated
(:mod:`wss_nlp.parameters.noise`) or the given weight is taken (``--velocity-weight``).
"""

from __future__ import annotations

import numpy as np

from ..models import geometry as geo
from ..models.coupled import likelihood_weight
from . import noise as nl


def coupled_weight(given: float | None, problem, gopt, raw, norm, mask, velocity_image, venc, where, signal=None):
    """``(weight, how)``: ``given`` (``--velocity-weight``), or the likelihood weight from the estimated noise
    levels (:func:`weight_from_data`)."""
    if given is not None:
        return given, {"weight_method": "given (--velocity-weight)"}
    weight, how = weight_from_data(problem, gopt, raw, norm, mask, velocity_image, venc, where, signal)
    how["weight_method"] = "likelihood: W sigma_m^2 / sigma_u^2 from the estimated noise levels"
    return weight, how


def weight_from_data(
    problem: geo.GeometryProblem,
    gopt: geo.GeometryOptions,
    raw_magnitude,
    norm,
    mask,
    velocity_image,
    venc: float | None,
    source: str = "",
    signal=None,
) -> tuple[float, dict]:
    """The likelihood weight with both noise levels estimated (:mod:`wss_nlp.parameters`); also returns how.

    ``sigma_u`` for a voxel fully inside the lumen: ``venc sigma / (pi m1)``
    with ``sigma`` from the Rayleigh background and ``m1`` the raw lumen
    level (phase data), else the high-pass estimate on the lumen plateau.
    ``signal`` (raw units, the image the geometry predicts) is subtracted
    from the background before ``sigma`` is measured (the PSF's tails,
    :func:`wss_nlp.parameters.noise.complex_noise_sigma`).
    """
    annulus = geo.fitted_voxels(problem, gopt)
    delta = nl.magnitude_noise(
        problem.magnitude, raw_magnitude, mask, norm.m0, norm.m1, problem.grid.voxel_area, annulus, source
    )
    sigma = nl.complex_noise_sigma(raw_magnitude, mask, signal=signal)
    if venc is not None and np.isfinite(sigma) and sigma > 0:
        sigma_u, how = venc * sigma / (np.pi * norm.m1), "venc sigma / (pi m1), sigma from the Rayleigh background"
    else:
        est = nl.velocity_noise(velocity_image, raw_magnitude, mask, np.zeros(0, int), np.zeros(0), None, source)
        sigma_u, how = est.value, est.method
    weights = problem.grid.voxel_area * np.clip(problem.magnitude, 0.0, 1.0) ** 2
    lam = likelihood_weight(delta.value, annulus.size, problem.grid.voxel_area, sigma_u, float(np.sum(weights)))
    return lam, {"delta_mm": delta.value, "sigma_u_m_s": float(sigma_u), "sigma_u_method": how}
