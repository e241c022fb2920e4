"""Plausibility ranges of the physical quantities a user gives, and the unit mistakes each one catches.

Every number with a unit that reaches wss-nlp (a file attribute, an option, a study key) is checked against
one :class:`Quantity` of :data:`QUANTITIES` before any work: viscosity, density, voxel size, field of view,
slice spacing, venc, velocity, vessel radius, frame spacing, cardiac period and SNR. Each has

* a **plausible range** ``[low, high]`` (with the source it comes from): a value outside it is refused with one
  line that names the file field or option, what the value would be in the unit it was most likely given in,
  and the fix (``'viscosity_pa_s' = 3.5 Pa s is 1000x blood's (3.5e-3 Pa s); mPa s (cP) given? store 3.5e-3``);
* a **usual range** inside it: a value outside the usual range that a unit slip would bring into it cannot be
  told from a real one (dm/s read as a 5 m/s stenotic jet, centimetre voxels in preclinical data); it is used
  as given, and the result says which reading was taken and why (a ``CHECK UNITS`` note).

``--allow-unphysical`` (all quantities) or ``--allow-unphysical viscosity,venc`` (those named) uses values
outside the plausible range as given; the result records it (a note on every slice, the options).

The ranges are deliberately wide: they exist to catch factors of 10 to 1000, not to judge physiology.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import InputError

#: The note's first words where a value could be a unit slip but is used as given.
CHECK_UNITS = "CHECK UNITS"


@dataclass(frozen=True)
class Slip:
    """A unit mistake: the value was given in ``unit``; ``value * factor`` is it in the quantity's unit."""

    unit: str
    factor: float


@dataclass(frozen=True)
class Quantity:
    """A physical quantity's plausible and usual ranges, the unit slips it catches and where the numbers come from.

    Attributes
    ----------
    name : str
        What ``--allow-unphysical`` names (``viscosity``, ``voxel_size``, ...).
    label, unit : str
        How messages name it and its unit (``"viscosity"``, ``"Pa s"``).
    low, high : float
        The plausible range: outside it a value is refused (unless allowed).
    usual : tuple of float
        The usual range: a value outside it but plausible, which a slip brings into it, is noted.
    reference : float
        A typical value, for the message's ratio ("1000x blood's").
    reference_text : str
        What ``reference`` is (``"blood's"``).
    slips : tuple of Slip
        Unit mistakes, the likeliest first.
    source : str
        Where the ranges come from.
    consequence : str
        What a slip does to the result (for the notes).
    """

    name: str
    label: str
    unit: str
    low: float
    high: float
    usual: tuple[float, float]
    reference: float
    reference_text: str
    slips: tuple[Slip, ...]
    source: str
    consequence: str = ""

    def slip_for(self, value: float) -> Slip | None:
        """The likeliest slip behind ``value``: the first that brings it into the usual range, else the first that
        brings it into the plausible one, else None."""
        for lo, hi in (self.usual, (self.low, self.high)):
            found = next((s for s in self.slips if lo <= value * s.factor <= hi), None)
            if found is not None:
                return found
        return None

    def slips_for(self, value: float, within: tuple[float, float]) -> list[Slip]:
        """Every slip that brings ``value`` into ``within``."""
        return [s for s in self.slips if within[0] <= value * s.factor <= within[1]]

    def range_text(self) -> str:
        return f"{_fmt(self.low)}-{_fmt(self.high)} {self.unit}"


def _fmt(x: float) -> str:
    return f"{x:.4g}"


