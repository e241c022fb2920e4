"""Whole-vessel reconstruction from a 4D flow volume: mask -> centreline -> wall -> velocity -> WSS (issue 38).

:func:`reconstruct_vessel` runs the steps on one :class:`wss_nlp.io.volume.VolumeAcquisition` (one frame or a
cine): the lumen mask (:func:`wss_nlp.vessel.segmentation.segment_vessel`, or a given one), the centreline
(:func:`wss_nlp.vessel.centerline.centerline_from_mask`, or a given one), the wall ``R(s, phi)``
(:mod:`wss_nlp.vessel.geometry3d`) from the time-mean magnitude, the three velocity components of every frame
(:mod:`wss_nlp.vessel.velocity3d`) and the WSS vector at wall points ``(s_i, phi_j)`` (:mod:`wss_nlp.vessel.wss3d`).
Walls are assumed rigid: one geometry (from the time-mean magnitude) serves every frame, and one factorization of
the velocity's normal equations all frames' right-hand sides.

Flags (per wall point, bits of :attr:`VesselResult.flags`): :data:`FLAG_BRANCH` (within a side branch's flagged
region: its ``s`` interval and angle sector from the centreline record; those voxels are also left out of the
fits), :data:`FLAG_NOT_VISIBLE` (the centreline less than one radius inside the field of view: part of the
cross-section is cut), :data:`FLAG_BORDER` (the wall point within ``border_mm``, default one voxel, of the field
of view's faces), :data:`FLAG_UNRESOLVED` (the wall's box constraint active nearby, a solver that did not converge,
a radius below :func:`min_radius_voxels` (1.69 voxels by default: fewer voxels in the cross-section than the
velocity prior leaves free modes), or a wall so far from round that the velocity's map capped its inner radius there:
:data:`wss_nlp.vessel.velocity3d.MAX_INNER_RATIO`). A wall point with no flag is "covered".

Result file (:meth:`VesselResult.write`, :meth:`VesselResult.read`): an HDF5 group ``vessel/`` (or
``baseline/``) with lengths in mm, stresses in Pa, vectors in the world frame of the volume's affine:

* attributes ``method`` ("reconstruction" or the baseline's name), ``source``, ``viscosity_pa_s``,
  ``affine_mm`` (4 x 4), ``parameters``, ``statuses``, ``seconds`` (JSON text), ``notes`` (JSON list);
* ``centerline/`` (:meth:`wss_nlp.vessel.centerline.Centerline.write`);
* ``s_mm (ns,)``, ``phi_rad (np,)``, ``time_ms (nt,)``;
* ``wall/point_mm (ns, np, 3)``, ``wall/normal (ns, np, 3)`` (outward), ``wall/radius_mm (ns, np)``,
  ``wall/area_mm2 (ns, np)`` (the surface each wall point stands for), ``wall/flags (ns, np)`` (uint8 bits);
* ``wss/vector_pa (nt, ns, np, 3)``, ``wss/axial_pa (nt, ns, np)`` (``tau . t``, signed),
  ``wss/circumferential_pa (nt, ns, np)``; with ``nt > 1``: ``wss/tawss_pa``, ``wss/osi`` ``(ns, np)``;
* ``planes/s_mm (ns,)``, ``planes/area_mm2 (ns,)``, ``planes/flow_ml_s (nt, ns)`` (through the cross-section along
  ``t``), ``planes/mean_wss_pa (nt, ns)`` (mean ``|tau|`` over the ring, by arc length),
  ``planes/mean_axial_pa (nt, ns)``, ``planes/flags (ns,)`` (the bits of the ring's points, or-ed);
* the uncertainty band (:mod:`wss_nlp.vessel.band3d`; velocity noise only; NaN without the venc; absent from
  files written before it and from the baseline): ``wss/axial_std_pa (nt, ns, np)`` (standard deviation of the
  axial WSS), ``planes/mean_wss_std_pa (nt, ns)`` (of the plane's mean ``|tau|``), and the attribute ``band``
  (JSON: ``available``, the covered wall's mean ``|tau|`` ``mean_pa`` and its ``mean_std_pa``,
  ``d_mean_d_beta``, ``d_mean_d_kappa``, ``beta``, ``kappa_mm4``, ``holds``; or ``note``: why there is none).
"""

from __future__ import annotations

import json
import logging
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.files import DEFAULT_DENSITY
from ..io.volume import VolumeAcquisition
from ..pipeline.driver import blas_threads
from . import band3d
from . import cycle3d
from . import geometry3d as g3
from .centerline import distance_to_border, intervals
from . import tube
from . import velocity3d as v3
from . import wss3d

log = logging.getLogger(__name__)

FLAG_BRANCH = 1
FLAG_NOT_VISIBLE = 2
FLAG_BORDER = 4
FLAG_UNRESOLVED = 8
FLAG_NAMES = {FLAG_BRANCH: "near a branch", FLAG_NOT_VISIBLE: "outside the visible part",
              FLAG_BORDER: "near the field of view's border", FLAG_UNRESOLVED: "unresolved"}  # fmt: skip
