"""Figures in the layout of the paper's Figures 1-5 (the only module drawing with matplotlib).

1. magnitude with the reconstructed contour (and the true wall when known);
2. R(phi), reconstructed and true;
3. raw velocity and the truncated velocity actually used;
4. reconstructed velocity (next to the true one when known);
5. WSS against angle with its mean (and the truth, and a band when known);
6. with ``--near-wall``: the near-wall voxels against the wall distance and the fitted profile.

Figures are :class:`matplotlib.figure.Figure` objects made without pyplot:
the user's backend is never changed, no global figure registry fills up,
and they display in notebooks and save anywhere (``fig.savefig``).
"""

from __future__ import annotations

import os

import numpy as np
from ..pipeline.results import SliceResult
from ..models.baselines import BaselineResult
from ..io.files import FailedSlice
from matplotlib.figure import Figure


def _subplots(*args, figsize, **kwargs):
    """``Figure.subplots`` on a figure of its own (what ``pyplot.subplots`` does, without pyplot's state)."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*args, **kwargs)


def _contour(ax, res, **kw):
    g = res.geometry
    phi = np.linspace(0, 2 * np.pi, 721)
    r = g.radius(phi)
    ax.plot(g.center[0] + r * np.cos(phi), g.center[1] + r * np.sin(phi), **kw)


def _image(ax, img, grid, **kw):
    return ax.imshow(img, origin="lower", extent=grid.extent(), interpolation="nearest", **kw)


def figure_geometry(res, truth=None):
    """Fig. 1 and 2: magnitude with contour; R(phi)."""
    fig, axes = _subplots(1, 2, figsize=(11, 4.6))
    ax = axes[0]
    im = _image(ax, res.magnitude, res.grid, cmap="gray", vmin=0, vmax=1)
    _contour(ax, res, color="tab:red", lw=1.2, label="reconstructed wall")
    phi = np.linspace(0, 2 * np.pi, 721)
    if truth is not None:
        rt = truth.radius_about(res.geometry.center, phi)
        ax.plot(
            res.geometry.center[0] + rt * np.cos(phi),
            res.geometry.center[1] + rt * np.sin(phi),
            "--",
            color="tab:cyan",
            lw=1,
            label="true wall",
        )
    ax.plot(*res.geometry.center, "+", color="tab:red")
    ax.set(xlabel="x [mm]", ylabel="y [mm]", title=f"normalized magnitude, h = {res.grid.h:g} mm")
    ax.legend(loc="lower right", fontsize=8)
    fig.colorbar(im, ax=ax, shrink=0.8)
    ax = axes[1]
    ax.plot(phi, res.geometry.radius(phi), color="tab:red", label=r"$R_\alpha^\delta$ (reconstructed)")
    if truth is not None:
        ax.plot(phi, rt, "--", color="tab:blue", label=r"$R^\dagger$ (true, about the same centre)")
    baseline = isinstance(res, BaselineResult)
    if not baseline:
        ax.axhspan(*res.geometry.box, color="0.92", zorder=0, label="box [r0, r1]")
    r = res.geometry.radius(phi)
    pad = 0.3 * (r.max() - r.min()) + 0.2
    title = (
        f"segmented wall ({res.method}: 50 % magnitude contour)"
        if baseline
        else rf"radius function, $\alpha$ = {res.geometry.alpha:g}"
    )
    ax.set(xlabel=r"$\varphi$ [rad]", ylabel="R [mm]", ylim=(r.min() - pad, r.max() + pad), title=title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def figure_velocity_data(res):
    """Fig. 3: raw velocity and the truncated velocity used in the fit."""
    fig, axes = _subplots(1, 2, figsize=(11, 4.6))
    raw = res.velocity_image
    lim = np.max(np.abs(raw))
    im = _image(axes[0], raw, res.grid, cmap="RdBu_r", vmin=-lim, vmax=lim)
    axes[0].set(title="velocity raw data [m/s]", xlabel="x [mm]", ylabel="y [mm]")
    fig.colorbar(im, ax=axes[0], shrink=0.8)
    used = np.full(raw.size, np.nan)
    used[res.velocity.voxel_index] = raw.ravel()[res.velocity.voxel_index]
    used = used.reshape(raw.shape)
    im = _image(axes[1], used, res.grid, cmap="viridis")
    _contour(axes[1], res, color="w", lw=0.8)
    axes[1].set(title=r"truncated data ($|V_i \cap \Omega| > 0$) [m/s]", xlabel="x [mm]")
    fig.colorbar(im, ax=axes[1], shrink=0.8)
    fig.tight_layout()
    return fig


def figure_velocity(res, truth=None):
    """Fig. 4: reconstructed velocity (and the true one)."""
    n = 2 if truth is not None else 1
    fig, axes = _subplots(1, n, figsize=(5.6 * n, 4.6), squeeze=False)
    xc, yc = res.grid.centers()
    rec = res.velocity.evaluate_physical(xc, yc)
    vmax = float(np.max(rec))
    if truth is not None:
        true = truth.flow.velocity(xc, yc)
        vmax = max(vmax, float(np.max(true)))
        im = _image(axes[0, 1], true, res.grid, cmap="viridis", vmin=0, vmax=vmax)
        axes[0, 1].set(title="true velocity [m/s]", xlabel="x [mm]")
        fig.colorbar(im, ax=axes[0, 1], shrink=0.8)
    im = _image(axes[0, 0], rec, res.grid, cmap="viridis", vmin=0, vmax=vmax)
    axes[0, 0].set(
        title=rf"reconstructed velocity [m/s], $\beta$ = {res.velocity.beta:g}", xlabel="x [mm]", ylabel="y [mm]"
    )
    fig.colorbar(im, ax=axes[0, 0], shrink=0.8)
    fig.tight_layout()
    return fig


def figure_wss(res, truth=None):
    """Fig. 5: WSS against angle with its arc-length mean."""
    fig, ax = _subplots(figsize=(8, 4.2))
    w = res.wss
    ax.plot(w.phi, w.tau, color="tab:red", lw=1.2, label=r"$\tau$ reconstructed")
    ax.axhline(w.mean, color="tab:red", ls=":", label=rf"mean {w.mean:.4g} Pa")
    std = getattr(w, "tau_std", None)
    if std is not None:
        ax.fill_between(w.phi, w.tau - 2 * std, w.tau + 2 * std, color="tab:red", alpha=0.2, label=r"$\pm 2\sigma$")
    if truth is not None:
        tt = truth.wss_at_points(w.wall_x, w.wall_y)
        ax.plot(w.phi, tt, color="tab:blue", lw=1.2, label=r"$\tau^\dagger$ true")
        ax.axhline(truth.mean_wss, color="tab:blue", ls=":", label=f"true mean {truth.mean_wss:.4g} Pa")
    ax.set(
        xlabel=r"$\varphi$ [rad]",
        ylabel=r"$\tau$ [Pa]",
        xlim=(0, 2 * np.pi),
        title=f"wall shear stress ({getattr(res, 'method', 'decoupled')})",
    )
    lo = min(0.0, float(np.min(w.tau)))
    ax.set_ylim(lo, 1.25 * max(float(np.max(w.tau)), truth.mean_wss if truth is not None else 0))
    ax.legend(fontsize=8, ncol=2, loc="lower right")
    fig.tight_layout()
    return fig


def figure_near_wall(res, truth=None):
    """Near-wall data against the distance to the wall, with the fitted profile: why the WSS came out as it did.

    Dots: measured velocity of each lumen voxel against the distance of its
    centre to the reconstructed wall (negative: centre outside; marker area
    ~ partial volume); circles: the fit's voxel means; line: the fitted
    velocity along the wall normal, averaged over the angle (and the true one
    for a phantom). Drawn for slices reconstructed with ``--near-wall``.
    """
    near = getattr(res, "near_wall", None)
    if near is None or not isinstance(res, SliceResult):
        return None
    g, v, grid = res.geometry, res.velocity, res.grid
    xc, yc = (a.ravel()[v.voxel_index] for a in grid.centers())
    t = np.arctan2(yc - g.center[1], xc - g.center[0])
    dist = g.radius(t) - np.hypot(xc - g.center[0], yc - g.center[1])
    reach = 4 * grid.h
    sel = dist < reach
    fig, ax = _subplots(figsize=(7.5, 4.4))
    measured = res.velocity_image.ravel()[v.voxel_index]
    ax.scatter(dist[sel], measured[sel], s=30 * v.voxel_fraction[sel], color="0.35", label="measured voxels")
    ax.scatter(dist[sel], v.fitted[sel], s=14, facecolors="none", edgecolors="tab:red", label="fitted voxel means")
    d = np.linspace(0, reach, 400)
    angles = np.linspace(0, 2 * np.pi, 73)[:-1]
    big_r = g.radius(angles)
    px = g.center[0] + (big_r[:, None] - d[None, :]) * np.cos(angles)[:, None]
    py = g.center[1] + (big_r[:, None] - d[None, :]) * np.sin(angles)[:, None]
    ax.plot(d, v.evaluate_physical(px, py).mean(axis=0), color="tab:red", lw=1.5, label="fitted profile (mean)")
    if truth is not None:
        ax.plot(d, truth.flow.velocity(px, py).mean(axis=0), color="tab:blue", lw=1.2, ls="--", label="true profile")
    title = f"near-wall model: {near.model}"
    if near.model != "plain":
        title += f", l = {near.scale_mm * 1000:.3g} um"
        ax.axvline(near.scale_mm, color="tab:green", ls=":", lw=1, label="layer scale l")
    ax.axvline(0, color="k", lw=0.6)
    ax.set(xlabel="distance of the voxel centre to the wall [mm]", ylabel="velocity [m/s]", title=title)
    ax.set_xlim(-grid.h, reach)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    return fig


FIGURES = {
    "fig1_2_geometry.png": figure_geometry,
    "fig3_velocity_data.png": lambda res, truth=None: figure_velocity_data(res),
    "fig4_velocity.png": figure_velocity,
    "fig5_wss.png": figure_wss,
    "fig6_near_wall.png": figure_near_wall,
}


def save_figures(res, folder, truth=None, prefix: str = "") -> list[str]:
    """Write all figures of one slice into ``folder``; returns the paths."""
    os.makedirs(folder, exist_ok=True)
    paths = []
    # classical baselines have a wall and a WSS but no velocity model
    names = [n for n in FIGURES if isinstance(res, SliceResult) or "velocity" not in n]
    for name in names:
        make = FIGURES[name]
        fig = make(res, truth)
        if fig is None:  # a figure that does not apply to this slice
            continue
        path = os.path.join(folder, prefix + name)
        fig.savefig(path, dpi=110)
        paths.append(path)
    return paths


def figure_parameter_choice(choice):
    """Residual (or criterion) against the parameter, with the threshold and the choice marked."""
    fig, ax = _subplots(figsize=(7, 4.2))
    sym = r"\alpha" if choice.name == "alpha" else r"\beta"
    if choice.rule in ("discrepancy", "lcurve") and choice.residuals.size:
        ax.loglog(choice.parameters, choice.residuals, "o-", ms=3, label="residual")
        if choice.rule == "discrepancy":
            ax.axhline(
                choice.threshold,
                color="tab:red",
                ls="--",
                label=rf"$\tau \cdot$ noise = {choice.tau:g} x {choice.noise:.3g}",
            )
        ax.set_ylabel("residual")
    elif choice.rule == "gcv" and choice.criterion.size:
        ax.loglog(choice.parameters, choice.criterion, "o-", ms=3, label="GCV")
        ax.set_ylabel("GCV")
    elif choice.rule == "balance" and choice.criterion.size:
        keep = choice.criterion > 0  # the last (least regularized) value has nothing to compare with
        what = "radius" if choice.name == "alpha" else "WSS"
        ax.loglog(
            choice.parameters[keep],
            choice.criterion[keep],
            "o-",
            ms=3,
            label=f"largest {what} difference to a smaller {choice.name} / its noise sd",
        )
        ax.axhline(choice.tau, color="tab:red", ls="--", label=rf"$\kappa$ = {choice.tau:g}")
        ax.set_ylabel("difference / noise sd")
    ax.axvline(choice.chosen, color="tab:green", label=rf"chosen ${sym}$ = {choice.chosen:.3g}")
    ax.set(
        xlabel=rf"${sym}$",
        title=f"{choice.name}: rule '{choice.rule}'" + ("" if choice.satisfied else " (inequality not reached)"),
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def save_parameter_figures(choices: dict, folder: str) -> list[str]:
    """One PNG per slice and parameter with a search to show."""
    os.makedirs(folder, exist_ok=True)
    paths = []
    for slice_name, per in choices.items():
        for ch in per.values():
            if ch.rule == "fixed":
                continue
            fig = figure_parameter_choice(ch)
            path = os.path.join(folder, f"{slice_name}_{ch.name}_{ch.rule}.png")
            fig.savefig(path, dpi=110)
            paths.append(path)
    return paths


def figure_band_check(phi, linearized, sampled, n_draws: int):
    """Linearized WSS standard deviation against a Monte-Carlo estimate, per angle."""
    fig, ax = _subplots(figsize=(8, 3.8))
    ax.plot(phi, sampled, color="tab:gray", lw=1.2, label=f"Monte Carlo ({n_draws} noise draws)")
    ax.plot(phi, linearized, color="tab:red", lw=1.2, ls="--", label="linearized (CasADi sensitivities)")
    ax.set(
        xlabel=r"$\varphi$ [rad]",
        ylabel=r"std of $\tau$ [Pa]",
        xlim=(0, 2 * np.pi),
        ylim=(0, None),
        title="uncertainty band: linearization vs sampling",
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def save_figure(fig, path: str, dpi: int = 120) -> str:
    """Write one figure as PNG (``dpi``: dots per inch; thumbnails take fewer)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".part.png"  # never a half-written figure under the final name
    fig.savefig(tmp, dpi=dpi)
    os.replace(tmp, path)
    return path


