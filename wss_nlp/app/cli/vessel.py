"""``wss-nlp reconstruct`` and ``export`` on a 4D flow volume file: the whole vessel's wall map (issue 38).

A volume file (:func:`wss_nlp.io.volume.is_volume_file`) goes through :func:`wss_nlp.vessel.reconstruct
.reconstruct_vessel` instead of the slice driver. The options that carry over from slices keep their flags
(:data:`VOLUME_OPTIONS`); any other reconstruction option set on the command line is refused with one line rather
than silently ignored. The result file holds the group ``vessel/`` (and ``baseline/`` with ``--baseline``), the
layout of :mod:`wss_nlp.vessel.reconstruct`; ``wss-nlp export RESULT --vtk wall.vtu`` writes the wall mesh
(:func:`wss_nlp.vessel.mesh.write_wall`).
"""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np

from ...core import schema
from ...errors import InputError
from ...io import outputs
from ...pipeline.options import ReconstructionOptions
from ..table import text_table

#: Reconstruction options (schema paths) that a volume honours, with what they set in the vessel's options.
VOLUME_OPTIONS = {
    "screen.vessel": "vessel_point (three numbers X,Y,Z in world mm)",
    "viscosity_pa_s": "viscosity_pa_s",
    "n_phi": "n_phi (wall points per cross-section)",
    "blas_threads": "blas_threads",
    "geometry.n_fourier": "geometry.n_fourier",
    "geometry.quad_order": "geometry.quad_order",
    "stack.z_smoothing_mm": "geometry.smoothing_mm and velocity.smoothing_mm (the smoothing length along s)",
    "choice.alpha_rule": "geometry.alpha (a number)",
    "choice.beta_rule": "velocity.beta (a number, gcv or discrepancy)",
    "velocity.degree": "velocity.degree",
    "velocity.angular_order": "velocity.angular_order",
    "velocity.laplacian_power": "velocity.laplacian_power",
    "velocity.inner_fraction": "velocity.inner_fraction",
    "tissue.offset_correction": "offset_correction (--no-offset-correction: keep the background offset)",
    "cine.model": "cycle (auto, independent -> frames, temporal; momentum is refused: not for curved vessels)",
}


