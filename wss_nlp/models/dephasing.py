"""The dephasing pass: what the phase variation took from the magnitude, predicted from a velocity fit.

A phase-contrast voxel measures the complex signal ``rho chi_Omega exp(i pi u / venc)``
averaged by the acquisition (Appendix B). Where the velocity varies within
that average, the phases partly cancel and the magnitude under-reports the
lumen, which biases the geometry step. Given a velocity reconstruction the
loss can be predicted and undone, and the geometry and velocity solved
again (:func:`correct`):

* box model (voxel means, Sec. 7): the factors
  ``D_i = |mean_{V_i cap Omega} e^{i theta}| <= 1``
  (:func:`wss_nlp.models.measurement.dephasing_factors`) divide the normalized
  magnitude of the wall voxels; the velocity data stay as they are.
* k-space model (:mod:`wss_nlp.models.kspace`): every voxel mixes the phases of
  its PSF neighbourhood, the lumen's plateau included, so the loss
  ``|K chi| - |K chi e^{i theta}|`` is added back on the geometry window,
  the raw magnitude is normalized again with the plateau level the
  prediction implies, and the velocity data are corrected for the
  nonlinearity of the phase (:func:`wss_nlp.models.kspace.dephasing_correction`).
  Each pass is judged by how well its state explains the measured
  magnitude (``Correction.misfit_moving``, the magnitude predicted with the
  phases, against the state before: ``misfit_still`` of the first geometry
  fit, which assumed none), and undone if it explains it worse.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import acquisition as acq_model
from . import kspace
from . import measurement as meas
from ..core import radius as rad

#: What a slice says when the first k-space dephasing pass is undone.
UNEXPLAINED_NOTE = (
    "k-space model: the dephasing pass did not explain the magnitude image better than the geometry without "
    "it (velocity detail finer than the acquired voxels?); it was undone, the wall may be biased by dephasing"
)


@dataclass
class Correction:
    """Outcome of :func:`correct`: whether to use it, the loss factors and the corrected data."""

    factors: np.ndarray  # box: D_i of the lumen voxels; k-space: moving / still where the signal exceeds 1/2
    magnitude: np.ndarray  # corrected normalized magnitude (ny, nx)
    velocity: np.ndarray  # corrected velocity image (ny, nx), m/s
    signal: np.ndarray | None = None  # k-space: the predicted magnitude (raw units, background included)
    window: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # k-space: voxels the misfits use
    misfit_still: float = float("nan")  # rms of raw - m0 - scale |K chi| on ``window`` (no phase)
    misfit_moving: float = float("nan")  # the same with the predicted phases, |K chi e^{i theta}|

    @property
    def worth_a_pass(self) -> bool:
        """Some voxel loses more than :data:`wss_nlp.models.measurement.DEPHASING_THRESHOLD` of its magnitude."""
        return bool(np.min(self.factors, initial=1.0) < 1 - meas.DEPHASING_THRESHOLD)


def correct(
    m, raw, m0: float, velocity_image, vp, velocity_at, venc: float, coefficients, center, grid, psf, window=None
):
    """Predict the dephasing of the data from ``velocity_at`` and return the corrected data (:class:`Correction`).

    Parameters
    ----------
    m : (ny, nx) normalized magnitude; raw : (ny, nx) the magnitude as measured; m0 : its background level
    velocity_image : (ny, nx) measured velocity, m/s
    vp : wss_nlp.models.velocity.VelocityProblem of the current geometry (its lumen voxels and weights)
    velocity_at : callable ``(x, y) -> u`` in m/s at points in mm (a GCV-beta fit keeps wall layers)
    venc : float, m/s; coefficients, center : the current radius function
    psf : wss_nlp.models.kspace.PSF or None (box model)
    window : flat voxel indices for the misfits (k-space; default: the geometry window of this state), so that
        states with different walls are compared on the same voxels
    """
    model = acq_model.of(psf)
    return _CORRECTIONS[type(model)](
        m, raw, m0, velocity_image, vp, velocity_at, venc, coefficients, center, grid, psf, window
    )


def _correct_kspace(m, raw, m0, velocity_image, vp, velocity_at, venc, coefficients, center, grid, psf, window):
    """The k-space model's correction (:func:`correct`): the PSF's phase mixing on a window about the wall."""
    reach = float(np.max(rad.evaluate(coefficients, rad.uniform_angles(360))))
    out = kspace.window_index(grid, center, reach, psf)
    out = out if window is None else np.union1d(out, window)
    still, moving, phase_error = kspace.dephasing_correction(grid, vp.voxels, velocity_at, venc, psf, out)
    flat = np.asarray(raw, dtype=float).ravel()
    measured = flat[out] - m0
    scale = kspace.signal_scale(flat[out], m0, moving)
    at = np.ones(out.size, bool) if window is None else np.isin(out, window)
    still_fit = measured - kspace.signal_scale(flat[out], m0, still) * still
    factors = (moving / np.maximum(still, 1e-12))[still > 0.5]
    m_corr = (flat - m0) / scale
    m_corr[out] += still - moving
    signal = np.zeros(flat.size)
    signal[out] = scale * moving
    u_corr = np.array(velocity_image, dtype=float).ravel()
    u_corr[vp.voxels.index] -= np.where(vp.weights > 0, phase_error, 0.0)
    shape = np.shape(m)
    return Correction(
        factors,
        np.maximum(m_corr, 0.0).reshape(shape),
        u_corr.reshape(shape),
        signal.reshape(shape),
        out[at],
        float(np.sqrt(np.mean(still_fit[at] ** 2))),
        float(np.sqrt(np.mean((measured - scale * moving)[at] ** 2))),
    )


def _correct_voxel_means(m, raw, m0, velocity_image, vp, velocity_at, venc, coefficients, center, grid, psf, window):
    """The voxel-mean model's correction (:func:`correct`): each wall voxel's magnitude divided by its predicted
    dephasing factor; the velocity stays as measured."""
    m_corr = np.array(m, dtype=float).ravel()
    factors = meas.dephasing_factors(vp.voxels, velocity_at, venc, near_wall=(coefficients, grid.h))
    m_corr[vp.voxels.index] = np.clip(m_corr[vp.voxels.index] / np.maximum(factors, 1e-3), 0.0, 1.0)
    return Correction(factors, m_corr.reshape(np.shape(m)), np.asarray(velocity_image, dtype=float))


#: The correction of each measurement model (dispatch on the model's type).
_CORRECTIONS = {acq_model.VoxelMeans: _correct_voxel_means, acq_model.KSpace: _correct_kspace}