QUANTITIES: dict[str, Quantity] = {
    q.name: q
    for q in (
        Quantity(
            "viscosity", "viscosity", "Pa s", 3e-4, 2e-2, (2.5e-3, 6e-3), 3.5e-3, "blood's",
            (Slip("mPa s (cP)", 1e-3), Slip("P (poise)", 0.1), Slip("a kinematic viscosity in m^2/s (nu; mu = rho nu)",
                                                                     1060.0)),
            "blood 3-4 mPa s at the high shear rates near a wall (Merrill, Physiol Rev 49:863, 1969), more in "
            "polycythaemia; water 0.3-1 mPa s (90-20 C); glycerol-water phantom fluids up to about 20 mPa s",
            "the WSS scales with the viscosity",
        ),
        Quantity(
            "density", "density", "kg/m^3", 500.0, 3000.0, (990.0, 1100.0), 1060.0, "blood's",
            (Slip("g/cm^3 (g/ml)", 1000.0),),
            "blood 1043-1060 kg/m^3 (Kenner, Basic Res Cardiol 84:111, 1989); water 998 kg/m^3; glycerol-water "
            "phantom fluids up to 1260 kg/m^3; the range admits any liquid a phantom may use",
            "only the law-of-the-wall layer uses it (nu = mu / rho)",
        ),
        Quantity(
            "voxel_size", "voxel size", "mm", 0.02, 5.0, (0.4, 4.0), 1.5, "a clinical voxel's",
            (Slip("cm", 10.0), Slip("m", 1000.0), Slip("um", 1e-3)),
            "clinical 2D phase contrast 0.5-2 mm, 4D flow 1.5-3.5 mm (Dyverfeldt et al., J Cardiovasc Magn Reson "
            "17:72, 2015); preclinical (7-9.4 T, mouse and rat) down to 0.05 mm, MR microscopy 0.02 mm",
            "lengths, the radius and the WSS scale with it (a 10x voxel gives 1/10 the WSS)",
        ),
        Quantity(
            "fov", "field of view", "mm", 0.5, 600.0, (2.0, 500.0), 300.0, "a body scan's",
            (Slip("m", 1000.0), Slip("um", 1e-3)),  # centimetres: cropped and whole fields of view overlap
            "no scanner bore is wider than 600 mm (whole-body 60-70 cm bores hold a field of view of at most "
            "50 cm); images cropped around a vessel may be a few millimetres wide",
            "as the voxel size's",
        ),
        Quantity(
            "slice_spacing", "slice spacing", "mm", 0.02, 50.0, (0.4, 20.0), 2.0, "a stack's",
            (Slip("cm", 10.0), Slip("m", 1000.0), Slip("um", 1e-3)),
            "2D stacks 1-10 mm, 4D flow 1.5-3.5 mm (Dyverfeldt 2015), preclinical 0.1-1 mm; 50 mm is no longer "
            "one vessel's stack",
            "z-derivatives of the wall and the z-regularization scale with it",
        ),
        Quantity(
            "venc", "venc", "m/s", 0.02, 8.0, (0.05, 4.0), 1.5, "an arterial venc's",
            (Slip("cm/s", 0.01), Slip("mm/s", 1e-3)),
            "CSF and venous flow 0.05-0.3 m/s, arteries 1-2 m/s, stenoses up to 4-6 m/s (Nayak et al., J "
            "Cardiovasc Magn Reson 17:71, 2015; Dyverfeldt 2015); no scanner encodes above 8 m/s in practice",
            "velocities from a phase scale with the venc, and the WSS with them",
        ),
        Quantity(
            "velocity", "peak lumen velocity", "m/s", 0.0, 10.0, (0.02, 2.5), 1.0, "peak arterial flow's",
            (Slip("cm/s", 0.01), Slip("dm/s", 0.1), Slip("mm/s", 1e-3)),
            "peak velocities 0.05-0.3 m/s in veins, 1-1.5 m/s in the aorta, 2.5-6 m/s only in stenotic jets "
            "(Nishimura et al., Circulation 129:e521, 2014: severe aortic stenosis >= 4 m/s); nothing in blood "
            "flow reaches 10 m/s",
            "the WSS scales with the velocity",
        ),
        Quantity(
            "radius", "lumen radius", "mm", 0.1, 40.0, (0.25, 20.0), 10.0, "the aorta's",
            (Slip("m", 1000.0),),  # centimetres: a mouse's aorta and a human's overlap (the voxel size's note says it)
            "mouse carotid 0.25 mm, human aorta 10-15 mm, aneurysms up to about 40 mm (Hiratzka et al., "
            "Circulation 121:e266, 2010)",
            "the WSS scales with 1/radius",
        ),
        Quantity(
            "frame_spacing", "frame spacing", "ms", 1.0, 300.0, (5.0, 100.0), 40.0, "a cine's",
            (Slip("s", 1000.0), Slip("us", 1e-3)),
            "temporal resolution 20-50 ms in human 2D and 4D flow (Dyverfeldt 2015), 5-10 ms in mice; 300 ms "
            "is less than three frames a cycle",
            "TAWSS and OSI weigh frames by their spacing",
        ),
        Quantity(
            "period", "cardiac period", "ms", 80.0, 3000.0, (300.0, 2000.0), 1000.0, "a resting human's",
            (Slip("s", 1000.0), Slip("us", 1e-3)),
            "heart rates 20-250 beats/min in humans (240-3000 ms), 300-750 in mice and rats (80-200 ms)",
            "TAWSS and OSI are averages over the period",
        ),
        Quantity(
            "snr", "SNR", "", 2.0, 1000.0, (5.0, 200.0), 25.0, "a typical image's",
            (),
            "phase-contrast magnitudes have SNR 10-100; below 2 no lumen stands out of the noise; above 1000 "
            "use a noise-free phantom (SNR 0)",
        ),
    )
}  # fmt: skip


