"""Is an acquisition physically plausible? Units, velocity aliasing, several vessels.

Runs once per acquisition before any solve (:func:`screen`, called by
:func:`wss_nlp.pipeline.reconstruct.reconstruct` for slices, stacks and baselines
alike), so that data a scanner could not have produced are refused with a
message naming the dataset and the likely cause, and data with a known
defect are repaired with a warning, never reconstructed into a confident
wrong number.

* **Units.** A velocity derived from a phase in (-pi, pi] lies in
  ``[-venc, venc]``; values beyond it (more than :data:`VENC_TOLERANCE`)
  mean the velocity is not in m/s (cm/s, mm/s) or the venc is not; a lumen
  velocity above :data:`MAX_BLOOD_SPEED_M_S` is implausible for blood flow.
* **Aliasing.** Where the true velocity leaves ``[-venc, venc]`` the phase
  wraps, and neighbouring lumen voxels differ by nearly ``2 venc``. The
  wrapped velocity is unwrapped inside the lumen by quality-guided path
  following (Ghiglia & Pritt, *Two-Dimensional Phase Unwrapping*, Wiley
  1998, ch. 4; the minimum-spanning-tree form of Itoh's condition): voxels
  are joined in order of increasing wrapped difference, each taking the
  multiple of ``2 venc`` that keeps its difference to the joined neighbour
  below ``venc``. The reference is the lumen rim, where the no-slip velocity
  is small. Unwrapped data that still jump by more than ``venc`` between
  bright neighbours are refused (the venc is too low for the resolution).
* **Several vessels.** Reported from :attr:`wss_nlp.models.preprocess.Lumen.others`.
* **Intravoxel dephasing** (:func:`check_dephasing`, after the solve). A wall voxel's phase averages
  ``exp(i pi u / venc)`` over the velocities inside it; the box model corrects the magnitude's loss to first
  order and takes the phase as the voxel's mean velocity. Where the velocity varies by about venc or more within
  a wall voxel (a venc below the peak velocity, unwrapped, and a steep boundary layer) neither holds, and the
  WSS comes out 10-60 % off with a residual of about the noise level, which :func:`check_fit` cannot see. The
  predicted magnitude factor ``D_i = |mean exp(i pi u / venc)|`` of the wall voxels tells: the slice is flagged
  when the smallest is below :data:`MIN_DEPHASING_FACTOR_ALIASED` (phase unwrapped) or
  :data:`MIN_DEPHASING_FACTOR` (not).
* **Consistency of the fit** (:func:`check_fit`, after the solve). A smooth
  no-slip velocity fitted at a parameter chosen for the noise leaves a
  residual of about the noise level. A residual far above it
  (:data:`MAX_RESIDUAL_TO_NOISE`) means the data contradict the model: a wrap
  the spatial unwrapping could not see (the velocity rises by more than venc
  within one voxel all around the wall), a wrong venc, a wrong lumen. The
  slice is then flagged with a warning, never passed off as a good answer.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .._lazy import scipy
from ..parameters import noise as nl
from ..models import preprocess as pp
from ..models import surround
from ..errors import InputError, WssNlpError
from ..core.schema import option
from ..io import ranges

#: Fastest plausible blood velocity: jets through severe valve stenoses reach 5-6 m/s.
MAX_BLOOD_SPEED_M_S = 10.0
#: Relative room beyond venc before a velocity counts as out of range (venc rounded in a header).
VENC_TOLERANCE = 0.02
#: Bright neighbour pairs that may still differ by more than venc after unwrapping (noise) before we refuse.
MAX_RESIDUAL_JUMPS = 2
#: Velocity-fit residual / noise level above which a slice is flagged. Measured (scripts/aliasing.py, column
#: res/eps): at most 1.37 on laminar, manufactured, circle and turbulent phantoms, unaliased or correctly unwrapped,
#: h 0.6-1.5 mm; 4.8-9.3 where a hidden wrap survived. 3 leaves a factor of about 2 on both sides.
MAX_RESIDUAL_TO_NOISE = 3.0
#: Smallest predicted dephasing factor D = |mean exp(i pi u / venc)| of a wall voxel (box model) a slice may have
#: before it is flagged (:func:`check_dephasing`). A linear velocity ramp of width du across a voxel gives
#: D = sin(x) / x with x = pi du / (2 venc) (:func:`dephasing_spread`); 2 / pi is a ramp of venc, which an
#: unaliased wall layer (|u| <= venc) exceeds only where it is steeper than linear. Unaliased, the accuracy
#: phantoms (circle, laminar, turbulent, turbulent-ellipse, h 0.6-1.5 mm, SNR 10 and 25, seeds 500-502) keep
#: D >= 0.83 (none of 72 flagged); the entrance flow, the steepest layer, reaches 0.70 at h 1.5 mm
#: (scripts/results/aliasing_clean.md and aliasing_dephasing.md).
MIN_DEPHASING_FACTOR = 2 / np.pi
#: The bound for a slice whose phase was unwrapped (venc below the peak velocity): D = 0.75 is a ramp of 0.8 venc.
#: Chosen on the soak's five silent wrong results (D 0.02-0.71, scripts/results/soak_failures.md) and on
#: scripts/aliasing.py's seed 300 (scripts/results/aliasing_dephasing.md: every unwrapped slice more than 10 % off
#: has D <= 0.68 or a residual flag; it also flags 5 of 14 aliased slices within 10 %, at D 0.47-0.72). Wraps the
#: screen cannot see (entrance flow at venc 0.35 x peak, 63-65 % off) are neither unwrapped nor flagged.
MIN_DEPHASING_FACTOR_ALIASED = 0.75
#: Normalized magnitude above which a voxel joins the unwrapping region (its phase noise is below ~0.4 rad at SNR 10).
UNWRAP_MAGNITUDE = 0.25
#: A magnitude voxel this many times above both the image's 97th percentile and its neighbours' median is a
#: corrupt value (a spike), not signal: inflow-enhanced blood and fat stay within a few times the 99th percentile.
SPIKE_FACTOR = 10.0
#: Mean / standard deviation of a Rayleigh-distributed background (pure noise): sqrt(pi/2) / sqrt(2 - pi/2).
RAYLEIGH_MEAN, RAYLEIGH_STD = float(np.sqrt(np.pi / 2)), float(np.sqrt(2 - np.pi / 2))
#: A background whose spread is below this fraction of its mean is not noise alone (Rayleigh: 0.52; the sample
#: value over the >= 20 background voxels required stays above 0.35 at three standard errors).
OFFSET_SPREAD = 0.25


def parse_point(text) -> tuple[float, float]:
    """``"X,Y"`` (mm) -> ``(x, y)``; an :class:`InputError` names the expected form."""
    try:
        x, y = (float(v) for v in str(text).split(","))
    except ValueError:
        raise InputError(f"--vessel takes two numbers X,Y in mm, e.g. --vessel 12.5,-3; got {text!r}") from None
    return (x, y)


@dataclass(frozen=True)
class ScreenOptions:
    """What the plausibility screen may do.

    ``vessel``: (x, y) in mm of the vessel to reconstruct when several are in
    view (default: the largest lumen). ``unwrap``: unwrap aliased phase
    (default); False uses the velocities as given (they were unwrapped
    elsewhere, or the user accepts them), with a warning where wraps are seen,
    and skips the ``[-venc, venc]`` range check. ``allow_unphysical``: the quantities
    (:data:`wss_nlp.io.ranges.QUANTITIES`, or ``("all",)``) whose values are used as given outside their plausible
    range. ``allow_large``: run options estimated to take longer than :data:`wss_nlp.pipeline.limits.TIME_LIMIT_S`
    a slice (:mod:`wss_nlp.pipeline.limits`).
    """

    schema_group = "input checks"

    vessel: tuple[float, float] | None = option(
        None,
        "with several vessels in view, reconstruct the one at this "
        "point (mm, image frame; default: the largest lumen; the others "
        "are reported)",
        cli="--vessel",
        metavar="X,Y",
        parse=parse_point,
    )
    unwrap: bool = option(
        True,
        "use the velocities as given: no phase unwrapping (aliasing is then only reported) "
        "and no [-venc, venc] range check (for data unwrapped by other software)",
        cli="--no-unwrap",
        flag_off=True,
    )
    allow_unphysical: tuple[str, ...] = option(
        (),
        "use values outside the plausible ranges of the docs page 'Input checks' as given (all quantities, or "
        "those named: viscosity, density, voxel_size, fov, slice_spacing, venc, velocity, radius, frame_spacing, "
        "period, snr); recorded in the result",
        cli="--allow-unphysical",
        toml=("allow_unphysical",),
        metavar="QUANTITY,...",
        parse=ranges.parse_allow,
        const="all",
        default_text="none",
    )
    allow_large: bool = option(
        False,
        "run options estimated to need more than the time limit per slice (docs, 'Input checks'); what would not "
        "fit in memory is refused anyway",
        cli="--allow-large",
        toml=("allow_large",),
        flag_on=True,
    )

    def __post_init__(self):
        object.__setattr__(self, "allow_unphysical", ranges.parse_allow(self.allow_unphysical) if
                           self.allow_unphysical else ())  # fmt: skip
        if self.vessel is not None:
            v = np.asarray(self.vessel, dtype=float)
            if v.shape != (2,) or not np.all(np.isfinite(v)):
                raise InputError(f"vessel must be two finite numbers X,Y in mm, got {self.vessel}")


def _wrap(d: np.ndarray | float, venc: float):
    """Map a velocity difference into ``[-venc, venc)``."""
    return (np.asarray(d) + venc) % (2 * venc) - venc


def unwrap_velocity(v: np.ndarray, region: np.ndarray, venc: float, rim: np.ndarray) -> np.ndarray:
    """Unwrap a velocity image inside ``region`` (bool mask) by quality-guided path following.

    Returns the unwrapped image; voxels outside ``region`` are unchanged.
    Each connected part of ``region`` is seeded at its rim voxel of smallest
    ``|v|`` and shifted afterwards by the multiple of ``2 venc`` that brings
    the median of its ``rim`` voxels closest to zero (no slip).
    """
    out = np.array(v, dtype=float, copy=True)
    ny, nx = v.shape
    done = np.zeros(v.shape, dtype=bool)
    heap: list = []  # (|wrapped difference|, y, x, unwrapped value): the most reliable join first

    def push(y, x):
        # 4-neighbours, as scipy.ndimage.label connects the parts: a neighbour in the region is in the same part
        for yy, xx in ((y - 1, x), (y + 1, x), (y, x - 1), (y, x + 1)):
            if 0 <= yy < ny and 0 <= xx < nx and region[yy, xx] and not done[yy, xx]:
                d = float(_wrap(v[yy, xx] - out[y, x], venc))
                heapq.heappush(heap, (abs(d), yy, xx, out[y, x] + d))

    labels, n = scipy.ndimage.label(region)
    for part in range(1, n + 1):
        inside = labels == part
        seeds = np.argwhere(inside & rim)
        if seeds.size == 0:
            seeds = np.argwhere(inside)
        iy, ix = seeds[np.argmin(np.abs(v[seeds[:, 0], seeds[:, 1]]))]
        done[iy, ix] = True
        push(iy, ix)
        while heap:
            _, y, x, value = heapq.heappop(heap)
            if done[y, x]:
                continue
            done[y, x] = True
            out[y, x] = value
            push(y, x)
        ref = rim & inside
        shift = np.round(-np.median(out[ref if ref.any() else inside]) / (2 * venc))
        out[inside] += 2 * venc * shift
    return out


def residual_jumps(u: np.ndarray, mask: np.ndarray, venc: float) -> int:
    """Number of 4-neighbour pairs inside ``mask`` whose velocities differ by more than ``venc``."""
    n = 0
    for a, b, ma, mb in ((u[1:], u[:-1], mask[1:], mask[:-1]), (u[:, 1:], u[:, :-1], mask[:, 1:], mask[:, :-1])):
        n += int(np.sum((np.abs(a - b) > venc) & ma & mb))
    return n


def _unit_hint(value: float, limit: float) -> str:
    """Which common units bring ``value`` within ``limit`` m/s (all that do: the data cannot tell them apart)."""
    fits = [
        f"{unit} (divide by {factor:g})"
        for factor, unit in ((100.0, "cm/s"), (1000.0, "mm/s"))
        if value / factor <= limit
    ]
    return "the values look like " + " or ".join(fits) if fits else "the values are not velocities in m/s"


def check_velocity_range(acq, name: str, velocity: np.ndarray) -> None:
    """Velocities from a phase in (-pi, pi] lie in ``[-venc, venc]``; raise :class:`InputError` otherwise."""
    venc = acq.venc_m_s
    finite = velocity[np.isfinite(velocity)]
    if venc is None or finite.size == 0:
        return
    vmax = float(np.max(np.abs(finite)))
    if vmax > venc * (1 + VENC_TOLERANCE):
        # a few times venc: unwrapped elsewhere, or a wrong venc; tens to thousands of times: another unit
        hint = (
            _unit_hint(vmax, venc * (1 + VENC_TOLERANCE))
            if vmax > 10 * venc
            else f"{vmax / venc:.2g} x venc: is venc_m_s right?"
        )
        raise InputError(
            f"{acq.source}: '{name}' reaches {vmax:.4g} but venc_m_s = {venc:g}: a velocity from a phase lies in "
            f"[-venc, venc] m/s; {hint}; if the velocities were unwrapped by other software, pass --no-unwrap"
        )


def _check_speed(acq, iz: int, name: str, velocity: np.ndarray, lumen_mask: np.ndarray, allow=()) -> str:
    """Refuse a lumen velocity beyond any blood flow; without venc, say which reading an unusual peak took."""
    vals = np.abs(velocity[lumen_mask])
    peak = float(np.percentile(vals, 99)) if vals.size else 0.0
    where = f"{acq.source} slice {iz}: '{name}'"
    if peak > MAX_BLOOD_SPEED_M_S and not ranges.allowed("velocity", allow):
        venc_hint = (
            f"; the venc is given as venc_m_s = {acq.venc_m_s:g}: is it in cm/s?" if acq.phase is not None else ""
        )
        raise InputError(
            f"{where} reaches {peak:.4g} m/s in the lumen, implausible for blood flow "
            f"(> {MAX_BLOOD_SPEED_M_S:g} m/s); {_unit_hint(peak, MAX_BLOOD_SPEED_M_S)}{venc_hint}"
        )
    if acq.venc_m_s is None:  # with a venc the velocity is in the venc's unit, whose range was checked
        return ranges.check("velocity", peak, f"{where} (99th percentile in the lumen)", allow, "store")
    return ""


def repair_spikes(magnitude: np.ndarray) -> tuple[np.ndarray, int, float]:
    """Isolated corrupt magnitude voxels (:data:`SPIKE_FACTOR`) replaced by their 3 x 3 neighbours' median.

    Returns ``(magnitude, number replaced, the largest)``; the input is not modified.
    """
    mag = np.asarray(magnitude, dtype=float)
    finite = mag[np.isfinite(mag)]
    if finite.size < 16:
        return mag, 0, 0.0
    level = float(np.percentile(finite, 97))  # robust to spikes in up to 3 % of the voxels
    if not level > 0:
        return mag, 0, 0.0
    around = scipy.ndimage.median_filter(mag, size=3, mode="nearest")
    spikes = np.isfinite(mag) & (mag > SPIKE_FACTOR * level) & (mag > SPIKE_FACTOR * np.abs(around))
    if not spikes.any():
        return mag, 0, 0.0
    out = np.where(spikes, around, mag)
    return out, int(spikes.sum()), float(mag[spikes].max())


def background_offset(magnitude: np.ndarray, lumen: pp.Lumen) -> float:
    """The constant added to a magnitude whose background is not noise alone (module notes), or 0.

    A background of pure noise is Rayleigh distributed, its spread 0.52 of its mean. A spread below
    :data:`OFFSET_SPREAD` of the mean is a constant offset (a scanner baseline, an export that shifted the values)
    or a signal in the background (static tissue): either way the noise level taken from the background's power
    would be that level's size, not the noise's. The offset is ``mean - sqrt(pi/2) sigma`` with ``sigma`` the
    Rayleigh scale of the spread; removing it leaves the normalized magnitude as it was (an affine change of the
    raw values) and the noise estimates their noise.
    """
    outer = ~scipy.ndimage.binary_dilation(lumen.noise_mask, iterations=2)
    bg = np.asarray(magnitude, dtype=float)[outer]
    bg = bg[np.isfinite(bg)]
    if bg.size < 20:
        return 0.0
    mean, spread = float(np.mean(bg)), float(np.std(bg))
    if not (mean > 0 and spread < OFFSET_SPREAD * mean):
        return 0.0
    sigma = spread / RAYLEIGH_STD
    return max(mean - RAYLEIGH_MEAN * sigma, 0.0)


@dataclass
class SliceScreen:
    """What the screen found in one slice (stored in the result as ``screen_json``)."""

    notes: list
    record: dict


def _screen_slice(
    acq, iz: int, velocity: np.ndarray, lumen: pp.Lumen, m: np.ndarray, options: ScreenOptions
) -> tuple[np.ndarray, SliceScreen]:
    where = f"{acq.source} slice {iz}"
    notes: list[str] = []
    record: dict[str, Any] = {
        "other_vessels": lumen.others,
        "vessel_chosen_by": lumen.chosen_by,
        "lumen_voxels": int(lumen.mask.sum()),
        "lumen_radius_mm": float(lumen.r_area),
    }
    radius_note = ranges.check(
        "radius", lumen.r_area, f"{where}: the lumen ({int(lumen.mask.sum())} voxels of 'voxel_size_mm' "
        f"{acq.voxel_size_mm[0]:g} x {acq.voxel_size_mm[1]:g} mm)", options.allow_unphysical,
    )  # fmt: skip
    if radius_note:
        notes.append(radius_note)
    if lumen.others:
        notes.append(lumen.others_note())
    if lumen.tissue and lumen.tissue.get("static_bright"):  # hook (issue 39)
        record["static_bright_regions"] = lumen.tissue["static_bright"]
    venc, out = acq.venc_m_s, velocity
    if venc is not None:
        region = (scipy.ndimage.binary_dilation(lumen.mask) & (m > UNWRAP_MAGNITUDE)) | lumen.mask
        changed = jumps = 0
        if residual_jumps(velocity, region, venc):  # no jump beyond venc anywhere: nothing can have wrapped
            rim = region & ~scipy.ndimage.binary_erosion(region)
            unwrapped = unwrap_velocity(velocity, region, venc, rim)
            changed = int(np.sum(np.abs(unwrapped - velocity) > venc))
            jumps = residual_jumps(unwrapped, lumen.mask, venc)
        record.update({"aliased_voxels": changed, "residual_jumps": jumps, "unwrapped": False})
        if changed and options.unwrap:
            if jumps > MAX_RESIDUAL_JUMPS:
                raise InputError(
                    f"{where}: velocity aliasing (venc_m_s = {venc:g}) that cannot be unwrapped consistently: "
                    f"{jumps} neighbouring lumen voxels still differ by more than venc; the venc is too low for "
                    "this resolution; re-acquire with a higher venc, or pass --no-unwrap to use the data as they are"
                )
            out = unwrapped
            record["unwrapped"] = True
            notes.append(
                f"velocity aliasing: {changed} voxel(s) wrapped beyond venc = {venc:g} m/s were unwrapped "
                f"by multiples of 2 venc (peak |v| now {float(np.max(np.abs(out[region]))):.3g} m/s; "
                "--no-unwrap keeps them as measured)"
            )
        elif changed:
            notes.append(
                f"velocity aliasing suspected: {changed} lumen voxel(s) differ from their neighbours by "
                f"about 2 venc = {2 * venc:g} m/s; used as measured (--no-unwrap)"
            )
    speed_note = _check_speed(
        acq, iz, "velocity" if acq.phase is None else "venc_m_s x phase / pi", out, lumen.mask, options.allow_unphysical
    )
    if speed_note:
        notes.append(speed_note)
    return out, SliceScreen(notes, record)


def screen(acq, options: ScreenOptions | None = None):
    """Check units, unwrap aliasing and report other vessels, for every usable slice.

    Returns ``(acquisition, {slice index: SliceScreen})``: the acquisition
    with the through-plane velocity replaced by the unwrapped one where
    wraps were found (``phase`` dropped, ``velocity`` in m/s); the input
    object is not modified. Slices that cannot be preprocessed (NaN, no
    vessel) are left to the reconstruction, which reports them; in a single
    slice such errors are raised here. Unit errors and aliasing that cannot
    be unwrapped are raised whatever the number of slices: they are
    properties of the acquisition, not of one slice.
    """
    options = options or ScreenOptions()
    velocity = acq.velocity_images()
    if options.unwrap:
        check_velocity_range(acq, "velocity" if acq.phase is None else "phase", velocity)
    bad = set(acq.nonfinite_slices())
    found, fixed, magnitude = {}, None, None
    repairs: dict[int, list[str]] = {}
    for iz in range(acq.nz):
        if iz in bad:
            continue
        mag_iz, spikes, worst = repair_spikes(acq.magnitude[iz])
        if spikes:
            repairs.setdefault(iz, []).append(
                f"{spikes} isolated magnitude voxel(s) exceeded {SPIKE_FACTOR:g}x both the image's 97th percentile "
                f"and their neighbours (up to {worst:.4g}): corrupt values, replaced by their neighbours' median"
            )
        try:
            # hook (issue 39): the lumen among the bright regions that flow; static bright tissue (fat) is
            # neither the vessel nor "another vessel in view" (wss_nlp.models.surround.screen_preprocess)
            _, m, lumen = surround.screen_preprocess(
                mag_iz, velocity[iz], acq.grid, f"{acq.source} slice {iz}", options.vessel, acq.venc_m_s
            )
            offset = background_offset(mag_iz, lumen) if not (lumen.tissue or {}).get("static_bright") else 0.0
            if offset > 0:  # issue 42: a constant offset in air (tissue is the surround model's: issue 39)
                repairs.setdefault(iz, []).append(
                    f"the magnitude's background is not noise alone (its spread is under {OFFSET_SPREAD:g} of its "
                    f"mean; pure noise: {RAYLEIGH_STD / RAYLEIGH_MEAN:.2f}): a constant offset of {offset:.4g} "
                    "(a scanner baseline, a shifted export) was subtracted, else the noise levels would be the "
                    "offset's size"
                )
                mag_iz = np.maximum(mag_iz - offset, 0.0)
                _, m, lumen = surround.screen_preprocess(
                    mag_iz, velocity[iz], acq.grid, f"{acq.source} slice {iz}", options.vessel, acq.venc_m_s
                )
        except WssNlpError:  # no vessel, lumen on the border: a stack reports the slice as failed later
            if acq.nz == 1:
                raise
            continue
        if iz in repairs:
            if magnitude is None:
                magnitude = np.array(acq.magnitude, dtype=float, copy=True)
            magnitude[iz] = mag_iz
        v_iz, found[iz] = _screen_slice(acq, iz, np.asarray(velocity[iz], dtype=float), lumen, m, options)
        if iz in repairs:
            found[iz].notes[:0] = repairs[iz]
            found[iz].record["magnitude_repaired"] = repairs[iz]
        if found[iz].record.get("unwrapped"):
            if fixed is None:
                fixed = np.array(velocity, dtype=float, copy=True)
            fixed[iz] = v_iz
    if fixed is not None:
        acq = replace(acq, velocity=fixed, phase=None)
    if magnitude is not None:
        acq = replace(acq, magnitude=magnitude)
    return acq, found


def check_fit(result, raw_magnitude: np.ndarray, venc: float | None) -> tuple[str, float]:
    """``(warning or "", residual / noise)`` of a reconstructed slice's velocity fit (see module notes).

    The noise level is the one the parameter rule estimated, or (fixed beta)
    the same estimate made here (:func:`wss_nlp.parameters.noise.velocity_noise`).
    """
    v = result.velocity
    noise = result.beta_choice.noise if result.beta_choice is not None else float("nan")
    if not (np.isfinite(noise) and noise > 0):
        try:
            noise = nl.velocity_noise(
                result.velocity_image,
                raw_magnitude,
                result.lumen.noise_mask,
                v.voxel_index,
                v.voxel_fraction * result.grid.voxel_area,
                venc,
                signal=result.lumen.signal,
            ).value
        except WssNlpError:
            return "", float("nan")
    if not noise > 0:
        return "", float("nan")
    ratio = float(v.residual_norm / noise)
    if ratio <= MAX_RESIDUAL_TO_NOISE:
        return "", ratio
    cause = (
        f"hidden velocity aliasing (venc_m_s = {venc:g}: re-acquire with a higher venc if the flow may exceed it)"
        if venc is not None
        else "velocities in other units or from another slice"
    )
    return (
        f"SUSPECT: the velocity fit leaves a residual {ratio:.1f} x the noise level (> "
        f"{MAX_RESIDUAL_TO_NOISE:g}): the data contradict a smooth no-slip flow in this lumen; likely {cause}, "
        "or a wrong lumen; this slice's WSS is not trustworthy"
    ), ratio


def dephasing_spread(factor: float) -> float:
    """The velocity range ``du / venc`` across a voxel that a linear ramp needs to give dephasing ``factor``.

    ``|mean_{t in [0, 1]} exp(i pi du t / venc)| = |sin(x) / x|`` with ``x = pi du / (2 venc)``, inverted on
    its first lobe (``0 < x <= pi``: factors 1 to 0, spreads 0 to 2 venc); a reading of the factor in words.
    """
    x = np.linspace(1e-9, np.pi, 2001)
    d = np.sin(x) / x  # decreasing from 1 to 0 on the first lobe
    return float(2 / np.pi * np.interp(min(max(factor, 0.0), 1.0), d[::-1], x[::-1]))


def check_dephasing(min_factor: float, venc: float | None, unwrapped: bool) -> str:
    """A SUSPECT warning (or ``""``) when a wall voxel's predicted dephasing factor is below
    :data:`MIN_DEPHASING_FACTOR` (module notes, "Intravoxel dephasing").

    ``min_factor``: the smallest ``D_i`` of the slice's first dephasing check (``SliceResult.dephasing``; 1 when
    none was predicted); ``unwrapped``: the screen unwrapped aliasing in the slice (named in the message).
    """
    bound = MIN_DEPHASING_FACTOR_ALIASED if unwrapped else MIN_DEPHASING_FACTOR
    if venc is None or not (np.isfinite(min_factor) and min_factor < bound):
        return ""
    cause = "the venc is below the peak velocity (the phase was unwrapped)" if unwrapped else "a low venc"
    return (
        f"SUSPECT: intravoxel dephasing: a wall voxel keeps {min_factor:.0%} of its magnitude (the fitted velocity "
        f"varies by about {dephasing_spread(min_factor):.2g} x venc inside it; flagged below {bound:.0%}"
        f"{' after unwrapping' if unwrapped else ''}): the voxel-mean model's dephasing correction and its reading "
        f"of the wall voxels' phase as their mean velocity do not hold there, and the WSS is biased; cause: {cause}; "
        f"re-acquire with a higher venc (venc_m_s = {venc:g}) or smaller voxels; this slice's WSS is not trustworthy"
    )
