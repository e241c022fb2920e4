"""The reconstruction options on the command line: declared once (:mod:`wss_nlp.core.schema`), read back here."""

from __future__ import annotations

import argparse

from ...core import schema
from ...pipeline import limits
from ...pipeline.options import ReconstructionOptions


def _add_reconstruction_arguments(p: argparse.ArgumentParser) -> None:
    """Every reconstruction option, from the options schema (:mod:`wss_nlp.core.schema`)."""
    schema.add_arguments(p, ReconstructionOptions)


def options_from_args(args) -> ReconstructionOptions:
    """The options the arguments set, each value checked first in the user's words (:mod:`wss_nlp.pipeline.limits`)."""
    return schema.from_args(ReconstructionOptions, args, check=limits.check_values)