def figure_rates(deltas, curves: dict):
    """Log-log error against noise level, one panel per Sobolev index r; ``curves[(k, rule)]`` is (n_delta, 3)."""
    fig, axes = _subplots(1, 3, figsize=(12, 3.8))
    for r, ax in enumerate(axes):
        for (k, rule), errs in curves.items():
            ax.loglog(deltas, errs[:, r], "o-" if rule == "a priori" else "s--", label=f"k = {k}, {rule}")
            ref = errs[-1, r] * (np.asarray(deltas) / deltas[-1]) ** (1 - r / k)
            ax.loglog(deltas, ref, ":", color="gray", lw=0.8)
        ax.set(
            xlabel=r"noise level $\delta$",
            ylabel=rf"$\|R_\alpha - R\|_{{H^{r}}}$",
            title=f"r = {r} (dotted: slope 1 - r/k)",
        )
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return fig


def figure_sweep(
    rows: list,
    x: str,
    y: str,
    by: str | None = None,
    panels: str | None = None,
    logx: bool = False,
    title: str = "",
    ylabel: str | None = None,
):
    """A metric against a parameter from sweep rows: mean over seeds with +-1 standard deviation.

    One line per value of ``by`` (e.g. the method), one panel per value of
    ``panels`` (e.g. the phantom); failed cases are left out and counted in
    the legend. ``rows`` are the rows to draw (:func:`wss_nlp.app.sweep.plot`
    selects them and names the metric).
    """
    sel = rows
    pvals = list(dict.fromkeys(r[panels] for r in sel)) if panels else [None]
    fig, axes = _subplots(1, len(pvals), figsize=(5.6 * len(pvals), 4.3), squeeze=False)
    for ax, pv in zip(axes[0], pvals):
        part = [r for r in sel if panels is None or r[panels] == pv]
        for k, bv in enumerate(dict.fromkeys(r[by] for r in part) if by else [None]):
            line = [r for r in part if by is None or r[by] == bv]
            xs = sorted(set(r[x] for r in line))
            mean, std, failed = [], [], 0
            for xv in xs:
                vals = [float(r[y]) for r in line if r[x] == xv and r["status"] != "error"]
                vals = [v for v in vals if np.isfinite(v)]
                failed += sum(1 for r in line if r[x] == xv) - len(vals)
                mean.append(np.mean(vals) if vals else np.nan)
                std.append(np.std(vals) if vals else np.nan)
            label = (str(bv) if by else y) + (f" ({failed} failed)" if failed else "")
            ax.errorbar(xs, mean, yerr=std, marker="os^dv<>"[k % 7], capsize=3, label=label)
        if y.endswith("_bias"):
            ax.axhline(0.0, color="0.5", lw=0.8)
        ax.set(
            xlabel={"h": "voxel size h [mm]"}.get(x, x),
            ylabel=ylabel or y,
            title=(f"{panels} = {pv}" if panels else title),
        )
        if logx:
            ax.set_xscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if title and panels:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def figure_stack(results, spacing_mm: float):
    """Radius and WSS over the unrolled wall (angle x z) of a stack; failed slices are blank rows.

    With three velocity components the axial and circumferential WSS are drawn too.
    """
    n = len(results)
    ok = [r for r in results if not isinstance(r, FailedSlice)]
    phi = ok[0].wss.phi
    vector = all(getattr(r.wss, "vector", None) is not None for r in ok)
    maps = {
        "radius R [mm]": lambda r: r.geometry.radius(r.wss.phi),
        r"wall shear stress $\tau$ [Pa]": lambda r: r.wss.tau,
    }
    if vector:
        maps = {
            "radius R [mm]": maps["radius R [mm]"],
            r"axial WSS $\tau \cdot e_a$ [Pa]": lambda r: r.wss.vector.axial,
            r"circumferential WSS $\tau \cdot e_c$ [Pa]": lambda r: r.wss.vector.circumferential,
        }
    z = np.arange(n) * spacing_mm
    fig, axes = _subplots(1, len(maps), figsize=(6 * len(maps), 4.6), sharey=True)
    extent = (0, 360, z[0] - spacing_mm / 2, z[-1] + spacing_mm / 2)
    for ax, (label, get), cmap in zip(axes, maps.items(), ("viridis", "magma", "coolwarm")):
        data = np.full((n, phi.size), np.nan)
        for r in ok:
            data[r.index] = get(r)
        im = ax.imshow(
            np.ma.masked_invalid(data), origin="lower", aspect="auto", extent=extent, cmap=cmap, interpolation="nearest"
        )
        fig.colorbar(im, ax=ax, label=label)
        ax.set(xlabel=r"angle $\varphi$ [deg] (unrolled wall)", title=label)
    axes[0].set_ylabel("z [mm] (slice position)")
    failed = [i for i in range(n) if isinstance(results[i], FailedSlice)]
    if failed:
        fig.suptitle(f"blank rows: slices {failed} failed (see the result file)")
    fig.tight_layout()
    return fig


