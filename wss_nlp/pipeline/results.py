"""Per-slice results: what every method returns for a slice, and the record of a reconstruction.

:class:`SliceOutcome` is the protocol every per-slice result satisfies
(:class:`SliceResult`, :class:`wss_nlp.models.baselines.BaselineResult`,
:class:`wss_nlp.io.files.FailedSlice`): an index, whether its solves converged,
and the warnings to show the user.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from ..models import near_wall as nw
from .state import DephasingRecord

if TYPE_CHECKING:
    from .state import SliceState
    from ..parameters import rules as pr
    from ..models import geometry as geo
    from ..models import preprocess as pp
    from ..models.steady import SteadyCheck
    from ..uncertainty import sensitivity as sens
    from ..models import velocity as vel
    from ..models import wss as wss_mod
    from ..models.measurement import VoxelGrid


@runtime_checkable
class SliceOutcome(Protocol):
    """What every per-slice result provides."""

    index: int

    @property
    def converged(self) -> bool: ...

    @property
    def warnings(self) -> list[str]: ...


#: A velocity fit with more effective parameters than this fraction of its voxels interpolates the noise.
DOF_LIMIT = 0.75


@dataclass
class SliceResult:
    """Result of one slice, with everything needed to write, plot and judge it."""

    index: int
    geometry: geo.GeometryResult
    velocity: vel.VelocityResult
    wss: wss_mod.WssResult
    normalization: pp.Normalization
    lumen: pp.Lumen
    grid: VoxelGrid
    magnitude: np.ndarray  # normalized, (ny, nx)
    velocity_image: np.ndarray  # measured velocity, (ny, nx)
    seconds: dict = field(default_factory=dict)  # wall-clock seconds per stage
    alpha_choice: pr.ParameterChoice | None = None
    beta_choice: pr.ParameterChoice | None = None
    method: str = "decoupled"
    coupled_info: dict = field(default_factory=dict)  # weight, how it was chosen, the decoupled start's numbers
    sensitivity: sens.Sensitivity | None = None
    notes: list = field(default_factory=list)  # things the user should know that are not failures
    screen: dict = field(default_factory=dict)  # what wss_nlp.pipeline.plausibility found (vessels, aliasing)
    near_wall: nw.NearWallChoice | None = None  # the near-wall model and why (wss_nlp.parameters.layer.choose_layer)
    dephasing: DephasingRecord = field(default_factory=DephasingRecord)  # what the dephasing passes did
    # the velocity problem of the final fit, kept only with a deferred band (cine frames), then dropped
    problem: vel.VelocityProblem | None = None
    # the uncertainty band still to compute (reconstruct(defer_band=True)): () -> (Sensitivity, note)
    pending_band: Callable[[], tuple] | None = None
    # whether the data can come from steady flow (wss_nlp.models.steady; None: not tested, --near-wall off)
    steady: SteadyCheck | None = None

    def finish_band(self) -> None:
        """Compute a deferred uncertainty band (sets ``wss.tau_std``, ``wss.mean_std``, ``sensitivity``)."""
        if self.pending_band is None:
            return
        t0 = time.perf_counter()
        self.sensitivity, note = self.pending_band()
        self.pending_band = None
        if note:
            self.notes.append(note)
        self.seconds["uncertainty"] = time.perf_counter() - t0

    @property
    def converged(self) -> bool:
        return bool(self.geometry.stats.converged and self.velocity.stats.converged)

    @property
    def warnings(self) -> list[str]:
        out = []
        for name, st in (("geometry", self.geometry.stats), ("velocity", self.velocity.stats)):
            if not st.converged:
                out.append(f"slice {self.index}: {name} solve did not converge ({st.solver}: {st.status})")
        for ch in (self.alpha_choice, self.beta_choice):
            if ch is not None and ch.noise == 0:
                out.append(f"slice {self.index}: {ch.name}: {ch.noise_method}: {ch.name} = {ch.chosen:g}")
            if ch is not None and ch.rule == "discrepancy" and not ch.satisfied:
                out.append(
                    f"slice {self.index}: no {ch.name} reached residual <= {ch.tau:g} x noise "
                    f"({ch.noise:.3g}); model error dominates, took {ch.name} = {ch.chosen:.3g} where the "
                    "residual stopped falling"
                )
        ch = self.beta_choice
        if ch is not None and ch.rule == "balance" and not ch.satisfied:
            out.append(
                f"slice {self.index}: SUSPECT: beta reached the end of its range ({ch.chosen:.2g}) without a "
                f"balance: the WSS kept changing by more than {ch.tau:g} noise deviations as beta fell, which "
                "noise cannot do; the data hold something the voxel model does not describe (resampled or "
                "misregistered images, another acquisition model); this slice's WSS is not trustworthy"
            )
        n_vox = int(np.count_nonzero(self.velocity.voxel_fraction))
        if self.velocity.dof > DOF_LIMIT * n_vox:
            out.append(
                f"slice {self.index}: SUSPECT: the velocity fit spends {self.velocity.dof:.0f} effective parameters "
                f"on {n_vox} voxels (beta {self.velocity.beta:.2g}): it follows the noise, and its WSS with it "
                "(a lumen few voxels across: use smaller voxels, or a fixed larger --beta)"
            )
        out.extend(f"slice {self.index}: {n}" for n in self.notes)
        nwc = self.near_wall
        if nwc is not None and nwc.criterion.startswith("no velocity noise"):
            out.append(
                f"slice {self.index}: near-wall layer not considered: {nwc.criterion} (noise-free data?); "
                "pass --noise-velocity, or --near-wall wall_law/exponential with --layer-scale"
            )
        if nwc is not None and np.isfinite(nwc.unresolved_mm):
            out.append(
                f"slice {self.index}: SUSPECT: the velocity does not vanish at the wall within a voxel: the best "
                f"fit is a layer {nwc.unresolved_mm:.2g} mm thick that the voxel data cannot resolve (under "
                f"1/{nw.UNRESOLVED_FRACTION:g} of the voxel, or fitted without any regularization); its WSS is not "
                "determined and the plain model's is not trustworthy either (causes: misregistered or resampled "
                "images, an acquisition the box model does not describe)"
            )
        if nwc is not None and nwc.warning:
            out.append(f"slice {self.index}: {nwc.warning}")
        if nwc is not None and nwc.ambiguous:
            runner = min((m for m in nwc.values if m != nwc.model), key=lambda m: nwc.values[m])
            out.append(
                f"slice {self.index}: near-wall model choice is ambiguous: {nwc.model} beats {runner} by "
                f"BIC {nwc.margin:.2f} < {nw.AMBIGUOUS_MARGIN:g}; the two may give different WSS (see analyze)"
            )
        if self.geometry.box_active:
            out.append(
                f"slice {self.index}: the radius reached the box [{self.geometry.box[0]:.3g}, "
                f"{self.geometry.box[1]:.3g}] mm; the lumen may not be star-shaped about the centre"
            )
        return out


def make_result(
    *,
    state: SliceState,
    wss: wss_mod.WssResult,
    grid: VoxelGrid,
    beta_choice: pr.ParameterChoice | None,
    method: str,
    coupled_info: dict,
    sensitivity: sens.Sensitivity | None,
    notes: list,
    pending_band: Callable[[], tuple] | None,
    seconds: dict,
    steady: SteadyCheck | None = None,
) -> SliceResult:
    """The :class:`SliceResult` of a slice at the end of the steps (keyword-only: the one place results are made).

    The magnitude is the normalized one preprocessing made, the velocity image the measured one (not a
    dephasing-corrected copy); the velocity problem is kept for a deferred band (the driver drops it otherwise).
    """
    data = state.data
    return SliceResult(
        index=data.index,
        geometry=state.geometry,
        velocity=state.velocity,
        wss=wss,
        normalization=data.norm,
        lumen=state.lumen,
        grid=grid,
        magnitude=data.magnitude,
        velocity_image=np.asarray(data.velocity, float),
        seconds=seconds,
        alpha_choice=state.alpha_choice,
        beta_choice=beta_choice,
        method=method,
        coupled_info=coupled_info,
        sensitivity=sensitivity,
        notes=notes,
        near_wall=state.near,
        dephasing=state.dephasing,
        problem=state.velocity_problem,
        pending_band=pending_band,
        steady=steady,
    )