#: A radius below this many voxels is unresolved, whatever the velocity basis (:func:`min_radius_voxels`).
MIN_RADIUS_VOXELS = 1.0
#: Bulk Reynolds number above which steady pipe flow may be transitional or turbulent (the classical 2300).
TRANSITION_REYNOLDS = 2300.0


def min_radius_voxels(velocity: v3.Velocity3DOptions) -> float:
    """The smallest radius, in voxels (the largest edge), at which a cross-section is resolved:
    ``max(MIN_RADIUS_VOXELS, sqrt((2 m + 1) / pi))`` with ``m`` the velocity basis' highest angular order.

    The velocity prior ``||Delta^2 v||^2`` leaves the ``2 m + 1`` modes ``(1 - rho^2)`` times a harmonic
    polynomial of order up to ``m`` free (``Delta^2`` kills them), so only the data fix them; a cross-section of
    radius ``R`` holds about ``pi (R / h)^2`` voxels. Below ``sqrt((2 m + 1) / pi)`` voxels (1.69 at the default
    ``m = 4``) it holds fewer voxels than free modes and the wall's velocity gradient follows the noise: on the
    carotid-sized phantom without tissue (development seeds 0, 1, SNR 20, ``scripts/results/vessel_limits_small.md``
    by ``scripts/vessel_limits.py``) the WSS error was 55 % at 1.2 voxels, 35 % at 1.5, 24.5 % at 1.75 and 15-16 %
    at 2, against 3-6 % at the aorta's 4-6 voxels (``scripts/results/vessel_accuracy.md``).
    """
    m = velocity.angular_order if velocity.angular_order is not None else velocity.degree
    return max(MIN_RADIUS_VOXELS, float(np.sqrt((2 * m + 1) / np.pi)))


@dataclass(frozen=True)
class VesselOptions:
    """Options of :func:`reconstruct_vessel`.

    Attributes
    ----------
    geometry, velocity : the steps' options.
    n_phi : int
        Wall points per cross-section.
    s_spacing_mm : float or None
        Spacing of the cross-sections (default ``h / 2``).
    extend_mm : float or None
        The fitted part of the centreline reaches this far beyond the visible part at each end (where the
        centreline goes; default ``4 h``): the fits' ends are loose, the visible part's are not.
    border_mm : float or None
        Wall points closer than this to the field of view's faces are flagged (default one voxel).
    vessel_point : (x, y, z) or None
        A world point (mm) in the wanted vessel (default: the largest one).
    viscosity_pa_s : float or None
        Overrides the file's viscosity.
    blas_threads : int
        BLAS threads during the fits (1: small products are fastest single-threaded; 0 leaves the BLAS as it is).
    offset_correction : bool
        Remove each velocity component's background offset, fitted on static tissue
        (:func:`wss_nlp.vessel.background.correct_volume`; nothing to do in a volume without static tissue).
    cycle : str or float
        The velocity over a cine's cycle (:mod:`wss_nlp.vessel.cycle3d`): "auto" (the periodic temporal prior
        where the BIC prefers it to the frames' own fits, GCV without the venc), "frames" (each frame's own fit),
        "temporal" (the prior, its weight by the criterion) or a number: the prior with that fixed weight gamma.
        Command line: ``--cine-model auto|independent|temporal``.
    """

    geometry: g3.Geometry3DOptions = field(default_factory=g3.Geometry3DOptions)
    velocity: v3.Velocity3DOptions = field(default_factory=v3.Velocity3DOptions)
    n_phi: int = 64
    s_spacing_mm: float | None = None
    extend_mm: float | None = None
    border_mm: float | None = None
    vessel_point: tuple[float, float, float] | None = None
    viscosity_pa_s: float | None = None
    blas_threads: int = 1
    offset_correction: bool = True
    cycle: str | float = "auto"

    def __post_init__(self):
        cycle3d.check_setting(self.cycle)
        if self.n_phi < 8:
            raise InputError(f"n_phi must be >= 8, got {self.n_phi}")
        if self.s_spacing_mm is not None and not self.s_spacing_mm > 0:
            raise InputError(f"s spacing must be > 0 mm, got {self.s_spacing_mm}")