def figure_cine(series, times_ms, truth_tau=None):
    """One slice over the cycle: WSS(t, phi), the mean WSS(t) (with the truth), and TAWSS and OSI around the wall.

    ``truth_tau`` (nt,) is the exact mean WSS of each frame, for phantoms.
    """
    fig, axes = _subplots(1, 3, figsize=(14, 4.2))
    ax = axes[0]
    deg = np.degrees(series.phi)
    im = ax.pcolormesh(deg, times_ms, series.tau, shading="nearest", cmap="coolwarm")
    lim = np.nanmax(np.abs(series.tau))
    im.set_clim(-lim, lim)
    fig.colorbar(im, ax=ax, label="WSS [Pa]")
    ax.set(xlabel="wall angle phi [deg]", ylabel="time after trigger [ms]", title="WSS(t, phi)")
    ax = axes[1]
    model = getattr(series, "model", None)
    which = "momentum model" if model is not None and model.model == "momentum" else "frames' own fits"
    ax.plot(times_ms, series.mean, "o-", label=f"reconstructed (wall mean; {which})")
    std = getattr(series, "mean_std", None)
    if std is not None and np.any(np.isfinite(std)):
        lo, hi = series.mean - 2 * std, series.mean + 2 * std
        ax.fill_between(times_ms, lo, hi, color="C0", alpha=0.25, lw=0, label="band (2 std, data noise)")
    if series.failed.any():
        ax.plot(np.asarray(times_ms)[series.failed], np.zeros(int(series.failed.sum())), "rx", label="failed frame")
    if truth_tau is not None:
        ax.plot(times_ms, truth_tau, "k--", label="truth")
    ax.axhline(0.0, color="0.7", lw=0.8)
    ax.set(xlabel="time after trigger [ms]", ylabel="mean WSS [Pa]", title="mean WSS over the cycle")
    ax.legend(fontsize=8)
    ax = axes[2]
    ax.plot(deg, series.tawss, label="TAWSS [Pa]")
    ax.set(xlabel="wall angle phi [deg]", ylabel="TAWSS [Pa]", title="TAWSS and OSI around the wall")
    finite = series.tawss[np.isfinite(series.tawss)]
    if finite.size:  # from zero: a per-mille ripple must not fill the axis as if it were a pattern
        ax.set_ylim(0.0, 1.1 * max(float(finite.max()), 1e-12))
    twin = ax.twinx()
    twin.plot(deg, series.osi, color="C3", label="OSI")
    twin.set_ylim(0, 0.5)
    twin.set_ylabel("OSI", color="C3")
    fig.tight_layout()
    return fig


