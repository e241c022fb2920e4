"""The uncertainty band of a single slice: the decoupled or coupled sensitivities with the slice's noise levels.

Stacks solved along z have their own (:mod:`wss_nlp.uncertainty.stack_band`, through
:meth:`wss_nlp.pipeline.fitters.ZCoupled.band`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..core import radius as rad
from ..errors import WssNlpError
from ..models import near_wall as nw
from ..models import wss as wss_mod
from ..uncertainty import sensitivity as sens
from . import steps

if TYPE_CHECKING:
    from .options import ReconstructionOptions
    from .state import SliceState


def _add_scale_spread(s, vp, v, w, near, viscosity_pa_s: float, sigma_m: float, sigma_u) -> None:
    """Let the band carry the law-of-the-wall scale's response to the noise (chain rule through l).

    The scale is a function of the data (``u_tau l = nu``), so the WSS moves
    with the data also through it: ``d tau/dp += (d tau/d log l)(d log l/dp)``
    with ``d log l/dp = -(dg/da_0)(da_0/dp)/(dg/d log l)`` for every input
    ``p`` (magnitude and velocity voxels, parameters; ``da_0/dp`` from the
    sensitivities, :func:`wss_nlp.models.near_wall.scale_sensitivity`). Also
    records the scale's own standard deviation (of ``log l``).
    """
    smat, _ = wss_mod.wss_matrix(v.basis, v.disk_map, viscosity_pa_s, w.phi.size)
    nu = viscosity_pa_s / near.density_kg_m3
    dg_da0, dg_dlog, dtau_dlog = nw.scale_sensitivity(vp, v.coefficients, v.beta, smat, nu)
    row = v.basis.base.size  # the layer's first coefficient a_0
    dlog_da0 = -dg_da0 / dg_dlog
    dlog_dp = dlog_da0 * s.d_coef_v[row]
    c = v.disk_map.coefficients
    ds = np.hypot(rad.evaluate(c, w.phi), rad.evaluate(c, w.phi, 1))
    dmean_dlog = float(np.sum(dtau_dlog * ds) / np.sum(ds))
    n_m, n_u = s.m_index.size, s.u_index.size
    # d tau/dp = (d tau/dc) (dc/dp) gains (d tau/d log l) (d log l/d a_0) (d a_0/dp): a term in d tau/d a_0
    s.d_tau_d_coef[:, s.d_coef_r.shape[0] + row] += dlog_da0 * dtau_dlog
    for name, cols in (("m", slice(0, n_m)), ("u", slice(n_m, n_m + n_u))):
        setattr(s, f"d_mean_d_{name}", getattr(s, f"d_mean_d_{name}") + dmean_dlog * dlog_dp[cols])
    s.d_tau = s.d_tau + np.outer(dtau_dlog, dlog_dp[n_m + n_u :])
    s.d_mean = s.d_mean + dmean_dlog * dlog_dp[n_m + n_u :]
    su = np.broadcast_to(np.asarray(sigma_u, float), (n_u,))
    var = sigma_m**2 * np.sum(dlog_dp[:n_m] ** 2) + np.sum((dlog_dp[n_m : n_m + n_u] * su) ** 2)
    near.scale_std_log = float(np.sqrt(var))


def slice_band(state: SliceState, w, viscosity_pa_s: float, options: ReconstructionOptions, coupled_result=None):
    """Sensitivities and the linearized band of one slice (sets ``w.tau_std``, ``w.mean_std``); returns
    ``(Sensitivity, note)``, or ``(None, why)`` when the band cannot be computed.

    The noise levels are the slice's (:func:`wss_nlp.pipeline.steps.noise_levels`, with the lumen as the last
    pass left it). A band that cannot be computed (no background for the noise level, no venc, a failed anchor
    re-solve) is reported in the note, not raised: the reconstruction itself is still valid. With a
    law-of-the-wall layer the band includes the scale's response to the noise; with a layer whose nearly
    equally good scales (an exponential layer's interval, a wall law's rival roots) give mean WSS further apart
    than the band, the note says so (:func:`wss_nlp.models.near_wall.scale_ambiguity_note`).
    """
    problem, g, vp, v, near = state.problem, state.geometry, state.velocity_problem, state.velocity, state.near
    try:
        if coupled_result is not None:
            s = sens.coupled(coupled_result, problem, options.geometry, options.velocity, viscosity_pa_s, w.phi.size)
        else:
            s = sens.decoupled(problem, options.geometry, g, vp, options.velocity, v, viscosity_pa_s, w.phi.size)
        sigma_m, sigma_u, how = steps.noise_levels(state.data, options, s.u_index, state.lumen)
    except WssNlpError as exc:
        return None, f"no uncertainty band: {exc}"
    if near is not None and near.consistent:
        _add_scale_spread(s, vp, v, w, near, viscosity_pa_s, sigma_m, sigma_u)
    w.tau_std, w.mean_std, s.mean_std_magnitude, s.mean_std_velocity = s.band(sigma_m, sigma_u)
    s.tau_std, s.mean_std = w.tau_std, w.mean_std
    s.noise.update({"sigma_m": sigma_m, "method": how})
    return s, nw.scale_ambiguity_note(near, w.mean, w.mean_std)
