"""The command line's arguments: one subparser per subcommand, the reconstruction options from their declarations
(:mod:`wss_nlp.core.schema`)."""

from __future__ import annotations

import argparse
from ... import __version__
from ...synthetic import invivo, phantoms, vessels
from ...core import schema
from ...models.kspace import AcquisitionOptions
from ..plotting import DEFAULT_DPI, FIGURE_FORMATS
from .batch import cmd_batch
from .demo import cmd_demo
from .exchange import add_allow as _add_allow
from .exchange import add_import_arguments, cmd_export, cmd_import
from .phantom import cmd_phantom
from .reconstruct import cmd_reconstruct
from .report import cmd_analyze, cmd_compare, cmd_sensitivity
from .studies import cmd_plot, cmd_sweep, cmd_table
from .arguments import _add_reconstruction_arguments, options_from_args  # noqa: F401


#: Exit codes of ``wss-nlp`` (the top-level help and the docs' command-line page show them).
EXIT_CODES = {
    0: "success",
    1: "a solver failed (no result could be computed from these data)",
    2: "bad input: a file, an option or a value (the message names it and the fix)",
    3: "internal error (a bug: please report it; WSS_NLP_DEBUG=1 shows the traceback)",
}

#: Examples shown under every subcommand's help (``wss-nlp SUBCOMMAND --help``); the newcomer test runs them in spirit.
EXAMPLES = {
    "demo": ["wss-nlp demo", "wss-nlp demo --case cine -o cine_demo", "wss-nlp demo --figure-format pdf --dpi 300"],
    "reconstruct": [
        "wss-nlp reconstruct in.h5 -o out.h5 --figures figs",
        "wss-nlp reconstruct stack.h5 -o out.h5 --method coupled",
    ],
    "phantom": [
        "wss-nlp phantom --case laminar -o in.h5 --truth truth.h5",
        "wss-nlp phantom --case cine --frames 12 -o cine.h5 --truth cine_truth.h5",
        "wss-nlp phantom --stack tapered --nz 5 -o stack.h5 --dicom dicom/ --nifti nifti/",
        "wss-nlp phantom --case cine --frames 12 -o cine.h5 --dicom cine_dicom/",
        "wss-nlp phantom --volume --nifti flow4d/",
    ],
    "analyze": ["wss-nlp analyze out.h5", "wss-nlp analyze out.h5 --slice 3 --figures choice_figs"],
    "sensitivity": ["wss-nlp sensitivity out.h5"],
    "sweep": ["wss-nlp sweep problems/resolution.toml --workers 2"],
    "batch": ["wss-nlp batch exams.csv -o cohort/ --workers 2", "wss-nlp batch exams.toml -o cohort/ --cluster local"],
    "table": ["wss-nlp table runs/resolution --rows h --cols method --metric wss_err"],
    "plot": ["wss-nlp plot runs/resolution --x h --y wss_err --by method --figure-format svg"],
    "export": ["wss-nlp export out.h5 --vtk wall.vtu", "wss-nlp export cine_out.h5 --vtk wall.pvd"],
    "import": [
        "wss-nlp import dicom_folder/ -o in.h5",
        "wss-nlp import mag.nii.gz phase.nii.gz -o in.h5",
        "wss-nlp import nifti_folder/ -o in.h5",
    ],
    "compare": ["wss-nlp compare out.h5 truth.h5"],
}

#: Descriptions of the subcommands that have no longer one where they are declared.
DESCRIPTIONS = {
    "analyze": "Show how each slice's regularization parameters (alpha for the wall, beta for the velocity), its "
    "near-wall model and its dephasing passes were chosen: the rule, the noise level it used, the residual and "
    "criterion at every parameter tried and the chosen one; optionally the residual-against-parameter figures.",
    "sensitivity": "Rank what moves each slice's mean WSS: the derivative of the mean WSS with respect to every "
    "regularization and model parameter, and the share of its variance each data group (magnitude, velocity) "
    "contributes, from the linearized band stored in the result file.",
    "plot": "Draw a metric against a parameter from a sweep's results.csv (mean over seeds, bars one standard "
    "deviation), one line per --by value and one panel per --panels value.",
    "compare": "Errors of a result file against the truth file of the phantom it came from: radius error in L2 "
    "and H1, velocity error, mean and pointwise WSS error, per slice (or per frame for cine).",
    "phantom": "Write a synthetic acquisition with its exact truth: one slice (--case), a stack of slices "
    "(--stack) or a time-resolved cine series (--case cine), as an HDF5 input file and optionally as the DICOM "
    "or NIfTI files a scanner would export; or a 4D-flow volume as NIfTI files (--volume).",
}