def save_cine_figures(series, result, folder: str, truth_tau=None) -> list[str]:
    """``cine_slice_NNN.png`` for every slice of a cine reconstruction; returns the paths."""
    paths = []
    for s in series:
        fig = figure_cine(s, result.times_ms, truth_tau)
        paths.append(save_figure(fig, os.path.join(folder, f"cine_slice_{s.index:03d}.png")))
    return paths


def save_tissue_figures(res, raw, folder, prefix: str = "") -> list[str]:
    """Write ``surround.png`` (:func:`figure_surround`) and ``offset.png`` (:func:`figure_offset`) of a slice the
    surround model or the offset correction looked at (``res.lumen.tissue``; none otherwise); returns the paths.

    ``raw``: the slice's measured magnitude (the result keeps the magnitude the geometry fitted)."""
    rec = getattr(getattr(res, "lumen", None), "tissue", None) or {}
    sm, o = rec.get("surround") or {}, rec.get("offset") or {}
    paths = []
    if sm.get("kind") == "tissue" or o.get("static_voxels", 0) > 0:
        os.makedirs(folder, exist_ok=True)
        for name, make in (("surround.png", figure_surround), ("offset.png", figure_offset)):
            path = os.path.join(folder, prefix + name)
            save_figure(make(res, np.asarray(raw, float)), path)
            paths.append(path)
    return paths