def _named(names) -> tuple[str, ...]:
    return tuple(names) if names else ()


def parse_allow(text) -> tuple[str, ...]:
    """``--allow-unphysical`` (``all`` or a comma list of :data:`QUANTITIES` names) -> the names allowed."""
    if isinstance(text, (list, tuple)):
        words = [str(w).strip() for w in text]
    else:
        words = [w.strip() for w in str(text).split(",")]
    words = [w.replace("-", "_").lower() for w in words if w]
    if not words or words == ["all"]:
        return ("all",)
    bad = [w for w in words if w not in QUANTITIES]
    if bad:
        raise InputError(
            f"--allow-unphysical {','.join(bad)}: unknown quantity; name some of {', '.join(QUANTITIES)}, or 'all'"
        )
    return tuple(words)


def allowed(name: str, allow) -> bool:
    allow = _named(allow)
    return "all" in allow or name in allow


def _ratio_text(value: float, q: Quantity) -> str:
    if not (q.reference and value > 0):
        return ""
    r = value / q.reference
    ref = f"{q.reference:g} {q.unit}".strip()
    if r >= 1:
        return f" is {_round_ratio(r)}x {q.reference_text} ({ref})"
    return f" is 1/{_round_ratio(1 / r)} of {q.reference_text} ({ref})"


def _round_ratio(r: float) -> str:
    """1000 for 999.7, 10 for 10.3, 2.3 for 2.3: powers of ten shown as such, others to two digits."""
    p = 10 ** round(math.log10(r))
    if abs(r / p - 1) < 0.05:
        return f"{p:g}"
    return f"{r:.2g}" if r < 100 else f"{r:.0f}"


def check(name: str, value, where: str, allow=(), fix: str = "", impossible=()) -> str:
    """Check ``value`` of quantity ``name`` (named ``where`` in messages: an option or a file field).

    Returns ``""``, or a note to put in the result: the value is outside the usual range where a unit slip would
    bring it in (the reading taken and why), or outside the plausible range but allowed (``allow``).
    ``impossible``: units of slips that other evidence rules out (no note for them).

    Raises
    ------
    InputError
        One line naming ``where``, the value, the likely unit slip and the fix, when the value is not a finite
        number or lies outside the plausible range and ``allow`` does not name the quantity.
    """
    q = QUANTITIES[name]
    unit = f" {q.unit}" if q.unit else ""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {value!r} is not a number ({q.label} in {q.unit or 'plain numbers'})") from None
    if not math.isfinite(v):
        raise InputError(f"{where}: {q.label} must be a finite number{' in ' + q.unit if q.unit else ''}, got {v}")
    if v <= 0 and q.low >= 0 and name != "velocity":
        raise InputError(f"{where}: {q.label} must be > 0{unit}, got {v:g}")
    if not q.low <= v <= q.high:
        if allowed(name, allow):
            return (
                f"{where}: {q.label} {v:g}{unit} lies outside the plausible range {q.range_text()}; used as given "
                f"(--allow-unphysical)"
            )
        slip = q.slip_for(v)
        hint = (
            f"; {slip.unit} given? {fix or 'pass'} {v * slip.factor:.4g}"
            if slip
            else f"; the plausible range is {q.range_text()}"
        )
        raise InputError(
            f"{where}: {q.label} {v:g}{unit}{_ratio_text(v, q)}{hint} (--allow-unphysical {name} if it is right)"
        )
    lo, hi = q.usual
    if not lo <= v <= hi:
        slips = [s for s in q.slips_for(v, q.usual) if s.unit not in impossible]
        if slips:
            side = "below" if v < lo else "above"
            alts = " or ".join(f"{s.unit} ({v * s.factor:.3g}{unit})" for s in slips)
            return (
                f"{CHECK_UNITS}: {where}: {q.label} {v:g}{unit} was read as {q.unit} (plausible, {q.range_text()}, "
                f"but {side} the usual {_fmt(lo)}-{_fmt(hi)}{unit}); if it was given in {alts}, the result is wrong "
                f"({q.consequence}): {fix or 'pass'} the value in {q.unit}"
            )
    return ""


