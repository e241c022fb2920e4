#!/usr/bin/env python
"""Calibrate the ``low_re`` near-wall family on the channel DNS (and only on it).

The four constants of Reichardt's form, ``kappa``, ``C``, ``B1``, ``B2``, each ``p_inf + p_low Re_min /
max(Re_tau, Re_min)``, are fitted by least squares in U+ jointly to the four channel DNS mean profiles of the
Madrid group (Re_tau 186, 547, 934, 2004; ``wss_nlp/data/channel_dns``), on 400 points per profile uniform in
ln y+ from 0.2 to the centreline (monotone cubic interpolation of each file), each profile with its own wake
``a2 eta^2 + a3 eta^3 + a4 eta^4`` (``eta = y+ / Re_tau``, zero value and slope at the wall) fitted beside the
constants and discarded. Start: Reichardt's constants, no Reynolds-number dependence, no wake. The pipe DNS
takes no part (it is the test, ``scripts/low_re.py``).

Writes ``scripts/results/calibrate_low_re.md``: the constants (to be copied into
``wss_nlp/models/families/low_re.py``, whose values it checks), the misfit per profile (max |Delta U+| of the
fit with its wake, y+ <= 30, <= 100, all), the same for Reichardt's law with a fitted wake, and a leave-one-out
check of the Reynolds-number law (constants fitted to three profiles, the fourth predicted, only its wake
fitted).

    python scripts/calibrate_low_re.py   (a few seconds)
"""

import sys
import time

import numpy as np
import scipy.interpolate
import scipy.optimize

from _report import study_parser, write_report
from wss_nlp.models.families import low_re
from wss_nlp.models.families.wall_law import KAPPA, REICHARDT_C

#: Points per profile, uniform in ln y+ from Y_MIN to the centreline.
N_POINTS, Y_MIN = 400, 0.2
NAMES = ("kappa", "C", "B1", "B2")


def samples(name: str) -> tuple[np.ndarray, np.ndarray, float]:
    """``(y+, U+, Re_tau)`` of a channel profile on the calibration's points (monotone cubic interpolation)."""
    y, u, re_tau = low_re.channel_profile(name)
    points = np.exp(np.linspace(np.log(Y_MIN), np.log(re_tau), N_POINTS))
    return points, scipy.interpolate.PchipInterpolator(y, u)(points), re_tau


def wake_columns(y: np.ndarray, re_tau: float) -> np.ndarray:
    """``eta^2, eta^3, eta^4`` with ``eta = y / re_tau``: a smooth outer part with zero value and slope at the wall."""
    eta = y / re_tau
    return np.stack([eta**2, eta**3, eta**4], axis=1)


def inner(y: np.ndarray, params) -> np.ndarray:
    """Reichardt's form with constants ``(kappa, C, B1, B2)``."""
    k, c, b1, b2 = params
    return np.log1p(k * y) / k + c * (1 - np.exp(-y / b1) - y / b1 * np.exp(-y / b2))


def wake_fit(y, u, re_tau, params) -> np.ndarray:
    """Residual ``inner + wake - U+`` with the wake's three coefficients fitted by linear least squares."""
    r = inner(y, params) - u
    cols = wake_columns(y, re_tau)
    return r - cols @ np.linalg.lstsq(cols, r, rcond=None)[0]


def calibrate(profiles: list, re_min: float) -> np.ndarray:
    """``(4, 2)``: ``(p_inf, p_low)`` of kappa, C, B1, B2 fitted jointly to ``profiles`` [(y+, U+, Re_tau)]."""

    def params(theta, re_tau):
        low = re_min / max(re_tau, re_min)
        return theta[0:8:2] + theta[1:8:2] * low

    def residual(theta):
        out = []
        for i, (y, u, re_tau) in enumerate(profiles):
            wake = theta[8 + 3 * i : 11 + 3 * i]
            out.append(inner(y, params(theta, re_tau)) + wake_columns(y, re_tau) @ wake - u)
        return np.concatenate(out)

    start = np.zeros(8 + 3 * len(profiles))
    start[0:8:2] = (KAPPA, REICHARDT_C, 11.0, 3.0)  # Reichardt's law, no Reynolds-number dependence
    fit = scipy.optimize.least_squares(residual, start, xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=20000)
    return fit.x[:8].reshape(4, 2)


def misfit(y, u, re_tau, params) -> tuple[float, float, float]:
    """Max |Delta U+| of ``params`` with the wake fitted: y+ <= 30, y+ <= 100, everywhere."""
    r = np.abs(wake_fit(y, u, re_tau, params))
    return float(r[y <= 30].max()), float(r[y <= 100].max()), float(r.max())


def main(argv=None) -> None:
    p = study_parser(__doc__, seeds=0, h="")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    names = list(low_re.CHANNEL_PROFILES)
    profiles = [samples(n) for n in names]
    re_min = min(re for _, _, re in profiles)
    constants = calibrate(profiles, re_min)
    module = np.array([low_re.CONSTANTS[n] for n in NAMES])
    same = bool(np.allclose(module, constants, rtol=2e-5, atol=2e-6)) and abs(low_re.RE_MIN - re_min) < 1e-9

    lines = [
        "Calibration of the `low_re` near-wall family on the channel DNS (Hoyas & Jimenez; `wss_nlp/data/channel_dns`)."
        " No pipe data.",
        "Made by `python scripts/calibrate_low_re.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])) + "`.",
        "",
        f"p(Re_tau) = p_inf + p_low Re_min / max(Re_tau, Re_min), Re_min = {re_min:.5f} (the lowest profile's).",
        "",
        "| constant | p_inf | p_low |",
        "|---|---|---|",
    ]
    lines += [f"| {n} | {c[0]:.6g} | {c[1]:.6g} |" for n, c in zip(NAMES, constants)]
    lines += [
        "",
        f"The constants in `wss_nlp/models/families/low_re.py` {'equal' if same else 'DIFFER FROM'} these "
        "(relative 2e-5).",
        "",
        "Max |Delta U+| against each channel profile (its wake fitted): the calibrated family, Reichardt's law, and"
        " the family with constants fitted to the other three profiles (leave one out).",
        "",
        "| profile | Re_tau | low_re y+<=30 | <=100 | all | Reichardt y+<=30 | <=100 | all | left out y+<=30 | <=100 "
        "| all |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for i, (name, (y, u, re_tau)) in enumerate(zip(names, profiles)):
        own = misfit(y, u, re_tau, low_re.shape(re_tau) if same else _params(constants, re_tau, re_min))
        reich = misfit(y, u, re_tau, (KAPPA, REICHARDT_C, 11.0, 3.0))
        others = [q for j, q in enumerate(profiles) if j != i]
        left = calibrate(others, re_min)  # Re_min stays the family's: a law in the same variable
        out = misfit(y, u, re_tau, _params(left, re_tau, re_min))
        cells = " | ".join(f"{v:.3f}" for v in (*own, *reich, *out))
        lines.append(f"| {name} | {re_tau:.1f} | {cells} |")
    lines += ["", f"({time.perf_counter() - t0:.0f} s)"]
    write_report(args.out, "calibrate_low_re.md", lines)


def _params(constants: np.ndarray, re_tau: float, re_min: float) -> np.ndarray:
    return constants[:, 0] + constants[:, 1] * re_min / max(re_tau, re_min)


if __name__ == "__main__":
    main()
