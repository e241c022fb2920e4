"""The steps of a reconstruction that act on one slice's data, whatever fits its geometry and velocity.

* :func:`prepare`: preprocessing (normalization, lumen, radius box) into a :class:`SliceData` record, which
  also fixes the noise venc the parameter rules and the band use;
* :func:`near_wall_model` and :func:`beta_choice`: the velocity model and its beta
  (:mod:`wss_nlp.parameters.layer`, :mod:`wss_nlp.parameters.beta`);
* :func:`predict_dephasing`: the signal loss that decides a corrected pass;
* :func:`coupled_weight`: the coupled method's velocity weight;
* :func:`noise_levels`: the band's noise levels.

The driver (:mod:`wss_nlp.pipeline.driver`) runs them on every segment, its fitter
(:mod:`wss_nlp.pipeline.fitters`) solving what couples the slices.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from ..models import dephasing as deph
from ..models import geometry as geo
from ..models import acquisition as acq_model
from ..models import kspace
from ..models import preprocess as pp
from ..models import surround
from ..models import velocity as vel
from ..errors import InputError
from ..models.measurement import VoxelGrid
from ..parameters import noise as nl
from ..parameters.beta import gcv_beta, velocity_beta
from ..parameters.coupled_weight import coupled_weight as choose_coupled_weight
from ..parameters.layer import layer_model

if TYPE_CHECKING:
    from .options import ReconstructionOptions

#: What a long stack solve is doing (segments, sweeps) goes here at INFO level (the CLI shows it on stderr).
logger = logging.getLogger("wss_nlp.models.stack")


@dataclass
class SliceData:
    """One slice's inputs and what preprocessing found: the record every step takes."""

    index: int
    where: str  # "<source> slice <index>", for messages
    raw: np.ndarray  # the measured magnitude (raw units)
    velocity: np.ndarray  # the measured through-plane velocity, m/s
    grid: VoxelGrid
    norm: pp.Normalization
    magnitude: np.ndarray  # normalized
    lumen: pp.Lumen
    venc: float | None  # of the phase data (None: velocity combined from encodings)
    noise_venc: float | None  # the venc of the velocity noise: venc, or the file's noise venc without a plateau
    psf: kspace.PSF | None = None  # the k-space acquisition model (None: voxel means)
    start: tuple | None = None  # radius coefficients to start the geometry from (a cine frame's neighbour)
    inplane: np.ndarray | None = None  # (2, ny, nx): the in-plane velocity components x, y in m/s (4D flow)
    seconds: float = 0.0  # preprocessing time

    @property
    def problem(self) -> geo.GeometryProblem:
        """The geometry problem of the slice (Sec. 2)."""
        lum = self.lumen
        return geo.GeometryProblem(self.grid, self.magnitude, lum.center, lum.r0, lum.r1, lum.r_area, psf=self.psf)


def prepare(
    raw,
    velocity,
    grid: VoxelGrid,
    index: int,
    source: str,
    vessel=None,
    psf: kspace.PSF | None = None,
    venc: float | None = None,
    noise_venc: float | None = None,
    box: pp.LumenBox | None = None,
    inplane: np.ndarray | None = None,
    tissue: surround.TissueOptions | None = None,
) -> SliceData:
    """Preprocess one slice (:func:`wss_nlp.models.surround.preprocess`) into its :class:`SliceData`.

    ``box`` replaces the lumen's own origin and radius box (cine frames) and may carry a warm start;
    ``inplane``: the slice's in-plane velocity components (4D flow). ``noise_venc`` sets the velocity
    noise when there is no ``venc`` and the lumen has no plateau to measure it on (the plateau's level is
    preferred: it also holds what the data's placement adds). ``tissue``: the surround model and the offset
    correction (:func:`wss_nlp.models.surround.preprocess`; None: their defaults).
    """
    where = f"{source} slice {index}"
    # hook (issue 39): the surround model, flow-aware lumen and background offset correction; the velocity the
    # fits use comes back with the offset removed and the partial-volume voxels' lumen phase, and the raw
    # magnitude with the magnitude that carries that phase (the noise estimates' |d_i|)
    near = None if box is None else box.center  # cine: the series' vessel, also in a frame of slow flow
    series = None if box is None else box.offset  # cine: the series' one background offset of this slice
    measured = raw
    norm, m, lumen, velocity, raw = surround.preprocess(
        raw, velocity, grid, where, vessel, venc, acq_model.of(psf), tissue, near, series
    )
    if inplane is not None and lumen.tissue is not None and (tissue is None or tissue.offset_correction):
        # each in-plane encoding direction has its own eddy-current offset (4D flow): fitted on the same static tissue
        inplane, records = surround.correct_inplane(inplane, measured, grid, lumen, venc, acq_model.of(psf))
        lumen.tissue["offset_inplane"] = records
    if box is not None:
        lumen = box.apply(lumen)
    nvenc = venc
    if venc is None and nl.velocity_plateau(lumen.noise_mask).sum() < nl.MIN_PLATEAU_VOXELS:
        nvenc = noise_venc
    start = None if box is None else box.start
    velocity = np.asarray(velocity, float)
    return SliceData(index, where, raw, velocity, grid, norm, m, lumen, venc, nvenc, psf, start, inplane)