class _HelpFormatter(argparse.HelpFormatter):
    """Wraps descriptions as usual, keeps the examples' and the case lists' line breaks."""

    def _fill_text(self, text, width, indent):
        if "\n" in text:
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


def _case_name(value: str) -> str:
    """``womersley``, the cine phantom's name before 0.2, is kept as an alias of ``cine``."""
    return "cine" if value == "womersley" else value


def _case_list(cases: dict, extra: dict | None = None) -> str:
    rows = {name: text for name, (_, text) in cases.items()} | (extra or {})
    width = max(map(len, rows))
    return "\n".join(f"  {name:<{width}}  {text}" for name, text in rows.items())


_CINE_TEXT = "Womersley flow over one cycle, time-resolved (alias: womersley); the cine options below"


def _add_verbosity_arguments(p: argparse.ArgumentParser, default) -> None:
    """``-q/--quiet`` (warnings and errors only) and ``-v/--verbose`` (the library's debug log)."""
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=default,
        help="no progress or information, only warnings and results",
    )
    group.add_argument(
        "-v", "--verbose", action="store_true", default=default, help="also the library's debug messages"
    )


def _add_figure_arguments(p: argparse.ArgumentParser) -> None:
    """``--figure-format`` and ``--dpi`` of a command that writes figures (:mod:`wss_nlp.app.plotting`)."""
    p.add_argument(
        "--figure-format",
        choices=FIGURE_FORMATS,
        default="png",
        help="file format of the figures: png, or pdf/svg (vector) for papers (default %(default)s)",
    )
    p.add_argument(
        "--dpi",
        type=float,
        default=DEFAULT_DPI,
        help="resolution in dots per inch of PNG figures and of the images inside PDF/SVG (default %(default)g)",
    )


