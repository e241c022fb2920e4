"""The options schema: CLI arguments and study keys come from the option declarations."""

import argparse
from dataclasses import dataclass, field

import pytest

from wss_nlp.core import schema
from wss_nlp.app.cli import build_parser, options_from_args
from wss_nlp.errors import InputError
from wss_nlp.pipeline import ReconstructionOptions

#: The study keys documented in problems/README.md and the README: none may disappear.
PUBLIC_STUDY_KEYS = {
    "method",
    "alpha",
    "N",
    "n_fourier",
    "sobolev",
    "prior",
    "gamma",
    "heaviside",
    "beta",
    "degree",
    "angular_order",
    "max_eigenvalue",
    "basis",
    "laplacian_power",
    "eta",
    "inner_fraction",
    "quad_order",
    "velocity_weight",
    "tau_alpha",
    "tau_beta",
    "kappa_alpha",
    "kappa_beta",
    "dephasing_correction",
    "uncertainty",
    "n_phi",
    "viscosity",
}


def _parse(*argv):
    return options_from_args(build_parser().parse_args(["reconstruct", "in.h5", "-o", "out.h5", *argv]))


def test_no_arguments_give_the_default_options():
    assert _parse() == ReconstructionOptions()


def test_arguments_reach_their_fields():
    o = _parse(
        "--n-fourier",
        "6",
        "--quad-order",
        "3",
        "--alpha",
        "auto",
        "--beta",
        "1e-7",
        "--no-uncertainty",
        "--vessel",
        "1.5,-2",
        "--z-smoothing",
        "0",
        "--method",
        "coupled",
        "--coupled-quad-order",
        "2",
        "--viscosity",
        "4e-3",
        "--no-unwrap",
        "--laplacian-power",
        "1",
    )
    assert o.geometry.n_fourier == 6 and o.geometry.quad_order == 3 and o.velocity.quad_order == 3
    assert o.alpha_rule == "balance" and o.geometry.alpha == 1e-3
    assert o.beta_rule == "fixed" and o.velocity.beta == 1e-7
    assert o.uncertainty is False and o.screen.vessel == (1.5, -2.0) and o.screen.unwrap is False
    assert o.stack.z_smoothing_mm == 0 and o.method == "coupled" and o.coupled.quad_order == 2
    assert o.viscosity_pa_s == 4e-3 and o.velocity.laplacian_power == 1


def test_bad_words_are_input_errors():
    with pytest.raises(InputError, match="--beta must be a number or one of auto"):
        _parse("--beta", "often")
    with pytest.raises(SystemExit):  # argparse: a choice outside the declared ones
        build_parser().parse_args(["reconstruct", "in.h5", "-o", "o.h5", "--basis", "fourier"])


def test_every_public_study_key_is_declared():
    keys = set(schema.toml_keys(ReconstructionOptions))
    assert PUBLIC_STUDY_KEYS <= keys
    o = schema.build(ReconstructionOptions, {"N": 6, "beta": "gcv", "alpha": 2e-3, "quad_order": 4})
    assert o.geometry.n_fourier == 6 and o.beta_rule == "gcv" and o.alpha_rule == "fixed"
    assert o.geometry.alpha == 2e-3 and o.velocity.quad_order == 4
    with pytest.raises(InputError, match="unknown option key 'frobnicate'"):
        schema.build(ReconstructionOptions, {"frobnicate": 1})


def test_a_new_option_is_one_declaration():
    @dataclass(frozen=True)
    class Inner:
        schema_group = "inner"
        width: float = schema.option(2.0, "a width", cli="--width", toml=("width",))

    @dataclass(frozen=True)
    class Outer:
        inner: Inner = field(default_factory=Inner)
        verbose: bool = schema.option(True, "be quiet", cli="--quiet", flag_off=True)

    p = argparse.ArgumentParser()
    schema.add_arguments(p, Outer)
    assert "--width" in p.format_help() and "(default 2.0)" in p.format_help()
    assert schema.from_args(Outer, p.parse_args(["--width", "3", "--quiet"])) == Outer(Inner(3.0), False)
    assert schema.from_args(Outer, p.parse_args([])) == Outer()
    assert schema.build(Outer, {"width": 5}) == Outer(Inner(5.0))
    # what the user set, by path, with the flag as written and the value argparse read: switches only when flipped
    assert schema.given(Outer, p.parse_args(["--width", "3", "--quiet"])) == {
        "inner.width": ("--width", 3.0),
        "verbose": ("--quiet", False),
    }
    assert schema.given(Outer, p.parse_args([])) == {}
    assert schema.cli_flag(Outer, "inner.width") == "--width" and schema.cli_flag(Outer, "nowhere") == "nowhere"


def test_the_study_file_docs_list_exactly_the_declared_keys():
    import pathlib
    import re

    text = (pathlib.Path(__file__).resolve().parent.parent / "problems" / "README.md").read_text()
    listed = text[text.index("Grid keys for options") : text.index("Metrics:")]
    documented = set(re.findall(r"`([A-Za-z_]+)`", listed)) - {"toml", "basis = ", "eigen"}
    declared = set(schema.toml_keys(ReconstructionOptions)) | {"M"}
    assert documented == declared, (documented - declared, declared - documented)
