r"""Integrals over one cardiac cycle from frames at given trigger times: weights, TAWSS, OSI, bridging.

With frames at trigger times :math:`t_0 < \dots < t_{n-1}` in a cycle of length :math:`T`, integrals over
the cycle use the periodic trapezoid rule, weights
:math:`w_k = (t_{k+1} - t_{k-1})/2` with :math:`t_{-1} = t_{n-1} - T`, :math:`t_n = t_0 + T`
(exact for trigonometric polynomials of degree below :math:`n/2` at equal spacing). Then, per wall point,

.. math::

    \mathrm{TAWSS} = \frac{1}{T}\sum_k w_k |\tau_k|, \qquad
    \mathrm{OSI} = \frac12\Big(1 - \frac{|\sum_k w_k \tau_k|}{\sum_k w_k |\tau_k|}\Big),

in Pa and dimensionless (the file contract), :math:`\tau_k` the WSS (a vector, or a signed scalar on a
slice's wall). A frame that failed is bridged by linear interpolation in time between its periodic
neighbours.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError


def cycle_weights(times_ms, period_ms: float) -> np.ndarray:
    """Periodic trapezoid weights (ms) of the frames over one cycle (see the module notes)."""
    t = np.asarray(times_ms, dtype=float)
    if t.size == 0 or np.any(np.diff(t) <= 0):
        raise InputError(f"trigger times must increase, got {t.tolist()}")
    if not period_ms > t[-1] - t[0]:
        raise InputError(f"the cardiac period {period_ms:g} ms must exceed the frames' span {t[-1] - t[0]:g} ms")
    if t.size == 1:
        return np.array([float(period_ms)])
    before = np.concatenate([[t[-1] - period_ms], t[:-1]])
    after = np.concatenate([t[1:], [t[0] + period_ms]])
    return (after - before) / 2


def tawss_osi(tau: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(TAWSS in Pa, OSI)`` per column of ``tau (nt, nphi)`` with the cycle weights (module notes)."""
    tau = np.asarray(tau, dtype=float)
    w = np.asarray(weights, dtype=float)[:, None]
    total = float(np.sum(w))
    magnitude = np.sum(w * np.abs(tau), axis=0)
    net = np.abs(np.sum(w * tau, axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        osi = np.where(magnitude > 0, 0.5 * (1 - net / magnitude), 0.0)
    return magnitude / total, osi


def bridge(values: np.ndarray, good: np.ndarray, times_ms, period_ms: float) -> np.ndarray:
    """Rows of ``values (nt, ...)`` where ``good`` is False, linearly interpolated in time (periodically)."""
    values = np.array(values, dtype=float)
    t = np.asarray(times_ms, dtype=float)
    if good.all():
        return values
    if not good.any():
        raise InputError("every frame failed; nothing to interpolate from")
    tg = t[good]
    ext_t = np.concatenate([tg - period_ms, tg, tg + period_ms])
    flat = values.reshape(t.size, -1)
    ext_v = np.concatenate([flat[good]] * 3)
    for k in np.nonzero(~good)[0]:
        flat[k] = [np.interp(t[k], ext_t, ext_v[:, j]) for j in range(flat.shape[1])]
    return flat.reshape(values.shape)