def figure_surround(res, raw):
    """Vessel in tissue: the raw magnitude with the wall, and the fitted outside level (issue 39).

    ``raw``: the slice's measured magnitude; the outside model comes from ``res.lumen.tissue``
    (:func:`wss_nlp.models.surround.model_images`).
    """
    from ..models import surround

    outside, _ = surround.model_images(res.lumen.tissue or {}, res.grid)
    if outside is not None:  # shown where it was fitted and used: up to the outer edge of the outside ring
        outside = np.where(surround.model_reach(res.lumen.mask, res.grid), outside, np.nan)
    fig, ax = _subplots(1, 2, figsize=(11, 4.5))
    fig.set_layout_engine("constrained")
    im = _image(ax[0], raw, res.grid, cmap="gray")
    _contour(ax[0], res, color="r", lw=1)
    fig.colorbar(im, ax=ax[0], label="magnitude (raw)")
    ax[0].set_title("magnitude and the reconstructed wall")
    if outside is None:
        ax[1].set_axis_off()
        ax[1].set_title("two-level model (Appendix B): no outside model")
    else:
        im = _image(ax[1], outside, res.grid, cmap="viridis")
        _contour(ax[1], res, color="w", lw=1)
        fig.colorbar(im, ax=ax[1], label="outside level (raw)")
        sm = (res.lumen.tissue or {}).get("surround", {})
        wall = (
            f"; wall ring {sm['wall_mm']:g} mm at {sm['wall_level']:.2f}"
            if np.isfinite(sm.get("wall_level", np.nan))
            else ""
        )
        ax[1].set_title("fitted outside level" + wall)
    for a in ax:
        a.set_xlabel("x [mm]")
        a.set_ylabel("y [mm]")
    return fig