@dataclass
class VesselResult:
    """A wall map of one vessel (module notes; arrays as in the result file)."""

    method: str
    centerline: Any
    s_mm: np.ndarray
    phi: np.ndarray
    time_ms: np.ndarray
    wall_mm: np.ndarray  # (ns, np, 3)
    normal: np.ndarray  # (ns, np, 3)
    radius_mm: np.ndarray  # (ns, np)
    area_mm2: np.ndarray  # (ns, np)
    flags: np.ndarray  # (ns, np) uint8
    wss_pa: np.ndarray  # (nt, ns, np, 3)
    axial_pa: np.ndarray  # (nt, ns, np)
    circumferential_pa: np.ndarray  # (nt, ns, np)
    planes: dict  # per-plane table (module notes)
    viscosity_pa_s: float
    affine_mm: np.ndarray
    source: str = ""
    tawss_pa: np.ndarray | None = None
    osi: np.ndarray | None = None
    parameters: dict = field(default_factory=dict)
    statuses: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    record: dict = field(default_factory=dict)  # the centreline record (branches, visible part)
    axial_std_pa: np.ndarray | None = None  # (nt, ns, np): the band (module notes)
    band: dict = field(default_factory=dict)  # the band's record (module notes)
    fits: Any = field(default=None, repr=False)  # VesselFits of a reconstruction in memory (not written)

    @property
    def nt(self) -> int:
        return int(self.wss_pa.shape[0])

    @property
    def covered(self) -> np.ndarray:
        """Wall points without a flag."""
        return self.flags == 0

    def plane_table(self) -> str:
        """The per-plane table as CSV text: ``s_mm, area_mm2, flow_ml_s, mean_wss_pa, mean_axial_pa, flags`` (the
        frame-mean flow and WSS for a cine), and ``mean_wss_std_pa`` (the band, the frames' mean) where the result
        has one."""
        p = self.planes
        std = p.get("mean_wss_std_pa")
        rows = ["s_mm,area_mm2,flow_ml_s,mean_wss_pa,mean_axial_pa,flags" + ("" if std is None else ",mean_wss_std_pa")]
        for i, s in enumerate(p["s_mm"]):
            rows.append(f"{s:.3f},{p['area_mm2'][i]:.4f},{np.mean(p['flow_ml_s'][:, i]):.5g},"
                        f"{np.mean(p['mean_wss_pa'][:, i]):.5g},{np.mean(p['mean_axial_pa'][:, i]):.5g},"
                        f"{int(p['flags'][i])}" + ("" if std is None else f",{np.mean(std[:, i]):.5g}"))  # fmt: skip
        return "\n".join(rows) + "\n"

    def write(self, group) -> None:
        """Store in an h5py group (module notes)."""
        group.attrs["method"] = self.method
        group.attrs["source"] = self.source
        group.attrs["viscosity_pa_s"] = float(self.viscosity_pa_s)
        group.attrs["affine_mm"] = np.asarray(self.affine_mm, float)
        for name in ("parameters", "statuses", "seconds", "record", "band"):
            group.attrs[name] = json.dumps(_jsonable(getattr(self, name)))
        group.attrs["notes"] = json.dumps(list(self.notes))
        self.centerline.write(group.create_group("centerline"))
        group.create_dataset("s_mm", data=self.s_mm)
        group.create_dataset("phi_rad", data=self.phi)
        group.create_dataset("time_ms", data=self.time_ms)
        wall = group.create_group("wall")
        wall.create_dataset("point_mm", data=self.wall_mm)
        wall.create_dataset("normal", data=self.normal)
        wall.create_dataset("radius_mm", data=self.radius_mm)
        wall.create_dataset("area_mm2", data=self.area_mm2)
        wall.create_dataset("flags", data=self.flags.astype(np.uint8))
        w = group.create_group("wss")
        w.create_dataset("vector_pa", data=self.wss_pa)
        w.create_dataset("axial_pa", data=self.axial_pa)
        w.create_dataset("circumferential_pa", data=self.circumferential_pa)
        if self.tawss_pa is not None:
            w.create_dataset("tawss_pa", data=self.tawss_pa)
            w.create_dataset("osi", data=self.osi)
        if self.axial_std_pa is not None:
            w.create_dataset("axial_std_pa", data=self.axial_std_pa)
        planes = group.create_group("planes")
        for k, v in self.planes.items():
            planes.create_dataset(k, data=np.asarray(v))

    @classmethod
    def read(cls, group) -> VesselResult:
        """The result :meth:`write` stored."""
        from .centerline import Centerline

        where = getattr(group, "name", "vessel group")
        for name in ("centerline", "s_mm", "phi_rad", "wall/point_mm", "wss/vector_pa", "planes/s_mm"):
            if name not in group:
                raise InputError(f"{where}: missing '{name}' of a vessel result")

        def text(name, default="{}"):
            v = group.attrs.get(name, default)
            return json.loads(v.decode() if isinstance(v, bytes) else v)

        w = group["wss"]
        src = group.attrs.get("source", "")
        return cls(
            method=str(group.attrs.get("method", "reconstruction")),
            centerline=Centerline.read(group["centerline"]),
            s_mm=group["s_mm"][()],
            phi=group["phi_rad"][()],
            time_ms=group["time_ms"][()],
            wall_mm=group["wall/point_mm"][()],
            normal=group["wall/normal"][()],
            radius_mm=group["wall/radius_mm"][()],
            area_mm2=group["wall/area_mm2"][()],
            flags=group["wall/flags"][()].astype(np.uint8),
            wss_pa=w["vector_pa"][()],
            axial_pa=w["axial_pa"][()],
            circumferential_pa=w["circumferential_pa"][()],
            planes={k: group["planes"][k][()] for k in group["planes"]},
            viscosity_pa_s=float(group.attrs["viscosity_pa_s"]),
            affine_mm=np.asarray(group.attrs["affine_mm"], float),
            source=src.decode() if isinstance(src, bytes) else str(src),
            tawss_pa=w["tawss_pa"][()] if "tawss_pa" in w else None,
            osi=w["osi"][()] if "osi" in w else None,
            parameters=text("parameters"),
            statuses=text("statuses"),
            seconds=text("seconds"),
            notes=text("notes", "[]"),
            record=text("record"),
            axial_std_pa=w["axial_std_pa"][()] if "axial_std_pa" in w else None,
            band=text("band"),
        )