class OneLineParser(argparse.ArgumentParser):
    """argparse with its usage errors as one ``wss-nlp: error:`` line naming the command, the argument and where
    the help is (exit code 2), like every other refusal."""

    def error(self, message: str):
        command = self.prog.split(" ", 1)[1] + ": " if " " in self.prog else ""
        self.exit(2, f"wss-nlp: error: {command}{message}; see '{self.prog} --help'\n")


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="wss-nlp",
        description="Vessel geometry, velocity and wall shear stress from phase-contrast MRI "
        "(Egger & Teschner), with every Tikhonov problem posed in CasADi.",
        epilog="exit codes:\n" + "\n".join(f"  {code}  {text}" for code, text in EXIT_CODES.items()),
        formatter_class=_HelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    _add_verbosity_arguments(p, False)
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser(
        "demo",
        help="reconstruct a built-in phantom and report errors against the truth",
        description="Build a phantom, reconstruct it, print errors, write files and figures.",
    )
    d.add_argument(
        "--case",
        choices=[*phantoms.CASES, *invivo.INVIVO_CASES, "cine"],
        type=_case_name,
        default="laminar",
        help="phantom (default %(default)s; the cases are listed below)",
    )
    d.add_argument("--h", type=float, default=1.0, help="voxel size in mm (default %(default)g)")
    d.add_argument("--snr", type=float, default=25.0, help="signal-to-noise ratio, <= 0 for none (default %(default)g)")
    d.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    d.add_argument("-o", "--output-dir", default="wss_nlp_demo", help="output folder (default %(default)s)")
    _add_figure_arguments(d)
    _add_reconstruction_arguments(d)
    d.set_defaults(func=cmd_demo)

    r = sub.add_parser(
        "reconstruct",
        help="reconstruct an acquisition file",
        description="Reconstruct geometry, velocity and WSS of every slice of INPUT, or of the whole vessel's wall "
        "when INPUT is a 4D flow volume file.",
    )
    r.add_argument("input", help='input HDF5 file (format: docs, "File formats")')
    r.add_argument("-o", "--output", required=True, help="result HDF5 file")
    r.add_argument("--figures", default=None, help="folder for the figures of every slice (--figure-format, --dpi)")
    _add_figure_arguments(r)
    r.add_argument(
        "--workers",
        type=int,
        default=1,
        help="independent slices (and the slices of each cine frame) in this many processes (default 1: serial)",
    )
    r.add_argument("--scheduler", default=None, help="run them on the Dask scheduler at this address instead")
    v = r.add_argument_group(
        "4D flow volumes",
        "a volume file (wss-nlp import without --plane) maps the whole vessel's wall; --vessel then takes X,Y,Z "
        "in world mm (docs: 4D flow)",
    )
    v.add_argument("--mask", default=None, metavar="FILE", help="the lumen as a NIfTI mask on the volume's grid")
    v.add_argument(
        "--centerline", default=None, metavar="FILE", help="the centreline as CSV (x,y,z per row) or VTK polyline, mm"
    )
    v.add_argument(
        "--baseline", action="store_true", help="also the wall-normal fit of common 4D flow tools on the same mask"
    )
    _add_reconstruction_arguments(r)
    r.set_defaults(func=cmd_reconstruct)

    ph = sub.add_parser("phantom", help="write a synthetic acquisition (and its truth)")
    ph.add_argument(
        "--case",
        choices=[*phantoms.CASES, *invivo.INVIVO_CASES, "cine"],
        type=_case_name,
        default="laminar",
        help="one slice's phantom (in air, or invivo: in tissue), or cine (default %(default)s; the cases are "
        "listed below)",
    )
    ph.add_argument("--frames", type=int, default=20, help="cine: frames over the cycle (default %(default)s)")
    ph.add_argument(
        "--distension",
        type=float,
        default=None,
        metavar="EPS",
        help="cine: the pipe breathes, radius R0 (1 + EPS sin(omega t)), EPS in [0, 0.3) (default 0: rigid)",
    )
    ph.add_argument(
        "--shape",
        choices=("circle", "ellipse"),
        default=None,
        help="cine: circular pipe, or elliptic (aspect 1.32, same area, its exact pulsatile flow; rigid)",
    )
    ph.add_argument(
        "--pipe-radius",
        type=float,
        default=None,
        metavar="MM",
        help="cine: pipe radius in mm (default 10: first harmonic's Womersley number about 14)",
    )
    ph.add_argument("--h", type=float, default=None, help="voxel size in mm (default 1; 2 for --volume-case)")
    ph.add_argument("--snr", type=float, default=25.0, help="signal-to-noise ratio, <= 0 for none")
    ph.add_argument("--seed", type=int, default=0)
    ph.add_argument("--venc", type=float, default=None, help="velocity encoding in m/s (default 1.25 x peak)")
    ph.add_argument("--velocity", action="store_true", help="store 'velocity' instead of 'phase' + venc")
    ph.add_argument(
        "--stack", choices=list(phantoms.STACK_CASES), default=None, help="a 3D stack phantom instead of one slice"
    )
    ph.add_argument("--nz", type=int, default=10, help="stack: number of slices (default %(default)s)")
    ph.add_argument("--spacing", type=float, default=2.0, help="stack: slice spacing in mm (default %(default)g)")
    ph.add_argument(
        "--swirl",
        type=float,
        default=None,
        help="stack: add in-plane velocity components (4D flow) of a swirl with this rate in 1/s",
    )
    ph.add_argument("-o", "--output", default=None, help="input file to write (every phantom but --volume)")
    ph.add_argument(
        "--volume",
        action="store_true",
        help="a 4D-flow volume instead (a tilted tube, three velocity components, two frames) as NIfTI files into "
        "--nifti FOLDER, for 'wss-nlp import FOLDER --plane ...' (the plane through the tube is printed)",
    )
    ph.add_argument(
        "--volume-case",
        default=None,
        choices=list(vessels.CASES),
        metavar="CASE",
        help="a whole-vessel 4D-flow phantom (" + ", ".join(vessels.CASES) + ") as a volume input file (-o) and/or "
        "NIfTI files (--nifti), for 'wss-nlp reconstruct' on the volume; --truth writes its exact wall and WSS "
        "vectors for 'wss-nlp compare'; pulsatile takes --frames",
    )
    ph.add_argument(
        "--tissue", action="store_true", help="--volume-case: static tissue and a wall ring around the lumen"
    )
    ph.add_argument("--truth", default=None, help="also write the exact geometry and WSS here")
    ph.add_argument(
        "--dicom", default=None, metavar="FOLDER", help="also write the images as DICOM files (for 'wss-nlp import')"
    )
    ph.add_argument(
        "--vendor",
        choices=["siemens", "philips", "ge", "enhanced"],
        default="siemens",
        help="DICOM convention of --dicom (default %(default)s)",
    )
    ph.add_argument("--nifti", default=None, metavar="FOLDER", help="also write NIfTI files with JSON sidecars")
    schema.add_arguments(ph, AcquisitionOptions)  # acquire in k-space: --acquisition kspace --kspace-filter ...
    _add_allow(ph)
    ph.set_defaults(func=cmd_phantom)

    a = sub.add_parser(
        "analyze", help="how alpha, beta, the near-wall model and the dephasing passes were chosen (tables, curves)"
    )
    a.add_argument("result", help="result file written by 'wss-nlp reconstruct'")
    a.add_argument(
        "--slice", type=int, default=None, metavar="K", help="only slice K (default: every slice; 0 is the first)"
    )
    a.add_argument("--figures", default=None, help="folder for residual-vs-parameter figures (--figure-format, --dpi)")
    _add_figure_arguments(a)
    a.set_defaults(func=cmd_analyze)

    se = sub.add_parser("sensitivity", help="which parameters and which noise the mean WSS is most sensitive to")
    se.add_argument("result", help="result file written by 'wss-nlp reconstruct'")
    se.set_defaults(func=cmd_sensitivity)

    sw = sub.add_parser(
        "sweep",
        help="run a parameter study from a TOML file (problems/*.toml)",
        description="Expand the study's grid, run the cases in parallel (resumable), write "
        "OUTDIR/results.csv, per-case result files and the study's tables and plots.",
    )
    sw.add_argument("study", help="study file (TOML; see problems/README.md)")
    sw.add_argument("-o", "--output-dir", default=None, help="output folder (default runs/STUDY_NAME)")
    sw.add_argument("--workers", type=int, default=None, help="local worker processes (default: all cores)")
    sw.add_argument(
        "--scheduler",
        default=None,
        help="address of a Dask distributed scheduler (tcp://HOST:PORT) to run the cases on",
    )
    sw.add_argument("--retry-failed", action="store_true", help="run again the cases that failed before")
    sw.set_defaults(func=cmd_sweep)

    b = sub.add_parser(
        "batch",
        help="reconstruct many exams from a manifest (local processes or Dask), resumable, with a cohort report",
        description="Run every exam of MANIFEST (CSV or TOML: id, input, and per-exam options by their long flag "
        "names) into DIR/<id>/ (result, VTK, thumbnail), then write DIR/summary.csv, DIR/report.html and "
        "DIR/batch.log; a rerun skips what is done. Exit 1 if any exam failed. Docs: 'Cohorts'.",
    )
    b.add_argument("manifest", help="manifest file (.csv, or .toml with [[exam]] tables)")
    b.add_argument("-o", "--output-dir", required=True, help="output folder DIR")
    b.add_argument("--workers", type=int, default=None, help="local processes (default: all cores), or LocalCluster's")
    b.add_argument("--scheduler", default=None, help="address of a Dask scheduler (tcp://HOST:PORT) to run on")
    b.add_argument(
        "--cluster",
        choices=["local", "slurm", "pbs"],
        default=None,
        help="start a Dask cluster: local (a LocalCluster of --workers processes), slurm or pbs (dask-jobqueue, "
        "keywords from --cluster-config)",
    )
    b.add_argument("--cluster-config", default=None, metavar="FILE", help="TOML file of dask-jobqueue keywords")
    b.add_argument("--job-script", action="store_true", help="print the job script --cluster would submit, and stop")
    b.add_argument("--figures", action="store_true", help="also every figure of every exam (DIR/<id>/figures)")
    b.add_argument("--no-vtk", action="store_true", help="skip the VTK wall (DIR/<id>/wall.vtu; needs meshio)")
    b.add_argument("--retry-failed", action="store_true", help="run again the exams that failed on their input")
    _add_reconstruction_arguments(b)  # every exam's defaults; the manifest's columns override them per exam
    b.set_defaults(func=cmd_batch)

    tb = sub.add_parser(
        "table",
        help="a paper-style table from a sweep's results.csv",
        description="Pivot a metric over two parameters (mean over seeds); best per row in bold.",
    )
    tb.add_argument("outdir", help="output folder of 'wss-nlp sweep'")
    tb.add_argument("--rows", required=True, help="parameter of the rows (or 'metric' for a single row)")
    tb.add_argument("--cols", required=True, help="parameter of the columns (or 'metric')")
    tb.add_argument("--metric", required=True, help="metric column, e.g. radius_err_h2, wss_err")
    tb.add_argument("--where", nargs="*", default=[], metavar="KEY=VALUE", help="fix other parameters")
    tb.add_argument(
        "--agg", choices=["mean", "median", "max", "min"], default="mean", help="over seeds (default %(default)s)"
    )
    tb.add_argument("--latex", action="store_true", help="print LaTeX instead of Markdown")
    tb.add_argument("--no-bold", action="store_true", help="do not mark the best value of each row")
    tb.add_argument("-o", "--output", default=None, help="also write the table (.tex: LaTeX, else Markdown)")
    tb.set_defaults(func=cmd_table)

    pl = sub.add_parser("plot", help="a metric against a parameter from a sweep's results.csv")
    pl.add_argument("outdir", help="output folder of 'wss-nlp sweep'")
    pl.add_argument("--x", required=True, help="parameter on the x axis, e.g. h")
    pl.add_argument("--y", required=True, help="metric on the y axis, e.g. wss_err")
    pl.add_argument("--by", default=None, help="one line per value of this parameter, e.g. method")
    pl.add_argument("--panels", default=None, help="one panel per value of this parameter, e.g. case")
    pl.add_argument("--where", nargs="*", default=[], metavar="KEY=VALUE", help="fix other parameters")
    pl.add_argument("--logx", action="store_true", help="logarithmic x axis")
    pl.add_argument(
        "-o", "--output", default=None, help="figure file, its extension the format (default OUTDIR/Y_vs_X.FORMAT)"
    )
    _add_figure_arguments(pl)
    pl.set_defaults(func=cmd_plot)

    ex = sub.add_parser(
        "export",
        help="the reconstructed wall with its WSS as a VTK file for ParaView",
        description="A slice becomes a polyline, a stack the wall surface; point data tau_pa (and tau_std_pa, "
        "wss_vector_pa, tawss_pa and osi where present). Imported data (DICOM, NIfTI, planes of 4D flow) are placed "
        "in the scanner's world frame, so the wall overlays the images in ParaView; field data world_frame and "
        "length_unit_mm. A cine result: its cycle average (.vtu/.vtk) or its frames as a time series (.pvd). "
        "A vessel result (4D flow) becomes the wall's quad mesh in world mm (wss_vector_pa, tau_pa, tawss_pa and "
        "osi for cines, one .vtu per frame and a .pvd), the centreline (_centerline.vtk) and the per-plane table "
        "(_planes.csv).",
    )
    ex.add_argument("result", help="result file written by 'wss-nlp reconstruct'")
    ex.add_argument(
        "--vtk", required=True, help="output file: .vtu (VTK XML), .vtk (legacy) or .pvd (cine: a time series)"
    )
    ex.add_argument(
        "--slice-spacing",
        type=float,
        default=None,
        help="mm between slices (default: the result's slice_spacing_mm, stored by reconstruct)",
    )
    _add_allow(ex)
    ex.set_defaults(func=cmd_export)

    im = sub.add_parser(
        "import",
        help="scanner exports (DICOM folder/files or NIfTI) to an input file",
        description="Read a magnitude and a phase (or velocity) series from DICOM (Siemens, Philips, GE, enhanced "
        "multi-frame) or NIfTI (with dcm2niix JSON sidecars) and write an input file of the format document; "
        "venc, voxel size, origin, slice spacing and trigger times come from the headers. A 4D flow NIfTI "
        "magnitude and three velocity components (*_vx, *_vy, *_vz or sidecar directions) without --plane "
        "become a volume file ('wss-nlp reconstruct' then maps the whole vessel's wall). See the docs pages "
        "'Your own data' and '4D flow'.",
    )
    im.add_argument("paths", nargs="+", metavar="PATH", help="DICOM folders or files, or NIfTI files")
    im.add_argument("-o", "--output", required=True, help="input file to write (.h5)")
    add_import_arguments(im)
    im.set_defaults(func=cmd_import)

    c = sub.add_parser("compare", help="errors of a result file against a truth file")
    c.add_argument("result", help="result file written by 'wss-nlp reconstruct'")
    c.add_argument("truth", help="truth file written by 'wss-nlp phantom --truth'")
    c.set_defaults(func=cmd_compare)

    cases = {
        "demo": _case_list({**phantoms.CASES, **invivo.INVIVO_CASES}, {"cine": _CINE_TEXT}),
        "phantom": _case_list({**phantoms.CASES, **invivo.INVIVO_CASES}, {"cine": _CINE_TEXT})
        + "\n\nstacks (--stack):\n"
        + _case_list(phantoms.STACK_CASES),
    }
    for name, sp in sub.choices.items():
        sp.formatter_class = _HelpFormatter
        sp.description = sp.description or DESCRIPTIONS.get(name)
        epilog = "examples:\n" + "\n".join(f"  {e}" for e in EXAMPLES[name])
        if name in cases:
            epilog = f"cases (--case):\n{cases[name]}\n\n{epilog}"
        sp.epilog = epilog
        _add_verbosity_arguments(sp, argparse.SUPPRESS)  # also after the subcommand: wss-nlp reconstruct -q ...
    return p