def figure_offset(res, raw):
    """The static tissue the offset was fitted to and the removed offset in % of the venc (issue 39)."""
    from ..models import offset as off
    from ..models import surround

    rec = res.lumen.tissue or {}
    _, offset = surround.model_images(rec, res.grid)
    sigma = rec.get("sigma_lumen_plateau", float("nan"))
    static = off.static_mask(raw, sigma, res.lumen.noise_mask) if np.isfinite(sigma) else np.zeros_like(raw, bool)
    fig, ax = _subplots(1, 2, figsize=(11, 4.5))
    fig.set_layout_engine("constrained")
    _image(ax[0], static.astype(float), res.grid, cmap="gray")
    _contour(ax[0], res, color="r", lw=1)
    ax[0].set_title(f"static tissue ({int(static.sum())} voxels)")
    o = rec.get("offset") or {}
    venc = o.get("at_vessel_m_s", float("nan")) / o.get("at_vessel_fraction_of_venc", float("nan"))
    if offset is None or not np.isfinite(venc):
        ax[1].set_axis_off()
        ax[1].set_title("offset not corrected: " + str(o.get("reason", ""))[:60])
    else:
        im = _image(ax[1], 100 * offset / venc, res.grid, cmap="RdBu_r")
        _contour(ax[1], res, color="k", lw=1)
        fig.colorbar(im, ax=ax[1], label="removed offset [% of venc]")
        ax[1].set_title(f"removed offset (degree {o['order']})")
    for a in ax:
        a.set_xlabel("x [mm]")
        a.set_ylabel("y [mm]")
    return fig


