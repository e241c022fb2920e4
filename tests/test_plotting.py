"""Plotting draws without pyplot (the user's matplotlib backend is never changed), writes PNG, PDF and SVG at the
asked resolution, and labels every mark, colourbar and angle (in degrees)."""

import os
import re
import subprocess
import sys
from types import SimpleNamespace
from xml.etree import ElementTree

import matplotlib.lines
import numpy as np
import pytest
from matplotlib import image

from wss_nlp.app import plotting
from wss_nlp.app.cli.parser import build_parser
from wss_nlp.errors import InputError
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
from wss_nlp.synthetic import phantoms


def test_plotting_leaves_the_backend_alone(tmp_path):
    code = (
        "import matplotlib, numpy as np\n"
        "matplotlib.use('svg')\n"
        "from wss_nlp import cli, plotting\n"
        "fig = plotting.figure_band_check(np.linspace(0, 6, 10), np.ones(10), np.ones(10), 5)\n"
        f"plotting.save_figure(fig, {str(tmp_path / 'band.png')!r})\n"
        "print(matplotlib.get_backend())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "svg"
    assert (tmp_path / "band.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------------------------------------------
# issue 44: formats, resolution and publication defaults


@pytest.fixture(scope="module")
def slice_result():
    """A laminar slice with its band and near-wall record (the demo's phantom at a coarser voxel), and its truth.

    Fixed alpha and beta: the figures, not the parameter choice, are under test (10x faster than the balance rule).
    """
    acq, truth = phantoms.make_phantom("laminar", h_mm=1.5, snr=25, seed=11)
    options = ReconstructionOptions(choice=ChoiceOptions(alpha_rule="fixed", beta_rule="fixed"))
    return reconstruct(acq, options)[0], truth


@pytest.fixture(scope="module")
def all_figures(slice_result):
    """Every figure the package draws, made once for the module (drawing them is most of these tests' time)."""
    res, truth = slice_result
    figs = {name: make(res, truth) for name, make in plotting.FIGURES.items()}
    assert all(f is not None for f in figs.values()), figs  # the near-wall record is there (near_wall: auto)
    deg = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    figs["band_check"] = plotting.figure_band_check(deg, np.ones(36), np.ones(36), 5)
    nt = 6
    tau = np.cos(deg)[None, :] + np.linspace(-1, 1, nt)[:, None]
    series = SimpleNamespace(
        phi=deg,
        tau=tau,
        mean=tau.mean(axis=1),
        mean_std=np.full(nt, 0.05),
        model=None,
        failed=np.zeros(nt, bool),
        tawss=np.abs(tau).mean(axis=0),
        osi=np.full(36, 0.2),
        index=0,
    )
    figs["cine"] = plotting.figure_cine(series, np.linspace(0, 800, nt), truth_tau=tau.mean(axis=1))
    return figs


def test_each_format_is_written_readable_and_at_the_asked_resolution(slice_result, all_figures, tmp_path, monkeypatch):
    res, truth = slice_result
    # save_figures over the figures already drawn (drawing them again would double this test's time)
    made = {name: (lambda r, t=None, fig=all_figures[name]: fig) for name in plotting.FIGURES}
    monkeypatch.setattr(plotting, "FIGURES", made)
    dpi = 20  # small: the test reads the pixels back, it does not look at them
    paths = plotting.save_figures(res, tmp_path / "png", truth, prefix="slice_000_", fmt="png", dpi=dpi)
    assert [os.path.basename(p) for p in paths] == [f"slice_000_{n}.png" for n in made]
    for fmt in ("pdf", "svg"):  # the vector formats: one figure is enough (the same writer)
        os.makedirs(tmp_path / fmt)
        plotting.write_figure(all_figures["fig5_wss"], str(tmp_path / fmt / f"slice_000_fig5_wss.{fmt}"))
    assert not [p for p in tmp_path.rglob("*.part")]
    # fig1_2 is 11 x 4.6 inches, fig5 8 x 4.2: PNG pixels = inches x dpi; PDF and SVG sizes in points (72 per inch)
    png = tmp_path / "png" / "slice_000_fig1_2_geometry.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert image.imread(png).shape[:2] == (round(4.6 * dpi), round(11 * dpi))
    pdf = (tmp_path / "pdf" / "slice_000_fig5_wss.pdf").read_bytes()
    assert pdf.startswith(b"%PDF-") and pdf.rstrip().endswith(b"%%EOF")
    box = [float(v) for v in re.search(rb"/MediaBox \[\s*([\d.\s]+)\]", pdf).group(1).split()]
    assert box == pytest.approx([0, 0, 8 * 72, 4.2 * 72])
    assert b"/CreationDate" not in pdf  # no date: the same figure gives the same file
    svg_path = tmp_path / "svg" / "slice_000_fig5_wss.svg"
    root = ElementTree.parse(svg_path).getroot()
    assert root.tag.endswith("svg") and root.get("width") == "576pt"
    assert "<dc:date>" not in svg_path.read_text()


def test_wrong_format_or_resolution_is_an_input_error(tmp_path):
    fig = plotting.figure_band_check(np.linspace(0, 6, 10), np.ones(10), np.ones(10), 5)
    with pytest.raises(InputError, match="png, pdf, svg"):
        plotting.save_figure(fig, str(tmp_path / "band.tiff"))
    with pytest.raises(InputError, match="--dpi"):
        plotting.save_figure(fig, str(tmp_path / "band.png"), dpi=0)
    assert not list(tmp_path.iterdir())  # nothing written
    args = build_parser().parse_args(["reconstruct", "in.h5", "-o", "out.h5", "--figure-format", "pdf", "--dpi", "300"])
    assert (args.figure_format, args.dpi) == ("pdf", 300.0)
    args = build_parser().parse_args(["demo"])
    assert (args.figure_format, args.dpi) == ("png", plotting.DEFAULT_DPI)


def _legend_texts(fig) -> set[str]:
    return {t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()}


def test_publication_defaults_label_every_mark_in_degrees(all_figures):
    for name, fig in all_figures.items():
        named = _legend_texts(fig)
        bars = [ax for ax in fig.axes if hasattr(ax, "_colorbar")]
        for cax in bars:  # a colourbar says what it shows and in which unit
            assert "[" in cax.get_ylabel(), (name, cax.get_ylabel())
        for ax in (a for a in fig.axes if a not in bars):
            labels = (ax.get_xlabel(), ax.get_ylabel(), ax.get_title())
            assert not any("rad]" in label for label in labels), (name, labels)
            if "angle" in ax.get_xlabel():
                assert "[deg]" in ax.get_xlabel() and ax.get_xlim() == (0, 360), (name, ax.get_xlabel())
            # every line and every filled or scattered set of marks is named in a legend
            for artist in [*ax.lines, *(c for c in ax.collections if c.get_array() is None or c.colorbar is None)]:
                if isinstance(artist, matplotlib.lines.Line2D) and len(artist.get_xdata()) == 0:
                    continue  # a legend proxy (the box bounds out of view)
                assert artist.get_label() in named, (name, artist, artist.get_label())
            for shown in [*ax.images, *(c for c in ax.collections if c.get_array() is not None and c.colorbar)]:
                assert shown.colorbar is not None and shown.colorbar.ax.get_ylabel(), (name, shown)
    assert {"fig1_2_geometry", "fig5_wss", "fig6_near_wall", "band_check", "cine"} <= set(all_figures)


def test_geometry_box_is_two_bounds_and_near_wall_dots_one_size(slice_result, all_figures):
    res, _ = slice_result
    radius_axis = all_figures["fig1_2_geometry"].axes[1]
    assert not radius_axis.patches  # no shaded band filling the axis
    (entry,) = [t.get_text() for t in radius_axis.get_legend().get_texts() if t.get_text().startswith("box bounds")]
    r0, r1 = res.geometry.box
    assert f"r0 = {r0:.3g}" in entry and f"r1 = {r1:.3g} mm" in entry
    fig = all_figures["fig6_near_wall"]
    dots = [c for c in fig.axes[0].collections if c.get_label().startswith("measured voxels")]
    assert len(dots) == 1 and np.unique(dots[0].get_sizes()).size == 1  # the size encodes nothing
    assert "fraction inside the lumen" in dots[0].colorbar.ax.get_ylabel()