def parse_point3(text) -> tuple[float, float, float]:
    """``"X,Y,Z"`` (world mm) -> ``(x, y, z)``; an :class:`InputError` names the expected form."""
    try:
        values = tuple(float(v) for v in str(text).split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(np.isfinite(values)):
        raise InputError(f"--vessel takes three numbers X,Y,Z in world mm for a 4D flow volume, e.g. 10,-4.5,32; "
                         f"got {text!r}")  # fmt: skip
    return values[0], values[1], values[2]


def _set(args) -> dict:
    """``{schema path: (flag, value)}`` of the reconstruction options given on the command line."""
    return schema.given(ReconstructionOptions, args)


def _number(flag: str, value) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{flag} {value}: a 4D flow volume takes a number here") from None
    if not out > 0:
        raise InputError(f"{flag} {value}: must be > 0")
    return out


def _cycle_model(flag: str, value) -> str:
    """``--cine-model`` for a cine volume: the cycle models of :mod:`wss_nlp.vessel.cycle3d`."""
    if value == "momentum":
        raise InputError(
            f"{flag} momentum: the momentum balance (Womersley) is not carried to 4D flow volumes: its profiles are "
            "those of fully developed flow in a straight pipe, which curvature, taper and swirl break; use auto, "
            "temporal or independent"
        )
    return {"independent": "frames"}.get(str(value), str(value))


def vessel_options(args):
    """The :class:`wss_nlp.vessel.reconstruct.VesselOptions` of the command line (refusing slice-only options)."""
    from ...vessel.reconstruct import VesselOptions

    given = _set(args)
    other = sorted(flag for path, (flag, _) in given.items() if path not in VOLUME_OPTIONS)
    if other:
        raise InputError(
            f"{', '.join(other)}: not an option of the volume reconstruction (it takes "
            f"{', '.join(sorted(given_flag(p) for p in VOLUME_OPTIONS))}, --mask, --centerline, --baseline)"
        )
    top: dict = {}
    geo: dict = {}
    vel: dict = {}
    for path, (flag, value) in given.items():
        if path == "screen.vessel":
            top["vessel_point"] = parse_point3(value)
        elif path == "viscosity_pa_s":
            top["viscosity_pa_s"] = _number(flag, value)
        elif path in ("n_phi", "blas_threads"):
            top[path] = int(value)
        elif path == "geometry.n_fourier":
            geo["n_fourier"] = int(value)
        elif path == "geometry.quad_order":
            geo["quad_order"] = int(value)
        elif path == "stack.z_smoothing_mm":
            geo["smoothing_mm"] = vel["smoothing_mm"] = _number(flag, value)
        elif path == "choice.alpha_rule":
            geo["alpha"] = _number(flag, value)
        elif path == "choice.beta_rule":
            vel["beta"] = value if str(value) in ("gcv", "discrepancy") else _number(flag, value)
        elif path == "velocity.degree":
            vel["degree"] = int(value)
        elif path == "velocity.angular_order":
            vel["angular_order"] = int(value)
        elif path == "velocity.laplacian_power":
            vel["laplacian_power"] = int(value)
        elif path == "velocity.inner_fraction":
            vel["inner_fraction"] = _number(flag, value)
        elif path == "tissue.offset_correction":
            top["offset_correction"] = bool(value)
        elif path == "cine.model":
            top["cycle"] = _cycle_model(flag, value)
    base = VesselOptions()
    return dataclasses.replace(
        base,
        geometry=dataclasses.replace(base.geometry, **geo),
        velocity=dataclasses.replace(base.velocity, **vel),
        **top,
    )


def given_flag(path: str) -> str:
    return schema.cli_flag(ReconstructionOptions, path)


def reconstruct_volume(args) -> int:
    """``wss-nlp reconstruct VOLUME.h5 -o RESULT.h5 [--vessel X,Y,Z] [--mask FILE] [--centerline FILE]``."""
    from ...io.files import atomic_h5
    from ...io.volume import read_volume
    from ...vessel.baseline import baseline_vessel
    from ...vessel.centerline import Centerline
    from ...vessel.reconstruct import FLAG_NAMES, FLAG_NOT_VISIBLE, check_volume, reconstruct_vessel, vessel_inputs
    from ...vessel.segmentation import read_mask

    options = vessel_options(args)
    if getattr(args, "workers", 1) != 1 or getattr(args, "scheduler", None):
        raise InputError("--workers/--scheduler: a vessel is one reconstruction; run it without them")
    inputs = [args.input] + [p for p in (args.mask, args.centerline) if p]
    outputs.check_outputs(files={"-o": args.output}, folders={"--figures": args.figures}, inputs=inputs)
    vol = read_volume(args.input)
    print(
        f"{args.input}: a 4D flow volume of {' x '.join(map(str, vol.shape))} voxels "
        f"({' x '.join(f'{v:.3g}' for v in vol.voxel_size_mm)} mm), {vol.nt} frame(s)",
        file=sys.stderr,
    )
    check_volume(vol, options)  # the volume's own refusals (no flow, components alike, no viscosity) come first
    mask = read_mask(args.mask, vol) if args.mask else None
    centerline = Centerline.from_file(args.centerline) if args.centerline else None
    prepared = vessel_inputs(vol, options, mask, centerline)
    result = reconstruct_vessel(vol, options, inputs=prepared)
    base = None
    if args.baseline:
        # on the volume the reconstruction used: the background offset removed as for it
        base = baseline_vessel(prepared.volume, prepared.mask, prepared.centerline, result.record, options,
                               s=result.s_mm, phi=result.phi)  # fmt: skip
    with outputs.StagedFolder(args.figures) as staged:  # figures and result land together or not at all
        if staged.path:
            from ..plotting import save_vessel_figures

            save_vessel_figures(result, staged.path, fmt=args.figure_format, dpi=args.dpi)
        with atomic_h5(args.output) as f:
            f.attrs["argv"] = " ".join(["wss-nlp", *args.argv])
            f.attrs["input"] = str(args.input)
            f.attrs["options"] = json.dumps(dataclasses.asdict(options), default=str)
            result.write(f.create_group("vessel"))
            if base is not None:
                base.write(f.create_group("baseline"))
        staged.commit()
    for note in result.notes:
        print(f"  {note}", file=sys.stderr)
    for b in result.record.get("branches", []):
        pos = ", ".join(f"{v:.1f}" for v in np.asarray(b.get("position_mm", []), float).ravel())
        print(f"side branch at s = {float(b.get('s_mm', np.nan)):.1f} mm ({pos} mm): its wall region is flagged")
    covered = result.covered
    area = result.area_mm2
    visible = (result.flags & FLAG_NOT_VISIBLE) == 0
    cov = float(np.sum(area[covered]) / np.sum(area[visible])) if np.any(visible) else 0.0
    counts = {name: int(np.count_nonzero(result.flags & bit)) for bit, name in FLAG_NAMES.items()}
    flagged = ", ".join(f"{name} {n}" for name, n in counts.items() if n)
    mean_wss = covered_mean_wss(result)
    print(
        f"vessel: {result.centerline.length_mm:.1f} mm of centreline, wall {result.s_mm.size} x {result.phi.size} "
        f"points, {100 * cov:.1f} % of the visible wall's area covered" + (f" (flagged: {flagged})" if flagged else "")
    )
    print(f"mean |WSS| over the covered wall {mean_wss:.4g} Pa" + ("" if result.nt == 1 else " (over the frames)"))
    if result.tawss_pa is not None and result.osi is not None:
        print(f"TAWSS {np.mean(result.tawss_pa[covered]):.4g} Pa (wall mean), OSI up to {np.max(result.osi):.3f}")
    if base is not None:
        bmag = np.linalg.norm(base.wss_pa, axis=-1)
        print(f"baseline ({base.method}): mean |WSS| {float(np.mean(bmag[:, covered])):.4g} Pa on the same points")
    print(f"wrote {args.output}")
    if args.figures:
        print(f"figures in {args.figures}")
    return 0


def covered_mean_wss(result) -> float:
    """Mean ``|tau|`` (Pa) over the covered wall, area-weighted, averaged over the frames."""
    covered = result.covered
    area = result.area_mm2[covered]
    mag = np.linalg.norm(result.wss_pa, axis=-1)[:, covered]
    return float(np.mean(mag @ area) / max(float(np.sum(area)), 1e-300))


def is_vessel_result(path: str) -> bool:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "vessel" in f
    except OSError:
        return False


def export_volume(args) -> int:
    """``wss-nlp export RESULT --vtk wall.vtu`` for a vessel result: the wall mesh, centreline and plane table."""
    from ...vessel.mesh import write_wall
    from ...vessel.reconstruct import read_result

    if not args.vtk.lower().endswith(".vtu"):
        raise InputError(f"--vtk {args.vtk}: a vessel wall is written as .vtu (VTK XML unstructured grid)")
    if args.slice_spacing is not None:
        raise InputError("--slice-spacing: a vessel result has its own geometry; leave it out")
    outputs.check_outputs(files={"--vtk": args.vtk}, inputs=[args.result])
    result = read_result(args.result)
    for name in write_wall(result, args.vtk):
        print(f"wrote {name}")
    return 0


def analyze_volume(args) -> int:
    """``wss-nlp analyze RESULT`` for a vessel result: how alpha and beta were chosen, the solvers' statuses."""
    from ...vessel import cycle3d
    from ...vessel.reconstruct import read_result

    if args.figures:
        raise InputError("--figures: no residual curves for a vessel result yet (the choice is printed)")
    res = read_result(args.result)
    p, st = res.parameters, res.statuses
    print(f"wall: alpha {p.get('alpha')} (fixed), smoothing along the vessel {p.get('smoothing_mm')} mm, "
          f"N = {p.get('n_fourier')}, {p.get('quad_order')}^3 points per voxel")  # fmt: skip
    for k, g in enumerate(st.get("geometry", [])):
        print(f"  wall solve {k}: {g.get('status')} ({g.get('iterations')} iterations)")
    vel = st.get("velocity", {})
    print(f"velocity: beta {p.get('beta')} by {vel.get('beta_rule')}, residual {vel.get('residual_m_s')} m/s")
    print(cycle3d.summary(p.get("cycle"), res.nt))
    for name, sec in res.seconds.items():
        print(f"  {name}: {float(sec):.1f} s")
    print(band_summary(res))
    for note in res.notes:
        print(f"note: {note}")
    return 0


def compare_volume(args) -> int:
    """``wss-nlp compare RESULT TRUTH`` for a vessel result and a vessel phantom's truth file: the measures of
    :func:`wss_nlp.vessel.metrics.accuracy` (issue 38), the truth interpolated from its samples
    (:class:`wss_nlp.vessel.metrics.SampledTruth`)."""
    from ...vessel.metrics import accuracy, read_truth
    from ...vessel.reconstruct import read_result

    truth = read_truth(args.truth)  # refuses a file of another layout in one line
    res = read_result(args.result)
    if res.nt > 1 and truth.times_ms.size != res.nt:
        raise InputError(f"{args.result} has {res.nt} frames but {args.truth} {truth.times_ms.size}")
    try:
        acc = accuracy(res, truth)
    except ValueError as exc:  # a frame time the truth does not have
        raise InputError(f"{args.truth}: {exc}") from None
    h = float(np.min(np.linalg.norm(np.asarray(res.affine_mm, float)[:3, :3], axis=0)))  # the smallest voxel edge
    rows = [
        ("WSS vector rel. L2 error (covered visible wall, all frames)", f"{acc.wss_rel_l2:.2%}"),
        ("axial WSS rel. L2 error", f"{acc.axial_rel_l2:.2%}"),
        ("wall RMS distance [mm]", f"{acc.wall_rms_mm:.4f}" + (f" ({acc.wall_rms_mm / h:.3f} h)" if h > 0 else "")),
        ("wall mean signed distance [mm] (+ outside)", f"{acc.wall_bias_mm:+.4f}"),
        ("coverage of the visible wall", f"{acc.coverage:.1%}"),
        ("mean |WSS| reconstructed [Pa] (first frame)", f"{acc.mean_wss_pa:.5g}"),
        ("mean |WSS| true [Pa]", f"{acc.true_mean_wss_pa:.5g}"),
    ]
    if np.isfinite(acc.tawss_rel_l2):
        rows += [("TAWSS rel. L2 error", f"{acc.tawss_rel_l2:.2%}"), ("OSI RMS error", f"{acc.osi_rms:.4f}"),
                 ("OSI max. error", f"{acc.osi_max:.4f}")]  # fmt: skip
    print(f"vessel against {args.truth} ({truth.case}, {acc.points} wall points):")
    print(text_table(rows, headers=("quantity", "value")))
    return 0


def band_summary(res) -> str:
    """One line on a vessel result's band (module :mod:`wss_nlp.vessel.band3d`), or why it has none."""
    band = res.band or {}
    if not band:
        return "band: none (a result written before the vessel band, or a baseline)"
    if not band.get("available"):
        return f"band: {band.get('note', 'not computed')}"
    covered = res.covered
    std = res.axial_std_pa[:, covered] if res.axial_std_pa is not None else np.zeros(0)
    spread = (f"; axial WSS std over the covered wall: median {np.median(std):.3g} Pa, largest {np.max(std):.3g} Pa"
              if std.size else "")  # fmt: skip
    return (f"band ({band.get('holds', 'velocity noise')}): mean |WSS| over the covered wall "
            f"{band['mean_pa']:.4g} Pa +- {band['mean_std_pa']:.2g} Pa (1 std){spread}")  # fmt: skip


#: Planes of the short per-plane table of ``sensitivity``.
SENSITIVITY_PLANES = 8


def sensitivity_volume(args) -> int:
    """``wss-nlp sensitivity RESULT`` for a vessel result: the covered wall's mean ``|WSS|`` with its band and what
    moves it (velocity noise, beta and kappa_v +10 %: exact derivatives stored by the reconstruction), and a short
    per-plane table. No band (no venc, an older file): one line, exit code 2."""
    from ...vessel.reconstruct import read_result

    res = read_result(args.result)
    band = res.band or {}
    if not band:
        raise InputError(f"{args.result}: the vessel result has no band record (written before the vessel band); "
                         "reconstruct it again")  # fmt: skip
    if not band.get("available"):
        raise InputError(f"{args.result}: {band.get('note', 'no uncertainty band')}")
    if not np.isfinite(band["mean_pa"]):
        raise InputError(f"{args.result}: no covered wall (every wall point is flagged): no mean WSS to show")
    mean, std = band["mean_pa"], band["mean_std_pa"]
    frames = "" if res.nt == 1 else f", the mean over {res.nt} frames"
    print(f"vessel: mean |WSS| over the covered wall {mean:.4g} Pa +- {std:.2g} Pa (1 std, linearized{frames}; "
          f"{band['holds']})")  # fmt: skip
    rows = [
        ("velocity noise (1 std)", std),
        ("beta +10 %", 0.1 * band["beta"] * band["d_mean_d_beta"]),
        ("kappa_v +10 % (smoothing along the vessel)", 0.1 * band["kappa_mm4"] * band["d_mean_d_kappa"]),
    ]
    cells = [(cause, f"{d:+.3e}", f"{100 * d / mean:+.3g} %") for cause, d in sorted(rows, key=lambda r: -abs(r[1]))]
    cells.append(("magnitude noise (the wall)", "not included", "see the 4D flow guide"))
    print(text_table(cells, headers=("what changes", "mean WSS change [Pa]", "relative"), indent="  "))
    p = res.planes
    covered = np.flatnonzero(p["flags"] == 0)
    if covered.size and "mean_wss_std_pa" in p:
        pick = covered[np.unique(np.round(np.linspace(0, covered.size - 1, SENSITIVITY_PLANES)).astype(int))]
        wss = np.mean(p["mean_wss_pa"][:, pick], axis=0)
        pstd = np.sqrt(np.sum(p["mean_wss_std_pa"][:, pick] ** 2, axis=0)) / res.nt  # frames' noise independent
        print(f"planes ({pick.size} of {covered.size} unflagged; mean |WSS| over the ring +- 1 std):")
        print(text_table([(f"{p['s_mm'][i]:.1f}", f"{w:.4g}", f"{e:.2g}") for i, w, e in zip(pick, wss, pstd)],
                         headers=("s [mm]", "mean |WSS| [Pa]", "std [Pa]"), indent="  "))  # fmt: skip
    return 0