def figure_cohort(values: dict, flagged=None):
    """Distributions across the exams of a batch: one panel per quantity, every exam a point over a box plot.

    ``values``: ``{label: {exam id: value}}`` (NaN values are left out: a steady exam has no TAWSS); ``flagged``:
    the ids of exams with flags, drawn as open orange circles.
    """
    flagged = set(flagged or ())
    panels = [(label, {k: v for k, v in vals.items() if np.isfinite(v)}) for label, vals in values.items()]
    fig, axes = _subplots(1, len(panels), figsize=(4.2 * len(panels), 4.0), squeeze=False)
    rng = np.random.default_rng(0)  # the points' sideways jitter, the same in every report
    for ax, (label, vals) in zip(axes[0], panels):
        ax.set(title=label, xticks=[])
        if not vals:
            ax.text(0.5, 0.5, "no exam has it", ha="center", va="center", transform=ax.transAxes, color="0.4")
            continue
        data = np.array(list(vals.values()), dtype=float)
        ax.boxplot(data, widths=0.5, showfliers=False)
        x = 1 + rng.uniform(-0.15, 0.15, data.size)
        bad = np.array([k in flagged for k in vals])
        ax.plot(x[~bad], data[~bad], "o", color="C0", ms=4, label="exam")
        if bad.any():
            ax.plot(x[bad], data[bad], "o", mfc="none", color="C1", ms=6, label="flagged exam")
        ax.set_xticks([])  # after the box plot, which sets its own
        ax.set_xlabel(f"{data.size} exam(s): median {np.median(data):.4g}")
        ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    return fig
