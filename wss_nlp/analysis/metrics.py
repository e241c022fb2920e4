"""Errors of a reconstruction against a known truth (phantoms).

A fair comparison does not depend on where the reconstruction put its
centre: the true radius is measured from the *reconstructed* centre along
the same rays, and the true WSS is taken at the true wall point in the
direction of each reconstructed wall point.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..core import radius as rad


@dataclass
class Errors:
    radius_rel_l2: float  # ||R - R_true||_{L2} / ||R_true||_{L2}
    radius_max_mm: float  # max |R - R_true|
    wss_rel_l2: float  # ||tau - tau_true||_{L2} / ||tau_true||_{L2}
    mean_wss_rel: float  # (mean tau - mean tau_true) / mean tau_true, signed
    mean_wss_pa: float
    mean_wss_true_pa: float

    def as_dict(self) -> dict:
        return asdict(self)


def compare(center, phi, radius, wall_x, wall_y, tau, mean_tau, truth) -> Errors:
    """Errors of sampled reconstruction arrays against ``truth``.

    ``truth`` needs ``radius_about(center, phi)``, ``wss_at_points(x, y)``
    and ``mean_wss`` (a :class:`wss_nlp.synthetic.phantoms.Truth` or :class:`TruthTable`).
    """
    rt = truth.radius_about(center, phi)
    tt = truth.wss_at_points(wall_x, wall_y)
    return Errors(
        radius_rel_l2=float(np.linalg.norm(radius - rt) / np.linalg.norm(rt)),
        radius_max_mm=float(np.max(np.abs(radius - rt))),
        wss_rel_l2=float(np.linalg.norm(tau - tt) / np.linalg.norm(tt)),
        mean_wss_rel=float((mean_tau - truth.mean_wss) / truth.mean_wss),
        mean_wss_pa=float(mean_tau),
        mean_wss_true_pa=float(truth.mean_wss),
    )


def compare_slice(res, truth) -> Errors:
    """Errors of a :class:`wss_nlp.pipeline.reconstruct.SliceResult`."""
    w = res.wss
    return compare(res.geometry.center, w.phi, res.geometry.radius(w.phi), w.wall_x, w.wall_y, w.tau, w.mean, truth)


class TruthTable:
    """Truth read back from a truth file: wall polygon and WSS samples about the true centre.

    Interpolation on 1440 or more samples per wall is far below the errors
    it is used to measure (the samples are exact values).
    """

    def __init__(self, center, phi, radius, tau, mean_tau):
        self.center = np.asarray(center, dtype=float)
        order = np.argsort(phi)
        self.phi, self.r, self.tau = np.asarray(phi)[order], np.asarray(radius)[order], np.asarray(tau)[order]
        self.mean_wss = float(mean_tau)
        self.x = self.center[0] + self.r * np.cos(self.phi)
        self.y = self.center[1] + self.r * np.sin(self.phi)

    @classmethod
    def from_file(cls, path) -> TruthTable:
        """The truth stored by ``wss-nlp phantom --truth`` (first slice)."""
        return cls.all_from_file(path)[0]

    @classmethod
    def all_from_file(cls, path) -> list:
        """One :class:`TruthTable` per slice of a truth file."""
        from ..io.files import read_result

        return [cls(d["center"], d["phi"], d["radius"], d["tau"], d["mean_tau"]) for d in read_result(path)]

    @staticmethod
    def _periodic(phi_s, vals, phi):
        p = np.concatenate([phi_s - 2 * np.pi, phi_s, phi_s + 2 * np.pi])
        v = np.concatenate([vals, vals, vals])
        return np.interp(np.mod(phi, 2 * np.pi), p, v)

    def radius_about(self, center, phi):
        ang = np.mod(np.arctan2(self.y - center[1], self.x - center[0]), 2 * np.pi)
        dist = np.hypot(self.x - center[0], self.y - center[1])
        order = np.argsort(ang)
        return self._periodic(ang[order], dist[order], phi)

    def wss_at_points(self, x, y):
        ang = np.arctan2(np.asarray(y) - self.center[1], np.asarray(x) - self.center[0])
        return self._periodic(np.mod(self.phi, 2 * np.pi), self.tau, ang)


def truth_samples(truth, n: int = 1440) -> dict:
    """Exact samples of a phantom truth, as stored in a truth file."""
    phi = rad.uniform_angles(n)
    lumen = truth.lumen
    r, dr = lumen.radius(phi), lumen.radius(phi, 1)
    return {
        "center": np.asarray(lumen.center, dtype=float),
        "phi": phi,
        "radius": r,
        "dradius": dr,
        "tau": truth.flow.wss(phi),
        "mean_tau": truth.mean_wss,
    }


def _pad(coefficients, n_fourier: int) -> np.ndarray:
    """Coefficients ``[b0, b1..bN, a1..aN]`` of V_N embedded in V_n (n >= N)."""
    c = np.asarray(coefficients, dtype=float)
    n0 = rad.n_fourier_from_size(c.size)
    out = np.zeros(rad.n_coefficients(n_fourier))
    out[: n0 + 1] = c[: n0 + 1]
    out[n_fourier + 1 : n_fourier + 1 + n0] = c[n0 + 1 :]
    return out


def radius_h2_error(center, coefficients, truth, n_fourier: int = 64) -> float:
    """``||R - R_true||_{H^2} / ||R_true||_{H^2}`` (paper Table 1), R_true about the same centre.

    The true radius is projected onto V_64 (its higher harmonics are below
    1e-10 mm for the built-in phantoms).
    """
    phi = rad.uniform_angles(8 * n_fourier)
    ct = rad.fit(phi, truth.radius_about(center, phi), n_fourier)
    return float(rad.sobolev_norm(_pad(coefficients, n_fourier) - ct, 2) / rad.sobolev_norm(ct, 2))


def velocity_error(velocity_result, truth, n_rho: int = 64, n_t: int = 128) -> float:
    """``||v - v_ref||_{L2(B)} / ||v_ref||_{L2(B)}`` on the reference disk (paper Table 2 uses H^2).

    Notes
    -----
    ``v_ref = u_true o phi_true`` with ``phi_true`` the map of the
    reconstruction (same centre, ``r_in``, ``eta``) built on the true
    radius, as in the paper's Table 2; midpoint rule in ``rho`` (weight
    ``rho``) and uniform in ``t``. Needs a phantom truth with its flow
    (NaN for a truth read from a file).
    """
    flow = getattr(truth, "flow", None)
    if flow is None or velocity_result is None:
        return float("nan")
    dm = velocity_result.disk_map
    phi = rad.uniform_angles(512)
    rt = rad.fit(phi, truth.radius_about(dm.center, phi), 64)
    true_map = type(dm)(
        coefficients=rt, center=dm.center, eta=dm.eta, r_in=min(dm.r_in, float(np.min(rad.evaluate(rt, phi))))
    )
    rho = (np.arange(n_rho) + 0.5) / n_rho
    rr, tt = np.meshgrid(rho, rad.uniform_angles(n_t))
    v = (
        velocity_result.basis.evaluate(rr.ravel() * np.cos(tt.ravel()), rr.ravel() * np.sin(tt.ravel()))
        @ velocity_result.coefficients
    )
    x, y = true_map.forward(rr, tt)
    v_ref = flow.velocity(x, y).ravel()
    w = rr.ravel()
    return float(np.sqrt(np.sum(w * (v - v_ref) ** 2) / np.sum(w * v_ref**2)))


@dataclass
class CineErrors:
    """Errors of one slice of a time-resolved result against a time-resolved truth (wall means).

    The reference is the truth's WSS times ``scale``, the viscosity the result states over the truth's (the
    stress scales with the viscosity it is told; 1 where either file does not record it).
    """

    frames: int
    scale: float  # stated over true viscosity
    worst_frame_rel_peak: float  # max_k |mean tau_k - reference_k| / max_k |reference_k|
    rms_frame_rel_peak: float
    worst_frame_time_ms: float
    tawss_rel: float  # (wall-mean TAWSS - reference) / reference, signed; NaN where not computed
    osi_abs: float  # wall-mean OSI - truth's, signed
    radius_max_mm: float  # largest |mean radius - truth's| over the frames
    nu_rel: float = float("nan")  # fitted / true kinematic viscosity - 1 (NaN without a fit or a truth)
    nu_inside: bool | None = None  # the fit's interval holds the true kinematic viscosity

    def as_dict(self) -> dict:
        return asdict(self)


def compare_cine(result: dict, truth: dict, model: dict | None = None, true_nu: float | None = None) -> CineErrors:
    """Errors of a slice of a time-resolved result (:func:`wss_nlp.io.files.read_result`) against a
    time-resolved truth's slice; ``model`` the slice's cycle-model record
    (:func:`wss_nlp.io.files.read_cine_models`), ``true_nu`` the truth's kinematic viscosity (m^2/s)."""
    from ..errors import InputError

    t_res, t_true = np.asarray(result["time_ms"], float), np.asarray(truth["time_ms"], float)
    if t_res.shape != t_true.shape or not np.allclose(t_res, t_true, atol=1e-6):
        raise InputError(
            f"the result's {t_res.size} frames and the truth's {t_true.size} are not at the same trigger times"
        )
    stated, true = result.get("viscosity_pa_s"), truth.get("viscosity_pa_s")
    scale = float(stated / true) if stated and true else 1.0
    reference = scale * np.asarray(truth["mean_tau_t"], dtype=float)
    mean = np.asarray(result["mean_tau_t"], dtype=float)
    peak = float(np.max(np.abs(reference)))
    err = np.abs(mean - reference) / peak
    worst = int(np.nanargmax(err)) if np.any(np.isfinite(err)) else 0
    tawss = np.asarray(result.get("tawss", np.nan), dtype=float)
    truth_tawss = scale * float(np.mean(truth["tawss"]))
    tawss_rel = float(np.mean(tawss) / truth_tawss - 1) if np.all(np.isfinite(tawss)) else float("nan")
    osi = np.asarray(result.get("osi", np.nan), dtype=float)
    osi_abs = float(np.mean(osi) - np.mean(truth["osi"])) if np.all(np.isfinite(osi)) else float("nan")
    radius = np.nanmean(np.atleast_2d(result["radius"]), axis=1)
    radius_true = np.mean(np.atleast_2d(truth["radius"]), axis=1)
    out = CineErrors(
        int(t_res.size), scale, float(err[worst]), float(np.sqrt(np.nanmean(err**2))), float(t_res[worst]),
        tawss_rel, osi_abs, float(np.nanmax(np.abs(radius - radius_true))),
    )  # fmt: skip
    viscosity = (model or {}).get("viscosity", {})
    if true_nu and viscosity.get("mode") == "fit":
        out.nu_rel = float(viscosity["nu_m2_s"] / true_nu - 1)
        lo, hi = viscosity["nu_interval_m2_s"]
        out.nu_inside = bool(lo <= true_nu <= hi)
    return out