def near_wall_model(
    data: SliceData, vp: vel.VelocityProblem, options: ReconstructionOptions, mu: float, density, lumen=None,
    around=None,
):  # fmt: skip
    """``(velocity problem, NearWallChoice)``: the slice's near-wall model (``--near-wall``; ``around``: an
    earlier choice on a nearby geometry to refine), or ``(vp, None)`` with ``--near-wall off``."""
    if options.velocity.near_wall == "off":
        return vp, None
    lumen = data.lumen if lumen is None else lumen
    return layer_model(
        vp, data.raw, lumen, data.noise_venc, options.velocity, options.choice.noise_velocity, data.where, mu, density,
        around=around,
    )  # fmt: skip


def beta_choice(data: SliceData, vp, near, options: ReconstructionOptions, mu: float, lumen=None):
    """The slice's beta (:func:`wss_nlp.parameters.beta.velocity_beta`: the rule's, or a layer's BIC beta)."""
    lumen = data.lumen if lumen is None else lumen
    return velocity_beta(
        vp, near, data.raw, lumen, data.noise_venc, options.choice, options.velocity, options.n_phi, data.where, mu
    )


def predict_dephasing(
    data: SliceData, vp: vel.VelocityProblem, v, geometry, options: ReconstructionOptions, window=None
):  # fmt: skip
    """``(Correction, the velocity it used)``: the dephasing factors of the wall voxels and the corrected images
    (:func:`wss_nlp.models.dephasing.correct`) from the velocity ``v`` or, by default (``--dephasing-beta gcv``, or
    without ``v``), from a GCV-beta fit: dephasing is set by the velocity variation inside wall voxels, which
    a beta tuned for WSS may smooth away (turbulent layers). ``window``: the k-space misfit window. Needs the
    phase data's venc (the drivers call it only then)."""
    if data.venc is None:
        raise InputError(f"{data.where}: the dephasing correction needs the venc of the phase data")
    if v is None or options.choice.dephasing_beta_rule == "gcv":
        v = vel.solve(vp, replace(options.velocity, solver="cholesky"), beta=gcv_beta(vp, options.choice).chosen)
    corr = deph.correct(
        data.magnitude, data.raw, data.norm.m0, data.velocity, vp, v.evaluate_physical, data.venc,
        geometry.coefficients, geometry.center, data.grid, data.psf, window,
    )  # fmt: skip
    return corr, v


def coupled_weight(data: SliceData, problem, velocity_image, options: ReconstructionOptions, lumen=None):
    """``(weight, how)``: the coupled method's velocity weight
    (:func:`wss_nlp.parameters.coupled_weight.coupled_weight`: ``--velocity-weight``, or the likelihood weight
    from the estimated noise levels)."""
    lumen = data.lumen if lumen is None else lumen
    return choose_coupled_weight(
        options.coupled.velocity_weight, problem, options.geometry, data.raw, data.norm, lumen.noise_mask,
        velocity_image, data.noise_venc, data.where, lumen.signal,
    )  # fmt: skip


def noise_levels(data: SliceData, options: ReconstructionOptions, u_index: np.ndarray, lumen=None):
    """``(sigma_m, sigma_u on u_index, how)`` of the band (:func:`wss_nlp.parameters.noise.band_noise_levels`)."""
    lumen = data.lumen if lumen is None else lumen
    return nl.band_noise_levels(
        data.raw, lumen.noise_mask, data.norm.m0, data.norm.m1, u_index, data.noise_venc, options.noise_sigma,
        lumen.signal,
    )  # fmt: skip
