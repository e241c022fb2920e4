"""Accuracy of a vessel wall map against a phantom's truth (issue 38's measures).

The truth is evaluated where the result's wall points are: :meth:`wss_nlp.synthetic.vessels.VesselTruth.locate`
gives each wall point's closest true wall point ``(s, phi)`` and signed distance (mm, positive outside), and the
true WSS, axial WSS, TAWSS and OSI are taken there. The visible part is the truth's (its centreline at least one
radius inside the field of view); sums are weighted by the wall area each point stands for
(:attr:`wss_nlp.vessel.reconstruct.VesselResult.area_mm2`).

* ``wss_rel_l2``: ``sqrt(sum a |tau - tau_true|^2 / sum a |tau_true|^2)`` over the covered visible wall, all
  frames;
* ``axial_rel_l2``: the same for ``tau . t`` (signed);
* ``wall_rms_mm`` (and ``wall_bias_mm``): the signed distance's RMS (mean) over the covered visible wall;
* ``coverage``: the area of the covered visible wall over the true visible wall's (the truth's wall surface over
  its visible s-intervals, :func:`visible_area`), so that a wall map that stops short of the visible part loses
  coverage too;
* ``tawss_rel_l2``, ``osi_rms``, ``osi_max`` (cines): TAWSS's relative L2 error, OSI's RMS and largest absolute
  error over the covered visible wall.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class VesselAccuracy:
    wss_rel_l2: float
    axial_rel_l2: float
    wall_rms_mm: float
    wall_bias_mm: float
    coverage: float
    tawss_rel_l2: float = float("nan")
    osi_rms: float = float("nan")
    osi_max: float = float("nan")
    mean_wss_pa: float = float("nan")  # area mean of |tau| over the covered visible wall (first frame)
    true_mean_wss_pa: float = float("nan")
    points: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


def visible_area(truth, ds: float = 0.25, n_phi: int = 256) -> float:
    """Area (mm^2) of the true wall over the truth's visible s-intervals: ``sum |x_s x x_phi| ds dphi`` with the
    tangents by central differences of :meth:`wss_nlp.synthetic.vessels.VesselTruth.wall_point` (midpoint rule)."""
    total = 0.0
    phi = np.linspace(-np.pi, np.pi, n_phi, endpoint=False) + np.pi / n_phi
    dphi = 2 * np.pi / n_phi
    for a, b in truth.visible:
        n = max(2, int(np.ceil((b - a) / ds)))
        step = (b - a) / n
        s = a + step * (np.arange(n) + 0.5)
        ss, pp = np.meshgrid(s, phi, indexing="ij")
        eps = 1e-4
        x_s = (truth.wall_point(ss + eps, pp) - truth.wall_point(ss - eps, pp)) / (2 * eps)
        x_p = (truth.wall_point(ss, pp + eps) - truth.wall_point(ss, pp - eps)) / (2 * eps)
        total += float(np.sum(np.linalg.norm(np.cross(x_s, x_p), axis=-1))) * step * dphi
    return total


def accuracy(result, truth) -> VesselAccuracy:
    """:class:`VesselAccuracy` of a :class:`wss_nlp.vessel.reconstruct.VesselResult` against a
    :class:`wss_nlp.synthetic.vessels.VesselTruth` (module notes)."""
    pts = result.wall_mm.reshape(-1, 3)
    s_t, phi_t, dist = truth.locate(pts, return_distance=True)
    visible = np.zeros(s_t.size, bool)
    for a, b in truth.visible:
        visible |= (s_t >= a) & (s_t <= b)
    area = result.area_mm2.ravel()
    covered = result.flags.ravel() == 0
    use = covered & visible
    coverage = float(np.sum(area[use]) / max(visible_area(truth), 1e-300))
    if not use.any():
        return VesselAccuracy(*(float("nan"),) * 4, coverage=coverage, points=0)
    a = area[use]
    nt = result.nt
    times = result.time_ms
    num = den = num_ax = den_ax = 0.0
    first_true = None
    for k in range(nt):
        t_ms = float(times[k]) if times.size == nt else None
        tau_true = truth.vessel.wss(s_t[use], phi_t[use], t_ms if t_ms is not None else 0.0)
        ax_true = truth.vessel.axial_wss(s_t[use], phi_t[use], t_ms if t_ms is not None else 0.0)
        tau = result.wss_pa[k].reshape(-1, 3)[use]
        ax = result.axial_pa[k].ravel()[use]
        num += float(np.sum(a * np.sum((tau - tau_true) ** 2, axis=1)))
        den += float(np.sum(a * np.sum(tau_true**2, axis=1)))
        num_ax += float(np.sum(a * (ax - ax_true) ** 2))
        den_ax += float(np.sum(a * ax_true**2))
        if k == 0:
            first_true = tau_true
    assert first_true is not None
    out = VesselAccuracy(
        wss_rel_l2=float(np.sqrt(num / den)),
        axial_rel_l2=float(np.sqrt(num_ax / den_ax)),
        wall_rms_mm=float(np.sqrt(np.sum(a * dist[use] ** 2) / np.sum(a))),
        wall_bias_mm=float(np.sum(a * dist[use]) / np.sum(a)),
        coverage=coverage,
        mean_wss_pa=float(np.sum(a * np.linalg.norm(result.wss_pa[0].reshape(-1, 3)[use], axis=1)) / np.sum(a)),
        true_mean_wss_pa=float(np.sum(a * np.linalg.norm(first_true, axis=1)) / np.sum(a)),
        points=int(use.sum()),
    )
    if result.tawss_pa is not None and nt > 1:
        tawss_true, osi_true, _ = truth.vessel.wss_cycle(s_t[use], phi_t[use])
        tawss = result.tawss_pa.ravel()[use]
        osi = result.osi.ravel()[use]
        out.tawss_rel_l2 = float(np.sqrt(np.sum(a * (tawss - tawss_true) ** 2) / np.sum(a * tawss_true**2)))
        out.osi_rms = float(np.sqrt(np.sum(a * (osi - osi_true) ** 2) / np.sum(a)))
        out.osi_max = float(np.max(np.abs(osi - osi_true)))
    return out