def write_result(path, result: VesselResult, name: str | None = None, mode: str = "a") -> None:
    """Add ``result`` as the group ``name`` (default ``vessel`` or ``baseline``) of the HDF5 file ``path``."""
    import h5py

    name = name or ("vessel" if result.method == "reconstruction" else "baseline")
    with h5py.File(path, mode) as f:
        if name in f:
            del f[name]
        result.write(f.create_group(name))


def read_result(path, name: str = "vessel") -> VesselResult:
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{path}: cannot read as HDF5 ({exc})") from None
    with f:
        if name not in f:
            raise InputError(f"{path}: no '{name}' group (a vessel result); run the volume reconstruction first")
        return VesselResult.read(f[name])


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)


# ------------------------------------------------------------------ helpers
def progress_bar(total: int, what: str):
    """A tqdm bar on stderr when it is a terminal, else nothing (the log has the steps)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=what, unit="step", disable=not sys.stderr.isatty(), leave=False)


def check_volume(vol: VolumeAcquisition, options: VesselOptions) -> float:
    """Validate the volume for the reconstruction; the viscosity (Pa s). Refusals are one :class:`InputError`."""
    vol.validate()
    mu = vol.viscosity(options.viscosity_pa_s)
    v = np.asarray(vol.velocity)
    names = "xyz"
    for a in range(3):
        for b in range(a + 1, 3):
            if np.any(v[:, a]) and np.array_equal(v[:, a], v[:, b]):
                raise InputError(
                    f"{vol.source}: velocity components {names[a]} and {names[b]} are identical; they cannot be told "
                    "apart (the same file given twice?); give one file per world component"
                )
    if not np.any(v):
        raise InputError(f"{vol.source}: the velocity is zero everywhere; nothing flows, no wall shear stress")
    return mu


def _record_for(centerline, mask, vol, coords, h) -> dict:
    """A centreline record for a given centreline: the visible part from the mask's radius, no branches."""
    s = np.linspace(0.0, centerline.length_mm, max(8, int(np.ceil(centerline.length_mm / (0.5 * h))) + 1))
    radius = g3.radius_from_mask(mask, vol, coords, s)
    dist = distance_to_border(centerline.position(s), vol.affine_mm, vol.shape)
    visible = [iv for iv in intervals(s, dist >= radius) if iv[1] - iv[0] >= h]
    return {"length_mm": centerline.length_mm, "radius": {"s_mm": s.tolist(), "radius_mm": radius.tolist()},
            "visible": visible, "branches": [], "given": True}  # fmt: skip


def _branch_test(branches: list):
    """``(s, phi) -> bool``: inside any branch's flagged region (its s interval and angle sector)."""
    regions = [(b["flag"]["s_mm"], b["flag"]["phi"]) for b in branches if "flag" in b]
    if not regions:
        return None

    def inside(s, phi):
        s, phi = np.asarray(s, float), np.asarray(phi, float)
        out = np.zeros(np.broadcast(s, phi).shape, bool)
        for (s0, s1), (p0, p1) in regions:
            mid, half = 0.5 * (p0 + p1), 0.5 * (p1 - p0)
            dphi = np.abs(np.angle(np.exp(1j * (phi - mid))))
            out |= (s >= s0) & (s <= s1) & (dphi <= half)
        return out

    return inside


# ------------------------------------------------------------------ the driver
def reconstruct_vessel(
    vol: VolumeAcquisition,
    options: VesselOptions | None = None,
    mask: np.ndarray | None = None,
    centerline=None,
    record: dict | None = None,
    inputs: VesselInputs | None = None,
) -> VesselResult:
    """Wall map of the vessel in ``vol`` (module notes): one frame, or every frame of a cine (rigid walls).

    Parameters
    ----------
    vol : VolumeAcquisition
    options : VesselOptions
    mask : bool array, optional
        The lumen on the volume's grid (``--mask``); default :func:`wss_nlp.vessel.segmentation.segment_vessel`.
    centerline : Centerline, optional
        (``--centerline``); default :func:`wss_nlp.vessel.centerline.centerline_from_mask`.
    record : dict, optional
        The centreline's record (visible part, branches) when ``centerline`` is given with one.
    inputs : VesselInputs, optional
        What :func:`vessel_inputs` prepared from ``vol`` (mask, centreline, the volume less its offset, their
        notes): used as they are, instead of ``mask``, ``centerline`` and ``record`` (the command line prepares
        them once for the reconstruction and the baseline).
    """
    options = options or VesselOptions()
    with blas_threads(options.blas_threads):
        return _reconstruct(vol, options, mask, centerline, record, inputs)


