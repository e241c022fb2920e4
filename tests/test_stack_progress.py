"""Progress of a z-tied stack while its joint solve runs (issue 44): stages and IPOPT iterations as they come."""

import io
from dataclasses import replace

import numpy as np

from wss_nlp.app.cli.reconstruct import _progress
from wss_nlp.core.solver import solve_progress
from wss_nlp.models import stack
from wss_nlp.pipeline import ReconstructionOptions, driver
from wss_nlp.synthetic import phantoms

FAST = ReconstructionOptions(uncertainty=False, dephasing_correction=False)
FAST = replace(FAST, velocity=replace(FAST.velocity, near_wall="off"))  # the plain basis: the cheapest velocity fit


def _stack():
    """Two slices of the tapered tube at a coarse 2 mm voxel: a joint solve of a second or two."""
    return phantoms.make_stack("tapered", nz=2, h_mm=2.0, spacing_mm=2.0, snr=25, seed=1)[0]


class _Recorder:
    """A progress callback with ``stage``: every event in order."""

    def __init__(self):
        self.events = []

    def __call__(self, done, total, res):
        self.events.append(("slice", done, res))

    def stage(self, text):
        self.events.append(("stage", text))


def test_the_joint_solve_reports_its_iterations_before_the_slices_are_done():
    """The stages and every IPOPT iteration of the coupled geometry solve arrive before any slice is reported
    done (the burst at the segment's end); the last iteration reported is the one IPOPT stopped at (its
    iteration count in the slices' solver statistics) - two independent counts of the same solve."""
    acq = _stack()
    rec = _Recorder()
    results, info = driver.reconstruct_stack(acq, FAST, stack.StackOptions(strategy="coupled"), progress=rec)
    kinds = [e[0] for e in rec.events]
    first_slice = kinds.index("slice")
    stages = [e[1] for e in rec.events[:first_slice]]
    assert kinds[first_slice:] == ["slice"] * 2 and first_slice == len(stages)  # every stage before the slices
    assert all(t.startswith("slices 0-1: ") for t in stages)
    assert stages[0] == "slices 0-1: geometry" and "slices 0-1: velocity" in stages
    iterations = [t for t in stages if t.startswith("slices 0-1: geometry: IPOPT iteration ")]
    numbers = [int(t.split("iteration ")[1].split(",")[0]) for t in iterations]
    assert numbers == list(range(numbers[-1] + 1))  # 0 (the start), 1, 2, ... in order, none missing
    assert numbers[-1] == results[0].geometry.stats.iterations  # IPOPT's own count
    assert np.isclose(float(iterations[-1].rsplit("objective ", 1)[1]), results[0].geometry.stats.objective,
                      rtol=1e-5)  # fmt: skip  # printed to 6 significant digits


def test_kaczmarz_sweeps_are_reported_and_nothing_leaks_outside_the_segment():
    acq = _stack()
    rec = _Recorder()
    _, info = driver.reconstruct_stack(acq, FAST, stack.StackOptions(strategy="kaczmarz"), progress=rec)
    sweeps = [e[1] for e in rec.events if e[0] == "stage" and ": geometry: sweep " in e[1]]
    assert len(sweeps) == info.sweeps["geometry"][0]  # one report per sweep the stack record counts
    got = []
    with solve_progress(got.append):  # the driver's listener is gone after the segment: a plain call says nothing
        driver.reconstruct_stack(acq, FAST, stack.StackOptions(strategy="kaczmarz"))
    assert got == []


def test_the_command_line_shows_stages_in_a_log_without_flooding_it():
    """Not a terminal: a line for each new stage, iterations of the same stage at most every STAGE_INTERVAL_S."""
    out = io.StringIO()
    report = _progress(out, total=3)
    for k in range(50):
        report.stage(f"slices 0-1: geometry: IPOPT iteration {k}, objective 1")
    report.stage("slices 0-1: velocity")
    lines = out.getvalue().splitlines()
    assert len(lines) == 2 and "geometry: IPOPT iteration 0" in lines[0] and "slices 0-1: velocity" in lines[1]
    quiet = io.StringIO()
    _progress(quiet, quiet=True).stage("slices 0-1: geometry")
    assert quiet.getvalue() == ""
