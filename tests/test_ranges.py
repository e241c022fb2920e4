"""Plausibility ranges (wss_nlp.io.ranges): each quantity refuses the unit slips it exists for, names the field and
the fix, notes the readings a slip cannot be told from, and honours --allow-unphysical."""

import numpy as np
import pytest

from wss_nlp.errors import InputError
from wss_nlp.io import ranges
from wss_nlp.io.files import Acquisition

# (quantity, value in a wrong unit, the unit named, the value to pass): every slip of the module's table, each
# caught from the value a user makes with it (blood's 3.5 mPa s in mPa s, poise and as nu in m^2/s; 1.5 mm voxels
# in m and um; a 1.5 m/s venc in cm/s and mm/s; a 1000 ms period in s and us; blood's density in g/cm^3)
SLIPS = [
    ("viscosity", 3.5, "mPa s", "0.0035"),
    ("viscosity", 0.035, "poise", "0.0035"),
    ("viscosity", 3.3e-6, "kinematic", "0.003498"),
    ("density", 1.06, "g/cm^3", "1060"),
    ("voxel_size", 0.0015, "m given", "1.5"),
    ("voxel_size", 1500.0, "um given", "1.5"),
    ("fov", 0.3, "m given", "300"),
    ("slice_spacing", 0.002, "m given", "2"),
    ("venc", 150.0, "cm/s", "1.5"),
    ("venc", 1500.0, "mm/s", "1.5"),
    ("velocity", 40.0, "cm/s", "0.4"),
    ("radius", 0.01, "m given", "10"),
    ("frame_spacing", 0.04, "s given", "40"),
    ("period", 1.0, "s given", "1000"),
]


@pytest.mark.parametrize("name, value, unit, fix", SLIPS)
def test_a_unit_slip_is_refused_with_the_unit_and_the_value_to_pass(name, value, unit, fix):
    with pytest.raises(InputError) as exc:
        ranges.check(name, value, "in.h5: 'field'")
    text = str(exc.value)
    assert text.startswith("in.h5: 'field': ") and unit in text and f"pass {fix}" in text, text
    assert f"--allow-unphysical {name}" in text and "\n" not in text


def test_the_issue_example_message():
    with pytest.raises(InputError, match=r"viscosity 3\.5 Pa s is 1000x blood's \(0\.0035 Pa s\); mPa s \(cP\) "):
        ranges.check("viscosity", 3.5, "--viscosity")


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -1.0, 0.0, "fast", None])
def test_not_a_finite_positive_number_is_refused(value):
    with pytest.raises(InputError, match="--venc"):
        ranges.check("venc", value, "--venc")


@pytest.mark.parametrize(
    "name, value, slip",
    [
        ("voxel_size", 0.15, "cm (1.5 mm)"),  # centimetre voxels, or preclinical ones
        ("velocity", 4.0, "dm/s (0.4 m/s)"),  # dm/s, or a stenotic jet
        ("venc", 5.0, "cm/s (0.05 m/s)"),  # a CSF venc in cm/s, or a stenosis venc
    ],
)
def test_a_value_a_slip_cannot_be_told_from_is_used_and_the_reading_said(name, value, slip):
    note = ranges.check(name, value, "f.h5: 'x'")
    assert note.startswith(ranges.CHECK_UNITS) and "was read as" in note and slip in note, note


@pytest.mark.parametrize("name, value", [("viscosity", 3.5e-3), ("voxel_size", 1.0), ("venc", 1.5),
                                         ("velocity", 0.8), ("period", 800.0), ("density", 998.0)])  # fmt: skip
def test_usual_values_pass_silently(name, value):
    assert ranges.check(name, value, "x") == ""


def test_allow_unphysical_uses_the_value_and_says_so():
    for allow in (("all",), ("viscosity",), ranges.parse_allow("viscosity,venc")):
        note = ranges.check("viscosity", 3.5, "--viscosity", allow)
        assert "used as given (--allow-unphysical)" in note
    with pytest.raises(InputError):
        ranges.check("viscosity", 3.5, "--viscosity", ("venc",))  # another quantity's override does not apply
    assert ranges.parse_allow("") == ("all",) and ranges.parse_allow("voxel-size") == ("voxel_size",)
    with pytest.raises(InputError, match="unknown quantity"):
        ranges.parse_allow("viscosity,frob")


def _acq(**kw):
    base = dict(magnitude=np.ones((1, 20, 20)), phase=np.zeros((1, 20, 20)), voxel_size_mm=(1.5, 1.5),
                venc_m_s=1.0, viscosity_pa_s=3.5e-3, source="in.h5")  # fmt: skip
    base.update(kw)
    return Acquisition(**base)


def test_file_fields_are_checked_and_named():
    assert ranges.check_acquisition(_acq()) == []
    with pytest.raises(InputError, match="in.h5: 'viscosity_pa_s': viscosity 3.5 Pa s"):
        ranges.check_acquisition(_acq(viscosity_pa_s=3.5))
    assert ranges.check_acquisition(_acq(viscosity_pa_s=3.5), viscosity_given=True) == []  # --viscosity replaces it
    with pytest.raises(InputError, match="'voxel_size_mm'"):
        ranges.check_acquisition(_acq(voxel_size_mm=(0.0015, 0.0015)))
    with pytest.raises(InputError, match="field of view"):  # 200 voxels of 4 mm: 800 mm, wider than any bore
        ranges.check_acquisition(_acq(magnitude=np.ones((1, 200, 200)), phase=np.zeros((1, 200, 200)),
                                      voxel_size_mm=(4.0, 4.0)))  # fmt: skip
    notes = ranges.check_acquisition(_acq(voxel_size_mm=(0.15, 0.15)))
    assert len(notes) == 1 and "'voxel_size_mm'" in notes[0] and "cm (1.5 mm)" in notes[0]
    # the lumen as read tells: a 1 mm lumen of 0.15 mm voxels may be a mouse's aorta or a human's in cm ...
    assert len(ranges.check_acquisition(_acq(voxel_size_mm=(0.15, 0.15)), radius_mm=1.0)) == 1
    # ... but a 10 mm lumen of 0.3 mm voxels would be 100 mm wide in cm: no vessel is, so mm it is, silently
    assert ranges.check_acquisition(_acq(voxel_size_mm=(0.3, 0.3)), radius_mm=10.0) == []


def test_cine_timing():
    assert ranges.check_frames([0, 40, 80], 1000.0, "c.h5") == []
    with pytest.raises(InputError, match="'cardiac_period_ms'.*s given"):
        ranges.check_frames([0, 0.04], 1.0, "c.h5")


def test_every_quantity_has_a_source_and_a_usual_range_inside_the_plausible_one():
    for q in ranges.QUANTITIES.values():
        assert q.low <= q.usual[0] < q.usual[1] <= q.high and q.source
        assert q.low <= q.reference <= q.high
        for s in q.slips:  # a slip takes a typical value out of the usual range: refused, or at least noted
            assert not q.usual[0] <= q.reference / s.factor <= q.usual[1], (q.name, s.unit)
    assert len(ranges.table_markdown()) == 2 + len(ranges.QUANTITIES)


def test_the_input_checks_page_lists_every_range_as_the_module_has_it():
    """docs/guide/input-checks.md holds the table the module makes: every quantity's ranges, slips and source."""
    import pathlib

    page = (pathlib.Path(__file__).parent.parent / "docs" / "guide" / "input-checks.md").read_text()
    for line in ranges.table_markdown():
        assert line in page, line