@dataclass
class VesselInputs:
    """The lumen mask, the centreline and its record (visible part, branches) a reconstruction starts from, and
    the volume its fits take (the background offset removed: ``offset``)."""

    mask: np.ndarray
    centerline: Any
    record: dict | None
    notes: list
    seconds: dict
    volume: VolumeAcquisition
    offset: dict = field(default_factory=dict)


def vessel_inputs(vol: VolumeAcquisition, options: VesselOptions | None = None, mask=None,
                  centerline=None, record: dict | None = None) -> VesselInputs:  # fmt: skip
    """The mask (given or :func:`wss_nlp.vessel.segmentation.segment_vessel`) and the centreline (given or
    :func:`wss_nlp.vessel.centerline.centerline_from_mask`): what :func:`reconstruct_vessel` and
    :func:`wss_nlp.vessel.baseline.baseline_vessel` share."""
    from .centerline import centerline_from_mask
    from .segmentation import segment_vessel

    options = options or VesselOptions()
    seconds: dict = {}
    notes: list[str] = []
    t0 = time.perf_counter()
    if mask is None:
        seg = segment_vessel(vol, options.vessel_point)
        mask = seg.mask
        notes.append(f"mask: PC-MRA segmentation ({seg.record['selected_by']}, {seg.record['voxels']} voxels)")
    else:
        mask = np.asarray(mask, bool)
        if mask.shape != tuple(vol.shape):
            raise InputError(f"{vol.source}: the mask's grid {list(mask.shape)} is not the volume's {list(vol.shape)}")
        notes.append("mask: given")
    seconds["segmentation"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if centerline is None:
        centerline, record = centerline_from_mask(mask, vol)
        notes.append("centreline: from the mask (minimal-path tree, cross-section centroids)")
    else:
        notes.append(f"centreline: given ({getattr(centerline, 'source', '')})")
    seconds["centerline"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    offset: dict = {"applied": False, "reason": "switched off (--no-offset-correction)"}
    if options.offset_correction:
        from .background import correct_volume

        vol, rec = correct_volume(vol, mask)
        offset = rec.as_dict()
        if rec.note():
            notes.append(str(rec.note()))
    seconds["offset"] = time.perf_counter() - t0
    return VesselInputs(mask, centerline, record, notes, seconds, vol, offset)


def _reconstruct(vol, options: VesselOptions, mask, centerline, record, inputs=None) -> VesselResult:
    import scipy.ndimage as ndi

    t_all = time.perf_counter()
    mu = check_volume(vol, options)
    h = float(np.max(vol.voxel_size_mm))
    bar = progress_bar(5 + vol.nt, "vessel")
    inputs = inputs or vessel_inputs(vol, options, mask, centerline, record)
    mask, centerline, record, vol = inputs.mask, inputs.centerline, inputs.record, inputs.volume
    seconds, notes = dict(inputs.seconds), list(inputs.notes)
    bar.update()
    # voxels near the vessel with their centres' centreline coordinates
    t0 = time.perf_counter()
    spacing = np.asarray(vol.voxel_size_mm, float)
    dt = ndi.distance_transform_edt(mask, sampling=spacing)
    r_max = float(dt.max())
    reach = 0.35 * 2 * r_max + 6 * h  # the widest box (R/4 or 2h) plus the points' reach, generously
    near = ndi.binary_dilation(mask, iterations=int(np.ceil(reach / spacing.min())))
    coords = tube.voxel_coordinates(vol, np.argwhere(near), centerline)
    if record is None:
        record = _record_for(centerline, mask, vol, coords, h)
        notes.append("branches: not known for a given centreline (none flagged)")
    visible = [tuple(v) for v in record.get("visible", [])]
    if not visible:
        raise InputError(
            f"{vol.source}: no part of the vessel's centreline lies one radius inside the field of view; "
            "nothing to reconstruct"
        )
    ext = 4 * h if options.extend_mm is None else float(options.extend_mm)
    s_range = (max(0.0, min(v[0] for v in visible) - ext), min(centerline.length_mm, max(v[1] for v in visible) + ext))
    s_grid = np.linspace(0.0, centerline.length_mm, max(16, int(np.ceil(centerline.length_mm / (0.5 * h))) + 1))
    exclude = _branch_test(record.get("branches", []))
    problem = g3.problem_from_mask(vol, centerline, mask, coords, s_range, s_grid, exclude)
    frame, levels = problem.frame, problem.levels
    seconds["preparation"] = time.perf_counter() - t0
    bar.update()
    t0 = time.perf_counter()
    geometry = g3.fit_wall(problem, options.geometry)
    seconds["geometry"] = time.perf_counter() - t0
    bar.update()
    t0 = time.perf_counter()
    vp = v3.assemble(vol, geometry, frame, coords, options.velocity,
                     static_level=lambda s: np.interp(s, levels.s_mm, levels.static), exclude=exclude)  # fmt: skip
    velocity = v3.fit_velocity(vol, vp, options.velocity, levels=levels)
    if "noise-free" in velocity.beta_choice.rule:  # no noise for a rule to balance: a fixed beta, which may not suit
        notes.append(
            f"noise-free data: beta fixed at {velocity.beta:g} (no noise for GCV or the discrepancy to balance); "
            "it suits parabolic-type profiles and over-smooths blunt ones (the pulsatile phantom without noise: 36 % "
            "off at 1e-5, 1.8 % at 1e-9): give --beta for noise-free phantoms of other flows"
        )
    seconds["velocity"] = time.perf_counter() - t0
    times = np.zeros(1) if vol.trigger_times_ms is None else np.asarray(vol.trigger_times_ms, float)
    period = vol.cardiac_period_ms
    cycle = None
    if vol.nt > 1:
        if period is None:  # frames equally spaced over one cycle, as a cine export has them
            period = float(times[-1] - times[0] + np.mean(np.diff(times)))
            notes.append(f"cardiac period not in the file: {period:.1f} ms assumed (the frames cover one cycle)")
        t0 = time.perf_counter()
        velocity, cycle = cycle3d.fit_cycle(vol, vp, velocity, options.cycle, times, period, levels)
        seconds["cycle"] = time.perf_counter() - t0
        notes.append(cycle.note())
    bar.update()
    t0 = time.perf_counter()
    s, phi = wss3d.wall_grid(s_range, h, options.n_phi, options.s_spacing_mm)
    ss, pp = (v.ravel() for v in np.meshgrid(s, phi, indexing="ij"))
    ns, nph = s.size, phi.size
    pieces = wss3d.wall_pieces(centerline, geometry, velocity.basis, ss, pp)
    ev = wss3d.wall_wss(centerline, geometry, velocity, ss, pp, mu=mu, progress=bar, pieces=pieces)
    seconds["wss"] = time.perf_counter() - t0
    wall = ev.x.reshape(ns, nph, 3)
    radius = geometry.radius(ss, pp).reshape(ns, nph)
    ds = float(s[1] - s[0]) if ns > 1 else h
    area = ev.area.reshape(ns, nph) * ds * (2 * np.pi / nph)
    flags = _flags(s, phi, wall, radius, geometry, velocity, record, exclude, vol, options, h)
    wss = ev.tau.reshape(vol.nt, ns, nph, 3)
    axial_a = ev.axial.reshape(vol.nt, ns, nph)
    circ_a = ev.circumferential.reshape(vol.nt, ns, nph)
    planes = plane_table(centerline, geometry, velocity, s, phi, radius, wss, axial_a, flags)
    note = reynolds_note(planes, mu, vol.density_kg_m3, times)
    if note:
        notes.append(note)
    t0 = time.perf_counter()
    prior = None if cycle is None else cycle.prior
    axial_std, planes["mean_wss_std_pa"], band = wall_band(vol, velocity, levels, pieces, wss, ring_weights(
        geometry, s, phi, radius), area, flags, mu, prior)  # fmt: skip
    if not band.get("available"):
        notes.append(band["note"])
    seconds["band"] = time.perf_counter() - t0
    tawss = osi = None
    if vol.nt > 1:
        tawss, osi = cycle_indices(wss, times, period)
    bar.update()
    bar.close()
    seconds["total"] = time.perf_counter() - t_all
    notes.append("walls rigid: one wall from the time-mean magnitude serves every frame")
    if vp.basis.capped:
        notes.append("velocity map: the wall is far from round at s in " + ", ".join(
            f"[{a:.1f}, {b:.1f}]" for a, b in vp.basis.capped) + " mm; the map's inner radius is capped there and "
            "the wall points are flagged unresolved")  # fmt: skip
    statuses = {"geometry": g3.stats_dicts(geometry.stats),
                "velocity": {"beta_rule": velocity.beta_choice.rule,
                             "residual_m_s": velocity.residual_norm}}  # fmt: skip
    parameters = {
        "alpha": geometry.alpha, "kappa_mm4": geometry.kappa, "smoothing_mm": geometry.smoothing_mm,
        "gamma_mm": geometry.gamma, "quad_order": geometry.q, "n_fourier": geometry.basis.n_fourier,
        "knot_spacing_mm": geometry.basis.spline.delta, "beta": velocity.beta,
        "velocity_kappa": vp.kappa, "velocity_knot_spacing_mm": vp.basis.spline.delta,
        "zernike_degree": vp.basis.disk.degree, "zernike_angular_order": vp.basis.disk.max_order,
        "fitted_range_mm": list(s_range), "levels": levels.as_dict(),
        "geometry_options": geometry.options, "velocity_options": dict(vars(options.velocity)),
        "offset": inputs.offset, "inner_capped_mm": [list(v) for v in vp.basis.capped],
        "cycle": None if cycle is None else cycle.as_dict(),
    }  # fmt: skip
    log.info("vessel: %d x %d wall points, %d frames, %.0f %% covered, %.1f s", ns, nph, vol.nt,
             100 * float(np.mean(flags == 0)), seconds["total"])  # fmt: skip
    return VesselResult(
        method="reconstruction", centerline=centerline, s_mm=s, phi=phi, time_ms=times, wall_mm=wall,
        normal=ev.normal.reshape(ns, nph, 3), radius_mm=radius, area_mm2=area, flags=flags, wss_pa=wss,
        axial_pa=axial_a, circumferential_pa=circ_a, planes=planes, viscosity_pa_s=mu,
        affine_mm=np.asarray(vol.affine_mm, float), source=vol.source, tawss_pa=tawss, osi=osi,
        parameters=parameters, statuses=statuses, seconds=seconds, notes=notes, record=record,
        axial_std_pa=axial_std, band=band, fits=VesselFits(vol, geometry, velocity, levels, pieces, mu),
    )  # fmt: skip


@dataclass
class VesselFits:
    """What a reconstruction in memory keeps beside its result (not written): the volume its fits took (the
    offset removed), the wall, the velocity fit, the magnitude's levels and noise, the wall points' pieces
    (:func:`wss_nlp.vessel.wss3d.wall_pieces`) and the viscosity."""

    volume: VolumeAcquisition
    geometry: Any
    velocity: Any
    levels: Any
    pieces: Any
    mu: float


def wall_band(vol, velocity, levels, pieces, wss, ring_w, area, flags, mu,
              prior: band3d.TemporalPrior | None = None) -> tuple[np.ndarray, np.ndarray, dict]:  # fmt: skip
    """The band of :mod:`wss_nlp.vessel.band3d` on a reconstruction's pieces: ``(wss/axial_std_pa,
    planes/mean_wss_std_pa, the band's record)``; NaN with a note in the record where it cannot be computed (no
    venc: the velocity noise needs it; none is invented)."""
    nt, ns, nph, _ = wss.shape
    if vol.venc_m_s is None:
        return band3d.unavailable(nt, ns, nph, "no uncertainty band: the volume has no velocity encoding (venc), "
                                  "which the velocity noise needs; import with --venc")  # fmt: skip
    covered = (flags == 0) * area
    total = float(np.sum(covered))
    area_w = covered / total if total > 0 else covered
    sigma = v3.velocity_noise(vol, velocity.problem, levels)
    try:
        b = band3d.vessel_band(pieces, velocity, sigma, wss, ring_w, area_w, mu, prior)
    except ValueError as exc:
        return band3d.unavailable(nt, ns, nph, f"no uncertainty band: {exc}")
    return b.axial_std_pa, b.plane_mean_std_pa, b.record()


def _flags(s, phi, wall, radius, geometry, velocity, record, exclude, vol, options, h) -> np.ndarray:
    ns, nph = radius.shape
    flags = np.zeros((ns, nph), np.uint8)
    ss, pp = np.meshgrid(s, phi, indexing="ij")
    if exclude is not None:
        flags[exclude(ss, pp)] |= FLAG_BRANCH
    visible = np.zeros(ns, bool)
    for a, b in record.get("visible", []):
        visible |= (s >= a) & (s <= b)
    flags[~visible] |= FLAG_NOT_VISIBLE
    border = h if options.border_mm is None else float(options.border_mm)
    dist = distance_to_border(wall.reshape(-1, 3), vol.affine_mm, vol.shape).reshape(ns, nph)
    flags[dist < border] |= FLAG_BORDER
    unresolved = radius < min_radius_voxels(options.velocity) * h
    if np.any(geometry.box_active):  # a box row on its bound: the points within a knot and a box angle of it
        i_s, i_p = np.nonzero(geometry.box_active)
        ds_box = geometry.basis.spline.delta
        dphi_box = 2 * np.pi / geometry.box_phi.size
        for a, b in zip(i_s, i_p):
            near_s = np.abs(s - geometry.box_s[a]) <= ds_box
            near_p = np.abs(np.angle(np.exp(1j * (phi - geometry.box_phi[b])))) <= dphi_box
            unresolved |= near_s[:, None] & near_p[None, :]
    for a, b in velocity.basis.capped:  # the velocity's map needed its inner radius capped: a wall far from round
        unresolved[(s >= a) & (s <= b)] = True
    if not all(st.converged for st in geometry.stats):
        unresolved[:] = True
    flags[unresolved] |= FLAG_UNRESOLVED
    return flags


def cycle_indices(wss: np.ndarray, times_ms, period_ms) -> tuple[np.ndarray, np.ndarray]:
    """TAWSS (Pa) and OSI of WSS vectors ``(nt, ...)`` over one cycle: periodic trapezoid weights
    (:func:`wss_nlp.pipeline.cine.cycle_weights`), ``TAWSS = sum w |tau| / T``,
    ``OSI = (1 - |sum w tau| / sum w |tau|) / 2``."""
    from ..pipeline.cine import cycle_weights, tawss_osi

    if period_ms is None:
        raise InputError("a cine needs its cardiac period ('cardiac_period_ms') for TAWSS and OSI")
    w = cycle_weights(times_ms, float(period_ms))
    mag = np.linalg.norm(wss, axis=-1)
    flat = mag.reshape(mag.shape[0], -1)
    tawss, _ = tawss_osi(flat, w)  # the magnitude's cycle mean (the scalar OSI of |tau| is not the vector's)
    net = np.linalg.norm(np.tensordot(w, wss, axes=(0, 0)), axis=-1).ravel()
    total = np.sum(w[:, None] * flat, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        osi = np.where(total > 0, 0.5 * (1.0 - net / total), 0.0)
    return tawss.reshape(mag.shape[1:]), np.clip(osi, 0.0, 0.5).reshape(mag.shape[1:])


def plane_table(centerline, geometry, velocity, s, phi, radius, wss, axial, flags, n_rho: int = 12) -> dict:
    """Per cross-section: area (``int R^2 / 2 dphi``), flow rate through it along ``t`` (``int u . t dA`` on the
    reference disk, Gauss-Legendre in ``rho``, uniform in ``theta``), mean ``|tau|`` and axial WSS over the ring
    (arc-length weights ``sqrt(R^2 + R_phi^2)``), flags or-ed."""
    ns, nph = radius.shape
    dphi = 2 * np.pi / nph
    area = 0.5 * np.sum(radius**2, axis=1) * dphi
    basis = velocity.basis
    x, wq = np.polynomial.legendre.leggauss(n_rho)
    rho = 0.5 * (x + 1)
    wr = 0.5 * wq
    ss, rr, pp = (v.ravel() for v in np.meshgrid(s, rho, phi, indexing="ij"))
    big_r = geometry.radius(ss, pp)
    r_in = basis.r_in(ss)
    r = r_in * rr + (big_r - r_in) * rr**2
    jac = r * (r_in + 2 * (big_r - r_in) * rr)  # r dr/drho
    t = centerline.frame(s)[0]
    nt = wss.shape[0]
    flow = np.zeros((nt, ns))
    for k in range(nt):
        u = basis.evaluate(velocity.coefficients[k], ss, r * (1 - 1e-12), pp)  # (m, 3)
        along = np.sum(u.reshape(ns, n_rho, nph, 3) * t[:, None, None, :], axis=-1)
        flow[k] = np.einsum("inj,n->i", along * jac.reshape(ns, n_rho, nph), wr) * dphi  # mm^2 m/s = 1e-6 m^3/s = mL/s
    weights = ring_weights(geometry, s, phi, radius)
    mean_wss = np.einsum("tij,ij->ti", np.linalg.norm(wss, axis=-1), weights)
    mean_axial = np.einsum("tij,ij->ti", axial, weights)
    ring = np.bitwise_or.reduce(flags, axis=1)
    return {"s_mm": s, "area_mm2": area, "flow_ml_s": flow, "mean_wss_pa": mean_wss, "mean_axial_pa": mean_axial,
            "flags": ring.astype(np.uint8)}  # fmt: skip


def bulk_reynolds(planes: dict, mu: float, density_kg_m3: float) -> np.ndarray:
    r"""The bulk Reynolds number ``Re = rho U D / mu`` per frame and plane ``(nt, ns)``: ``U = Q / A`` the mean
    velocity through the plane (``planes['flow_ml_s']``, ``planes['area_mm2']``), ``D = 2 sqrt(A / pi)`` its
    equivalent diameter; ``|Q|`` (reverse flow counts alike)."""
    area_m2 = np.asarray(planes["area_mm2"], float) * 1e-6
    u = np.abs(np.asarray(planes["flow_ml_s"], float)) * 1e-6 / np.maximum(area_m2, 1e-300)
    return density_kg_m3 * u * 2.0 * np.sqrt(area_m2 / np.pi) / mu


def reynolds_note(planes: dict, mu: float, density_kg_m3: float | None, times_ms) -> str | None:
    """A note when the flow may be transitional or turbulent: the median over the unflagged planes of the bulk
    Reynolds number (:func:`bulk_reynolds`) above :data:`TRANSITION_REYNOLDS` in some frame. The volume route fits
    the plain basis (no near-wall models for volumes), which underestimates a wall layer thinner than the voxels."""
    rho = DEFAULT_DENSITY if density_kg_m3 is None else float(density_kg_m3)
    keep = np.asarray(planes["flags"]) == 0
    if not np.any(keep):
        return None
    re = np.median(bulk_reynolds(planes, mu, rho)[:, keep], axis=1)
    k = int(np.argmax(re))
    if not re[k] > TRANSITION_REYNOLDS:
        return None
    when = f" at {float(np.asarray(times_ms)[k]):g} ms" if re.size > 1 else ""
    source = "stated" if density_kg_m3 is not None else "assumed (blood's)"
    return (
        f"bulk Reynolds number {re[k]:.0f}{when} (median over the planes; density {rho:g} kg/m^3 {source}) is "
        f"above {TRANSITION_REYNOLDS:.0f}: the flow may be transitional or turbulent, and a wall layer thinner "
        "than the voxels is not resolved by the volume route (no near-wall models for volumes): its WSS may be "
        "underestimated there"
    )


def ring_weights(geometry, s, phi, radius) -> np.ndarray:
    """Each plane's arc-length weights ``sqrt(R^2 + R_phi^2)`` over its ring ``(ns, np)``, rows summing to one."""
    ns, nph = radius.shape
    r_phi = geometry.radius(np.repeat(s, nph), np.tile(phi, ns), dphi=1).reshape(ns, nph)
    arc = np.sqrt(radius**2 + r_phi**2)
    return arc / arc.sum(axis=1, keepdims=True)
