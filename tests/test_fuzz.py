"""Bad and odd inputs through the CLI: never a traceback, never a corrupted file, never a silent answer.

Every case runs ``wss-nlp reconstruct`` in-process on a mutated copy of a
small valid phantom (layout, dtype, values, paths, options, stacks) and
asserts:

* the exit code is 0 or 2 (an exception escaping ``main`` fails the test);
* exit 2: exactly one line ``wss-nlp: error: ...``, no output file and no
  temporary file left behind;
* exit 0: the result reads back; where the input was defective (``"warn"``)
  the run printed a warning;
* every input file is byte-identical after the run.

Random choices (which voxel, which value) come from a generator seeded
with the case's name, so every case is reproducible on its own.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import zlib

import h5py
import numpy as np
import pytest

from wss_nlp.io import files as wio
from wss_nlp.synthetic import phantoms
from wss_nlp.app.cli import main

FAST = ["--no-uncertainty"]


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzzbase")
    files = {}
    acq, _ = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=61)
    wio.write_acquisition(d / "slice.h5", acq)
    files["slice"] = d / "slice.h5"
    acq, _ = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=61, venc=0.25)  # peak 0.4 m/s: aliased
    wio.write_acquisition(d / "aliased.h5", acq)
    files["aliased"] = d / "aliased.h5"
    acq, _ = phantoms.make_two_vessels(h_mm=1.5, snr=25, seed=62)
    wio.write_acquisition(d / "two.h5", acq)
    files["two"] = d / "two.h5"
    acq, _ = phantoms.make_stack("tapered", nz=3, h_mm=1.5, spacing_mm=2.0, snr=25, seed=63)
    wio.write_acquisition(d / "stack.h5", acq)
    files["stack"] = d / "stack.h5"
    return files


# ------------------------------------------------------------------ mutations: f is the copied file, open r+
def _replace(f, name, data):
    if name in f:
        del f[name]
    f[name] = data


def _scale(name, factor, dtype=None):
    def mutate(f, rng):
        a = f[name][()] * factor
        _replace(f, name, a.astype(dtype) if dtype else a)

    return mutate


def _set_attr(name, value):
    def mutate(f, rng):
        f.attrs[name] = value

    return mutate


def _del(name, attr=False):
    def mutate(f, rng):
        del (f.attrs if attr else f)[name]

    return mutate


def _voxel(name, value, n=1):
    def mutate(f, rng):
        a = f[name][()]
        for _ in range(n):
            a[tuple(rng.integers(0, s) for s in a.shape)] = value
        _replace(f, name, a)

    return mutate


def _phase_to_velocity(factor=1.0, dtype=None, keep_venc=True):
    def mutate(f, rng):
        v = f.attrs["venc_m_s"] * f["phase"][()] / np.pi * factor
        del f["phase"]
        f["velocity"] = v.astype(dtype) if dtype else v
        if not keep_venc:
            del f.attrs["venc_m_s"]

    return mutate


def _each(*mutations):
    def mutate(f, rng):
        for m in mutations:
            m(f, rng)

    return mutate


def _crop(sl):
    def mutate(f, rng):
        for k in ("magnitude", "phase"):
            _replace(f, k, f[k][()][(slice(None), *sl)])

    return mutate


def _noise_magnitude(f, rng):
    _replace(f, "magnitude", np.abs(rng.normal(size=f["magnitude"].shape) + 1j * rng.normal(size=f["magnitude"].shape)))


def _stack_slice(name, iz, value):
    def mutate(f, rng):
        a = f[name][()]
        a[iz] = value
        _replace(f, name, a)

    return mutate


def _stack_noise_slice(iz):
    def mutate(f, rng):
        a = f["magnitude"][()]
        a[iz] = np.abs(rng.normal(size=a[iz].shape) + 1j * rng.normal(size=a[iz].shape)) * 0.04
        _replace(f, "magnitude", a)

    return mutate


def _unwrapped_elsewhere(f, rng):
    # velocities already unwrapped by other software: beyond venc, valid with --no-unwrap
    from wss_nlp.pipeline import plausibility as pl
    from wss_nlp.models import preprocess as pp

    venc = float(f.attrs["venc_m_s"])
    v = venc * f["phase"][()] / np.pi
    mag = f["magnitude"][()]
    grid = wio.Acquisition(
        magnitude=mag, velocity=v, voxel_size_mm=tuple(f.attrs["voxel_size_mm"]), origin_mm=tuple(f.attrs["origin_mm"])
    ).grid
    _, m, lumen = pp.preprocess(mag[0], grid)
    rim = lumen.mask & ~np.roll(lumen.mask, 1, 0)
    v[0] = pl.unwrap_velocity(v[0], lumen.mask, venc, rim)
    del f["phase"]
    f["velocity"] = v


# name -> (base file, mutation or None, extra CLI args, expectation: "error", "ok", "warn" or "any")
CASES = {
    # layout
    "valid": ("slice", None, [], "ok"),
    "missing_magnitude": ("slice", _del("magnitude"), [], "error"),
    "missing_phase": ("slice", _del("phase"), [], "error"),
    "velocity_and_phase": ("slice", lambda f, r: f.create_dataset("velocity", data=f["phase"][()]), [], "error"),
    "missing_voxel_size": ("slice", _del("voxel_size_mm", attr=True), [], "error"),
    "missing_origin": ("slice", _del("origin_mm", attr=True), [], "error"),
    "missing_venc_with_phase": ("slice", _del("venc_m_s", attr=True), [], "error"),
    "magnitude_is_group": (
        "slice",
        lambda f, r: (f.__delitem__("magnitude"), f.create_group("magnitude")),
        [],
        "error",
    ),
    "magnitude_1d": ("slice", lambda f, r: _replace(f, "magnitude", f["magnitude"][()].ravel()), [], "error"),
    "magnitude_4d": ("slice", lambda f, r: _replace(f, "magnitude", f["magnitude"][()][None]), [], "error"),
    "cine_file": (
        "slice",
        _each(
            lambda f, r: _replace(f, "magnitude", f["magnitude"][()][None]),
            lambda f, r: _replace(f, "phase", f["phase"][()][None]),
            _set_attr("trigger_times_ms", np.array([0.0])),
        ),
        [],
        "error",
    ),
    "nz_zero": (
        "slice",
        _each(
            lambda f, r: _replace(f, "magnitude", f["magnitude"][()][:0]),
            lambda f, r: _replace(f, "phase", f["phase"][()][:0]),
        ),
        [],
        "error",
    ),
    "shape_mismatch": ("slice", lambda f, r: _replace(f, "phase", f["phase"][()][:, 1:]), [], "error"),
    "no_nz_axis": (
        "slice",
        _each(
            lambda f, r: _replace(f, "magnitude", f["magnitude"][0]), lambda f, r: _replace(f, "phase", f["phase"][0])
        ),
        [],
        "ok",
    ),
    "tiny_image": ("slice", _crop((slice(0, 3), slice(0, 3))), [], "error"),
    "velocity_x_alone": (
        "slice",
        lambda f, r: f.create_dataset("velocity_x", data=np.zeros(f["phase"].shape)),
        [],
        "error",
    ),
    "velocity_4d_wrong": (
        "slice",
        _each(_phase_to_velocity(), lambda f, r: _replace(f, "velocity", np.stack([f["velocity"][()]] * 2))),
        [],
        "error",
    ),
    "velocity_4d_valid": (
        "slice",
        _each(
            _phase_to_velocity(),
            lambda f, r: _replace(
                f, "velocity", np.stack([0 * f["velocity"][()], 0 * f["velocity"][()], f["velocity"][()]])
            ),
        ),
        [],
        "ok",
    ),
    "extra_datasets": ("slice", lambda f, r: f.create_dataset("notes", data=np.arange(3)), [], "ok"),
    # dtypes
    "magnitude_float32": ("slice", _scale("magnitude", 1.0, np.float32), [], "ok"),
    "magnitude_int16": ("slice", _scale("magnitude", 1000.0, np.int16), [], "ok"),
    "magnitude_uint8": ("slice", _scale("magnitude", 200.0, np.uint8), [], "ok"),
    "magnitude_complex": ("slice", _scale("magnitude", 1.0, np.complex128), [], "error"),
    "phase_complex": ("slice", _scale("phase", 1.0, np.complex64), [], "error"),
    "magnitude_strings": (
        "slice",
        lambda f, r: _replace(f, "magnitude", np.full(f["magnitude"].shape, b"a")),
        [],
        "error",
    ),
    "magnitude_bool": ("slice", lambda f, r: _replace(f, "magnitude", f["magnitude"][()] > 0.5), [], "any"),
    "phase_float16": ("slice", _scale("phase", 1.0, np.float16), [], "ok"),
    "voxel_size_string": ("slice", _set_attr("voxel_size_mm", "1.5,1.5"), [], "error"),
    "voxel_size_3_values": ("slice", _set_attr("voxel_size_mm", np.array([1.5, 1.5, 2.0])), [], "error"),
    "voxel_size_negative": ("slice", _set_attr("voxel_size_mm", np.array([-1.5, 1.5])), [], "error"),
    "voxel_size_zero": ("slice", _set_attr("voxel_size_mm", np.array([0.0, 1.5])), [], "error"),
    "voxel_size_nan": ("slice", _set_attr("voxel_size_mm", np.array([np.nan, 1.5])), [], "error"),
    "origin_inf": ("slice", _set_attr("origin_mm", np.array([np.inf, 0.0])), [], "error"),
    "venc_negative": ("slice", _set_attr("venc_m_s", -0.5), [], "error"),
    "venc_zero": ("slice", _set_attr("venc_m_s", 0.0), [], "error"),
    "venc_string": ("slice", _set_attr("venc_m_s", "fast"), [], "error"),
    "viscosity_negative": ("slice", _set_attr("viscosity_pa_s", -3.5e-3), [], "error"),
    "viscosity_missing": ("slice", _del("viscosity_pa_s", attr=True), [], "error"),
    "viscosity_missing_given": ("slice", _del("viscosity_pa_s", attr=True), ["--viscosity", "3.5e-3"], "ok"),
    "viscosity_string": ("slice", _set_attr("viscosity_pa_s", "blood"), [], "error"),
    # values
    "nan_in_magnitude": ("slice", _voxel("magnitude", np.nan), [], "error"),
    "inf_in_phase": ("slice", _voxel("phase", np.inf), [], "error"),
    "all_nan": ("slice", _scale("magnitude", np.nan), [], "error"),
    "constant_magnitude": ("slice", _scale("magnitude", 0.0, None), [], "error"),
    "pure_noise": ("slice", _noise_magnitude, [], "error"),
    "negative_magnitude": ("slice", lambda f, r: _replace(f, "magnitude", f["magnitude"][()] - 0.2), [], "error"),
    "magnitude_times_1e6": ("slice", _scale("magnitude", 1e6), [], "ok"),
    "magnitude_times_1e-6": ("slice", _scale("magnitude", 1e-6), [], "ok"),
    "phase_in_degrees": ("slice", _scale("phase", 180 / np.pi), [], "error"),
    "phase_raw_12bit": (
        "slice",
        lambda f, r: _replace(f, "phase", np.round((f["phase"][()] + np.pi) / (2 * np.pi) * 4095).astype(np.int16)),
        [],
        "error",
    ),
    "phase_negated": ("slice", _scale("phase", -1.0), [], "ok"),
    "velocity_m_s": ("slice", _phase_to_velocity(), [], "ok"),
    "velocity_cm_s": ("slice", _phase_to_velocity(100.0), [], "error"),
    "velocity_int16_mm_s": ("slice", _phase_to_velocity(1000.0, np.int16), [], "error"),
    "velocity_cm_s_no_venc": ("slice", _phase_to_velocity(100.0, keep_venc=False), [], "error"),
    "velocity_no_venc": ("slice", _phase_to_velocity(keep_venc=False), [], "ok"),
    "venc_in_cm_s": ("slice", lambda f, r: f.attrs.__setitem__("venc_m_s", 100 * f.attrs["venc_m_s"]), [], "error"),
    "aliased": ("aliased", None, [], "warn"),
    "aliased_no_unwrap": ("aliased", None, ["--no-unwrap"], "warn"),
    "aliased_as_velocity": ("aliased", _phase_to_velocity(), [], "warn"),
    "unwrapped_elsewhere": ("aliased", _unwrapped_elsewhere, [], "error"),
    "unwrapped_elsewhere_no_unwrap": ("aliased", _unwrapped_elsewhere, ["--no-unwrap"], "ok"),
    "lumen_on_border": ("slice", _crop((slice(0, 10), slice(None))), [], "error"),
    "two_vessels": ("two", None, [], "warn"),
    "two_vessels_pick_vein": ("two", None, ["--vessel", "9,5"], "warn"),
    "vessel_nowhere": ("slice", None, ["--vessel", "100,100"], "error"),
    "vessel_malformed": ("slice", None, ["--vessel", "3"], "error"),
    "rectangular_image": ("slice", _crop((slice(None), slice(1, None))), [], "ok"),
    "anisotropic_voxels": ("slice", _set_attr("voxel_size_mm", np.array([1.5, 1.4])), [], "any"),
    "magnitude_phase_swapped": (
        "slice",
        lambda f, r: f.move("magnitude", "tmp") or f.move("phase", "magnitude") or f.move("tmp", "phase"),
        [],
        "error",
    ),
    "magnitude_offset": ("slice", lambda f, r: _replace(f, "magnitude", f["magnitude"][()] + 10.0), [], "any"),
    "salt_voxels": ("slice", _voxel("magnitude", 1e3, n=5), [], "any"),
    "phase_salt": ("slice", _voxel("phase", np.pi, n=5), [], "any"),
    # options
    "beta_word": ("slice", None, ["--beta", "abc"], "error"),
    "alpha_negative": ("slice", None, ["--alpha", "-1"], "error"),
    "n_phi_small": ("slice", None, ["--n-phi", "10"], "error"),
    "unknown_option": ("slice", None, ["--frobnicate"], "error"),
    "z_smoothing_single": ("slice", None, ["--z-smoothing", "5"], "ok"),
    "baseline_oyre": ("slice", None, ["--method", "oyre"], "ok"),
    "baseline_two_vessels": ("two", None, ["--method", "stalder"], "warn"),
    # stacks
    "stack_valid": ("stack", None, [], "ok"),
    "stack_nan_slice": ("stack", _stack_slice("magnitude", 1, np.nan), [], "warn"),
    "stack_all_nan": ("stack", _scale("magnitude", np.nan), [], "error"),
    "stack_no_spacing": ("stack", _del("slice_spacing_mm", attr=True), [], "error"),
    "stack_spacing_zero": ("stack", _set_attr("slice_spacing_mm", 0.0), [], "error"),
    "stack_empty_slice": ("stack", _stack_noise_slice(2), [], "warn"),
    "stack_cm_s": ("stack", _phase_to_velocity(100.0), [], "error"),
    "stack_independent": ("stack", None, ["--z-smoothing", "0"], "ok"),
}

# output paths: name -> (function(tmp dir, input path) -> (extra args, -o path), expectation)
PATHS = {
    "o_existing_dir": (lambda d, i: ([], _mkdir(d / "outdir")), "error"),
    "o_missing_folder": (lambda d, i: ([], d / "missing" / "out.h5"), "error"),
    "o_is_input": (lambda d, i: ([], i), "error"),
    "o_is_input_dotted": (lambda d, i: ([], d / "." / i.name), "error"),
    "o_symlink_to_input": (lambda d, i: ([], _symlink(i, d / "link.h5")), "error"),
    "o_unwritable": (lambda d, i: ([], "/proc/wss-nlp-fuzz.h5"), "error"),
    "o_overwrites_result": (lambda d, i: ([], _touch(d / "old.h5")), "ok"),
    "figures_existing_file": (lambda d, i: (["--figures", str(_touch(d / "figs"))], d / "out.h5"), "error"),
    "figures_nested_new": (lambda d, i: (["--figures", str(d / "a" / "b")], d / "out.h5"), "ok"),
    "figures_is_output": (lambda d, i: (["--figures", str(d / "out.h5")], d / "out.h5"), "error"),
    "figures_unwritable": (lambda d, i: (["--figures", "/proc/wss-nlp-figs"], d / "out.h5"), "error"),
}


def _mkdir(p):
    p.mkdir()
    return p


def _touch(p):
    p.write_bytes(b"not a result")
    return p


def _symlink(target, link):
    os.symlink(target, link)
    return link


def _digests(folder) -> dict:
    out = {}
    for root, _, names in os.walk(folder):
        for n in names:
            p = os.path.join(root, n)
            if not os.path.islink(p):
                with open(p, "rb") as fh:
                    out[p] = hashlib.sha256(fh.read()).hexdigest()
    return out


def _leftovers(folder) -> list:
    return [n for n in os.listdir(folder) if n.endswith(".part") or n.startswith(".wss-nlp-part")]


def _run(argv, capsys):
    capsys.readouterr()
    rc = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err


def _check(rc, err, expect, out_path, existed):
    errors = [ln for ln in err.splitlines() if ln.startswith("wss-nlp: error:")]
    assert rc in (0, 2), err
    if rc == 2:
        assert expect in ("error", "any"), f"unexpected error: {err}"
        assert len(errors) == 1 and err.rstrip().splitlines()[-1] == errors[0], err
        assert not os.path.exists(out_path) or out_path in existed, "output left after a failure"
    else:
        assert expect in ("ok", "warn", "any"), f"bad input accepted: {err}"
        assert not errors
        wio.read_result(out_path)
        if expect == "warn":
            assert "wss-nlp: warning:" in err, err


@pytest.mark.parametrize("name", sorted(CASES))
def test_fuzz_input(name, base, tmp_path, capsys):
    which, mutate, extra, expect = CASES[name]
    inp = tmp_path / "in.h5"
    shutil.copy(base[which], inp)
    if mutate is not None:
        rng = np.random.default_rng(zlib.crc32(name.encode()))
        with h5py.File(inp, "r+") as f:
            mutate(f, rng)
    before = _digests(tmp_path)
    out = tmp_path / "out.h5"
    rc, err = _run(["reconstruct", str(inp), "-o", str(out), *FAST, *extra], capsys)
    _check(rc, err, expect, str(out), ())
    assert {p: d for p, d in _digests(tmp_path).items() if p in before} == before, "an input was modified"
    assert not _leftovers(tmp_path)


@pytest.mark.parametrize("name", sorted(PATHS))
def test_fuzz_output_path(name, base, tmp_path, capsys):
    make, expect = PATHS[name]
    inp = tmp_path / "in.h5"
    shutil.copy(base["slice"], inp)
    extra, out = make(tmp_path, inp)
    before = _digests(tmp_path)
    existed = {str(out)} if os.path.exists(out) else set()
    rc, err = _run(["reconstruct", str(inp), "-o", str(out), *FAST, *extra], capsys)
    _check(rc, err, expect, str(out), existed)
    after = _digests(tmp_path)
    if rc == 2:
        assert after == before, "a failed run changed the folder"
    assert after[str(inp)] == before[str(inp)]
    assert not _leftovers(tmp_path)


@pytest.mark.parametrize(
    "argv, expect",
    [
        (["phantom", "-o", "{d}/p.h5", "--truth", "{d}/p.h5"], "error"),
        (["phantom", "-o", "{d}/nofolder/p.h5"], "error"),
        (["phantom", "-o", "{d}"], "error"),
        (["phantom", "--case", "circle", "--h", "1.5", "--venc", "0.2", "-o", "{d}/p.h5"], "warn"),
        (["phantom", "--h", "-1", "-o", "{d}/p.h5"], "error"),
        (["analyze", "{d}/in.h5"], "error"),
        (["compare", "{d}/in.h5", "{d}/in.h5"], "error"),
        (["sensitivity", "{d}/missing.h5"], "error"),
        (["table", "{d}", "--rows", "h", "--cols", "snr", "--metric", "wss_err"], "error"),
        (["sweep", "{d}/in.h5"], "error"),
        (["sweep", "{d}/study.toml", "-o", "{d}/in.h5"], "error"),
        (["table", "{d}/runs", "--rows", "h", "--cols", "snr", "--metric", "wss_err", "-o", "{d}/runs"], "error"),
        (["demo", "-o", "{d}/in.h5"], "error"),
    ],
)
def test_fuzz_other_commands(argv, expect, base, tmp_path, capsys):
    shutil.copy(base["slice"], tmp_path / "in.h5")
    (tmp_path / "study.toml").write_text(
        '[study]\nname = "t"\n[grid]\ncase = ["circle"]\nh = [1.5]\nsnr = [25]\nseed = [0]\n'
    )
    (tmp_path / "runs").mkdir()
    before = _digests(tmp_path)
    rc, err = _run([a.format(d=tmp_path) for a in argv], capsys)
    errors = [ln for ln in err.splitlines() if ln.startswith("wss-nlp: error:")]
    if expect == "error":
        assert rc == 2 and len(errors) == 1, err
        assert _digests(tmp_path) == before and not _leftovers(tmp_path)
    else:
        assert rc == 0 and "wss-nlp: warning:" in err
    assert _digests(tmp_path)[str(tmp_path / "in.h5")] == before[str(tmp_path / "in.h5")]


def test_fuzz_suite_is_large_enough():
    assert len(CASES) + len(PATHS) + 13 >= 80