def check_acquisition(
    acq, allow=(), viscosity_given: bool = False, density_given: bool = False, radius_mm: float | None = None
) -> list[str]:
    """The ranges of an acquisition's file fields (voxel size, field of view, slice spacing, venc, viscosity,
    density, the components' venc, the acquired voxel size); returns the notes (:func:`check`).

    ``viscosity_given`` / ``density_given``: the option replaces the file's value, which is then not checked (a
    user who fixes a wrong attribute with ``--viscosity`` is not refused for it). ``radius_mm``: the lumen's radius
    as read, if known: a length slip that would make it wider than any vessel is ruled out (0.3 mm voxels over a
    10 mm lumen are not centimetres).
    """
    src = acq.source
    notes = []
    radius = QUANTITIES["radius"]
    too_wide = tuple(s.unit for s in QUANTITIES["voxel_size"].slips if radius_mm and radius_mm * s.factor > radius.high)
    dy, dx = (float(h) for h in acq.voxel_size_mm)
    for axis, h in (("dy", dy), ("dx", dx)) if dy != dx else (("", dy),):
        where = f"{src}: 'voxel_size_mm'{f' ({axis})' if axis else ''}"
        notes.append(check("voxel_size", h, where, allow, "store", too_wide))
    ny, nx = acq.magnitude.shape[-2:]
    fov = max(ny * acq.voxel_size_mm[0], nx * acq.voxel_size_mm[1])
    if not any(notes):  # a voxel size out of range already explains the field of view
        notes.append(check("fov", fov, f"{src}: field of view ({ny} x {nx} voxels of 'voxel_size_mm')", allow))
    if acq.acquired_voxel_size_mm is not None:
        for h in acq.acquired_voxel_size_mm:
            notes.append(check("voxel_size", h, f"{src}: 'acquired_voxel_size_mm'", allow, "store"))
    if acq.nz > 1 and acq.slice_spacing_mm is not None:
        notes.append(check("slice_spacing", acq.slice_spacing_mm, f"{src}: 'slice_spacing_mm'", allow, "store"))
    for field, name in (("venc_m_s", "venc"), ("noise_venc_m_s", "venc"), ("viscosity_pa_s", "viscosity"),
                        ("density_kg_m3", "density")):  # fmt: skip
        if (field == "viscosity_pa_s" and viscosity_given) or (field == "density_kg_m3" and density_given):
            continue
        value = getattr(acq, field)
        if value is not None:
            notes.append(check(name, value, f"{src}: '{field}'", allow, "store"))
    return _unique(notes)


def check_frames(times_ms, period_ms: float, where: str, allow=()) -> list[str]:
    """The ranges of a cine's timing: the frame spacing and the cardiac period (ms); returns the notes."""
    import numpy as np

    times = np.asarray(times_ms, dtype=float)
    notes = [check("period", period_ms, f"{where}: 'cardiac_period_ms'", allow, "store")]
    if times.size > 1:
        notes.append(check("frame_spacing", float(np.min(np.diff(times))), f"{where}: 'trigger_times_ms'", allow))
    return _unique(notes)


def _unique(notes) -> list[str]:
    out: list[str] = []
    for n in notes:
        if n and n not in out:
            out.append(n)
    return out


def table_markdown() -> list[str]:
    """The ranges as Markdown table rows (the docs page "Input checks" shows them)."""
    lines = [
        "| quantity | plausible (refused outside) | usual (a slip into it is noted) | unit slips caught | source |",
        "|---|---|---|---|---|",
    ]
    for q in QUANTITIES.values():
        unit = f" {q.unit}" if q.unit else ""
        slips = ", ".join(f"{s.unit} (x{s.factor:g})" for s in q.slips) or "-"
        lines.append(
            f"| {q.label} (`{q.name}`) | {_fmt(q.low)}-{_fmt(q.high)}{unit} | {_fmt(q.usual[0])}-{_fmt(q.usual[1])}"
            f"{unit} | {slips} | {q.source} |"
        )
    return lines
